//! SO(3), the rotations, as a type: `Exp`/`Log`, composition, adjoint and the left and
//! right Jacobians, with 3-vector tangents (`φ`, axis times angle).
//!
//! [`SO3`] wraps nalgebra's unit quaternion (the storage of [`crate::SE3`]'s rotation), so
//! converting between the two costs nothing: `SO3::from(pose.rotation)`, `rot.quaternion()`.

use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};

use crate::pose::PoseError;

/// Below this angle the closed forms switch to Taylor expansions.
pub(crate) const SMALL_ANGLE: f64 = 1e-4;

/// How far from 1 the norm of a quaternion read from a file or a message may be.
/// g2o and KITTI files print 6 digits; a norm off by more than 1 % is not a rounding error.
pub const UNIT_QUATERNION_TOLERANCE: f64 = 1e-2;

/// `[v]×`, the skew-symmetric matrix with `[v]× w = v × w`.
pub fn hat(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The inverse of [`hat`] on the skew-symmetric part of `m`.
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(
        0.5 * (m[(2, 1)] - m[(1, 2)]),
        0.5 * (m[(0, 2)] - m[(2, 0)]),
        0.5 * (m[(1, 0)] - m[(0, 1)]),
    )
}

/// A rotation of 3-D space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SO3(UnitQuaternion<f64>);

impl From<UnitQuaternion<f64>> for SO3 {
    fn from(q: UnitQuaternion<f64>) -> Self {
        Self(q)
    }
}

impl From<SO3> for UnitQuaternion<f64> {
    fn from(r: SO3) -> Self {
        r.0
    }
}

impl SO3 {
    pub fn identity() -> Self {
        Self(UnitQuaternion::identity())
    }

    /// A rotation from quaternion components read from outside (a file, a message): every
    /// component finite and the norm within [`UNIT_QUATERNION_TOLERANCE`] of 1, then
    /// normalized. A zero or NaN quaternion is an error, never a silent identity.
    pub fn from_quaternion_checked(x: f64, y: f64, z: f64, w: f64) -> Result<Self, PoseError> {
        if ![x, y, z, w].iter().all(|v| v.is_finite()) {
            return Err(PoseError::NonFinite);
        }
        let q = Quaternion::new(w, x, y, z);
        let norm = q.norm();
        if (norm - 1.0).abs() > UNIT_QUATERNION_TOLERANCE {
            return Err(PoseError::NotUnitQuaternion { norm });
        }
        Ok(Self(UnitQuaternion::from_quaternion(q)))
    }

    /// The closest rotation to a 3×3 matrix (SVD projection, determinant +1). Not
    /// nalgebra's `UnitQuaternion::from_matrix`: it iterates from the identity and returns
    /// the identity for an exact half turn.
    pub fn from_matrix(m: &Matrix3<f64>) -> Self {
        let r = nalgebra::Rotation3::from_matrix_unchecked(project_so3(m));
        let mut q = UnitQuaternion::from_rotation_matrix(&r);
        q.renormalize();
        Self(q)
    }

    pub fn quaternion(&self) -> UnitQuaternion<f64> {
        self.0
    }

    pub fn matrix(&self) -> Matrix3<f64> {
        self.0.to_rotation_matrix().into_inner()
    }

    pub fn compose(&self, other: &Self) -> Self {
        Self(self.0 * other.0)
    }

    pub fn inverse(&self) -> Self {
        Self(self.0.inverse())
    }

    /// `R v`.
    pub fn act(&self, v: &Vector3<f64>) -> Vector3<f64> {
        self.0 * v
    }

    /// `Exp(φ)`.
    pub fn exp(phi: &Vector3<f64>) -> Self {
        let theta = phi.norm();
        if theta < SMALL_ANGLE {
            // q = (1, φ/2) normalized is exact to O(θ³).
            let q = Quaternion::new(1.0, 0.5 * phi.x, 0.5 * phi.y, 0.5 * phi.z);
            return Self(UnitQuaternion::from_quaternion(q));
        }
        let (s, c) = (0.5 * theta).sin_cos();
        let v = phi * (s / theta);
        Self(UnitQuaternion::from_quaternion(Quaternion::new(
            c, v.x, v.y, v.z,
        )))
    }

    /// `Log(R)`, robust at 0 and near π.
    pub fn log(&self) -> Vector3<f64> {
        let (mut w, mut v) = (self.0.w, self.0.imag());
        if w < 0.0 {
            // q and -q are the same rotation; take the one with angle in [0, π].
            w = -w;
            v = -v;
        }
        let n = v.norm();
        if n < 1e-12 {
            // θ ≈ 2n/w: first order, exact to O(n³).
            return v * (2.0 / w);
        }
        let theta = 2.0 * n.atan2(w);
        v * (theta / n)
    }

    /// The rotation angle in [0, π].
    pub fn angle(&self) -> f64 {
        self.0.angle()
    }

    /// `Ad(R) = R`: `R · Exp(δ) = Exp(R δ) · R`.
    pub fn adjoint(&self) -> Matrix3<f64> {
        self.matrix()
    }

    /// Left Jacobian: `Jl(φ) = I + a[φ]× + b[φ]×²`.
    pub fn left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
        let (a, b) = jacobian_coeffs(phi.norm());
        let k = hat(phi);
        Matrix3::identity() + k * a + k * k * b
    }

    /// Right Jacobian: `Exp(φ + δ) ≈ Exp(φ) · Exp(Jr(φ) δ)`; `Jr(φ) = Jl(-φ)`.
    pub fn right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
        Self::left_jacobian(&-phi)
    }

    /// `Jl(φ)⁻¹ = I - ½[φ]× + c[φ]×²`.
    pub fn left_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
        let k = hat(phi);
        Matrix3::identity() - k * 0.5 + k * k * inv_coeff(phi.norm())
    }

    /// `Jr(φ)⁻¹ = I + ½[φ]× + c[φ]×²`.
    pub fn right_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
        Self::left_jacobian_inv(&-phi)
    }
}

/// Coefficients `(1-cosθ)/θ²` and `(θ-sinθ)/θ³` of the SO(3) Jacobians.
fn jacobian_coeffs(theta: f64) -> (f64, f64) {
    let t2 = theta * theta;
    if theta < SMALL_ANGLE {
        (0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        (
            (1.0 - theta.cos()) / t2,
            (theta - theta.sin()) / (t2 * theta),
        )
    }
}

/// Coefficient `1/θ² - (1+cosθ)/(2θ sinθ)` of the inverse Jacobians.
fn inv_coeff(theta: f64) -> f64 {
    if theta < SMALL_ANGLE {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        1.0 / (theta * theta) - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    }
}

/// Nearest rotation (Frobenius) to a 3×3 matrix: `U diag(1, 1, det) Vᵀ` of its SVD.
pub fn project_so3(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = m.svd(true, true);
    let (u, vt) = (
        svd.u.unwrap_or_else(Matrix3::identity),
        svd.v_t.unwrap_or_else(Matrix3::identity),
    );
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    u * d * vt
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_closest_rotation_of_a_half_turn_is_the_half_turn() {
        let half_turn = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
        let r = SO3::from_matrix(&half_turn);
        assert!((r.matrix() - half_turn).norm() < 1e-12, "{}", r.matrix());
        // A scaled, slightly sheared rotation projects back onto it.
        let q = SO3::exp(&Vector3::new(0.3, -1.2, 2.0));
        let mut m = q.matrix() * 2.0;
        m[(0, 1)] += 1e-3;
        let back = SO3::from_matrix(&m);
        assert!((back.compose(&q.inverse())).log().norm() < 1e-3);
        assert!((back.quaternion().into_inner().norm() - 1.0).abs() < 1e-12);
    }
}
