//! # doorslam-frontend
//!
//! Stereo visual odometry: features, stereo depth, tracking, keyframes, and PnP-RANSAC
//! geometric verification of loop-closure candidates (paper §III-A, §III-C). Every image
//! operation (detection, descriptors, row stereo, KLT, PnP) is `doorslam-vision`'s.
//!
//! - [`error`]: the front-end's errors;
//! - [`refine`]: Gauss-Newton on the stereo reprojection error and its information matrix;
//! - [`vo`]: the odometry ([`StereoVo`]): the frame loop (predict, track, estimate and
//!   validate, keyframe), lost / re-init / segments; its stages in `tracking` (KLT of the
//!   landmarks), `motion` (PnP-RANSAC, refinement, checks) and `map` (the landmarks);
//! - [`keyframe`]: its outputs, the contract for downstream services;
//! - [`verify`]: geometric verification of loop-closure candidates (PnP-RANSAC);
//! - [`packet`]: the verification feature packet sent between robots (wire form);
//! - [`run`]: the odometry over a dataset folder, with timing and drift;
//! - [`service`]: the robot's `frontend` service: frames in, keyframes and odometry edges
//!   out over iceoryx2, lost / segments / restarts, status.

mod bundle;
pub mod config;
pub mod error;
pub mod keyframe;
mod map;
mod motion;
pub mod packet;
pub mod refine;
pub mod run;
pub mod service;
mod tracking;
pub mod verify;
pub mod verify_bench;
pub mod vo;

pub use config::{ConfigError, Detector, VoConfig};
pub use doorslam_vision::Gray;
pub use error::FrontendError;
pub use keyframe::{Feature, Keyframe, OdometryEdge, SegmentLink};
pub use packet::{from_packet, to_packet, PacketError, MAX_PACKET_FEATURES};
pub use verify::{verify, Rejection, Verified, VerifyConfig};
pub use vo::{FrameResult, LostByReason, LostReason, StageCpu, StereoVo, TrackState, VoStats};
