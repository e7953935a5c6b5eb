//! Nonlinear refinement of a camera motion against stereo points, and the information
//! matrix of the result.
//!
//! Each correspondence is a point `P` of a reference frame (a keyframe's triangulation, or
//! a map point fused from several), with covariance `ΣP`, seen as `m_c = (u, v, d)` in the
//! current frame. With `X` the current camera's pose in the reference frame and
//! `p = X⁻¹ P`, the residual is `r = h(p) − m_c`, `h(p) = (fx x/z + cx, fy y/z + cy,
//! fx b / z)`: a stereo reprojection error (two rows when the current frame has no
//! disparity for the point). Both are uncertain, so `r` has covariance
//! `Σr = S + A ΣP Aᵀ`, `S = diag(σu², σv², σd²)`, `A = ∂h/∂p · ∂p/∂P`: far points, whose
//! depth is poor, weigh little in the directions their depth moves them. A point
//! triangulated from one stereo measurement has `ΣP = G S Gᵀ`, `G = ∂P/∂(u, v, d)`
//! ([`stereo_point_covariance`]).
//! Gauss-Newton minimises `Σ rᵀ Σr⁻¹ r` over `X ⊕ δ`; the information of the estimate is
//! `Σ Jᵀ Σr⁻¹ J` at the optimum, `J = ∂h/∂p · ∂p/∂δ` (rotation first).

use doorslam_vision::triangulation_jacobian;
use nalgebra::{Matrix2, Matrix3, Matrix3x6, Vector3};

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::{inverse_action_jacobian, LieGroup, Tangent, TangentMatrix, SE3};

/// A reference-frame point matched in the current frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    /// The point in the reference frame (a keyframe's camera frame).
    pub point: Vector3<f64>,
    /// Its covariance in that frame (m²).
    pub point_covariance: Matrix3<f64>,
    /// Its measurement in the current frame.
    pub pixel: [f64; 2],
    pub disparity: Option<f64>,
}

/// Measurement noise of one feature, and what the information of the estimate must also
/// account for beyond the features' independent noise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Noise {
    pub pixel_sigma_px: f64,
    pub disparity_sigma_px: f64,
    /// Scale the information down by the a-posteriori variance factor
    /// `σ̂² = χ² / (residual dimensions − 6)` when it exceeds 1: the residuals say the
    /// pixel noise is larger than `pixel_sigma_px` assumed.
    pub posterior_variance: bool,
    /// Relative standard deviation of the stereo rig's scale (baseline and focal length):
    /// an error every point shares, which no residual reveals, and which moves the
    /// translation along itself: `Σ += σs² (Rᵀt)(Rᵀt)ᵀ` on the translation block.
    pub scale_sigma: f64,
    /// Standard deviation (rad, per axis) of a rotation error every feature shares
    /// (rectification and calibration errors of a real rig, which bias the pose without
    /// showing in the residuals): `Σ += σ² I` on the rotation block (0: none).
    pub rotation_sigma_rad: f64,
    /// A rotation error that grows with the distance the edge spans (rad per m of
    /// translation): a rig's calibration errors bend the path the further it goes.
    pub rotation_sigma_rad_per_m: f64,
    /// The same for the translation (m per axis): `Σ += σ² I` on the translation block.
    pub translation_sigma_m: f64,
    /// A translation error per axis growing with the edge's length (m per m).
    pub translation_sigma_per_m: f64,
}

impl Noise {
    /// `S = diag(σu², σv², σd²)`: the covariance of one stereo measurement (u, v, d).
    pub fn measurement(&self) -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(
            self.pixel_sigma_px.powi(2),
            self.pixel_sigma_px.powi(2),
            self.disparity_sigma_px.powi(2),
        ))
    }
}

/// `ΣP = G S Gᵀ` of the point triangulated from `(u, v, d)`, `G = ∂P/∂(u, v, d)`.
pub fn stereo_point_covariance(
    calib: &StereoCalibration,
    noise: &Noise,
    u: f64,
    v: f64,
    d: f64,
) -> Matrix3<f64> {
    let g = triangulation_jacobian(calib, u, v, d);
    g * noise.measurement() * g.transpose()
}

/// A refined motion.
#[derive(Debug, Clone, PartialEq)]
pub struct Refined {
    /// Pose of the current camera in the keyframe frame.
    pub pose: SE3,
    /// Information of `pose` (right perturbation, rotation first).
    pub information: TangentMatrix,
    /// Indices of the correspondences kept.
    pub inliers: Vec<usize>,
    /// Mean χ² per inlier (about the residual dimension when the noise model is right).
    pub mean_chi2: f64,
}

/// Residual, whitening and Jacobian of one correspondence at `pose`.
struct Linearized {
    r: Vector3<f64>,
    w: Matrix3<f64>,
    j: Matrix3x6<f64>,
    chi2: f64,
}

/// Points closer than this to the camera plane (m) are not projected.
const MIN_DEPTH_M: f64 = 0.05;

/// A world point seen by the rectified stereo camera at `pose` (camera to world): the
/// rotation world to camera `rt`, the point in the camera frame `p`, its measurement
/// h = (u, v, disparity) and ∂h/∂p. `None` for points behind or on the camera plane.
pub(crate) struct StereoProjection {
    pub rt: Matrix3<f64>,
    pub p: Vector3<f64>,
    pub h: Vector3<f64>,
    pub dh: Matrix3<f64>,
}

pub(crate) fn project_stereo(
    calib: &StereoCalibration,
    pose: &SE3,
    x: &Vector3<f64>,
) -> Option<StereoProjection> {
    let rt = pose.rotation.to_rotation_matrix().into_inner().transpose();
    let p = rt * (x - pose.translation.vector);
    if p.z < MIN_DEPTH_M {
        return None;
    }
    let (fx, fy, b) = (calib.fx, calib.fy, calib.baseline_m);
    let iz = 1.0 / p.z;
    let h = Vector3::new(
        fx * p.x * iz + calib.cx,
        fy * p.y * iz + calib.cy,
        fx * b * iz,
    );
    let dh = Matrix3::new(
        fx * iz,
        0.0,
        -fx * p.x * iz * iz,
        0.0,
        fy * iz,
        -fy * p.y * iz * iz,
        0.0,
        0.0,
        -fx * b * iz * iz,
    );
    Some(StereoProjection { rt, p, h, dh })
}

fn linearize(
    calib: &StereoCalibration,
    noise: &Noise,
    pose: &SE3,
    c: &Correspondence,
) -> Option<Linearized> {
    let StereoProjection { rt, p, h, dh } = project_stereo(calib, pose, &c.point)?;
    let s = noise.measurement();
    let a = dh * rt;
    let cov = s + a * c.point_covariance * a.transpose();
    let j = dh * inverse_action_jacobian(&p);
    let (r, w) = match c.disparity {
        Some(d) => (
            Vector3::new(h.x - c.pixel[0], h.y - c.pixel[1], h.z - d),
            cov.try_inverse()?,
        ),
        None => {
            let w2 =
                Matrix2::new(cov[(0, 0)], cov[(0, 1)], cov[(1, 0)], cov[(1, 1)]).try_inverse()?;
            let mut w = Matrix3::zeros();
            w.fixed_view_mut::<2, 2>(0, 0).copy_from(&w2);
            (Vector3::new(h.x - c.pixel[0], h.y - c.pixel[1], 0.0), w)
        }
    };
    let chi2 = (r.transpose() * w * r)[0];
    chi2.is_finite().then_some(Linearized { r, w, j, chi2 })
}

/// `Ω` of a pose `X` (right perturbation, rotation first) after adding the covariance of
/// a relative scale error `σs` of its translation, `t' = (1 + s) t`, i.e. `δt = s Rᵀ t`:
/// with `u = σs (0, Rᵀt)`, `(Ω⁻¹ + u uᵀ)⁻¹ = Ω − Ω u uᵀ Ω / (1 + uᵀ Ω u)`.
fn with_scale_uncertainty(
    information: &TangentMatrix,
    pose: &SE3,
    scale_sigma: f64,
) -> Option<TangentMatrix> {
    let mut u = Tangent::zeros();
    let body_t = pose.rotation.inverse() * pose.translation.vector;
    u.fixed_rows_mut::<3>(3).copy_from(&(body_t * scale_sigma));
    let w = information * u;
    let denominator = 1.0 + u.dot(&w);
    (denominator.is_finite() && denominator > 0.0)
        .then(|| information - w * w.transpose() / denominator)
}

/// The information of a relative pose `pose` after adding the errors every feature
/// shares ([`Noise::scale_sigma`], [`Noise::rotation_sigma_rad`],
/// [`Noise::translation_sigma_m`]); `None` when the result is not positive definite.
pub fn with_shared_errors(
    information: &TangentMatrix,
    pose: &SE3,
    noise: &Noise,
) -> Option<TangentMatrix> {
    let mut information = *information;
    if noise.scale_sigma > 0.0 {
        information = with_scale_uncertainty(&information, pose, noise.scale_sigma)?;
    }
    let distance = pose.translation.vector.norm();
    let rotation_variance =
        noise.rotation_sigma_rad.powi(2) + (noise.rotation_sigma_rad_per_m * distance).powi(2);
    let translation_variance =
        noise.translation_sigma_m.powi(2) + (noise.translation_sigma_per_m * distance).powi(2);
    if rotation_variance > 0.0 || translation_variance > 0.0 {
        let mut covariance = information.try_inverse()?;
        for k in 0..3 {
            covariance[(k, k)] += rotation_variance;
            covariance[(k + 3, k + 3)] += translation_variance;
        }
        information = covariance.try_inverse()?;
    }
    // Symmetric to rounding: mirror the upper triangle so downstream checks see exact symmetry.
    let information = 0.5 * (information + information.transpose());
    information.cholesky()?;
    Some(information)
}

/// Adds to an edge's information the rotation errors that motion blur leaves in its two
/// keyframes (`pose` = `Tₐ⁻¹ T_b`, `omega_a|b` their angular velocities, rad/s, body
/// frame). A blurred image shows the mean pose over the exposure `T`; when the rotation
/// rate changes by `Δω` within it, that mean is `Δω · T / 8` away from the mid-exposure pose
/// (the largest offset, a change at mid-exposure), along `Δω`. A turn may start or stop in
/// any exposure, so `Δω` is taken as large as the keyframe's angular velocity: keyframe
/// `k`'s rotation error has covariance `(T/8)² ωₖ ωₖᵀ`, independent between keyframes, and
/// the relative pose's `δ = δ_b − Ad(Tₐ⁻¹T_b)⁻¹ δₐ` collects both.
pub fn with_blur_errors(
    information: &TangentMatrix,
    pose: &SE3,
    omega_a: &Vector3<f64>,
    omega_b: &Vector3<f64>,
    exposure_s: f64,
) -> Option<TangentMatrix> {
    let k = exposure_s / 8.0;
    if k <= 0.0 || (omega_a.norm() == 0.0 && omega_b.norm() == 0.0) {
        return Some(*information);
    }
    let keyframe = |omega: &Vector3<f64>| {
        let mut c = TangentMatrix::zeros();
        c.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(k * k * omega * omega.transpose()));
        c
    };
    let m = pose.inverse().adjoint();
    let covariance =
        information.try_inverse()? + m * keyframe(omega_a) * m.transpose() + keyframe(omega_b);
    let information = covariance.try_inverse()?;
    let information = 0.5 * (information + information.transpose());
    information.cholesky()?;
    Some(information)
}

/// Gauss-Newton from `initial` on the correspondences `start` (RANSAC's inliers), then
/// re-selecting inliers among all correspondences by `χ² < outlier_chi2` and refining
/// again, until the set settles. `None` when fewer than `min_inliers` remain or the normal
/// equations are singular (a degenerate configuration: no pose is better than a wrong one).
pub fn refine(
    calib: &StereoCalibration,
    noise: &Noise,
    correspondences: &[Correspondence],
    initial: SE3,
    start: &[usize],
    outlier_chi2: f64,
    min_inliers: usize,
) -> Option<Refined> {
    let mut pose = initial;
    let mut active: Vec<usize> = start.to_vec();
    // Huber on the whitened norm keeps a few gross outliers among RANSAC's inliers from
    // pulling the first iterations.
    let huber = outlier_chi2.sqrt();
    for _round in 0..4 {
        if active.len() < min_inliers {
            return None;
        }
        for _it in 0..10 {
            let mut hess = TangentMatrix::zeros();
            let mut grad = Tangent::zeros();
            for &i in &active {
                let Some(l) = linearize(calib, noise, &pose, &correspondences[i]) else {
                    continue;
                };
                let e = l.chi2.sqrt();
                let weight = if e > huber { huber / e } else { 1.0 };
                let jtw = l.j.transpose() * l.w * weight;
                hess += jtw * l.j;
                grad += jtw * l.r;
            }
            let delta = -hess.cholesky()?.solve(&grad);
            if !delta.iter().all(|x| x.is_finite()) {
                return None;
            }
            pose = pose.oplus(&delta);
            if delta.norm() < 1e-10 {
                break;
            }
        }
        let next: Vec<usize> = (0..correspondences.len())
            .filter(|&i| {
                linearize(calib, noise, &pose, &correspondences[i])
                    .is_some_and(|l| l.chi2 < outlier_chi2)
            })
            .collect();
        let settled = next == active;
        active = next;
        if settled {
            break;
        }
    }
    if active.len() < min_inliers {
        return None;
    }
    let mut information = TangentMatrix::zeros();
    let mut chi2 = 0.0;
    for &i in &active {
        let l = linearize(calib, noise, &pose, &correspondences[i])?;
        information += l.j.transpose() * l.w * l.j;
        chi2 += l.chi2;
    }
    let dims: usize = active
        .iter()
        .map(|&i| {
            if correspondences[i].disparity.is_some() {
                3
            } else {
                2
            }
        })
        .sum();
    if noise.posterior_variance && dims > 6 {
        let variance_factor = chi2 / (dims - 6) as f64;
        if variance_factor > 1.0 {
            information /= variance_factor;
        }
    }
    let information = with_shared_errors(&information, &pose, noise)?;
    Some(Refined {
        pose,
        information,
        mean_chi2: chi2 / active.len() as f64,
        inliers: active,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn blur_adds_rotation_uncertainty_along_the_turn_axis_only() {
        let information = TangentMatrix::identity() * 1e6;
        let still = Vector3::zeros();
        let same = with_blur_errors(&information, &SE3::identity(), &still, &still, 0.02).unwrap();
        assert_eq!(same, information);
        // A 1 rad/s yaw (camera y) in both keyframes: (T/8)² ω² each, summed on the
        // relative rotation's y axis; the other axes keep their information.
        let yaw = Vector3::new(0.0, 1.0, 0.0);
        let blurred = with_blur_errors(&information, &SE3::identity(), &yaw, &yaw, 0.02).unwrap();
        let covariance = blurred.try_inverse().unwrap();
        let expected = 1e-6 + 2.0 * (0.02f64 / 8.0).powi(2);
        assert!(
            (covariance[(1, 1)] - expected).abs() < 1e-12,
            "{}",
            covariance[(1, 1)]
        );
        assert!((covariance[(0, 0)] - 1e-6).abs() < 1e-12);
        assert!((covariance[(2, 2)] - 1e-6).abs() < 1e-12);
    }

    #[test]
    fn scale_uncertainty_adds_its_covariance_along_the_translation() {
        let pose = SE3::from_parts(
            Translation3::new(0.3, -0.1, 1.5),
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.05),
        );
        let mut information = TangentMatrix::identity() * 1e4;
        information[(0, 4)] = 20.0;
        information[(4, 0)] = 20.0;
        let sigma = 0.01;
        let updated = with_scale_uncertainty(&information, &pose, sigma).unwrap();
        // (Ω⁻¹ + u uᵀ)⁻¹ with u = σ (0, Rᵀt).
        let mut u = Tangent::zeros();
        u.fixed_rows_mut::<3>(3)
            .copy_from(&(pose.rotation.inverse() * pose.translation.vector * sigma));
        let want = (information.try_inverse().unwrap() + u * u.transpose())
            .try_inverse()
            .unwrap();
        assert!(
            (updated - want).amax() < 1e-6 * want.amax(),
            "{updated}\n{want}"
        );
        // Only the direction of the translation loses information.
        let along = u.normalize();
        assert!(
            (along.transpose() * updated * along)[0] < (along.transpose() * information * along)[0]
        );
        // A rotation axis that nothing couples to the translation keeps all of it.
        let mut across = Tangent::zeros();
        across[1] = 1.0;
        assert!(((across.transpose() * updated * across)[0] - 1e4).abs() < 1e-6);
    }
}
