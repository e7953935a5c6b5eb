//! Tuning of the stereo visual odometry, with serde defaults (a `[frontend]` table of
//! robot.toml may set any subset of the fields).

use doorslam_geometry::TangentMatrix;
use serde::{Deserialize, Serialize};

pub use doorslam_vision::Detector;
use doorslam_vision::{FeatureConfig, KltConfig};

/// Every threshold of [`crate::StereoVo`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VoConfig {
    pub detector: Detector,
    /// Keypoints detected per left image.
    pub max_features: usize,
    /// Smallest distance between two GFTT corners (px).
    pub min_feature_distance_px: f64,
    /// GFTT quality level (fraction of the strongest corner's score).
    pub gftt_quality: f64,
    /// FAST threshold (intensity difference).
    pub fast_threshold: i32,
    /// Half size of the stereo block-matching window (px): (2r+1)² pixels.
    pub stereo_window_radius: usize,
    /// Largest disparity searched along the row (px).
    pub max_disparity_px: usize,
    /// Smallest accepted disparity (px); further points carry almost no depth.
    pub min_disparity_px: f64,
    /// The best block cost must be below this fraction of the best one away from it.
    pub stereo_uniqueness: f64,
    /// Mean absolute intensity difference above which a block match is refused.
    pub stereo_max_mean_abs_diff: f64,
    /// Refine block-matched disparities on the image gradients (see
    /// `doorslam_vision::refine_disparity`); off keeps the parabola's sub-pixel value.
    pub stereo_gradient_refine: bool,
    /// Standard deviation of a feature's pixel position (px), both axes.
    pub pixel_sigma_px: f64,
    /// Standard deviation of a sub-pixel disparity (px).
    pub disparity_sigma_px: f64,
    /// Scale each edge's information down by the refinement's a-posteriori variance
    /// factor (χ² per degree of freedom) when the residuals exceed the noise model.
    pub posterior_variance: bool,
    /// Errors every feature of an edge shares, which the residuals cannot show: the rig's
    /// calibration and rectification (and, against a dataset's ground truth, the ground
    /// truth's own noise). Added to each edge's covariance: the relative uncertainty of the
    /// rig's scale (baseline, focal length) along the translation, a rotation (degrees
    /// per axis, plus degrees per metre the edge spans: these errors bend the path the
    /// further it goes) and a translation (m per axis). Set to 0 for a perfectly
    /// calibrated (simulated) camera; the defaults are fitted to the KITTI 06 clip's
    /// per-frame and 3-frame errors (BENCHMARKS.md, "Stereo VO at drone speed").
    pub scale_sigma: f64,
    pub rotation_sigma_deg: f64,
    /// ... and a rotation error growing with the edge's length (degrees per m).
    pub rotation_sigma_deg_per_m: f64,
    pub translation_sigma_m: f64,
    /// ... and a translation error per axis growing with the edge's length (m per m).
    pub translation_sigma_per_m: f64,
    /// The camera's longest exposure (s): motion blur makes an image show the camera's
    /// mean pose over the exposure, not the mid-exposure pose its stamp names. The two
    /// differ when the rotation rate changes within the exposure (a turn starting or
    /// stopping: up to `|Δω| · exposure / 8`), an error every feature of the keyframe
    /// shares. Each keyframe's rotation gets that σ along its rotation axis, with `|Δω|`
    /// up to its angular speed; 0 for a camera that does not blur (BENCHMARKS.md, "Stereo
    /// VO at drone speed": the NEES of fast turns).
    pub blur_exposure_s: f64,
    /// Landmarks tracked from frame to frame (new ones are added at keyframes, strongest
    /// corners first, away from the tracked ones).
    pub max_tracks: usize,
    /// Pyramidal KLT: half window (px), pyramid levels, and the largest mean absolute
    /// difference (DN) of the brightness-matched windows at full resolution.
    pub klt_window_radius: usize,
    pub klt_levels: usize,
    pub klt_max_residual_dn: f64,
    /// Smallest eigenvalue of a window's gradient matrix per pixel ((DN/px)²): flatter
    /// windows are not tracked.
    pub klt_min_eigenvalue: f64,
    /// A point tracked back from the current frame must land within this (px) of where
    /// it started (forward-backward consistency).
    pub klt_max_back_error_px: f64,
    /// Of the tracked points, at least this fraction must be inliers of the pose: fewer
    /// means the frame does not show what the track expected (another place, a swapped
    /// camera), a loss rather than a pose.
    pub min_inlier_fraction: f64,
    /// The pose must agree with the constant-velocity prediction within this rotation
    /// (degrees) and translation (m), each growing with the time since the last frame:
    /// `bound × max(1, dt / 0.1 s)²` (a drone cannot change its motion faster; measured on
    /// simulated flights at 5-7 m/s: 99 % of frames within 4° and 8 cm). Not checked on a
    /// segment's first frame, whose motion is unknown.
    pub max_prediction_error_deg: f64,
    pub max_prediction_error_m: f64,
    /// Keyframes in the local bundle adjustment's window (the oldest one is held fixed),
    /// and its Levenberg-Marquardt steps at most.
    pub window_keyframes: usize,
    pub window_iterations: usize,
    /// Unused since the tracking is KLT (kept so existing robot.toml files still load):
    /// the search radii and descriptor thresholds of the former frame-to-keyframe
    /// descriptor matching.
    pub search_radius_px: f64,
    pub wide_search_radius_px: f64,
    /// Largest Hamming distance of an accepted descriptor match (of 256 bits).
    pub max_hamming: u32,
    /// Best match must be below this fraction of the second best in the window.
    pub match_ratio: f64,
    /// RANSAC reprojection threshold (px) and iterations of solvePnPRansac.
    pub ransac_threshold_px: f64,
    pub ransac_iterations: i32,
    /// Fewest inliers of a tracked frame; below it the frame is lost.
    pub min_inliers: usize,
    /// Fewest 3-D points to start a segment or make a keyframe.
    pub min_keyframe_points: usize,
    /// χ² (3 dof) above which a refined correspondence is an outlier.
    pub outlier_chi2: f64,
    /// A new keyframe when the tracked fraction of the keyframe's points falls below this...
    pub keyframe_min_tracked_fraction: f64,
    /// ... or the camera moved further than this from the keyframe (m) ...
    pub keyframe_max_distance_m: f64,
    /// ... or turned more than this (degrees) ...
    pub keyframe_max_rotation_deg: f64,
    /// ... or the median image motion of the tracked points exceeds this (px).
    pub keyframe_max_parallax_px: f64,
    /// Images darker/brighter than this mean, or flatter than this standard deviation, are
    /// unusable (blank, over-exposed, lens cap).
    pub min_mean_intensity: f64,
    pub max_mean_intensity: f64,
    pub min_intensity_std: f64,
    /// A gap between frame stamps longer than this (s) loses the track: the motion prior
    /// means nothing after the camera stopped or frames were dropped for that long.
    pub max_frame_gap_s: f64,
    /// Implausible speed (m/s): a faster refined motion is refused, never emitted.
    pub max_speed_mps: f64,
    /// The weak prior linking a new segment to the previous one: standard deviations of
    /// its rotation (rad) and translation (m) per second lost (and at least one second).
    pub segment_prior_rotation_sigma: f64,
    pub segment_prior_translation_sigma_m: f64,
    /// OpenCV worker threads (1: the robot's budget is per core).
    pub threads: usize,
}

impl Default for VoConfig {
    fn default() -> Self {
        Self {
            detector: Detector::Gftt,
            max_features: 1000,
            min_feature_distance_px: 8.0,
            gftt_quality: 0.01,
            fast_threshold: 20,
            stereo_window_radius: 3,
            max_disparity_px: 128,
            min_disparity_px: 1.0,
            stereo_uniqueness: 0.9,
            stereo_max_mean_abs_diff: 25.0,
            stereo_gradient_refine: true,
            pixel_sigma_px: 0.5,
            disparity_sigma_px: 0.5,
            posterior_variance: true,
            scale_sigma: 0.0075,
            rotation_sigma_deg: 0.02,
            rotation_sigma_deg_per_m: 0.025,
            translation_sigma_m: 0.003,
            translation_sigma_per_m: 0.005,
            blur_exposure_s: 0.02,
            max_tracks: 600,
            klt_window_radius: 5,
            klt_levels: 4,
            klt_max_residual_dn: 14.0,
            klt_min_eigenvalue: 0.5,
            klt_max_back_error_px: 1.0,
            min_inlier_fraction: 0.3,
            max_prediction_error_deg: 8.0,
            max_prediction_error_m: 0.3,
            window_keyframes: 6,
            window_iterations: 6,
            search_radius_px: 20.0,
            wide_search_radius_px: 80.0,
            max_hamming: 64,
            match_ratio: 0.9,
            ransac_threshold_px: 2.0,
            ransac_iterations: 100,
            min_inliers: 15,
            min_keyframe_points: 40,
            outlier_chi2: 11.34,
            keyframe_min_tracked_fraction: 0.5,
            keyframe_max_distance_m: 3.0,
            keyframe_max_rotation_deg: 10.0,
            keyframe_max_parallax_px: 60.0,
            min_mean_intensity: 10.0,
            max_mean_intensity: 245.0,
            min_intensity_std: 4.0,
            max_frame_gap_s: 0.5,
            max_speed_mps: 60.0,
            segment_prior_rotation_sigma: 0.2,
            segment_prior_translation_sigma_m: 2.0,
            threads: 1,
        }
    }
}

/// A configuration value outside its range; names the field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("frontend config: {field} = {value}: {reason}")]
pub struct ConfigError {
    pub field: &'static str,
    pub value: String,
    pub reason: &'static str,
}

impl VoConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field, value: &dyn ToString, reason| ConfigError {
            field,
            value: value.to_string(),
            reason,
        };
        let positive = [
            ("min_feature_distance_px", self.min_feature_distance_px),
            ("gftt_quality", self.gftt_quality),
            ("min_disparity_px", self.min_disparity_px),
            ("stereo_uniqueness", self.stereo_uniqueness),
            ("stereo_max_mean_abs_diff", self.stereo_max_mean_abs_diff),
            ("pixel_sigma_px", self.pixel_sigma_px),
            ("disparity_sigma_px", self.disparity_sigma_px),
            ("search_radius_px", self.search_radius_px),
            ("wide_search_radius_px", self.wide_search_radius_px),
            ("match_ratio", self.match_ratio),
            ("ransac_threshold_px", self.ransac_threshold_px),
            ("outlier_chi2", self.outlier_chi2),
            ("keyframe_max_distance_m", self.keyframe_max_distance_m),
            ("klt_max_residual_dn", self.klt_max_residual_dn),
            ("klt_min_eigenvalue", self.klt_min_eigenvalue),
            ("klt_max_back_error_px", self.klt_max_back_error_px),
            ("max_prediction_error_deg", self.max_prediction_error_deg),
            ("max_prediction_error_m", self.max_prediction_error_m),
            ("keyframe_max_rotation_deg", self.keyframe_max_rotation_deg),
            ("keyframe_max_parallax_px", self.keyframe_max_parallax_px),
            ("max_frame_gap_s", self.max_frame_gap_s),
            ("max_speed_mps", self.max_speed_mps),
            (
                "segment_prior_rotation_sigma",
                self.segment_prior_rotation_sigma,
            ),
            (
                "segment_prior_translation_sigma_m",
                self.segment_prior_translation_sigma_m,
            ),
        ];
        for (field, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(bad(field, &value, "must be finite and > 0"));
            }
        }
        for (field, value) in [
            ("stereo_uniqueness", self.stereo_uniqueness),
            ("match_ratio", self.match_ratio),
            (
                "keyframe_min_tracked_fraction",
                self.keyframe_min_tracked_fraction,
            ),
            ("min_inlier_fraction", self.min_inlier_fraction),
        ] {
            if !(0.0..=1.0).contains(&value) {
                return Err(bad(field, &value, "must be in [0, 1]"));
            }
        }
        if !(10..=20_000).contains(&self.max_features) {
            return Err(bad(
                "max_features",
                &self.max_features,
                "must be 10..=20000",
            ));
        }
        if !(1..=10).contains(&self.stereo_window_radius) {
            return Err(bad(
                "stereo_window_radius",
                &self.stereo_window_radius,
                "must be 1..=10",
            ));
        }
        if !(4..=512).contains(&self.max_disparity_px) {
            return Err(bad(
                "max_disparity_px",
                &self.max_disparity_px,
                "must be 4..=512",
            ));
        }
        if !(self.min_inliers..=20_000).contains(&self.max_tracks) {
            return Err(bad(
                "max_tracks",
                &self.max_tracks,
                "must be min_inliers..=20000",
            ));
        }
        if !(1..=15).contains(&self.klt_window_radius) {
            return Err(bad(
                "klt_window_radius",
                &self.klt_window_radius,
                "must be 1..=15",
            ));
        }
        if !(2..=20).contains(&self.window_keyframes) {
            return Err(bad(
                "window_keyframes",
                &self.window_keyframes,
                "must be 2..=20",
            ));
        }
        if !(1..=50).contains(&self.window_iterations) {
            return Err(bad(
                "window_iterations",
                &self.window_iterations,
                "must be 1..=50",
            ));
        }
        if !(1..=8).contains(&self.klt_levels) {
            return Err(bad("klt_levels", &self.klt_levels, "must be 1..=8"));
        }
        if self.max_hamming > 256 {
            return Err(bad("max_hamming", &self.max_hamming, "must be <= 256"));
        }
        if !(1..=100_000).contains(&self.ransac_iterations) {
            return Err(bad(
                "ransac_iterations",
                &self.ransac_iterations,
                "must be 1..=100000",
            ));
        }
        if self.min_inliers < 6 {
            return Err(bad("min_inliers", &self.min_inliers, "must be >= 6"));
        }
        if self.min_keyframe_points < self.min_inliers {
            return Err(bad(
                "min_keyframe_points",
                &self.min_keyframe_points,
                "must be >= min_inliers",
            ));
        }
        if !(self.min_mean_intensity.is_finite()
            && self.max_mean_intensity.is_finite()
            && self.min_mean_intensity < self.max_mean_intensity)
        {
            return Err(bad(
                "max_mean_intensity",
                &self.max_mean_intensity,
                "must be above min_mean_intensity",
            ));
        }
        if !(self.min_intensity_std.is_finite() && self.min_intensity_std >= 0.0) {
            return Err(bad(
                "min_intensity_std",
                &self.min_intensity_std,
                "must be finite and >= 0",
            ));
        }
        if !(self.rotation_sigma_deg.is_finite() && (0.0..10.0).contains(&self.rotation_sigma_deg))
        {
            return Err(bad(
                "rotation_sigma_deg",
                &self.rotation_sigma_deg,
                "must be in [0, 10)",
            ));
        }
        if !(self.rotation_sigma_deg_per_m.is_finite()
            && (0.0..10.0).contains(&self.rotation_sigma_deg_per_m))
        {
            return Err(bad(
                "rotation_sigma_deg_per_m",
                &self.rotation_sigma_deg_per_m,
                "must be in [0, 10)",
            ));
        }
        if !(self.translation_sigma_per_m.is_finite()
            && (0.0..1.0).contains(&self.translation_sigma_per_m))
        {
            return Err(bad(
                "translation_sigma_per_m",
                &self.translation_sigma_per_m,
                "must be in [0, 1)",
            ));
        }
        if !(self.translation_sigma_m.is_finite()
            && (0.0..10.0).contains(&self.translation_sigma_m))
        {
            return Err(bad(
                "translation_sigma_m",
                &self.translation_sigma_m,
                "must be in [0, 10)",
            ));
        }
        if !(self.blur_exposure_s.is_finite() && (0.0..1.0).contains(&self.blur_exposure_s)) {
            return Err(bad(
                "blur_exposure_s",
                &self.blur_exposure_s,
                "must be in [0, 1)",
            ));
        }
        if !(self.scale_sigma.is_finite() && (0.0..1.0).contains(&self.scale_sigma)) {
            return Err(bad("scale_sigma", &self.scale_sigma, "must be in [0, 1)"));
        }
        if !(1..=64).contains(&self.threads) {
            return Err(bad("threads", &self.threads, "must be 1..=64"));
        }
        if !(0..=255).contains(&self.fast_threshold) {
            return Err(bad(
                "fast_threshold",
                &self.fast_threshold,
                "must be 0..=255",
            ));
        }
        Ok(())
    }
}

impl VoConfig {
    /// The feature extractor's and row stereo's share of the settings.
    pub fn features(&self) -> FeatureConfig {
        FeatureConfig {
            detector: self.detector,
            max_features: self.max_features,
            min_feature_distance_px: self.min_feature_distance_px,
            gftt_quality: self.gftt_quality,
            fast_threshold: self.fast_threshold,
            stereo_window_radius: self.stereo_window_radius,
            max_disparity_px: self.max_disparity_px,
            min_disparity_px: self.min_disparity_px,
            stereo_uniqueness: self.stereo_uniqueness,
            stereo_max_mean_abs_diff: self.stereo_max_mean_abs_diff,
            stereo_gradient_refine: self.stereo_gradient_refine,
        }
    }

    /// The KLT tracker's settings.
    pub fn klt(&self) -> KltConfig {
        KltConfig {
            window_radius: self.klt_window_radius,
            levels: self.klt_levels,
            max_residual_dn: self.klt_max_residual_dn as f32,
            min_eigenvalue: self.klt_min_eigenvalue as f32,
            ..KltConfig::default()
        }
    }

    /// Information of the weak prior that links a new segment to the previous one after
    /// `seconds_lost` (at least one second): the standard deviations grow with the time.
    pub fn segment_prior_information(&self, seconds_lost: f64) -> TangentMatrix {
        let dt = seconds_lost.max(1.0);
        let (sr, st) = (
            self.segment_prior_rotation_sigma * dt,
            self.segment_prior_translation_sigma_m * dt,
        );
        let mut information = TangentMatrix::zeros();
        for k in 0..3 {
            information[(k, k)] = 1.0 / (sr * sr);
            information[(k + 3, k + 3)] = 1.0 / (st * st);
        }
        information
    }
}
