//! PCM on the outlier benchmarks of ../shared/data/outliers: the kept closures are exactly
//! the labelled inliers, and the maximum clique sizes are those the upstream tests expect.

// Paths are relative to the package root, the working directory cargo runs tests in (a
// compile-time CARGO_MANIFEST_DIR goes stale when one target dir serves several clones).
use std::collections::BTreeSet;
use std::path::PathBuf;

use doorslam_backend::graph::between_residual;
use doorslam_backend::init::Chordal;
use doorslam_backend::outliers::{
    pairwise_mahalanobis2, readmit, Closure, Odometry, Pcm, PcmError, Scope,
};
use doorslam_backend::robust::chi2_quantile;
use doorslam_backend::{
    key, optimize, read_g2o, BetweenFactor, Graph, LieGroup, PoseGraph, SolverOptions, UnknownTags,
};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

fn folder(rel: &str) -> PathBuf {
    std::env::var_os("DOORSLAM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(".").join("../../../shared/data"))
        .join("outliers/pcm_simulation")
        .join(rel)
}

/// Merges the per-robot files (inter-robot edges appear in both; keep them once).
fn load(rel: &str, robots: usize) -> PoseGraph<Isometry3<f64>> {
    let mut merged = PoseGraph::new();
    let mut seen = BTreeSet::new();
    for r in 0..robots {
        let file = read_g2o(&folder(rel).join(format!("{r}.g2o")), UnknownTags::Skip).unwrap();
        let Graph::Se3(g) = file.graph else {
            panic!("3-D expected")
        };
        for (i, (&k, p)) in g.keys().iter().zip(g.poses()).enumerate() {
            if file.has_vertex[i] || merged.index_of(k).is_none() {
                merged.add_pose(k, *p);
            }
        }
        for e in g.edges() {
            let (a, b) = (g.keys()[e.i], g.keys()[e.j]);
            if seen.insert((a, b)) {
                let (i, j) = (merged.index_of(a).unwrap(), merged.index_of(b).unwrap());
                merged.add_edge(i, j, e.measured, e.information).unwrap();
            }
        }
    }
    merged
}

/// Labelled inliers as unordered (robot, index) pairs.
fn labelled_inliers(rel: &str) -> (BTreeSet<[(u8, u64); 2]>, usize) {
    let text = std::fs::read_to_string(folder(rel).join("inter_robot_labels.txt")).unwrap();
    let mut inliers = BTreeSet::new();
    let mut total = 0;
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
    {
        let f: Vec<&str> = line.split_whitespace().collect();
        total += 1;
        if f[6] == "1" {
            let a = (f[2].as_bytes()[0] - b'a', f[3].parse().unwrap());
            let b = (f[4].as_bytes()[0] - b'a', f[5].parse().unwrap());
            inliers.insert(if a <= b { [a, b] } else { [b, a] });
        }
    }
    (inliers, total)
}

fn as_label(k: u64) -> (u8, u64) {
    (key::robot(k).unwrap(), key::index(k))
}

#[test]
fn pcm_keeps_exactly_the_labelled_inliers() {
    // (folder, robots, expected clique size from the upstream unit tests)
    for (rel, robots, expected) in [
        ("clean/example_2robots", 2, 10),
        ("spoiled/example_2robots", 2, 10),
        ("spoiled_not_in_order/example_2robots", 2, 10),
        ("spoiled/example_4robots", 4, 24),
    ] {
        let graph = load(rel, robots);
        let (truth, total) = labelled_inliers(rel);
        let mut pcm = Pcm::new(0.99, Scope::InterRobot).unwrap();
        let s = pcm.run(&graph).unwrap();
        assert_eq!(s.closures, total, "{rel}");
        assert!(s.exact);
        assert_eq!(s.clique_size, expected, "{rel}");
        let kept: BTreeSet<[(u8, u64); 2]> = s
            .inliers
            .iter()
            .map(|&(a, b)| {
                let (a, b) = (as_label(a), as_label(b));
                if a <= b {
                    [a, b]
                } else {
                    [b, a]
                }
            })
            .collect();
        assert_eq!(
            kept, truth,
            "{rel}: kept closures differ from the labelled inliers"
        );
    }
}

#[test]
fn a_consistent_pair_passes_and_a_perturbed_one_fails() {
    let graph = load("clean/example_2robots", 2);
    let odo = Odometry::from_graph(&graph).unwrap();
    let keys = graph.keys();
    let closures: Vec<Closure> = graph
        .edges()
        .iter()
        .filter(|e| key::robot(keys[e.i]) != key::robot(keys[e.j]))
        .map(|e| Closure {
            u: keys[e.i],
            v: keys[e.j],
            measured: e.measured,
            covariance: e.information.cholesky().unwrap().inverse(),
        })
        .collect();
    let d2 = pairwise_mahalanobis2(&odo, &closures[0], &closures[1]).unwrap();
    assert!(d2 < 16.81, "two inliers: d² = {d2}");
    // The same pair seen from the other side gives the same distance, up to the
    // first-order propagation (linearized at different points: measured 3e-4 relative).
    let d2r =
        pairwise_mahalanobis2(&odo, &closures[0].reversed(), &closures[1].reversed()).unwrap();
    assert!((d2r - d2).abs() < 1e-2 * d2.max(1.0), "{d2r} vs {d2}");
    // Turning one closure by 0.3 rad (20 odometry steps of σ_R = 0.01 explain ~0.05 rad)
    // makes the pair inconsistent.
    let mut bad = closures[1].clone();
    bad.measured.rotation =
        nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3) * bad.measured.rotation;
    let d2 = pairwise_mahalanobis2(&odo, &closures[0], &bad).unwrap();
    assert!(d2 > 16.81, "perturbed pair: d² = {d2}");
}

#[test]
fn incremental_pcm_equals_batch() {
    let graph = load("spoiled_not_in_order/example_2robots", 2);
    let mut batch = Pcm::new(0.99, Scope::InterRobot).unwrap();
    let batch = batch.run(&graph).unwrap();
    // Same graph with only the first half of the inter-robot edges, then all of them.
    let keys = graph.keys().to_vec();
    let edges = graph.edges();
    let inter: Vec<usize> = (0..edges.len())
        .filter(|&n| key::robot(keys[edges[n].i]) != key::robot(keys[edges[n].j]))
        .collect();
    let mut partial = graph.clone();
    let drop: BTreeSet<usize> = inter[inter.len() / 2..].iter().copied().collect();
    let mut n = 0;
    partial.retain_edges(|_| {
        n += 1;
        !drop.contains(&(n - 1))
    });
    let mut incremental = Pcm::new(0.99, Scope::InterRobot).unwrap();
    let first = incremental.run(&partial).unwrap();
    assert_eq!(first.closures, inter.len() / 2);
    let second = incremental.run(&graph).unwrap();
    assert_eq!(
        second.closures, batch.closures,
        "old closures must not be added twice"
    );
    assert_eq!(second.clique_size, batch.clique_size);
    assert_eq!(second.consistent_pairs, batch.consistent_pairs);
}

#[test]
fn bad_thresholds_and_graphs_without_candidates_are_clear_errors() {
    for p in [0.0, 1.0, -0.5, 1.5, f64::NAN] {
        assert!(
            matches!(Pcm::new(p, Scope::InterRobot), Err(PcmError::Threshold(_))),
            "{p}"
        );
    }
    let Graph::Se3(single) = read_g2o(
        &PathBuf::from(".").join("../../../shared/data/pose_graphs/se-sync/tinyGrid3D.g2o"),
        UnknownTags::Error,
    )
    .unwrap()
    .graph
    else {
        panic!()
    };
    let err = Pcm::new(0.99, Scope::InterRobot)
        .unwrap()
        .run(&single)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("no inter-robot edges") && err.contains("--intra"),
        "{err}"
    );
    // The same single-robot graph has intra-robot loop closures to check.
    let s = Pcm::new(0.99, Scope::IntraRobot)
        .unwrap()
        .run(&single)
        .unwrap();
    assert!(s.closures > 0 && s.clique_size > 0);
}

/// Indices of the inter-robot edges of `g`.
fn inter_edges(g: &PoseGraph<Isometry3<f64>>) -> Vec<usize> {
    let keys = g.keys();
    (0..g.edges().len())
        .filter(|&n| key::robot(keys[g.edges()[n].i]) != key::robot(keys[g.edges()[n].j]))
        .collect()
}

/// `g` with only the inter-robot edges at the positions in `keep` (odometry stays).
fn with_closures(g: &PoseGraph<Isometry3<f64>>, keep: &[usize]) -> PoseGraph<Isometry3<f64>> {
    let inter: BTreeSet<usize> = inter_edges(g).into_iter().collect();
    let mut out = g.clone();
    let mut n = 0;
    out.retain_edges(|_| {
        n += 1;
        !inter.contains(&(n - 1)) || keep.contains(&(n - 1))
    });
    out
}

/// A wrong measurement on the poses of `e`: 2 m and 0.3 rad off (20 odometry steps of
/// σ_R = 0.01 explain ~0.05 rad), as confident as the real one.
fn wrong(e: &BetweenFactor<Isometry3<f64>>) -> Isometry3<f64> {
    e.measured
        * Isometry3::from_parts(
            Translation3::new(2.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
        )
}

#[test]
fn an_outlier_closure_sent_twice_in_one_batch_is_rejected() {
    let clean = load("clean/example_2robots", 2);
    let inter = inter_edges(&clean);
    // One real closure, and a wrong one received twice (a retransmission).
    let mut g = with_closures(&clean, &inter[..1]);
    let e = clean.edges()[inter[1]].clone();
    g.add_edge(e.i, e.j, wrong(&e), e.information).unwrap();
    let copy = g.add_edge(e.i, e.j, wrong(&e), e.information).unwrap();
    let s = Pcm::new(0.99, Scope::InterRobot).unwrap().run(&g).unwrap();
    // The two copies would be a consistent pair of their own and pass min_clique = 2.
    assert!(s.inliers.is_empty(), "kept {:?}", s.inliers);
    assert_eq!(s.clique_size, 0);
    assert_eq!(s.duplicates, vec![copy]);
    assert_eq!(s.closures, 2, "the copy is not a candidate of its own");
    // The closure it copies is still a candidate: with a consistent second real closure
    // the real pair is kept and the wrong one (with its copy) is not.
    let mut h = with_closures(&clean, &inter[..1]);
    h.add_edge(e.i, e.j, wrong(&e), e.information).unwrap();
    h.add_edge(e.i, e.j, wrong(&e), e.information).unwrap();
    let real = &clean.edges()[inter[2]];
    h.add_edge(real.i, real.j, real.measured, real.information)
        .unwrap();
    let s = Pcm::new(0.99, Scope::InterRobot).unwrap().run(&h).unwrap();
    let keys = clean.keys();
    let pair = |e: &BetweenFactor<Isometry3<f64>>| (keys[e.i], keys[e.j]);
    let kept: BTreeSet<(u64, u64)> = s.inliers.iter().copied().collect();
    let want: BTreeSet<(u64, u64)> = [pair(&clean.edges()[inter[0]]), pair(real)].into();
    assert_eq!(kept, want);
}

#[test]
fn a_copy_in_a_later_batch_does_not_confirm_a_closure() {
    let clean = load("clean/example_2robots", 2);
    let inter = inter_edges(&clean);
    let e = clean.edges()[inter[1]].clone();
    let mut g = with_closures(&clean, &[]);
    g.add_edge(e.i, e.j, wrong(&e), e.information).unwrap();
    let mut pcm = Pcm::new(0.99, Scope::InterRobot).unwrap();
    let s = pcm.run(&g).unwrap();
    assert_eq!(
        (s.closures, s.inliers.len()),
        (1, 0),
        "a lone closure waits"
    );
    // The same closure again, sent from the other robot's side: z⁻¹ with the information
    // moved to that frame (Ω' = Ad(z)⁻ᵀ Ω Ad(z)⁻¹), equal only up to rounding.
    let z = wrong(&e);
    let ad_inv = z.adjoint().try_inverse().unwrap();
    let reversed_info = ad_inv.transpose() * e.information * ad_inv;
    let reversed = g.add_edge(e.j, e.i, z.inverse(), reversed_info).unwrap();
    let s = pcm.run(&g).unwrap();
    assert!(s.inliers.is_empty(), "kept {:?}", s.inliers);
    assert_eq!(s.duplicates, vec![reversed]);
    assert_eq!(s.closures, 1);
    // And once more, bit for bit, in a third batch.
    let exact = g.add_edge(e.i, e.j, z, e.information).unwrap();
    let s = pcm.run(&g).unwrap();
    assert_eq!(s.duplicates, vec![reversed, exact]);
    assert_eq!((s.closures, s.inliers.len()), (1, 0));
}

#[test]
fn readmit_takes_back_an_inlier_and_not_an_outlier() {
    let clean = load("clean/example_2robots", 2);
    let inter = inter_edges(&clean);
    // The estimate built without one of the real closures, as if PCM had rejected it.
    let left_out = clean.edges()[inter[3]].clone();
    let mut rest: Vec<usize> = inter.clone();
    rest.remove(3);
    let mut estimate = with_closures(&clean, &rest);
    Isometry3::chordal(&mut estimate, 0).unwrap();
    assert!(
        optimize(&mut estimate, 0, &SolverOptions::default())
            .unwrap()
            .converged
    );
    let outlier = BetweenFactor {
        measured: wrong(&left_out),
        ..left_out.clone()
    };
    let keys = clean.keys();
    let (a, b) = (keys[left_out.i], keys[left_out.j]);
    let gamma = chi2_quantile(0.99, 6).unwrap();
    let candidates = [
        (a, b, &outlier),
        (a, b, &left_out),
        // A pose the estimate does not have cannot be checked: not re-admitted.
        (key::symbol(0, 1_000_000).unwrap(), b, &left_out),
    ];
    assert_eq!(readmit(&estimate, &candidates, gamma), vec![1]);
    // The test is the closure's own residual against γ, inclusive.
    let r = between_residual(
        &estimate.poses()[left_out.i],
        &estimate.poses()[left_out.j],
        &left_out.measured,
    );
    let own = r.dot(&(left_out.information * r));
    assert!(own < gamma, "{own}");
    assert_eq!(readmit(&estimate, &candidates, own), vec![1]);
    assert!(readmit(&estimate, &candidates, own * 0.999).is_empty());
}

/// Three robots on parallel circles (true poses known): odometry and closures exact up to
/// their stated noise; `closures` lists (robot, index, robot, index) pairs, `outliers`
/// the same with a wrong measurement (3 m and 40° off).
fn three_robots(
    closures: &[(u8, u64, u8, u64)],
    outliers: &[(u8, u64, u8, u64)],
) -> PoseGraph<Isometry3<f64>> {
    let info = nalgebra::Matrix6::from_diagonal(&nalgebra::Vector6::new(
        1e4, 1e4, 1e4, 100.0, 100.0, 100.0,
    ));
    let truth = |r: u8, i: u64| {
        let a = i as f64 * 0.2;
        Isometry3::from_parts(
            Translation3::new(10.0 * a.cos(), 10.0 * a.sin(), r as f64),
            UnitQuaternion::from_euler_angles(0.0, 0.0, a + 0.1 * r as f64),
        )
    };
    let mut g = PoseGraph::new();
    for r in 0..3u8 {
        for i in 0..30 {
            g.add_pose(key::symbol(r, i).unwrap(), truth(r, i));
        }
    }
    let at = |g: &PoseGraph<Isometry3<f64>>, r: u8, i: u64| {
        g.index_of(key::symbol(r, i).unwrap()).unwrap()
    };
    for r in 0..3u8 {
        for i in 0..29 {
            let z = truth(r, i).inverse() * truth(r, i + 1);
            let (a, b) = (at(&g, r, i), at(&g, r, i + 1));
            g.add_edge(a, b, z, info).unwrap();
        }
    }
    let off = Isometry3::from_parts(
        Translation3::new(3.0, 0.0, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7),
    );
    for (list, bad) in [(closures, false), (outliers, true)] {
        for &(ra, ia, rb, ib) in list {
            let mut z = truth(ra, ia).inverse() * truth(rb, ib);
            if bad {
                z *= off;
            }
            let (a, b) = (at(&g, ra, ia), at(&g, rb, ib));
            g.add_edge(a, b, z, info).unwrap();
        }
    }
    g
}

#[test]
fn a_lone_closure_is_checked_through_a_third_robot() {
    // a-c and b-c have three closures each (pairwise PCM confirms them); a-b has one.
    let shared = [
        (0, 3, 2, 4),
        (0, 10, 2, 11),
        (0, 20, 2, 19),
        (1, 5, 2, 5),
        (1, 12, 2, 14),
        (1, 25, 2, 24),
    ];
    let kept = |g: &PoseGraph<Isometry3<f64>>, min_clique: usize, cycles: bool| {
        let mut pcm = Pcm::new(0.99, Scope::InterRobot).unwrap();
        pcm.min_clique = min_clique;
        pcm.cycles = cycles;
        let s = pcm.run(g).unwrap();
        let ab: Vec<(u64, u64)> = s
            .inliers
            .iter()
            .copied()
            .filter(|(u, v)| key::robot(*u) != Some(2) && key::robot(*v) != Some(2))
            .collect();
        (s.clique_size, s.cycle_confirmed, ab)
    };
    let lone = (0, 15, 1, 17);
    let right = three_robots(&[shared.as_slice(), &[lone]].concat(), &[]);
    // Plain PCM cannot check it: rejected with min clique 2, kept blindly with 1.
    assert_eq!(kept(&right, 2, false).0, 6);
    assert_eq!(kept(&right, 1, false).0, 7);
    // Through c it closes cycles with the confirmed closures: kept.
    let (size, confirmed, ab) = kept(&right, 2, true);
    assert_eq!((size, confirmed), (7, 1));
    assert_eq!(
        ab,
        vec![(key::symbol(0, 15).unwrap(), key::symbol(1, 17).unwrap())]
    );
    // A wrong lone closure fails those cycles: rejected, where min clique 1 keeps it.
    let wrong = three_robots(&shared, &[lone]);
    assert_eq!(kept(&wrong, 1, false).0, 7);
    assert_eq!(kept(&wrong, 2, true), (6, 0, vec![]));
    // One right and one wrong between a and b (a clique of one, either): the cycles pick
    // the right one.
    let both = three_robots(&[shared.as_slice(), &[lone]].concat(), &[(0, 8, 1, 2)]);
    let (size, confirmed, ab) = kept(&both, 2, true);
    assert_eq!((size, confirmed), (7, 1));
    assert_eq!(
        ab,
        vec![(key::symbol(0, 15).unwrap(), key::symbol(1, 17).unwrap())]
    );
}

/// Robot c closes closures with a and with b, three times as many as the true a–b ones and
/// each set exactly consistent, but lying: robot `liar` (a or b) displaced by 4 m and 0.5
/// rad in the world. Pairwise PCM takes all three cliques, so the a–c–b path outweighs
/// the true a–b closures; the contradicted triangle sets aside one of c's pairs instead
/// (the one not touching a, the lowest robot: c may misplace itself, never b relative to
/// a).
#[test]
fn a_contradicted_triangle_does_not_go_to_the_larger_closure_sets() {
    let true_ab = [(0, 3, 1, 4), (0, 12, 1, 11), (0, 20, 1, 21)];
    let with_c: Vec<(u8, u64, u8, u64)> = (0..9u64)
        .flat_map(|m| [(0, 2 + 3 * m, 2, 1 + 3 * m), (1, 1 + 3 * m, 2, 2 + 3 * m)])
        .collect();
    let w = Isometry3::from_parts(
        Translation3::new(4.0, -2.0, 0.5),
        UnitQuaternion::from_euler_angles(0.0, 0.0, 0.5),
    );
    let kept = |liar: Option<u8>, cycles: bool| {
        let mut g = three_robots(&true_ab, &[]);
        // The same circles as `three_robots`, for c's measurements.
        let truth = |r: u8, i: u64| {
            let a = i as f64 * 0.2;
            let t = Isometry3::from_parts(
                Translation3::new(10.0 * a.cos(), 10.0 * a.sin(), r as f64),
                UnitQuaternion::from_euler_angles(0.0, 0.0, a + 0.1 * r as f64),
            );
            if Some(r) == liar {
                w * t
            } else {
                t
            }
        };
        let info = g.edges()[0].information;
        for &(ra, ia, rb, ib) in &with_c {
            let z = truth(ra, ia).inverse() * truth(rb, ib);
            let (a, b) = (
                g.index_of(key::symbol(ra, ia).unwrap()).unwrap(),
                g.index_of(key::symbol(rb, ib).unwrap()).unwrap(),
            );
            g.add_edge(a, b, z, info).unwrap();
        }
        let mut pcm = Pcm::new(0.99, Scope::InterRobot).unwrap();
        pcm.cycles = cycles;
        let s = pcm.run(&g).unwrap();
        let count = |x: u8, y: u8| {
            s.inliers
                .iter()
                .filter(|(u, v)| {
                    let mut p = [key::robot(*u).unwrap(), key::robot(*v).unwrap()];
                    p.sort_unstable();
                    p == [x, y]
                })
                .count()
        };
        ([count(0, 1), count(0, 2), count(1, 2)], s.set_aside)
    };
    // Honest: every closure kept, with or without cycles.
    assert_eq!(kept(None, false), ([3, 9, 9], 0));
    assert_eq!(kept(None, true), ([3, 9, 9], 0));
    for liar in [0, 1] {
        // Plain PCM keeps the lie: each set is consistent in itself.
        assert_eq!(kept(Some(liar), false), ([3, 9, 9], 0), "liar {liar}");
        // The triangle contradicts: b–c goes, a–b stays.
        assert_eq!(kept(Some(liar), true), ([3, 9, 0], 9), "liar {liar}");
    }
}

/// The odometry kept up to date while a graph grows (as the back-end's own-loop PCM keeps
/// it: only new keyframes and steps chained) equals the one chained from the whole graph,
/// whatever order poses and edges arrive in: appended at the end, or filling a gap in the
/// middle of a robot's flight (which splits and then joins segments).
#[test]
fn odometry_kept_up_to_date_equals_odometry_chained_at_once() {
    let full = load("clean/example_2robots", 2);
    let keys = full.keys().to_vec();
    let at_once = Odometry::from_graph(&full).unwrap();
    // Poses in a scrambled order (a fixed permutation), each edge added as soon as both of
    // its poses are in; the odometry brought up to date every 7 poses.
    let n = keys.len();
    let order: Vec<usize> = (0..n).map(|i| (i * 37 + 11) % n).collect();
    assert_eq!(
        order.iter().collect::<BTreeSet<_>>().len(),
        n,
        "not a permutation"
    );
    let mut grown = PoseGraph::new();
    let mut added = vec![false; full.edges().len()];
    let mut odo = Odometry::default();
    for (step, &i) in order.iter().enumerate() {
        grown.add_pose(keys[i], full.poses()[i]);
        for (n_edge, e) in full.edges().iter().enumerate() {
            let (a, b) = (keys[e.i], keys[e.j]);
            if let (false, Some(ia), Some(ib)) =
                (added[n_edge], grown.index_of(a), grown.index_of(b))
            {
                grown.add_edge(ia, ib, e.measured, e.information).unwrap();
                added[n_edge] = true;
            }
        }
        if step % 7 == 0 {
            odo.update(&grown).unwrap();
        }
    }
    odo.update(&grown).unwrap();
    let mut compared = 0;
    for (x, &u) in keys.iter().enumerate() {
        for &v in keys.iter().skip(x) {
            match (at_once.between(u, v), odo.between(u, v)) {
                (None, None) => {}
                (Some((t1, s1)), Some((t2, s2))) => {
                    let dt = (t1.inverse() * t2).translation.vector.norm();
                    let ds = (s1 - s2).norm() / s1.norm().max(1e-12);
                    assert!(dt < 1e-9 && ds < 1e-9, "{u} - {v}: {dt} m, {ds} relative");
                    compared += 1;
                }
                (a, b) => panic!(
                    "{u} - {v}: at once {}, kept up to date {}",
                    a.is_some(),
                    b.is_some()
                ),
            }
        }
    }
    assert!(compared > 400, "only {compared} pairs on one segment");
}
