//! Exp/Log/Jacobians of SE(2) and SE(3) against finite differences, over tangents that reach
//! the small-angle branch (0, 1e-6, 1e-4) and angles near π.

use doorslam_geometry::{LieGroup, Tangent, TangentMatrix, SO3};
use nalgebra::{Isometry2, Isometry3, Vector3};
use proptest::prelude::*;

const H: f64 = 1e-6;

fn dim_of<G: LieGroup>() -> usize {
    G::DIM
}

fn pad<G: LieGroup>(v: &[f64]) -> Tangent {
    let mut t = Tangent::zeros();
    for (i, x) in v.iter().take(G::DIM).enumerate() {
        t[i] = *x;
    }
    t
}

fn max_abs_diff<G: LieGroup>(a: &TangentMatrix, b: &TangentMatrix) -> f64 {
    let d = G::DIM;
    (a.view((0, 0), (d, d)) - b.view((0, 0), (d, d))).amax()
}

/// Numerical `d f(δ) / d δ` at 0 by central differences.
fn numeric<G: LieGroup>(f: impl Fn(&Tangent) -> Tangent) -> TangentMatrix {
    let mut j = TangentMatrix::zeros();
    for k in 0..G::DIM {
        let mut e = Tangent::zeros();
        e[k] = H;
        let col = (f(&e) - f(&-e)) / (2.0 * H);
        j.set_column(k, &col);
    }
    j
}

fn check_group<G: LieGroup>(xi: &Tangent, tol: f64) -> Result<(), TestCaseError> {
    let x = G::exp(xi);
    // Log ∘ Exp = id (angles below π).
    let back = x.log();
    prop_assert!(
        (back - xi).amax() < 1e-9,
        "log(exp(xi)) = {back:?} vs {xi:?}"
    );
    // Right Jacobian: Log(Exp(ξ)⁻¹ Exp(ξ + δ)) ≈ Jr δ.
    let jr_num = numeric::<G>(|d| x.inverse().compose(&G::exp(&(xi + d))).log());
    prop_assert!(
        max_abs_diff::<G>(&G::right_jacobian(xi), &jr_num) < tol,
        "Jr mismatch at {xi:?}"
    );
    // Its inverse: Log(Exp(ξ) Exp(δ)) ≈ ξ + Jr⁻¹ δ.
    let jri_num = numeric::<G>(|d| x.compose(&G::exp(d)).log() - xi);
    prop_assert!(
        max_abs_diff::<G>(&G::right_jacobian_inv(xi), &jri_num) < tol,
        "Jr⁻¹ mismatch at {xi:?}"
    );
    // Adjoint: X Exp(δ) X⁻¹ = Exp(Ad δ).
    let ad_num = numeric::<G>(|d| x.compose(&G::exp(d)).compose(&x.inverse()).log());
    prop_assert!(
        max_abs_diff::<G>(&x.adjoint(), &ad_num) < tol,
        "Ad mismatch at {xi:?}"
    );
    Ok(())
}

fn tangent_strategy(max_angle: f64) -> impl Strategy<Value = [f64; 6]> {
    (
        prop_oneof![
            Just(0.0),
            Just(1e-6),
            Just(1e-4),
            0.0..max_angle,
            (max_angle - 0.05)..max_angle
        ],
        prop::array::uniform3(-1.0..1.0f64),
        prop::array::uniform3(-5.0..5.0f64),
    )
        .prop_map(|(angle, axis, rho)| {
            let a = Vector3::from(axis);
            let a = if a.norm() < 1e-3 {
                Vector3::x()
            } else {
                a.normalize()
            } * angle;
            [a.x, a.y, a.z, rho[0], rho[1], rho[2]]
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    #[test]
    fn se3_exp_log_and_jacobians(v in tangent_strategy(3.0)) {
        check_group::<Isometry3<f64>>(&pad::<Isometry3<f64>>(&v), 1e-5)?;
    }

    #[test]
    fn se2_exp_log_and_jacobians(v in tangent_strategy(3.0)) {
        // SE(2) tangent (θ, x, y): use the angle as θ (with the sign of its x).
        let t = [v[0].signum() * (v[0]*v[0] + v[1]*v[1] + v[2]*v[2]).sqrt(), v[3], v[4]];
        check_group::<Isometry2<f64>>(&pad::<Isometry2<f64>>(&t), 1e-5)?;
    }

    #[test]
    fn so3_log_near_pi_and_zero(v in tangent_strategy(std::f64::consts::PI - 1e-9)) {
        let phi = Vector3::new(v[0], v[1], v[2]);
        let back = SO3::exp(&phi).log();
        prop_assert!((SO3::exp(&back).matrix() - SO3::exp(&phi).matrix()).amax() < 1e-9);
        prop_assert!(back.norm() <= std::f64::consts::PI + 1e-9);
    }
}

#[test]
fn dimensions_and_identity() {
    assert_eq!(dim_of::<Isometry3<f64>>(), 6);
    assert_eq!(dim_of::<Isometry2<f64>>(), 3);
    assert_eq!(Isometry3::<f64>::identity().log(), Tangent::zeros());
    assert_eq!(
        <Isometry2<f64> as LieGroup>::identity().log(),
        Tangent::zeros()
    );
}

#[test]
fn inverse_action_jacobian_matches_finite_differences() {
    use doorslam_geometry::inverse_action_jacobian;
    let x = Isometry3::new(Vector3::new(0.3, -1.2, 2.0), Vector3::new(0.4, -0.2, 0.9));
    let world = nalgebra::Point3::new(1.5, -0.7, 6.0);
    let p = (x.inverse() * world).coords;
    let analytic = inverse_action_jacobian(&p);
    for k in 0..6 {
        let mut d = Tangent::zeros();
        d[k] = H;
        let plus = (x.oplus(&d).inverse() * world).coords;
        let minus = (x.oplus(&(-d)).inverse() * world).coords;
        let column = (plus - minus) / (2.0 * H);
        assert!(
            (column - analytic.column(k)).amax() < 1e-6,
            "column {k}: numeric {column:?} vs analytic {:?}",
            analytic.column(k)
        );
    }
}
