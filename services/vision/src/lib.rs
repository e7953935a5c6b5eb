//! # doorslam-vision
//!
//! The one place for image-level vision code, shared by the front-end (odometry,
//! verification) and place recognition (bag-of-words descriptors); neither of them
//! reaches OpenCV's feature code any other way.
//!
//! - [`image`]: borrowed grayscale images ([`Gray`]) and image files;
//! - [`detect`]: GFTT / FAST / ORB keypoints, 32-byte ORB descriptors, a stereo frame's
//!   features ([`Extractor`]);
//! - [`stereo`]: sub-pixel row disparities on rectified pairs, triangulation and its
//!   Jacobian;
//! - [`klt`]: pyramidal Lucas-Kanade tracking seeded by a guess;
//! - [`pnp`], PnP-RANSAC.

pub mod config;
pub mod detect;
pub mod error;
pub mod image;
pub mod klt;
pub mod pnp;
pub mod stereo;

pub use config::{Detector, FeatureConfig};
pub use detect::{
    detect_gftt, detect_orb, detect_orb_gray, hamming, Corner, Extractor, FrameFeature,
    FrameFeatures, OrbFeatures, ORB_EDGE,
};
pub use error::VisionError;
pub use image::{load_gray, Gray};
pub use klt::{KltConfig, KltFailure, KltScratch, Pyramid, Tracked};
pub use pnp::pnp_ransac;
pub use stereo::{match_along_row, refine_disparity, triangulate, triangulation_jacobian};

/// Re-exported so callers use the exact OpenCV binding this crate was built against.
pub use opencv;

/// Sets OpenCV's worker thread count for the process (1: the robot's budget is per core).
pub fn set_threads(threads: usize) -> Result<(), VisionError> {
    opencv::core::set_num_threads(threads as i32).map_err(error::cv_error("setNumThreads"))
}
