//! The graph API refuses edges that would make a wrong problem, with one rule for
//! information matrices shared with the g2o reader, and the optimizer's cached structure
//! follows the edge list itself.

// Paths are relative to the package root, the working directory cargo runs tests in.
use std::path::PathBuf;

use doorslam_backend::g2o::parse_g2o;
use doorslam_backend::sparsity::BlockPattern;
use doorslam_backend::{
    check_information, key, optimize, read_g2o, EdgeError, Graph, InformationCheck,
    InformationError, Optimizer, PoseGraph, SolverOptions, UnknownTags,
};
use doorslam_geometry::information::nearest_positive_definite;
use doorslam_geometry::TangentMatrix;
use nalgebra::{Isometry2, Isometry3, Translation3, UnitQuaternion, Vector2};

fn data(rel: &str) -> PathBuf {
    std::env::var_os("DOORSLAM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(".").join("../../../shared/data"))
        .join("pose_graphs")
        .join(rel)
}

fn two_poses() -> PoseGraph<Isometry3<f64>> {
    let mut g = PoseGraph::new();
    g.add_pose(key::symbol(0, 0).unwrap(), Isometry3::identity());
    g.add_pose(
        key::symbol(0, 1).unwrap(),
        Isometry3::from_parts(Translation3::new(1.0, 0.0, 0.0), UnitQuaternion::identity()),
    );
    g
}

fn step() -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(1.0, 0.0, 0.0), UnitQuaternion::identity())
}

/// Positive semi-definite only: one direction has no information.
fn indefinite() -> TangentMatrix {
    let mut m = TangentMatrix::identity();
    m[(0, 1)] = 2.0;
    m[(1, 0)] = 2.0;
    m
}

#[test]
fn add_edge_refuses_self_loops_and_out_of_range_poses() {
    let mut g = two_poses();
    let info = TangentMatrix::identity();
    assert!(matches!(
        g.add_edge(1, 1, step(), info),
        Err(EdgeError::SelfLoop { index: 1, ref label }) if label == "a1"
    ));
    assert_eq!(
        g.add_edge(0, 2, step(), info),
        Err(EdgeError::UnknownPose { index: 2, len: 2 })
    );
    assert_eq!(
        g.add_edge(7, 0, step(), info),
        Err(EdgeError::UnknownPose { index: 7, len: 2 })
    );
    // Even an as-is information check does not admit a structurally wrong edge.
    assert!(g
        .add_edge_with(0, 0, step(), info, InformationCheck::AsIs)
        .is_err());
    assert!(g.edges().is_empty(), "a refused edge must not be added");
    assert_eq!(g.add_edge(0, 1, step(), info), Ok(0));
    assert_eq!(g.add_edge(1, 0, step().inverse(), info), Ok(1));
    assert_eq!(g.edges().len(), 2);
}

#[test]
fn add_edge_refuses_bad_information_and_measurements() {
    let mut g = two_poses();
    let mut nan = TangentMatrix::identity();
    nan[(4, 2)] = f64::NAN;
    let mut asymmetric = TangentMatrix::identity();
    asymmetric[(3, 0)] = 0.5;
    let cases = [
        (nan, "not finite"),
        (asymmetric, "not symmetric"),
        (indefinite(), "not positive definite"),
        (TangentMatrix::zeros(), "not positive definite"),
    ];
    for (m, what) in cases {
        let err = g.add_edge(0, 1, step(), m).unwrap_err();
        assert!(matches!(err, EdgeError::Information { .. }), "{err:?}");
        let text = err.to_string();
        assert!(text.contains(what) && text.contains("a0 -> a1"), "{text}");
    }
    // The explicit escape hatch takes the indefinite matrix, but never NaN or asymmetry.
    assert_eq!(
        g.add_edge_with(0, 1, step(), indefinite(), InformationCheck::AsIs),
        Ok(0)
    );
    for m in [nan, asymmetric] {
        assert!(g
            .add_edge_with(0, 1, step(), m, InformationCheck::AsIs)
            .is_err());
    }
    let mut broken = step();
    broken.translation.vector.x = f64::INFINITY;
    assert!(matches!(
        g.add_edge(0, 1, broken, TangentMatrix::identity()),
        Err(EdgeError::NonFiniteMeasurement { .. })
    ));
    assert_eq!(g.edges().len(), 1);
}

#[test]
fn symmetry_is_checked_relative_to_the_matrix_scale() {
    // An inverse or a JᵀΩJ product is symmetric only to rounding: accepted.
    let mut m = TangentMatrix::identity() * 1e6;
    m[(1, 0)] = 1.0;
    m[(0, 1)] = 1.0 + 1e-7;
    assert_eq!(
        check_information(&m, 6, InformationCheck::PositiveDefinite),
        Ok(())
    );
    m[(0, 1)] = 1.1;
    assert!(matches!(
        check_information(&m, 6, InformationCheck::PositiveDefinite),
        Err(InformationError::NotSymmetric { row: 1, col: 0, .. })
    ));
    // SE(2) uses the leading 3 × 3 block; the padding is not part of the problem.
    let mut planar = TangentMatrix::zeros();
    planar.fixed_view_mut::<3, 3>(0, 0).fill_with_identity();
    assert_eq!(
        check_information(&planar, 3, InformationCheck::PositiveDefinite),
        Ok(())
    );
}

/// The g2o reader accepts an EDGE_SE2 exactly when `check_information` accepts its matrix.
#[test]
fn the_g2o_reader_applies_the_same_information_rule() {
    // Upper triangles in g2o order (x, y, θ).
    let cases: [[f64; 6]; 6] = [
        [1.0, 0.0, 0.0, 1.0, 0.0, 1.0],   // identity
        [4.0, 1.0, 0.5, 3.0, 0.2, 2.0],   // positive definite
        [1.0, 2.0, 0.0, 1.0, 0.0, 1.0],   // indefinite
        [1.0, 1.0, 0.0, 1.0, 0.0, 1.0],   // singular (semi-definite)
        [1.0, 0.0, 0.0, 1.0, 0.0, -1e-9], // barely indefinite
        [1e8, 0.0, 0.0, 1e-8, 0.0, 1.0],  // badly scaled but definite
    ];
    for upper in cases {
        // The solver's order is (θ, x, y).
        let order = [1, 2, 0];
        let mut m = TangentMatrix::zeros();
        let mut k = 0;
        for r in 0..3 {
            for c in r..3 {
                m[(order[r], order[c])] = upper[k];
                m[(order[c], order[r])] = upper[k];
                k += 1;
            }
        }
        let rule = check_information(&m, 3, InformationCheck::PositiveDefinite).is_ok();
        let text = format!(
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 {}\n",
            upper.map(|v| v.to_string()).join(" ")
        );
        let read = parse_g2o(&text, "case.g2o", UnknownTags::Error);
        assert_eq!(read.is_ok(), rule, "{upper:?}: {:?}", read.err());
        let mut g = PoseGraph::<Isometry2<f64>>::new();
        g.add_pose(0, Isometry2::identity());
        g.add_pose(1, Isometry2::new(Vector2::new(1.0, 0.0), 0.0));
        assert_eq!(
            g.add_edge(0, 1, Isometry2::identity(), m).is_ok(),
            rule,
            "{upper:?}"
        );
    }
}

#[test]
fn nearest_positive_definite_repairs_and_keeps_definite_matrices() {
    let repaired = nearest_positive_definite(&indefinite(), 6).unwrap();
    assert_eq!(
        check_information(&repaired, 6, InformationCheck::PositiveDefinite),
        Ok(())
    );
    // The eigenvalues 3 and -1 of the 2 × 2 block become 3 and the floor: the positive
    // part is kept.
    let eig = repaired.symmetric_eigen().eigenvalues;
    assert!((eig.max() - 3.0).abs() < 1e-12, "{eig}");
    assert!(eig.min() > 0.0 && eig.min() < 1e-6, "{eig}");
    // A definite matrix comes back unchanged (to rounding).
    let mut pd = TangentMatrix::identity() * 10.0;
    pd[(2, 5)] = 1.0;
    pd[(5, 2)] = 1.0;
    let same = nearest_positive_definite(&pd, 6).unwrap();
    assert!((same - pd).amax() < 1e-12);
    assert!(nearest_positive_definite(&TangentMatrix::zeros(), 6).is_none());
}

#[test]
fn retain_edges_is_the_only_way_to_remove_edges() {
    let mut g = two_poses();
    for k in 0..4 {
        g.add_edge(0, 1, step(), TangentMatrix::identity() * f64::from(k + 1))
            .unwrap();
    }
    g.retain_edges(|e| e.information[(0, 0)] > 2.5);
    assert_eq!(g.edges().len(), 2);
    assert_eq!(g.edges()[0].information[(0, 0)], 3.0);
}

#[test]
fn diagonal_and_off_diagonal_slots_cannot_be_confused() {
    let p = BlockPattern::new(3, 2, [(0, 1), (1, 1), (2, 0)]);
    // A self-pair is a diagonal block: it has no off-diagonal slot to write past.
    assert!(p.off_diagonal_block(1, 1).is_none());
    assert!(
        p.off_diagonal_block(1, 2).is_none(),
        "pair not in the pattern"
    );
    assert!(p.diagonal_block(3).is_none());
    // Writing every block once gives exactly the dense matrix.
    let mut values = vec![0.0; p.nnz()];
    let block = |base: f64| TangentMatrix::from_fn(|r, c| base + (r * 2 + c) as f64);
    for (a, slot) in p.diagonal_blocks().iter().enumerate() {
        let mut m = block(10.0 * (a as f64 + 1.0));
        m[(0, 1)] = m[(1, 0)];
        p.add_diagonal(&mut values, slot, &m);
    }
    p.add_off_diagonal(
        &mut values,
        &p.off_diagonal_block(0, 1).unwrap(),
        &block(100.0),
    );
    p.add_off_diagonal(
        &mut values,
        &p.off_diagonal_block(2, 0).unwrap(),
        &block(200.0),
    );
    let m = p.as_matrix(&values).to_dense();
    let want = |r: usize, c: usize| -> f64 {
        let (br, bc, ir, ic) = (r / 2, c / 2, r % 2, c % 2);
        match (br, bc) {
            (a, b) if a == b => 10.0 * (a as f64 + 1.0) + (ir.max(ic) * 2 + ir.min(ic)) as f64,
            (1, 0) => 100.0 + (ir * 2 + ic) as f64,
            (2, 0) => 200.0 + (ir * 2 + ic) as f64,
            _ => 0.0,
        }
    };
    for r in 0..6 {
        for c in 0..=r {
            assert_eq!(m[(r, c)], want(r, c), "({r}, {c})");
        }
    }
}

/// Replacing one edge by another keeps the pose and edge counts: the optimizer must still
/// notice that its offsets are stale (it used to compare counts only).
#[test]
fn the_optimizer_cache_follows_the_edge_list_not_its_length() {
    let Graph::Se3(full) = read_g2o(&data("se-sync/smallGrid3D.g2o"), UnknownTags::Error)
        .unwrap()
        .graph
    else {
        panic!("3-D expected")
    };
    let closures: Vec<usize> = (0..full.edges().len())
        .filter(|&n| full.edges()[n].j != full.edges()[n].i + 1)
        .collect();
    let without = |drop: usize| {
        let mut g = full.clone();
        let mut n = 0;
        g.retain_edges(|_| {
            n += 1;
            n - 1 != drop
        });
        g
    };
    let first = without(closures[0]);
    let mut second = without(closures[closures.len() - 1]);
    assert_eq!(first.len(), second.len());
    assert_eq!(first.edges().len(), second.edges().len());

    let mut opt = Optimizer::new(&first, 0).unwrap();
    assert!(opt.matches(&first));
    let stale = opt.matches(&second);
    let mut fresh = second.clone();
    let want = optimize(&mut fresh, 0, &SolverOptions::default()).unwrap();
    let got = opt
        .optimize(&mut second, &SolverOptions::default())
        .unwrap();
    assert!(opt.matches(&second));
    assert!(
        (got.final_chi2 - want.final_chi2).abs() <= 1e-9 * want.final_chi2,
        "{} vs {}",
        got.final_chi2,
        want.final_chi2
    );
    for (a, b) in second.poses().iter().zip(fresh.poses()) {
        assert!((a.translation.vector - b.translation.vector).amax() < 1e-9);
    }
    assert!(!stale, "same counts, different edges");
}
