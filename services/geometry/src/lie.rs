//! SE(2) and SE(3) as Lie groups: `Exp`, `Log`, adjoint and right Jacobians.
//!
//! Conventions, stated once:
//! - perturbations are on the **right**: `X ⊕ δ = X · Exp(δ)`;
//! - tangent vectors put **rotation first**: SE(3) `(φx, φy, φz, ρx, ρy, ρz)`,
//!   SE(2) `(θ, ρx, ρy)`; g2o files store translation first, converted at the IO boundary;
//! - tangent vectors and matrices are padded to 6: a group of dimension `DIM` uses the
//!   leading `DIM` entries (and the top-left `DIM × DIM` block), the rest is zero. This keeps
//!   the solver free of generic-dimension plumbing at the cost of a few unused flops in 2D.
//!
//! Closed forms follow Barfoot, *State Estimation for Robotics* (SE(3) `Q` matrix) and
//! Solà et al., *A micro Lie theory* (SE(2) Jacobians); every one is tested against finite
//! differences, including the small-angle branches and angles near π.

use nalgebra::{
    Isometry2, Isometry3, Matrix3, Matrix3x6, Matrix6, Translation2, Translation3, UnitComplex,
    Vector3, Vector6,
};

use crate::so3::{hat, SMALL_ANGLE, SO3};

/// A rigid motion of 3-D space: nalgebra's isometry (translation + unit quaternion), with the
/// Lie-group operations of [`LieGroup`]. An alias, not a wrapper, so OpenCV/nalgebra results
/// need no conversion and `pose * point` keeps working.
pub type SE3 = Isometry3<f64>;
/// A rigid motion of the plane, as [`SE3`].
pub type SE2 = Isometry2<f64>;

/// Tangent vector, padded to 6 (see module docs).
pub type Tangent = Vector6<f64>;
/// Square matrix on the tangent space, padded to 6×6.
pub type TangentMatrix = Matrix6<f64>;

/// How a point seen from a pose moves when the pose is perturbed: for `p = X⁻¹ · x` (a fixed
/// point `x` expressed in the frame of `X`), the Jacobian of `(X · Exp(δ))⁻¹ · x` at `δ = 0`,
/// rotation first: `[ [p]ₓ | −I ]`, since `Exp(−δ) · p ≈ p − φ × p − ρ`. Pose refinement
/// of a camera `X` against fixed 3-D points (visual odometry, PnP) chains this with the
/// projection's Jacobian.
pub fn inverse_action_jacobian(p: &Vector3<f64>) -> Matrix3x6<f64> {
    let mut j = Matrix3x6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&hat(p));
    j.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-Matrix3::identity()));
    j
}

/// A matrix Lie group used as a pose.
pub trait LieGroup: Copy + Clone + std::fmt::Debug + PartialEq + Send + Sync + 'static {
    /// Degrees of freedom (3 for SE(2), 6 for SE(3)).
    const DIM: usize;
    fn identity() -> Self;
    fn compose(&self, other: &Self) -> Self;
    fn inverse(&self) -> Self;
    /// The logarithm: the tangent vector whose `Exp` is `self`.
    fn log(&self) -> Tangent;
    /// The exponential of the leading `DIM` entries of `xi`.
    fn exp(xi: &Tangent) -> Self;
    /// `Ad(X)`: `X · Exp(δ) = Exp(Ad(X) δ) · X`.
    fn adjoint(&self) -> TangentMatrix;
    /// `Jr(ξ)`: `Exp(ξ + δ) ≈ Exp(ξ) · Exp(Jr(ξ) δ)`.
    fn right_jacobian(xi: &Tangent) -> TangentMatrix;
    /// `Jr(ξ)⁻¹`: `Log(Exp(ξ) · Exp(δ)) ≈ ξ + Jr(ξ)⁻¹ δ`.
    fn right_jacobian_inv(xi: &Tangent) -> TangentMatrix;
    /// `X ⊕ δ = X · Exp(δ)`.
    fn oplus(&self, delta: &Tangent) -> Self {
        self.compose(&Self::exp(delta))
    }
    /// `X ⊖ Y = Log(Y⁻¹ · X)`.
    fn ominus(&self, other: &Self) -> Tangent {
        other.inverse().compose(self).log()
    }
    /// The 3-D translation of the pose (z = 0 in 2-D), for trajectory output and evaluation.
    fn translation3(&self) -> Vector3<f64>;
}

/// Barfoot's `Q(ρ, φ)`, the translation-rotation block of the SE(3) left Jacobian.
fn se3_q(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let (c1, c2, c3) = if theta < SMALL_ANGLE {
        let t2 = theta * theta;
        (
            1.0 / 6.0 - t2 / 120.0,
            1.0 / 24.0 - t2 / 720.0,
            1.0 / 120.0 - t2 / 2520.0,
        )
    } else {
        let (s, c) = theta.sin_cos();
        let t2 = theta * theta;
        let t4 = t2 * t2;
        (
            (theta - s) / (t2 * theta),
            (t2 + 2.0 * c - 2.0) / (2.0 * t4),
            (2.0 * theta - 3.0 * s + theta * c) / (2.0 * t4 * theta),
        )
    };
    let (p, r) = (hat(phi), hat(rho));
    let pr = p * r;
    let rp = r * p;
    let prp = pr * p;
    r * 0.5 + (pr + rp + prp) * c1 + (p * pr + rp * p - prp * 3.0) * c2 + (prp * p + p * prp) * c3
}

fn split3(xi: &Tangent) -> (Vector3<f64>, Vector3<f64>) {
    (
        xi.fixed_rows::<3>(0).into_owned(),
        xi.fixed_rows::<3>(3).into_owned(),
    )
}

impl LieGroup for Isometry3<f64> {
    const DIM: usize = 6;

    fn identity() -> Self {
        Isometry3::identity()
    }
    fn compose(&self, other: &Self) -> Self {
        self * other
    }
    fn inverse(&self) -> Self {
        Isometry3::inverse(self)
    }
    fn log(&self) -> Tangent {
        let phi = SO3::from(self.rotation).log();
        let rho = SO3::left_jacobian_inv(&phi) * self.translation.vector;
        Tangent::new(phi.x, phi.y, phi.z, rho.x, rho.y, rho.z)
    }
    fn exp(xi: &Tangent) -> Self {
        let (phi, rho) = split3(xi);
        Isometry3::from_parts(
            Translation3::from(SO3::left_jacobian(&phi) * rho),
            SO3::exp(&phi).quaternion(),
        )
    }
    fn adjoint(&self) -> TangentMatrix {
        let r = self.rotation.to_rotation_matrix().into_inner();
        let mut ad = TangentMatrix::zeros();
        ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
        ad.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(hat(&self.translation.vector) * r));
        ad
    }
    fn right_jacobian(xi: &Tangent) -> TangentMatrix {
        let (phi, rho) = split3(xi);
        let jr = SO3::right_jacobian(&phi);
        let mut j = TangentMatrix::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jr);
        j.fixed_view_mut::<3, 3>(3, 3).copy_from(&jr);
        // Jr(ρ, φ) = Jl(-ρ, -φ).
        j.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&se3_q(&-rho, &-phi));
        j
    }
    fn right_jacobian_inv(xi: &Tangent) -> TangentMatrix {
        let (phi, rho) = split3(xi);
        let a_inv = SO3::right_jacobian_inv(&phi);
        let q = se3_q(&-rho, &-phi);
        // [[A, 0], [Q, A]]⁻¹ = [[A⁻¹, 0], [-A⁻¹ Q A⁻¹, A⁻¹]].
        let mut j = TangentMatrix::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&a_inv);
        j.fixed_view_mut::<3, 3>(3, 3).copy_from(&a_inv);
        j.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(-a_inv * q * a_inv));
        j
    }
    fn translation3(&self) -> Vector3<f64> {
        self.translation.vector
    }
}

/// `sinθ/θ` and `(1-cosθ)/θ`, the entries of SE(2)'s `V(θ)`.
fn se2_ab(theta: f64) -> (f64, f64) {
    if theta.abs() < SMALL_ANGLE {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0, theta / 2.0 - theta * t2 / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / theta)
    }
}

impl LieGroup for Isometry2<f64> {
    const DIM: usize = 3;

    fn identity() -> Self {
        Isometry2::identity()
    }
    fn compose(&self, other: &Self) -> Self {
        self * other
    }
    fn inverse(&self) -> Self {
        Isometry2::inverse(self)
    }
    fn log(&self) -> Tangent {
        let theta = self.rotation.angle();
        let (a, b) = se2_ab(theta);
        let t = self.translation.vector;
        // V = [[a, -b], [b, a]];  V⁻¹ = [[a, b], [-b, a]] / (a² + b²).
        let d = a * a + b * b;
        Tangent::new(
            theta,
            (a * t.x + b * t.y) / d,
            (-b * t.x + a * t.y) / d,
            0.0,
            0.0,
            0.0,
        )
    }
    fn exp(xi: &Tangent) -> Self {
        let (theta, x, y) = (xi[0], xi[1], xi[2]);
        let (a, b) = se2_ab(theta);
        Isometry2::from_parts(
            Translation2::new(a * x - b * y, b * x + a * y),
            UnitComplex::new(theta),
        )
    }
    fn adjoint(&self) -> TangentMatrix {
        let (c, s) = (self.rotation.cos_angle(), self.rotation.sin_angle());
        let t = self.translation.vector;
        let mut ad = TangentMatrix::zeros();
        ad[(0, 0)] = 1.0;
        ad[(1, 0)] = t.y;
        ad[(2, 0)] = -t.x;
        ad[(1, 1)] = c;
        ad[(1, 2)] = -s;
        ad[(2, 1)] = s;
        ad[(2, 2)] = c;
        ad
    }
    fn right_jacobian(xi: &Tangent) -> TangentMatrix {
        let (theta, x, y) = (xi[0], xi[1], xi[2]);
        let (a, b) = se2_ab(theta);
        // d/dθ of the translation part; Solà eq. (163) reordered to (θ, x, y).
        let (dx, dy) = if theta.abs() < SMALL_ANGLE {
            (-y / 2.0 + theta * x / 6.0, x / 2.0 + theta * y / 6.0)
        } else {
            let (s, c) = theta.sin_cos();
            let t2 = theta * theta;
            (
                (theta * x - y + y * c - x * s) / t2,
                (x + theta * y - x * c - y * s) / t2,
            )
        };
        let mut j = TangentMatrix::zeros();
        j[(0, 0)] = 1.0;
        j[(1, 0)] = dx;
        j[(2, 0)] = dy;
        j[(1, 1)] = a;
        j[(1, 2)] = b;
        j[(2, 1)] = -b;
        j[(2, 2)] = a;
        j
    }
    fn right_jacobian_inv(xi: &Tangent) -> TangentMatrix {
        let j = Self::right_jacobian(xi);
        // [[1, 0], [d, M]]⁻¹ = [[1, 0], [-M⁻¹d, M⁻¹]] with M = [[a, b], [-b, a]].
        let (a, b) = (j[(1, 1)], j[(1, 2)]);
        let det = a * a + b * b;
        let (ia, ib) = (a / det, -b / det);
        let mut inv = TangentMatrix::zeros();
        inv[(0, 0)] = 1.0;
        inv[(1, 1)] = ia;
        inv[(1, 2)] = ib;
        inv[(2, 1)] = -ib;
        inv[(2, 2)] = ia;
        let (dx, dy) = (j[(1, 0)], j[(2, 0)]);
        inv[(1, 0)] = -(ia * dx + ib * dy);
        inv[(2, 0)] = -(-ib * dx + ia * dy);
        inv
    }
    fn translation3(&self) -> Vector3<f64> {
        Vector3::new(self.translation.vector.x, self.translation.vector.y, 0.0)
    }
}

/// A relative-pose measurement `z ≈ X_a⁻¹ X_b` (information rotation-first, right
/// perturbation) seen from its other end: `z⁻¹ ≈ X_b⁻¹ X_a`. Its residual is
/// `Log(z X_b⁻¹ X_a) = −Ad(z) Log(z⁻¹ X_a⁻¹ X_b)`, so the covariance becomes
/// `Ad(z) Σ Ad(z)ᵀ` and the information `Ad(z⁻¹)ᵀ Ω Ad(z⁻¹)` (symmetrized against rounding).
pub fn reverse_measurement(z: &SE3, information: &TangentMatrix) -> (SE3, TangentMatrix) {
    let ad = z.inverse().adjoint();
    let reversed = ad.transpose() * information * ad;
    (z.inverse(), (reversed + reversed.transpose()) * 0.5)
}
