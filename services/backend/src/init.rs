//! Initial guesses: chaining edges outward from the anchor, and chordal relaxation
//! (rotations first, then translations), GTSAM's `InitializePose3` idea.
//!
//! Chordal initialization solves two linear least-squares problems over the graph:
//! 1. rotations, relaxed to unconstrained 3×3 (2×1 in 2-D) matrices: `Rⱼ ≈ Rᵢ Zᵢⱼ`,
//!    weighted by the edge's rotational precision, then projected back onto SO(3);
//! 2. translations with those rotations fixed: `tⱼ - tᵢ ≈ Rᵢ tᵢⱼ`, weighted by the
//!    translational precision — a scalar Laplacian system, one right-hand side per axis.
//!
//! It does not depend on the initial estimate, which is what lets the default
//! `doorslam pgo` reach the good minimum of torus3D where LM from the file's poses stalls.

use std::collections::VecDeque;

use faer::Mat;
use nalgebra::{
    Isometry2, Isometry3, Matrix2, Matrix3, Translation2, Translation3, UnitComplex,
    UnitQuaternion, Vector2, Vector3,
};

use crate::graph::{EdgeClass, PoseGraph};
use crate::linear::SparseCholesky;
use crate::solver::{check_connected, var_of, SolveError};
use crate::sparsity::BlockPattern;
use doorslam_geometry::{project_so3, LieGroup, TangentMatrix};

/// Sets every pose not marked `known` by composing edges breadth-first from `start`,
/// odometry edges first (they are the most accurate chain). Returns the poses reached.
pub fn chain<G: LieGroup>(graph: &mut PoseGraph<G>, start: usize, known: &[bool]) -> usize {
    let mut adj: Vec<Vec<(usize, usize)>> = vec![Vec::new(); graph.len()];
    let mut order: Vec<usize> = (0..graph.edges().len()).collect();
    order.sort_by_key(|&n| graph.edge_class(&graph.edges()[n]) != EdgeClass::Odometry);
    for n in order {
        let e = &graph.edges()[n];
        adj[e.i].push((e.j, n));
        adj[e.j].push((e.i, n));
    }
    let mut done = vec![false; graph.len()];
    let mut queue = VecDeque::from([start]);
    done[start] = true;
    let mut reached = 1;
    while let Some(a) = queue.pop_front() {
        for &(b, n) in &adj[a] {
            if done[b] {
                continue;
            }
            done[b] = true;
            reached += 1;
            queue.push_back(b);
            if known.get(b).copied().unwrap_or(false) {
                continue;
            }
            let e = &graph.edges()[n];
            let xa = graph.poses()[a];
            // Xⱼ = Xᵢ Z, or Xᵢ = Xⱼ Z⁻¹ when walking the edge backwards.
            graph.poses_mut()[b] = if e.i == a {
                xa.compose(&e.measured)
            } else {
                xa.compose(&e.measured.inverse())
            };
        }
    }
    reached
}

/// Re-initializes all poses but the anchor from the edges alone (odometry chain first).
pub fn odometry<G: LieGroup>(graph: &mut PoseGraph<G>, anchor: usize) -> Result<(), SolveError> {
    if graph.is_empty() {
        return Err(SolveError::Empty);
    }
    // Before chaining: poses the chain cannot reach would keep stale estimates.
    check_connected(graph, anchor)?;
    let known: Vec<bool> = (0..graph.len()).map(|p| p == anchor).collect();
    chain(graph, anchor, &known);
    Ok(())
}

/// Groups with a chordal initialization.
pub trait Chordal: LieGroup {
    /// Replaces all poses but the anchor by the chordal estimate.
    fn chordal(graph: &mut PoseGraph<Self>, anchor: usize) -> Result<(), SolveError>;
}

/// Weights from an information matrix (rotation first, `d_rot` rotational dofs), as
/// SE-Sync derives its isotropic weights: κ from the rotational block, τ from the
/// translational one.
pub(crate) fn isotropic_weights(info: &TangentMatrix, d_rot: usize, d_trans: usize) -> (f64, f64) {
    let trace_inv = |offset: usize, n: usize| -> f64 {
        let block = info.view((offset, offset), (n, n)).into_owned();
        block
            .try_inverse()
            .map(|m| m.trace())
            .filter(|t| *t > 0.0)
            .unwrap_or(f64::INFINITY)
    };
    let kappa = if d_rot == 1 {
        info[(0, 0)]
    } else {
        d_rot as f64 / (2.0 * trace_inv(0, d_rot))
    };
    let tau = d_trans as f64 / trace_inv(d_rot, d_trans);
    (kappa, tau)
}

/// Solves the translation Laplacian `Σ τ |tⱼ - tᵢ - Rᵢtᵢⱼ|²` with rotations fixed.
/// `rotated[e]` is `Rᵢ tᵢⱼ` for edge e, `anchor_t` the anchor's translation.
fn solve_translations(
    graph_edges: &[(usize, usize)],
    weights: &[f64],
    rotated: &[Vector3<f64>],
    n_poses: usize,
    anchor: usize,
    anchor_t: Vector3<f64>,
) -> Result<Vec<Vector3<f64>>, SolveError> {
    let n = n_poses - 1;
    let pairs = graph_edges
        .iter()
        .filter_map(|&(i, j)| Some((var_of(i, anchor)?, var_of(j, anchor)?)));
    let pattern = BlockPattern::new(n, 1, pairs);
    let mut values = vec![0.0; pattern.nnz()];
    let mut rhs = Mat::<f64>::zeros(n, 3);
    let one = |w: f64| {
        let mut m = TangentMatrix::zeros();
        m[(0, 0)] = w;
        m
    };
    for (k, &(i, j)) in graph_edges.iter().enumerate() {
        let (w, d) = (weights[k], rotated[k]);
        let (vi, vj) = (var_of(i, anchor), var_of(j, anchor));
        // Residual tⱼ - tᵢ - d.
        if let Some(a) = vi {
            if let Some(slot) = pattern.diagonal_block(a) {
                pattern.add_diagonal(&mut values, &slot, &one(w));
            }
            for ax in 0..3 {
                rhs[(a, ax)] -= w * d[ax];
            }
        }
        if let Some(b) = vj {
            if let Some(slot) = pattern.diagonal_block(b) {
                pattern.add_diagonal(&mut values, &slot, &one(w));
            }
            for ax in 0..3 {
                rhs[(b, ax)] += w * d[ax];
            }
        }
        match (vi, vj) {
            (Some(a), Some(b)) => {
                if let Some(slot) = pattern.off_diagonal_block(a, b) {
                    pattern.add_off_diagonal(&mut values, &slot, &one(-w));
                }
            }
            (None, Some(b)) => (0..3).for_each(|ax| rhs[(b, ax)] += w * anchor_t[ax]),
            (Some(a), None) => (0..3).for_each(|ax| rhs[(a, ax)] += w * anchor_t[ax]),
            (None, None) => {}
        }
    }
    SparseCholesky::new().solve_in_place(pattern.as_matrix(&values), rhs.as_mut())?;
    Ok((0..n_poses)
        .map(|p| match var_of(p, anchor) {
            Some(v) => Vector3::new(rhs[(v, 0)], rhs[(v, 1)], rhs[(v, 2)]),
            None => anchor_t,
        })
        .collect())
}

/// The chordal initialization's second stage alone: every translation from the graph's
/// rotations as they are (`Σ τ ‖tⱼ − tᵢ − Rᵢtᵢⱼ‖²`, the anchor's translation held). With
/// a distributed method's rotations this is the fixed point its translation stage should
/// reach, so the two can be told apart when it does not.
pub(crate) fn translations_from_rotations(
    graph: &mut PoseGraph<Isometry3<f64>>,
    anchor: usize,
) -> Result<(), SolveError> {
    check_connected(graph, anchor)?;
    let rotations: Vec<Matrix3<f64>> = graph
        .poses()
        .iter()
        .map(|x| x.rotation.to_rotation_matrix().into_inner())
        .collect();
    let t = translations_given(graph, anchor, &rotations)?;
    for (p, pose) in graph.poses_mut().iter_mut().enumerate() {
        if p != anchor {
            pose.translation = Translation3::from(t[p]);
        }
    }
    Ok(())
}

/// Stage 2 of the chordal initialization in 3-D: every translation from the rotations
/// `rotations[p]` of the poses, the anchor's translation held.
fn translations_given(
    graph: &PoseGraph<Isometry3<f64>>,
    anchor: usize,
    rotations: &[Matrix3<f64>],
) -> Result<Vec<Vector3<f64>>, SolveError> {
    let pairs: Vec<(usize, usize)> = graph.edges().iter().map(|e| (e.i, e.j)).collect();
    let taus: Vec<f64> = graph
        .edges()
        .iter()
        .map(|e| isotropic_weights(&e.information, 3, 3).1)
        .collect();
    let rotated: Vec<Vector3<f64>> = graph
        .edges()
        .iter()
        .map(|e| rotations[e.i] * e.measured.translation.vector)
        .collect();
    let anchor_t = graph.poses()[anchor].translation.vector;
    solve_translations(&pairs, &taus, &rotated, graph.len(), anchor, anchor_t)
}

impl Chordal for Isometry3<f64> {
    fn chordal(graph: &mut PoseGraph<Self>, anchor: usize) -> Result<(), SolveError> {
        let n = graph.len().checked_sub(1).ok_or(SolveError::Empty)?;
        // A part not connected to the anchor makes the linear systems singular; name it
        // instead of failing in the Cholesky factorization.
        check_connected(graph, anchor)?;
        let pairs: Vec<(usize, usize)> = graph.edges().iter().map(|e| (e.i, e.j)).collect();
        let w: Vec<(f64, f64)> = graph
            .edges()
            .iter()
            .map(|e| isotropic_weights(&e.information, 3, 3))
            .collect();
        // 1. Rotations: unknowns cₚ⁽ᵏ⁾ = (row k of Rₚ)ᵀ; per edge cⱼ = Zᵀcᵢ, 3 right-hand sides.
        let pattern = BlockPattern::new(
            n,
            3,
            pairs
                .iter()
                .filter_map(|&(i, j)| Some((var_of(i, anchor)?, var_of(j, anchor)?))),
        );
        let mut values = vec![0.0; pattern.nnz()];
        let mut rhs = Mat::<f64>::zeros(3 * n, 3);
        let r_anchor = graph.poses()[anchor]
            .rotation
            .to_rotation_matrix()
            .into_inner();
        for (e, &(kappa, _)) in graph.edges().iter().zip(&w) {
            let z = e.measured.rotation.to_rotation_matrix().into_inner();
            let mut id = TangentMatrix::zeros();
            id.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(Matrix3::identity() * kappa));
            let (vi, vj) = (var_of(e.i, anchor), var_of(e.j, anchor));
            for slot in [vi, vj]
                .into_iter()
                .flatten()
                .filter_map(|v| pattern.diagonal_block(v))
            {
                pattern.add_diagonal(&mut values, &slot, &id);
            }
            match (vi, vj) {
                (Some(a), Some(b)) => {
                    // Block (rows b, cols a) = -κ Zᵀ; (rows a, cols b) = -κ Z.
                    let block = if b > a {
                        -z.transpose() * kappa
                    } else {
                        -z * kappa
                    };
                    let mut m = TangentMatrix::zeros();
                    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&block);
                    if let Some(slot) = pattern.off_diagonal_block(a, b) {
                        pattern.add_off_diagonal(&mut values, &slot, &m);
                    }
                }
                (None, Some(b)) => {
                    for k in 0..3 {
                        let c = z.transpose() * r_anchor.row(k).transpose() * kappa;
                        (0..3).for_each(|r| rhs[(3 * b + r, k)] += c[r]);
                    }
                }
                (Some(a), None) => {
                    for k in 0..3 {
                        let c = z * r_anchor.row(k).transpose() * kappa;
                        (0..3).for_each(|r| rhs[(3 * a + r, k)] += c[r]);
                    }
                }
                (None, None) => {}
            }
        }
        SparseCholesky::new().solve_in_place(pattern.as_matrix(&values), rhs.as_mut())?;
        let rotations: Vec<Matrix3<f64>> = (0..graph.len())
            .map(|p| match var_of(p, anchor) {
                Some(v) => project_so3(&Matrix3::from_fn(|k, c| rhs[(3 * v + c, k)])),
                None => r_anchor,
            })
            .collect();
        // 2. Translations with those rotations.
        let t = translations_given(graph, anchor, &rotations)?;
        // The anchor keeps its pose exactly (a matrix-quaternion round trip would move it
        // by rounding, and the solver holds it where it is).
        for (p, pose) in graph.poses_mut().iter_mut().enumerate() {
            if p == anchor {
                continue;
            }
            let q = UnitQuaternion::from_rotation_matrix(
                &nalgebra::Rotation3::from_matrix_unchecked(rotations[p]),
            );
            *pose = Isometry3::from_parts(Translation3::from(t[p]), q);
        }
        Ok(())
    }
}

impl Chordal for Isometry2<f64> {
    fn chordal(graph: &mut PoseGraph<Self>, anchor: usize) -> Result<(), SolveError> {
        let n = graph.len().checked_sub(1).ok_or(SolveError::Empty)?;
        // A part not connected to the anchor makes the linear systems singular; name it
        // instead of failing in the Cholesky factorization.
        check_connected(graph, anchor)?;
        let pairs: Vec<(usize, usize)> = graph.edges().iter().map(|e| (e.i, e.j)).collect();
        let w: Vec<(f64, f64)> = graph
            .edges()
            .iter()
            .map(|e| isotropic_weights(&e.information, 1, 2))
            .collect();
        // 1. Rotations as unit complex numbers uₚ = (cos, sin): uⱼ = M(z) uᵢ.
        let pattern = BlockPattern::new(
            n,
            2,
            pairs
                .iter()
                .filter_map(|&(i, j)| Some((var_of(i, anchor)?, var_of(j, anchor)?))),
        );
        let mut values = vec![0.0; pattern.nnz()];
        let mut rhs = Mat::<f64>::zeros(2 * n, 1);
        let ua = {
            let r = graph.poses()[anchor].rotation;
            Vector2::new(r.cos_angle(), r.sin_angle())
        };
        for (e, &(kappa, _)) in graph.edges().iter().zip(&w) {
            let (c, s) = (
                e.measured.rotation.cos_angle(),
                e.measured.rotation.sin_angle(),
            );
            let mz = Matrix2::new(c, -s, s, c);
            let mut id = TangentMatrix::zeros();
            id.fixed_view_mut::<2, 2>(0, 0)
                .copy_from(&(Matrix2::identity() * kappa));
            let (vi, vj) = (var_of(e.i, anchor), var_of(e.j, anchor));
            for slot in [vi, vj]
                .into_iter()
                .flatten()
                .filter_map(|v| pattern.diagonal_block(v))
            {
                pattern.add_diagonal(&mut values, &slot, &id);
            }
            match (vi, vj) {
                (Some(a), Some(b)) => {
                    let block = if b > a {
                        -mz * kappa
                    } else {
                        -mz.transpose() * kappa
                    };
                    let mut m = TangentMatrix::zeros();
                    m.fixed_view_mut::<2, 2>(0, 0).copy_from(&block);
                    if let Some(slot) = pattern.off_diagonal_block(a, b) {
                        pattern.add_off_diagonal(&mut values, &slot, &m);
                    }
                }
                (None, Some(b)) => {
                    let v = mz * ua * kappa;
                    rhs[(2 * b, 0)] += v.x;
                    rhs[(2 * b + 1, 0)] += v.y;
                }
                (Some(a), None) => {
                    let v = mz.transpose() * ua * kappa;
                    rhs[(2 * a, 0)] += v.x;
                    rhs[(2 * a + 1, 0)] += v.y;
                }
                (None, None) => {}
            }
        }
        SparseCholesky::new().solve_in_place(pattern.as_matrix(&values), rhs.as_mut())?;
        let angles: Vec<UnitComplex<f64>> = (0..graph.len())
            .map(|p| match var_of(p, anchor) {
                Some(v) => UnitComplex::new(rhs[(2 * v + 1, 0)].atan2(rhs[(2 * v, 0)])),
                None => graph.poses()[anchor].rotation,
            })
            .collect();
        let rotated: Vec<Vector3<f64>> = graph
            .edges()
            .iter()
            .map(|e| {
                let d = angles[e.i] * e.measured.translation.vector;
                Vector3::new(d.x, d.y, 0.0)
            })
            .collect();
        let taus: Vec<f64> = w.iter().map(|(_, t)| *t).collect();
        let at = graph.poses()[anchor].translation.vector;
        let t = solve_translations(
            &pairs,
            &taus,
            &rotated,
            graph.len(),
            anchor,
            Vector3::new(at.x, at.y, 0.0),
        )?;
        for (p, pose) in graph.poses_mut().iter_mut().enumerate() {
            if p == anchor {
                continue;
            }
            *pose = Isometry2::from_parts(Translation2::new(t[p].x, t[p].y), angles[p]);
        }
        Ok(())
    }
}
