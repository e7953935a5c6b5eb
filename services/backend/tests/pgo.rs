//! Pose-graph optimization on real benchmark graphs and on broken input.

// Paths are relative to the package root, the working directory cargo runs tests in (a
// compile-time CARGO_MANIFEST_DIR goes stale when one target dir serves several clones).
use std::path::PathBuf;

use doorslam_backend::g2o::parse_g2o;
use doorslam_backend::init::{self, Chordal};
use doorslam_backend::robust::chi2_quantile;
use doorslam_backend::{
    key, optimize, read_g2o, read_g2o_with, write_g2o, Criterion, Graph, GraphError,
    InformationPolicy, Kernel, LieGroup, Method, Optimizer, PoseGraph, ReadOptions, SolveError,
    SolverOptions, StopReason, UnknownTags,
};
use doorslam_geometry::TangentMatrix;
use nalgebra::{Isometry2, Isometry3, Translation3, UnitQuaternion, Vector3};

fn data(rel: &str) -> PathBuf {
    let root = std::env::var_os("DOORSLAM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(".").join("../../../shared/data"));
    root.join("pose_graphs").join(rel)
}

/// The held-out set (`shared/acceptance`): measured on, never tuned on.
fn acceptance(rel: &str) -> PathBuf {
    std::env::var_os("DOORSLAM_ACCEPTANCE")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(".").join("../../../shared/acceptance"))
        .join(rel)
}

fn gauss_newton() -> SolverOptions {
    SolverOptions {
        method: Method::GaussNewton,
        ..Default::default()
    }
}

fn se2(rel: &str) -> PoseGraph<Isometry2<f64>> {
    match read_g2o(&data(rel), UnknownTags::Error).unwrap().graph {
        Graph::Se2(g) => g,
        Graph::Se3(_) => panic!("{rel} is 3-D"),
    }
}

fn se3(rel: &str) -> PoseGraph<Isometry3<f64>> {
    match read_g2o(&data(rel), UnknownTags::Error).unwrap().graph {
        Graph::Se3(g) => g,
        Graph::Se2(_) => panic!("{rel} is 2-D"),
    }
}

fn wrap(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI
}

#[test]
fn noisy_toy_graph_reaches_gtsam_lago_optimum() {
    let mut g = se2("gtsam/noisyToyGraph.txt");
    Isometry2::chordal(&mut g, 0).unwrap();
    let s = optimize(&mut g, 0, &SolverOptions::default()).unwrap();
    assert!(s.converged && s.final_chi2 < s.initial_chi2);
    // GTSAM's testLago checks its full estimate against this file to 1e-2.
    let want = se2("gtsam/optimizedNoisyToyGraph.txt");
    for (p, q) in g.poses().iter().zip(want.poses()) {
        assert!(
            (p.translation.vector - q.translation.vector).amax() < 1e-2,
            "{p} vs {q}"
        );
        assert!(
            wrap(p.rotation.angle() - q.rotation.angle()).abs() < 1e-2,
            "{p} vs {q}"
        );
    }
}

/// Every small perturbation of every pose raises the cost: the solution is a minimum.
fn assert_local_minimum<G: LieGroup>(g: &PoseGraph<G>, anchor: usize) {
    let best = g.chi2();
    let mut probe = g.clone();
    for p in (0..g.len()).filter(|&p| p != anchor) {
        for k in 0..G::DIM {
            for sign in [-1.0, 1.0] {
                let mut d = doorslam_geometry::Tangent::zeros();
                d[k] = sign * 1e-4;
                probe.poses_mut()[p] = g.poses()[p].oplus(&d);
                assert!(
                    probe.chi2() >= best - 1e-9 * best,
                    "pose {p} dir {k}: {} < {best}",
                    probe.chi2()
                );
                probe.poses_mut()[p] = g.poses()[p];
            }
        }
    }
}

#[test]
fn tiny_grid_3d_gn_and_lm_agree_on_a_minimum() {
    let mut lm = se3("se-sync/tinyGrid3D.g2o");
    let mut gn = lm.clone();
    Isometry3::chordal(&mut lm, 0).unwrap();
    let s_lm = optimize(&mut lm, 0, &SolverOptions::default()).unwrap();
    let opts = SolverOptions {
        method: Method::GaussNewton,
        relative_tolerance: 1e-10,
        ..Default::default()
    };
    let s_gn = optimize(&mut gn, 0, &opts).unwrap();
    assert!(s_lm.converged && s_gn.converged);
    assert!(
        (s_lm.final_chi2 - s_gn.final_chi2).abs() < 1e-4 * s_gn.final_chi2,
        "{} vs {}",
        s_lm.final_chi2,
        s_gn.final_chi2
    );
    assert_local_minimum(&gn, 0);
    assert_eq!(
        s_lm.symbolic_builds, 1,
        "symbolic factorization must be reused across iterations"
    );
}

#[test]
fn torus_chordal_default_avoids_the_local_minimum_lm_from_file_hits() {
    let file = se3("se-sync/torus3D.g2o");
    let mut chordal = file.clone();
    Isometry3::chordal(&mut chordal, 0).unwrap();
    let s = optimize(&mut chordal, 0, &SolverOptions::default()).unwrap();
    // SE-Sync's certified optimum of its own (isotropic) objective is 2.423e4; GTSAM's
    // chordal + LM reaches ≈ 24,235 in this χ², LM from the file's poses ≈ 59,908.
    assert!(s.final_chi2 < 24_300.0, "chordal + LM: {}", s.final_chi2);
    let mut from_file = file;
    let s_file = optimize(&mut from_file, 0, &SolverOptions::default()).unwrap();
    assert!(
        s_file.final_chi2 > s.final_chi2 * 1.5,
        "LM from file: {}",
        s_file.final_chi2
    );
}

#[test]
fn files_without_vertices_are_chained_from_odometry() {
    let file = read_g2o(&data("se-sync/kitti_00.g2o"), UnknownTags::Error).unwrap();
    // No VERTEX lines at all: every pose is chained, the first one at the identity.
    assert_eq!(file.chained, 4541);
    let Graph::Se2(mut g) = file.graph else {
        panic!("kitti_00 is 2-D")
    };
    // Odometry chaining reproduces consecutive odometry exactly.
    let e = g.edges().iter().find(|e| e.j == e.i + 1).unwrap();
    assert!(g.edge_chi2(e) < 1e-12);
    init::odometry(&mut g, 0).unwrap();
    let s = optimize(&mut g, 0, &SolverOptions::default()).unwrap();
    assert!(s.final_chi2 < 1e-3 * s.initial_chi2);
}

/// Online use: a robot optimizes what it has, then extends the estimate by odometry and
/// re-solves warm-started with the same optimizer. That must land on the batch optimum.
#[test]
fn incremental_resolve_matches_batch() {
    let full = se3("se-sync/smallGrid3D.g2o");
    let mut batch = full.clone();
    Isometry3::chordal(&mut batch, 0).unwrap();
    let batch_chi2 = optimize(&mut batch, 0, &SolverOptions::default())
        .unwrap()
        .final_chi2;

    // The first half of the poses with the edges among them, initialized and optimized on
    // their own (nothing from the batch solution).
    let half = full.len() / 2;
    let mut g = PoseGraph::new();
    for (k, p) in full.keys().iter().zip(full.poses()).take(half) {
        g.add_pose(*k, *p);
    }
    for e in full.edges().iter().filter(|e| e.i < half && e.j < half) {
        g.add_edge(e.i, e.j, e.measured, e.information).unwrap();
    }
    Isometry3::chordal(&mut g, 0).unwrap();
    let mut opt = Optimizer::new(&g, 0).unwrap();
    assert!(
        opt.optimize(&mut g, &SolverOptions::default())
            .unwrap()
            .converged
    );
    // Then the rest, each new pose where odometry puts it from the previous estimate.
    for p in half..full.len() {
        let odometry = full
            .edges()
            .iter()
            .find(|e| e.i + 1 == p && e.j == p)
            .expect("smallGrid3D has the full odometry chain");
        let x = g.poses()[p - 1].compose(&odometry.measured);
        g.add_pose(full.keys()[p], x);
    }
    for e in full.edges().iter().filter(|e| e.i >= half || e.j >= half) {
        g.add_edge(e.i, e.j, e.measured, e.information).unwrap();
    }
    assert!(!opt.matches(&g));
    // The seed is far from the optimum: the re-solve has real work to do.
    let seeded = g.chi2();
    assert!(seeded > 2.0 * batch_chi2, "{seeded} vs {batch_chi2}");
    let s = opt.optimize(&mut g, &SolverOptions::default()).unwrap();
    assert!(s.converged, "{}", s.stop_reason);
    // LM stops once a step gains less than 1e-5 of the cost: both runs are that close.
    assert!(
        (s.final_chi2 - batch_chi2).abs() < 1e-4 * batch_chi2,
        "{} vs {batch_chi2}",
        s.final_chi2
    );
    // Same gauge (pose 0 fixed at the file's pose in both), so the poses agree too.
    let worst = g
        .poses()
        .iter()
        .zip(batch.poses())
        .map(|(a, b)| (a.translation.vector - b.translation.vector).norm())
        .fold(0.0, f64::max);
    assert!(worst < 1e-3, "incremental and batch differ by {worst} m");
}

#[test]
fn gnc_rejects_wrong_loop_closures_that_bend_the_map() {
    let mut clean = se3("se-sync/smallGrid3D.g2o");
    Isometry3::chordal(&mut clean, 0).unwrap();
    let clean_chi2 = optimize(&mut clean, 0, &SolverOptions::default())
        .unwrap()
        .final_chi2;
    let reference = clean.clone();

    // Ten confident, wrong loop closures between far-apart poses.
    let mut spoiled = clean.clone();
    let n_inliers = spoiled.edges().len();
    let info = spoiled.edges()[0].information;
    for k in 0..10 {
        let (i, j) = (k * 7 % spoiled.len(), (k * 13 + 60) % spoiled.len());
        if i == j {
            continue;
        }
        let z = Isometry3::from_parts(
            Translation3::new(5.0, -3.0, 2.0),
            UnitQuaternion::from_euler_angles(0.5, 0.2, -0.4),
        );
        spoiled.add_edge(i, j, z, info).unwrap();
    }
    let mut ls = spoiled.clone();
    optimize(&mut ls, 0, &SolverOptions::default()).unwrap();
    let c2 = chi2_quantile(0.99, 6).unwrap();
    let opts = SolverOptions {
        loop_kernel: Kernel::Gnc { c2 },
        ..Default::default()
    };
    let s = optimize(&mut spoiled, 0, &opts).unwrap();
    assert!(s.converged, "GNC: {}", s.stop_reason);
    let outlier_weights = &s.weights[n_inliers..];
    assert!(
        outlier_weights.iter().all(|w| *w < 1e-6),
        "outlier weights {outlier_weights:?}"
    );
    let kept = s.weights[..n_inliers].iter().filter(|w| **w > 0.5).count();
    eprintln!(
        "GNC kept {kept} of {n_inliers} inliers, {} iterations",
        s.iterations
    );
    assert!(
        kept as f64 >= 0.97 * n_inliers as f64,
        "kept {kept} of {n_inliers} inliers"
    );
    let err = |g: &PoseGraph<Isometry3<f64>>| -> f64 {
        g.poses()
            .iter()
            .zip(reference.poses())
            .map(|(a, b)| (a.translation.vector - b.translation.vector).norm())
            .fold(0.0, f64::max)
    };
    // GNC at p = 0.99 may also drop ~1 % of the inliers (those beyond the quantile), which
    // moves the estimate a little; the outliers must move it far more without GNC.
    eprintln!(
        "max position error: GNC {:.3} m, least squares {:.3} m",
        err(&spoiled),
        err(&ls)
    );
    assert!(
        err(&spoiled) < 0.5,
        "GNC estimate is {} m off the clean optimum",
        err(&spoiled)
    );
    assert!(
        err(&ls) > 10.0 * err(&spoiled),
        "plain least squares should be bent by the outliers"
    );
    let _ = clean_chi2;
}

#[test]
fn g2o_round_trip_preserves_the_problem() {
    for rel in [
        "se-sync/tinyGrid3D.g2o",
        "gtsam/noisyToyGraph.txt",
        "gtsam/pose3example-offdiagonal.txt",
    ] {
        let a = read_g2o(&data(rel), UnknownTags::Error).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out.g2o");
        write_g2o(&a.graph, &out).unwrap();
        let b = read_g2o(&out, UnknownTags::Error).unwrap();
        let chi2 = |g: &Graph| match g {
            Graph::Se2(g) => g.chi2(),
            Graph::Se3(g) => g.chi2(),
        };
        assert!(
            (chi2(&a.graph) - chi2(&b.graph)).abs() <= 1e-9 * (1.0 + chi2(&a.graph)),
            "{rel}"
        );
    }
}

#[test]
fn off_diagonal_information_is_permuted_to_rotation_first() {
    let Graph::Se3(g) = read_g2o(
        &data("gtsam/pose3example-offdiagonal.txt"),
        UnknownTags::Error,
    )
    .unwrap()
    .graph
    else {
        panic!()
    };
    let info = g.edges()[0].information;
    assert!((info - info.transpose()).amax() < 1e-12);
    // The file's first diagonal entries are translational; ours start with rotation.
    let text = std::fs::read_to_string(data("gtsam/pose3example-offdiagonal.txt")).unwrap();
    let line = text
        .lines()
        .find(|l| l.starts_with("EDGE_SE3:QUAT"))
        .unwrap();
    let v: Vec<f64> = line
        .split_whitespace()
        .skip(3)
        .map(|x| x.parse().unwrap())
        .collect();
    let upper = &v[7..];
    assert_eq!(info[(3, 3)], upper[0]); // file (tx, tx)
    assert_eq!(info[(3, 4)], upper[1]); // file (tx, ty)
    assert_eq!(info[(0, 0)], upper[15]); // file (rx, rx)
    assert_eq!(info[(3, 0)], upper[3]); // file (tx, rx)
}

#[test]
fn malformed_files_name_the_line() {
    let cases = [
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0\n",
            ":2:",
            "needs 3 numbers",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 NaN 0 0\n",
            ":2:",
            "not finite",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 -1\n",
            ":2:",
            "1 of 1 edges",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 3 1 2\n",
            ":3:",
            "unknown tag \"LANDMARK\"",
        ),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 2\n", ":1:", "norm"),
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n",
            ":2:",
            "mixes 2-D and 3-D",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 zero 1 1 0 0 1 0 0 1 0 1\n",
            ":2:",
            "not a pose id",
        ),
    ];
    for (text, line, what) in cases {
        let err = doorslam_backend::g2o::parse_g2o(text, "bad.g2o", UnknownTags::Error)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(&format!("bad.g2o{line}")) && err.contains(what),
            "{err}"
        );
    }
    // Unknown tags can be skipped with a warning.
    let ok = doorslam_backend::g2o::parse_g2o(
        "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 3 1 2\n",
        "lenient.g2o",
        UnknownTags::Skip,
    )
    .unwrap();
    assert_eq!(ok.warnings.len(), 1);
    assert!(ok.warnings[0].contains("lenient.g2o:3"));
    // Disconnected poses are refused by the solver instead of producing garbage.
    let Graph::Se2(mut g) = doorslam_backend::g2o::parse_g2o(
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n",
        "lonely.g2o",
        UnknownTags::Error,
    )
    .unwrap()
    .graph
    else {
        panic!()
    };
    assert!(optimize(&mut g, 0, &SolverOptions::default()).is_err());
    let _ = Vector3::<f64>::zeros();
}

#[test]
fn gauss_newton_divergence_is_not_reported_as_converged() {
    // From its file's poses (dead reckoning, large drift), dpgo's Intel graph is too far
    // from the minimum for an undamped step: Gauss-Newton's first step raises the cost.
    let file = se2("dpgo/input_INTEL_g2o.g2o");
    let mut gn = file.clone();
    let s = optimize(&mut gn, 0, &gauss_newton()).unwrap();
    assert_eq!(s.stop_reason, StopReason::Diverged);
    assert!(!s.converged);
    assert_eq!(s.iterations, 1);
    // The step was rejected: the estimate is the one it started from.
    assert_eq!(s.final_chi2, s.initial_chi2);
    assert_eq!(gn.poses(), file.poses());
    // Levenberg-Marquardt damps the same step and makes progress, if slowly from here.
    let mut lm = file.clone();
    let s = optimize(&mut lm, 0, &SolverOptions::default()).unwrap();
    assert_ne!(s.stop_reason, StopReason::Diverged);
    assert!(s.final_chi2 < 0.05 * s.initial_chi2, "{}", s.final_chi2);
}

#[test]
fn re_solving_an_optimum_is_converged_and_an_iteration_limit_is_not() {
    for opts in [SolverOptions::default(), gauss_newton()] {
        let mut g = se3("se-sync/smallGrid3D.g2o");
        Isometry3::chordal(&mut g, 0).unwrap();
        let first = optimize(&mut g, 0, &opts).unwrap();
        assert!(first.converged, "{:?}: {}", opts.method, first.stop_reason);
        // No step gains anything any more: that is convergence, not a failure.
        let again = optimize(&mut g, 0, &opts).unwrap();
        assert!(
            matches!(
                again.stop_reason,
                StopReason::Converged(Criterion::SmallDecrease | Criterion::SmallPredictedDecrease)
            ),
            "{:?}: {}",
            opts.method,
            again.stop_reason
        );
        assert!(again.final_chi2 <= first.final_chi2 * (1.0 + 1e-9));
    }
    let mut torus = se3("se-sync/torus3D.g2o");
    let opts = SolverOptions {
        max_iterations: 2,
        ..Default::default()
    };
    let s = optimize(&mut torus, 0, &opts).unwrap();
    assert_eq!(s.stop_reason, StopReason::MaxIterations);
    assert!(!s.converged);
    assert_eq!(s.stop_reason.as_str(), "max_iterations");
}

#[test]
fn a_disconnected_graph_names_the_poses_not_connected_to_the_anchor() {
    // Robots a and b, 13 poses each, each with its own odometry and nothing between them.
    let mut g = PoseGraph::<Isometry3<f64>>::new();
    for robot in 0..2u8 {
        for k in 0..13u64 {
            let p = Isometry3::translation(k as f64, f64::from(robot), 0.0);
            g.add_pose(key::symbol(robot, k).unwrap(), p);
        }
    }
    for base in [0, 13] {
        for k in 0..12 {
            let z = Isometry3::translation(1.0, 0.0, 0.0);
            g.add_edge(base + k, base + k + 1, z, TangentMatrix::identity())
                .unwrap();
        }
    }
    let check = |what: &str, r: Result<(), SolveError>| {
        let err = r.unwrap_err();
        let text = err.to_string();
        match err {
            SolveError::Disconnected {
                anchor,
                count,
                first,
            } => {
                assert_eq!(anchor, "a0", "{what}");
                assert_eq!(count, 13, "{what}");
                let want: Vec<String> = (0..10).map(|k| format!("b{k}")).collect();
                assert_eq!(first, want, "{what}");
            }
            other => panic!("{what}: {other}"),
        }
        assert!(
            text.contains("13 poses are not connected to the anchor a0")
                && text.contains("b0, b1, b2")
                && text.contains("and 3 more"),
            "{what}: {text}"
        );
        assert!(!text.contains("Cholesky"), "{what}: {text}");
    };
    // Every entry point that factorizes names the problem before it would fail there.
    check(
        "optimize",
        optimize(&mut g.clone(), 0, &SolverOptions::default()).map(|_| ()),
    );
    check("chordal", Isometry3::chordal(&mut g.clone(), 0));
    check("odometry", init::odometry(&mut g.clone(), 0));
    check("Optimizer::new", Optimizer::new(&g, 0).map(|_| ()));
    // Anchored in b, robot a is the disconnected part.
    let err = optimize(&mut g.clone(), 20, &SolverOptions::default()).unwrap_err();
    assert!(
        err.to_string().contains("anchor b7") && err.to_string().contains("a0, a1"),
        "{err}"
    );
    // Planar graphs too.
    let Graph::Se2(mut lonely) = parse_g2o(
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n",
        "lonely.g2o",
        UnknownTags::Error,
    )
    .unwrap()
    .graph
    else {
        panic!()
    };
    let err = Isometry2::chordal(&mut lonely, 0).unwrap_err().to_string();
    assert!(
        err.contains("1 pose is not connected to the anchor 0 "),
        "{err}"
    );
}

#[test]
fn a_fix_line_anchors_that_pose_exactly() {
    let text = std::fs::read_to_string(data("se-sync/tinyGrid3D.g2o")).unwrap() + "FIX 4\n";
    let file = parse_g2o(&text, "fixed.g2o", UnknownTags::Error).unwrap();
    assert_eq!(file.fixed, vec![4]);
    let Graph::Se3(g) = file.graph else {
        panic!("3-D expected")
    };
    let anchor = g.index_of(4).unwrap();
    let held = g.poses()[anchor];
    let mut reference = g.clone();
    Isometry3::chordal(&mut reference, 0).unwrap();
    let reference = optimize(&mut reference, 0, &SolverOptions::default()).unwrap();
    for chordal in [false, true] {
        let mut h = g.clone();
        if chordal {
            Isometry3::chordal(&mut h, anchor).unwrap();
            assert_eq!(h.poses()[anchor], held, "chordal moved the anchor");
        }
        let s = optimize(&mut h, anchor, &SolverOptions::default()).unwrap();
        assert!(s.converged, "{}", s.stop_reason);
        assert_eq!(h.poses()[anchor], held, "the solver moved the anchor");
        assert_local_minimum(&h, anchor);
        // The cost does not depend on which pose fixes the gauge.
        assert!(
            (s.final_chi2 - reference.final_chi2).abs() < 1e-4 * reference.final_chi2,
            "{} vs {}",
            s.final_chi2,
            reference.final_chi2
        );
    }
}

/// SE-Sync's cubicle (held-out set) has 5,021 edges whose information matrix is indefinite.
#[test]
fn cubicle_loads_only_by_explicit_choice_and_then_optimizes() {
    let path = acceptance("pose_graphs/se-sync/cubicle.g2o");
    let err = read_g2o(&path, UnknownTags::Error).unwrap_err();
    let text = err.to_string();
    let GraphError::NotPositiveDefinite {
        lines,
        count,
        edges,
        ..
    } = err
    else {
        panic!("{text}")
    };
    assert_eq!((count, edges), (5021, 16869));
    assert_eq!(lines.len(), 10);
    assert!(lines.contains(&5753), "{lines:?}");
    assert!(lines.windows(2).all(|w| w[0] < w[1]));
    for want in [
        format!("cubicle.g2o:{}:", lines[0]),
        "5021 of 16869 edges".into(),
        "and 5011 more".into(),
        "--information as-is".into(),
        "--information nearest-pd".into(),
    ] {
        assert!(text.contains(&want), "{want:?} missing: {text}");
    }
    for policy in [InformationPolicy::AsIs, InformationPolicy::NearestPd] {
        let file = read_g2o_with(
            &path,
            ReadOptions {
                unknown: UnknownTags::Error,
                information: policy,
            },
        )
        .unwrap();
        assert_eq!(file.not_positive_definite.len(), 5021);
        assert_eq!(file.not_positive_definite[..10], lines[..]);
        let repaired = if policy == InformationPolicy::NearestPd {
            5021
        } else {
            0
        };
        assert_eq!(file.repaired_edges, repaired);
        let Graph::Se3(mut g) = file.graph else {
            panic!("3-D expected")
        };
        assert_eq!((g.len(), g.edges().len()), (5750, 16869));
        let initial = g.chi2();
        Isometry3::chordal(&mut g, 0).unwrap();
        let s = optimize(&mut g, 0, &SolverOptions::default()).unwrap();
        eprintln!(
            "cubicle {policy:?}: chi2 {initial:.6e} (file) -> {:.6e} in {} iterations, {}",
            s.final_chi2, s.iterations, s.stop_reason
        );
        assert!(s.final_chi2.is_finite() && s.final_chi2 < initial);
        if policy == InformationPolicy::AsIs {
            // As written, the objective is unbounded below (the cost goes negative): the
            // solver must say so instead of calling it converged.
            assert_eq!(s.stop_reason, StopReason::NegativeCost);
            assert!(!s.converged);
        } else {
            assert!(s.converged, "{}", s.stop_reason);
            assert!(s.final_chi2 > 0.0);
        }
    }
}
