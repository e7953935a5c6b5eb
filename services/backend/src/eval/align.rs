//! Least-squares alignment of two point sets (Umeyama 1991, "Least-squares estimation of
//! transformation parameters between two point patterns", IEEE PAMI 13(4)).
//!
//! Written to give the same numbers as evo's `geometry.umeyama_alignment`
//! (evo/core/geometry.py): variance and covariance normalized by n (eq. 36, 38), the last
//! singular direction flipped when det(U)·det(V) < 0 (eq. 43), and a covariance with fewer
//! than 2 singular values above machine epsilon rejected as degenerate.

use nalgebra::{
    Isometry3, Matrix3, Point3, Rotation3, Similarity3, Translation3, UnitQuaternion, Vector3,
};

use super::error::EvalError;
use super::trajectory::Trajectory;

/// Which transform to fit before computing absolute errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Alignment {
    /// Compare the trajectories as they are.
    None,
    /// Rotation and translation (stereo / metric estimates).
    Se3,
    /// Rotation, translation and scale (monocular estimates).
    Sim3,
}

/// The similarity `y ≈ c R x + t` that minimizes `Σ ||y_i - (c R x_i + t)||²` over the
/// pairs `(x_i, y_i) = (source[i], target[i])`; `c = 1` unless `with_scale`.
pub fn umeyama(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    with_scale: bool,
) -> Result<Similarity3<f64>, EvalError> {
    if source.len() != target.len() {
        return Err(EvalError::LengthMismatch {
            reference: target.len(),
            estimate: source.len(),
        });
    }
    if source.is_empty() {
        return Err(EvalError::DegenerateAlignment("no points".into()));
    }
    let n = source.len() as f64;
    // Means, eq. 34 and 35.
    let mean_x = source.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mean_y = target.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    // Variance of the source, eq. 36, and covariance, eq. 38.
    let mut sigma_x = 0.0;
    let mut outer_sum = Matrix3::zeros();
    for (x, y) in source.iter().zip(target) {
        let dx = x.coords - mean_x;
        sigma_x += dx.norm_squared();
        outer_sum += (y.coords - mean_y) * dx.transpose();
    }
    let sigma_x = sigma_x / n;
    let cov_xy = outer_sum / n;

    // `try_new` sorts the singular values in decreasing order, as numpy does, so the sign
    // correction below lands on the smallest one.
    let svd = nalgebra::SVD::try_new(cov_xy, true, true, f64::EPSILON, 1000)
        .ok_or_else(|| EvalError::DegenerateAlignment("SVD did not converge".into()))?;
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(EvalError::DegenerateAlignment("SVD without U or V".into()));
    };
    let d = svd.singular_values;
    let rank = d.iter().filter(|&&s| s > f64::EPSILON).count();
    if rank < 2 {
        return Err(EvalError::DegenerateAlignment(format!(
            "covariance has rank {rank} (points coincide or are collinear)"
        )));
    }
    // S, eq. 43: keep a right-handed rotation (Kabsch).
    let mut s = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s[2] = -1.0;
    }
    // Rotation, eq. 40.
    let r = u * Matrix3::from_diagonal(&s) * v_t;
    // Scale and translation, eq. 42 and 41.
    let c = if with_scale { d.dot(&s) / sigma_x } else { 1.0 };
    if !(c.is_finite() && c > 0.0) {
        return Err(EvalError::DegenerateAlignment(format!("scale {c}")));
    }
    let t = mean_y - c * (r * mean_x);
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Ok(Similarity3::from_parts(Translation3::from(t), rotation, c))
}

/// The transform that maps the estimate's positions onto the reference's (pose k onto
/// pose k; associate first), or the identity for [`Alignment::None`].
pub fn align(
    reference: &Trajectory,
    estimate: &Trajectory,
    alignment: Alignment,
) -> Result<Similarity3<f64>, EvalError> {
    if reference.len() != estimate.len() {
        return Err(EvalError::LengthMismatch {
            reference: reference.len(),
            estimate: estimate.len(),
        });
    }
    match alignment {
        Alignment::None => Ok(Similarity3::identity()),
        Alignment::Se3 => umeyama(&estimate.positions(), &reference.positions(), false),
        Alignment::Sim3 => umeyama(&estimate.positions(), &reference.positions(), true),
    }
}

/// Applies an alignment to every pose as evo does: positions are scaled, then the poses
/// are left-multiplied by the rigid part (`R_k' = R R_k`, `t_k' = c R t_k + t`).
pub fn apply_alignment(trajectory: &Trajectory, transform: &Similarity3<f64>) -> Trajectory {
    let rigid = transform.isometry;
    let c = transform.scaling();
    let poses = trajectory
        .poses()
        .iter()
        .map(|p| {
            let scaled =
                Isometry3::from_parts(Translation3::from(p.translation.vector * c), p.rotation);
            rigid * scaled
        })
        .collect();
    trajectory.with_poses(poses)
}
