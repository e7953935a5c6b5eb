//! One robot's block of the distributed problem, with its neighbours' separator estimates
//! held fixed: the three solves one Gauss-Seidel step of each stage runs.
//!
//! Stage 1 and 2 are the two linear systems of the chordal initialization (see
//! [`crate::init`]) restricted to the robot's own poses: an inter-robot closure to a
//! neighbour pose with a known estimate becomes a unary term, exactly as a fixed anchor
//! does in the centralized solve. Stage 3 is the full nonlinear cost of the robot's
//! poses, solved by the back-end's Levenberg-Marquardt with the neighbour terms rewritten
//! as between-factors from one fixed node (exact, see [`prior_through`]).

use faer::Mat;
use nalgebra::{Matrix3, Vector3};

use super::DpgoError;
use crate::graph::PoseGraph;
use crate::linear::SparseCholesky;
use crate::solver::{optimize, SolveError, SolverOptions};
use crate::sparsity::BlockPattern;
use doorslam_geometry::{LieGroup, TangentMatrix, SE3};

/// An edge between two of the robot's own poses (indices into its pose list).
#[derive(Debug, Clone)]
pub(crate) struct OwnEdge {
    pub i: usize,
    pub j: usize,
    pub z: SE3,
    pub information: TangentMatrix,
    pub kappa: f64,
    pub tau: f64,
}

/// An inter-robot closure seen from this robot: `z ≈ X_own⁻¹ X_other`, information in that
/// orientation.
#[derive(Debug, Clone)]
pub(crate) struct OwnClosure {
    pub own: usize,
    pub other: u64,
    pub z: SE3,
    pub information: TangentMatrix,
    pub kappa: f64,
    pub tau: f64,
}

/// What is fixed in one local solve, per own pose: the gauge pose (the anchor robot's
/// first pose) and, per closure, the neighbour's estimate if one is usable.
pub(crate) struct Fixed<'a, T> {
    /// Own poses that are not variables (the gauge pose), with their value.
    pub own: &'a [Option<T>],
    /// Per closure (same order as the closure list): the neighbour's estimate, if usable.
    pub other: &'a [Option<T>],
}

/// Variable index of each own pose that is solved for: poses in `active` not fixed.
fn variables<T>(active: &[bool], fixed_own: &[Option<T>]) -> (Vec<Option<usize>>, usize) {
    let mut n = 0;
    let var = active
        .iter()
        .zip(fixed_own)
        .map(|(&a, f)| {
            (a && f.is_none()).then(|| {
                n += 1;
                n - 1
            })
        })
        .collect();
    (var, n)
}

fn block3(m: &Matrix3<f64>) -> TangentMatrix {
    let mut t = TangentMatrix::zeros();
    t.fixed_view_mut::<3, 3>(0, 0).copy_from(m);
    t
}

/// Stage 1: relaxed rotations of the active own poses minimizing
/// `Σ κ ‖Rⱼ − Rᵢ Zᵢⱼ‖²_F` over own edges and closures, fixed terms as given. Unknowns are
/// the rows of each `R` (three right-hand sides), as in the centralized chordal solve.
/// Returns the new relaxed matrix of each active variable pose (`None` elsewhere).
pub(crate) fn solve_rotations(
    active: &[bool],
    edges: &[OwnEdge],
    closures: &[OwnClosure],
    fixed: Fixed<'_, Matrix3<f64>>,
) -> Result<Vec<Option<Matrix3<f64>>>, SolveError> {
    let (var, n) = variables(active, fixed.own);
    if n == 0 {
        return Ok(vec![None; active.len()]);
    }
    let pairs = edges.iter().filter_map(|e| Some((var[e.i]?, var[e.j]?)));
    let pattern = BlockPattern::new(n, 3, pairs);
    let mut values = vec![0.0; pattern.nnz()];
    let mut rhs = Mat::<f64>::zeros(3 * n, 3);
    let value = |p: usize| fixed.own[p].filter(|_| active[p]);
    let diag = |values: &mut [f64], v: usize, kappa: f64| {
        if let Some(slot) = pattern.diagonal_block(v) {
            pattern.add_diagonal(values, &slot, &block3(&(Matrix3::identity() * kappa)));
        }
    };
    // Per row k of R: cⱼ = Zᵀ cᵢ with c = (row k)ᵀ.
    let add_rhs = |rhs: &mut Mat<f64>, v: usize, m: &Matrix3<f64>, known: &Matrix3<f64>| {
        for k in 0..3 {
            let c = m * known.row(k).transpose();
            (0..3).for_each(|r| rhs[(3 * v + r, k)] += c[r]);
        }
    };
    for e in edges {
        if !(active[e.i] && active[e.j]) {
            continue;
        }
        let z = e.z.rotation.to_rotation_matrix().into_inner();
        let k = e.kappa;
        match (var[e.i], var[e.j]) {
            (Some(a), Some(b)) => {
                diag(&mut values, a, k);
                diag(&mut values, b, k);
                let block = if b > a { -z.transpose() * k } else { -z * k };
                if let Some(slot) = pattern.off_diagonal_block(a, b) {
                    pattern.add_off_diagonal(&mut values, &slot, &block3(&block));
                }
            }
            (None, Some(b)) => {
                if let Some(ri) = value(e.i) {
                    diag(&mut values, b, k);
                    add_rhs(&mut rhs, b, &(z.transpose() * k), &ri);
                }
            }
            (Some(a), None) => {
                if let Some(rj) = value(e.j) {
                    diag(&mut values, a, k);
                    add_rhs(&mut rhs, a, &(z * k), &rj);
                }
            }
            (None, None) => {}
        }
    }
    for (c, other) in closures.iter().zip(fixed.other) {
        let (Some(a), Some(r_other)) = (var[c.own], other) else {
            continue;
        };
        let z = c.z.rotation.to_rotation_matrix().into_inner();
        diag(&mut values, a, c.kappa);
        add_rhs(&mut rhs, a, &(z * c.kappa), r_other);
    }
    SparseCholesky::new().solve_in_place(pattern.as_matrix(&values), rhs.as_mut())?;
    Ok(var
        .iter()
        .map(|v| v.map(|v| Matrix3::from_fn(|k, c| rhs[(3 * v + c, k)])))
        .collect())
}

/// Stage 2: translations of the active own poses minimizing `Σ τ ‖tⱼ − tᵢ − Rᵢ tᵢⱼ‖²`
/// with every rotation fixed (own: `rotations`, neighbours: their estimates), fixed
/// translations as given.
pub(crate) fn solve_translations(
    active: &[bool],
    rotations: &[Matrix3<f64>],
    edges: &[OwnEdge],
    closures: &[OwnClosure],
    fixed: Fixed<'_, Vector3<f64>>,
) -> Result<Vec<Option<Vector3<f64>>>, SolveError> {
    let (var, n) = variables(active, fixed.own);
    if n == 0 {
        return Ok(vec![None; active.len()]);
    }
    let pairs = edges.iter().filter_map(|e| Some((var[e.i]?, var[e.j]?)));
    let pattern = BlockPattern::new(n, 1, pairs);
    let mut values = vec![0.0; pattern.nnz()];
    let mut rhs = Mat::<f64>::zeros(n, 3);
    let one = |w: f64| {
        let mut m = TangentMatrix::zeros();
        m[(0, 0)] = w;
        m
    };
    let diag = |values: &mut [f64], v: usize, w: f64| {
        if let Some(slot) = pattern.diagonal_block(v) {
            pattern.add_diagonal(values, &slot, &one(w));
        }
    };
    let add = |rhs: &mut Mat<f64>, v: usize, x: Vector3<f64>| {
        (0..3).for_each(|ax| rhs[(v, ax)] += x[ax]);
    };
    for e in edges {
        if !(active[e.i] && active[e.j]) {
            continue;
        }
        let (w, d) = (e.tau, rotations[e.i] * e.z.translation.vector);
        match (var[e.i], var[e.j]) {
            (Some(a), Some(b)) => {
                diag(&mut values, a, w);
                diag(&mut values, b, w);
                add(&mut rhs, a, -w * d);
                add(&mut rhs, b, w * d);
                if let Some(slot) = pattern.off_diagonal_block(a, b) {
                    pattern.add_off_diagonal(&mut values, &slot, &one(-w));
                }
            }
            (None, Some(b)) => {
                if let Some(ti) = fixed.own[e.i] {
                    diag(&mut values, b, w);
                    add(&mut rhs, b, w * (d + ti));
                }
            }
            (Some(a), None) => {
                if let Some(tj) = fixed.own[e.j] {
                    diag(&mut values, a, w);
                    add(&mut rhs, a, w * (tj - d));
                }
            }
            (None, None) => {}
        }
    }
    for (c, other) in closures.iter().zip(fixed.other) {
        let (Some(a), Some(t_other)) = (var[c.own], other) else {
            continue;
        };
        let d = rotations[c.own] * c.z.translation.vector;
        diag(&mut values, a, c.tau);
        add(&mut rhs, a, c.tau * (t_other - d));
    }
    SparseCholesky::new().solve_in_place(pattern.as_matrix(&values), rhs.as_mut())?;
    Ok(var
        .iter()
        .map(|v| v.map(|v| Vector3::new(rhs[(v, 0)], rhs[(v, 1)], rhs[(v, 2)])))
        .collect())
}

/// The closure term `‖Log(z⁻¹ X_own⁻¹ X_other)‖²_Ω` with `X_other` fixed, as a between-factor
/// from a fixed node `X_a`: measured `X_a⁻¹ X_other z⁻¹`, information `Ad(z⁻¹)ᵀ Ω Ad(z⁻¹)`.
///
/// Exact, not an approximation: its residual is `Log(z X_other⁻¹ X_own)`, the conjugate by
/// `z` of the inverse of the closure's error, i.e. `−Ad_z r`, whose Ω-weighted norm is the
/// closure's cost for every `X_own`.
pub(crate) fn prior_through(
    x_a: &SE3,
    x_other: &SE3,
    z: &SE3,
    information: &TangentMatrix,
) -> (SE3, TangentMatrix) {
    let ad = z.inverse().adjoint();
    let measured = x_a.inverse().compose(x_other).compose(&z.inverse());
    let info = ad.transpose() * information * ad;
    (measured, (info + info.transpose()) * 0.5)
}

/// Stage 3: the robot's poses minimizing the full cost of its own edges and of its closures
/// to fixed neighbour estimates, Levenberg-Marquardt from `poses`. Node 0 of the local graph
/// is the fixed node: the gauge pose if this robot holds it, else the origin.
/// Returns the refined poses of the active own poses (`None` elsewhere).
pub(crate) fn refine(
    active: &[bool],
    poses: &[SE3],
    gauge: Option<usize>,
    edges: &[OwnEdge],
    closures: &[OwnClosure],
    other: &[Option<SE3>],
    options: &SolverOptions,
) -> Result<Vec<Option<SE3>>, DpgoError> {
    let mut graph = PoseGraph::<SE3>::new();
    let x_a = gauge.map(|g| poses[g]).unwrap_or_else(SE3::identity);
    graph.add_pose(u64::MAX, x_a);
    let mut node = vec![None; poses.len()];
    for (p, pose) in poses.iter().enumerate() {
        if !active[p] {
            continue;
        }
        node[p] = Some(if Some(p) == gauge {
            0
        } else {
            graph.add_pose(p as u64, *pose)
        });
    }
    for e in edges {
        if let (Some(a), Some(b)) = (node[e.i], node[e.j]) {
            graph.add_edge(a, b, e.z, e.information)?;
        }
    }
    for (c, x_other) in closures.iter().zip(other) {
        let (Some(n), Some(x_other)) = (node[c.own], x_other) else {
            continue;
        };
        if n == 0 {
            // The gauge pose does not move: the term is a constant.
            continue;
        }
        let (measured, info) = prior_through(&x_a, x_other, &c.z, &c.information);
        graph.add_edge(0, n, measured, info)?;
    }
    if graph.len() == 1 {
        return Ok(vec![None; poses.len()]);
    }
    optimize(&mut graph, 0, options)?;
    Ok(node
        .iter()
        .map(|n| n.filter(|&n| n != 0).map(|n| graph.poses()[n]))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::between_residual;
    use doorslam_geometry::Tangent;

    fn pose(v: [f64; 6]) -> SE3 {
        SE3::exp(&Tangent::from_row_slice(&v))
    }

    /// The rewritten closure term has the closure's cost at every own pose.
    #[test]
    fn prior_through_a_fixed_node_is_exact() {
        let z = pose([0.3, -0.2, 0.5, 1.0, 2.0, -0.5]);
        let x_other = pose([-0.4, 0.1, 0.2, 5.0, -3.0, 1.0]);
        let x_a = pose([0.1, 0.7, -0.3, -2.0, 0.5, 4.0]);
        let mut info = TangentMatrix::identity() * 50.0;
        info[(0, 4)] = 3.0;
        info[(4, 0)] = 3.0;
        info[(5, 5)] = 400.0;
        let (m, om) = prior_through(&x_a, &x_other, &z, &info);
        for v in [
            [0.0; 6],
            [0.2, 0.1, -0.3, 0.5, 0.4, -1.0],
            [-1.0, 0.5, 0.9, 3.0, -2.0, 0.1],
        ] {
            let x_own = pose(v);
            let r = between_residual(&x_own, &x_other, &z);
            let r2 = between_residual(&x_a, &x_own, &m);
            let (c1, c2) = (r.dot(&(info * r)), r2.dot(&(om * r2)));
            assert!((c1 - c2).abs() <= 1e-9 * c1.max(1.0), "{c1} vs {c2}");
        }
    }
}
