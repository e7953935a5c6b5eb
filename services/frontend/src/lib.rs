//! # doorslam-frontend
//!
//! Stereo visual odometry with OpenCV: features, stereo depth, tracking, keyframes, and
//! PnP-RANSAC geometric verification of loop-closure candidates (paper §III-A, §III-C).
//!
//! - [`features`]: image loading, GFTT/ORB detection with 32-byte ORB descriptors;
//! - [`stereo`]: per-frame features with sub-pixel row disparities and 3-D points;
//! - [`refine`]: Gauss-Newton on the stereo reprojection error and its information matrix;
//! - [`vo`]: the odometry ([`StereoVo`]): tracking, keyframes, lost / re-init / segments;
//! - [`keyframe`]: its outputs, the contract for downstream services;
//! - [`verify`]: geometric verification of loop-closure candidates (PnP-RANSAC);
//! - [`packet`]: the verification feature packet sent between robots (wire form);
//! - [`run`]: the odometry over a dataset folder, with timing and drift;
//! - [`service`]: the robot's `frontend` service: frames in, keyframes and odometry edges
//!   out over iceoryx2, lost / segments / restarts, status.

pub mod config;
pub mod features;
pub mod keyframe;
pub mod packet;
pub mod refine;
pub mod run;
pub mod service;
pub mod stereo;
pub mod verify;
pub mod verify_bench;
pub mod vo;

pub use config::{ConfigError, Detector, VoConfig};
pub use features::{detect_gftt, detect_orb, load_gray, FrontendError, OrbFeatures};
pub use keyframe::{Feature, Keyframe, OdometryEdge, SegmentLink};
pub use packet::{from_packet, to_packet, PacketError, MAX_PACKET_FEATURES};
pub use stereo::Gray;
pub use verify::{verify, Rejection, Verified, VerifyConfig};
pub use vo::{FrameResult, LostReason, StereoVo, TrackState, VoStats};

/// Re-exported so callers use the exact OpenCV binding this crate was built against.
pub use opencv;
