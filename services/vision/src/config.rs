//! Settings of the feature extractor and the row stereo matcher.

use serde::{Deserialize, Serialize};

/// Which detector finds the left image's keypoints; descriptors are always 32-byte ORB.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Detector {
    /// Shi-Tomasi corners refined to sub-pixel (the paper's GFTT+ORB choice).
    #[default]
    Gftt,
    /// FAST-9 corners, strongest first.
    Fast,
    /// ORB's own oriented FAST on an image pyramid (scale-invariant, slower).
    Orb,
}

/// What [`crate::Extractor`] and [`crate::match_along_row`] need (the odometry's
/// configuration carries the same fields; its defaults are these).
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureConfig {
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
    /// Refine each block match's disparity by Gauss-Newton on the image gradients
    /// ([`crate::refine_disparity`]) instead of keeping the parabola's: the parabola
    /// through three SAD costs pulls sub-pixel disparities towards whole pixels.
    pub stereo_gradient_refine: bool,
}

impl Default for FeatureConfig {
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
        }
    }
}
