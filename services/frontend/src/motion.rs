//! The current camera's pose from its tracked landmarks: PnP-RANSAC, then the stereo
//! reprojection refinement ([`crate::refine`]), then checks that turn a doubtful pose into
//! a loss: enough inliers, a large enough share of the tracks, and agreement with the
//! motion prediction. A wrong pose is worse than a loss: the back-end trusts every edge.

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::SE3;
use doorslam_vision::pnp_ransac;
use nalgebra::Vector3;

use crate::refine::{refine, Correspondence, Noise, Refined};

/// Thresholds of [`estimate_motion`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct MotionSettings {
    pub noise: Noise,
    pub ransac_iterations: i32,
    pub ransac_threshold_px: f64,
    pub outlier_chi2: f64,
    pub min_inliers: usize,
    pub min_inlier_fraction: f64,
}

/// Why no pose was accepted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MotionFailure {
    pub correspondences: usize,
    pub inliers: usize,
}

/// Refined pose of the current camera in the reference frame from the correspondences;
/// RANSAC first, and the prediction `prior` as a second start when RANSAC's pose does
/// not hold (few tracks, most of them right).
pub(crate) fn estimate_motion(
    calib: &StereoCalibration,
    correspondences: &[Correspondence],
    prior: &SE3,
    settings: &MotionSettings,
) -> Result<Refined, MotionFailure> {
    let n = correspondences.len();
    let fail = |inliers| MotionFailure {
        correspondences: n,
        inliers,
    };
    if n < settings.min_inliers {
        return Err(fail(0));
    }
    let needed = settings
        .min_inliers
        .max((settings.min_inlier_fraction * n as f64).ceil() as usize);
    let mut best: Option<Refined> = None;
    let mut best_inliers = 0;
    let points: Vec<Vector3<f64>> = correspondences.iter().map(|c| c.point).collect();
    let pixels: Vec<[f32; 2]> = correspondences
        .iter()
        .map(|c| [c.pixel[0] as f32, c.pixel[1] as f32])
        .collect();
    if let Ok(Some((pose, inliers))) = pnp_ransac(
        &points,
        &pixels,
        calib,
        settings.ransac_iterations,
        settings.ransac_threshold_px,
    ) {
        best_inliers = inliers.len();
        if inliers.len() >= settings.min_inliers {
            best = refine(
                calib,
                &settings.noise,
                correspondences,
                pose,
                &inliers,
                settings.outlier_chi2,
                settings.min_inliers,
            );
        }
    }
    if best.as_ref().is_none_or(|b| b.inliers.len() < needed) {
        // The prediction's own inliers: correspondences it reprojects within the RANSAC
        // threshold.
        let inverse = prior.inverse();
        let start: Vec<usize> = (0..n)
            .filter(|&i| {
                let q = inverse * nalgebra::Point3::from(correspondences[i].point);
                if q.z < 0.05 {
                    return false;
                }
                let u = calib.fx * q.x / q.z + calib.cx - correspondences[i].pixel[0];
                let v = calib.fy * q.y / q.z + calib.cy - correspondences[i].pixel[1];
                u * u + v * v < (2.0 * settings.ransac_threshold_px).powi(2)
            })
            .collect();
        best_inliers = best_inliers.max(start.len());
        if start.len() >= settings.min_inliers {
            if let Some(r) = refine(
                calib,
                &settings.noise,
                correspondences,
                *prior,
                &start,
                settings.outlier_chi2,
                settings.min_inliers,
            ) {
                if best
                    .as_ref()
                    .is_none_or(|b| r.inliers.len() > b.inliers.len())
                {
                    best = Some(r);
                }
            }
        }
    }
    match best {
        Some(r) if r.inliers.len() >= needed => Ok(r),
        Some(r) => Err(fail(r.inliers.len())),
        None => Err(fail(best_inliers)),
    }
}

/// How far an estimate is from the prediction: rotation (degrees) and translation (m) of
/// `predicted⁻¹ · estimate`.
pub(crate) fn prediction_error(predicted: &SE3, estimate: &SE3) -> (f64, f64) {
    let d = predicted.inverse() * estimate;
    (d.rotation.angle().to_degrees(), d.translation.vector.norm())
}
