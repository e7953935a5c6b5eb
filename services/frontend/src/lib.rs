//! # doorslam-frontend
//!
//! Stereo visual odometry with OpenCV: features, stereo depth, tracking, keyframes, and
//! PnP-RANSAC geometric verification of loop-closure candidates (paper §III-A, §III-C).
//!
//! Landed so far: [`features`], image loading and GFTT/ORB feature detection with
//! 32-byte ORB descriptors, the inputs of every later stage.

pub mod features;

pub use features::{detect_gftt, detect_orb, load_gray, FrontendError, OrbFeatures};

/// Re-exported so callers use the exact OpenCV binding this crate was built against.
pub use opencv;
