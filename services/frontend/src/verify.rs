//! Geometric verification of a loop-closure candidate (paper §III-C): the features of a
//! remote keyframe (another robot's, or an old one of ours) against a local keyframe.
//! Descriptors are matched both ways (ratio test + cross-check), solvePnPRansac finds the
//! pose from the remote keyframe's 3-D points and the local pixels, and the refinement of
//! the odometry ([`crate::refine`]) gives the pose its information matrix. A candidate is
//! accepted with at least `min_inliers` inliers, or refused with a typed reason.

use nalgebra::Vector3;

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::{TangentMatrix, SE3};
use serde::{Deserialize, Serialize};

use crate::keyframe::Feature;
use crate::refine::{refine, stereo_point_covariance, Correspondence, Noise};
use doorslam_vision::{hamming, pnp_ransac as pnp_from_points};

/// Thresholds of [`verify`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VerifyConfig {
    /// Best match below this fraction of the second best (Lowe's ratio test).
    pub ratio: f64,
    /// Largest Hamming distance of a match (of 256 bits).
    pub max_hamming: u32,
    /// Fewest inliers of an accepted closure. The paper uses 5; with a few hundred
    /// features, random matches reach 5 RANSAC inliers too often, so the default asks more.
    pub min_inliers: usize,
    pub ransac_threshold_px: f64,
    pub ransac_iterations: i32,
    /// Noise model of the refinement (as the odometry's).
    pub pixel_sigma_px: f64,
    pub disparity_sigma_px: f64,
    /// As the odometry's (`VoConfig`): a-posteriori variance factor, rig scale σ.
    pub posterior_variance: bool,
    pub scale_sigma: f64,
    pub rotation_sigma_deg: f64,
    pub translation_sigma_m: f64,
    /// χ² (3 dof) above which a refined match is an outlier.
    pub outlier_chi2: f64,
}

impl Default for VerifyConfig {
    fn default() -> Self {
        Self {
            ratio: 0.8,
            max_hamming: 64,
            min_inliers: 15,
            ransac_threshold_px: 2.0,
            ransac_iterations: 200,
            pixel_sigma_px: 0.5,
            disparity_sigma_px: 0.5,
            posterior_variance: true,
            scale_sigma: 0.0075,
            rotation_sigma_deg: 0.03,
            translation_sigma_m: 0.006,
            outlier_chi2: 11.34,
        }
    }
}

/// An accepted closure.
#[derive(Debug, Clone, PartialEq)]
pub struct Verified {
    /// Pose of the local keyframe's camera in the remote keyframe's frame:
    /// `X_remote⁻¹ · X_local` (an edge from the remote keyframe to the local one).
    pub relative: SE3,
    /// Its information (right perturbation, rotation first).
    pub information: TangentMatrix,
    pub inliers: usize,
    /// Cross-checked descriptor matches that went into RANSAC.
    pub matches: usize,
}

/// Why a candidate was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Rejection {
    #[error("too few features ({local} local, {remote} remote, need {needed})")]
    TooFewFeatures {
        local: usize,
        remote: usize,
        needed: usize,
    },
    #[error("a remote feature is not a valid 3-D point in front of the camera (index {index})")]
    BadFeature { index: usize },
    #[error("{matches} descriptor matches, need {needed}")]
    TooFewMatches { matches: usize, needed: usize },
    #[error("PnP-RANSAC found no pose")]
    NoPose,
    #[error("{inliers} inliers, need {needed}")]
    TooFewInliers { inliers: usize, needed: usize },
}

impl Rejection {
    /// The reason's name in JSON output (`doorslam verify --json`).
    pub fn name(&self) -> &'static str {
        match self {
            Rejection::TooFewFeatures { .. } => "too_few_features",
            Rejection::BadFeature { .. } => "bad_feature",
            Rejection::TooFewMatches { .. } => "too_few_matches",
            Rejection::NoPose => "no_pose",
            Rejection::TooFewInliers { .. } => "too_few_inliers",
        }
    }
}

/// For each `a[i]`: the index of its best match in `b` if it passes the ratio test.
fn best_matches(a: &[Feature], b: &[Feature], config: &VerifyConfig) -> Vec<Option<usize>> {
    a.iter()
        .map(|fa| {
            let (mut best, mut second, mut best_j) = (u32::MAX, u32::MAX, 0);
            for (j, fb) in b.iter().enumerate() {
                let d = hamming(&fa.descriptor, &fb.descriptor);
                if d < best {
                    (second, best, best_j) = (best, d, j);
                } else if d < second {
                    second = d;
                }
            }
            let passes = best <= config.max_hamming
                && (second == u32::MAX || (best as f64) < config.ratio * second as f64);
            passes.then_some(best_j)
        })
        .collect()
}

/// Verifies a candidate: `local` are the features of a keyframe seen with the rectified
/// camera `local_calib`, `remote` those of the other keyframe, seen with `remote_calib`
/// (another robot's camera: from its packet, [`crate::packet::from_packet`]).
pub fn verify(
    local_calib: &StereoCalibration,
    local: &[Feature],
    remote_calib: &StereoCalibration,
    remote: &[Feature],
    config: &VerifyConfig,
) -> Result<Verified, Rejection> {
    let calib = local_calib;
    let needed = config.min_inliers.max(4);
    if local.len() < needed || remote.len() < needed {
        return Err(Rejection::TooFewFeatures {
            local: local.len(),
            remote: remote.len(),
            needed,
        });
    }
    // Input from another robot: every point must be usable before any math touches it.
    for (index, f) in remote.iter().chain(local).enumerate() {
        let ok = f.point.iter().chain(&f.pixel).all(|x| x.is_finite()) && f.point[2] > 0.0;
        if !ok {
            return Err(Rejection::BadFeature {
                index: index % remote.len().max(1),
            });
        }
    }
    let forward = best_matches(remote, local, config);
    let backward = best_matches(local, remote, config);
    let pairs: Vec<(usize, usize)> = forward
        .iter()
        .enumerate()
        .filter_map(|(r, m)| m.filter(|&l| backward[l] == Some(r)).map(|l| (r, l)))
        .collect();
    if pairs.len() < needed {
        return Err(Rejection::TooFewMatches {
            matches: pairs.len(),
            needed,
        });
    }
    let points: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|&(r, _)| remote[r].point.map(|x| x as f64).into())
        .collect();
    let pixels: Vec<[f32; 2]> = pairs.iter().map(|&(_, l)| local[l].pixel).collect();
    let (pose, ransac_inliers) = pnp_from_points(
        &points,
        &pixels,
        calib,
        config.ransac_iterations,
        config.ransac_threshold_px,
    )
    .ok()
    .flatten()
    .ok_or(Rejection::NoPose)?;
    if ransac_inliers.len() < needed {
        return Err(Rejection::TooFewInliers {
            inliers: ransac_inliers.len(),
            needed,
        });
    }
    let disparity = |c: &StereoCalibration, f: &Feature| c.fx * c.baseline_m / f.point[2] as f64;
    let noise = Noise {
        pixel_sigma_px: config.pixel_sigma_px,
        disparity_sigma_px: config.disparity_sigma_px,
        posterior_variance: config.posterior_variance,
        scale_sigma: config.scale_sigma,
        rotation_sigma_rad: config.rotation_sigma_deg.to_radians(),
        // Two views of one place: no path between them for calibration errors to bend.
        rotation_sigma_rad_per_m: 0.0,
        translation_sigma_per_m: 0.0,
        translation_sigma_m: config.translation_sigma_m,
    };
    let correspondences: Vec<Correspondence> = pairs
        .iter()
        .zip(&points)
        .map(|(&(r, l), p)| {
            let fr = &remote[r];
            Correspondence {
                point: *p,
                // The remote point's covariance comes from the remote camera's noise.
                point_covariance: stereo_point_covariance(
                    remote_calib,
                    &noise,
                    fr.pixel[0] as f64,
                    fr.pixel[1] as f64,
                    disparity(remote_calib, fr),
                ),
                pixel: [local[l].pixel[0] as f64, local[l].pixel[1] as f64],
                disparity: Some(disparity(calib, &local[l])),
            }
        })
        .collect();
    let refined = refine(
        calib,
        &noise,
        &correspondences,
        pose,
        &ransac_inliers,
        config.outlier_chi2,
        needed,
    )
    .ok_or(Rejection::TooFewInliers {
        inliers: ransac_inliers.len(),
        needed,
    })?;
    Ok(Verified {
        relative: refined.pose,
        information: refined.information,
        inliers: refined.inliers.len(),
        matches: pairs.len(),
    })
}
