//! Inter-robot wire messages: a compact, versioned binary format for everything that
//! crosses between robots over the team link (Zenoh), with bounded decoding.
//!
//! Every message is a [`Header`] (version, kind, sender id, epoch, sequence) and one
//! [`Body`] ([`Kind`]). Integers that count or name things are LEB128 varints; fixed-width
//! values are little-endian. Decoding untrusted bytes ([`Message::decode`]):
//!
//! - refuses any version but [`WIRE_VERSION`] ([`WireError::UnknownVersion`]) and unknown
//!   kinds, before reading anything else;
//! - checks every count against its limit (`MAX_*`) *and* against the bytes left before
//!   allocating, so no allocation is sized by the sender beyond what it actually sent;
//! - checks every value where it enters: poses with `doorslam_geometry::pose_from_array`,
//!   information with `doorslam_geometry::check_information` (positive definite), keys
//!   with `doorslam_geometry::key::symbol`, robot ids with robot.toml's rule;
//! - refuses trailing bytes; every encoding is canonical, so a message that decodes
//!   re-encodes to the same bytes.
//!
//! [`Message::encoded_len`] is exactly the length [`Message::encode`] produces (the same
//! encoder, writing to a counter), for the bandwidth ledger. No field holds a time.
//!
//! Sizes (measured by `tests/wire.rs`, targets from the paper's Table II): a place
//! descriptor 135 bytes per keyframe in a batch of 10, header share included (≤ 140); a
//! pose estimate 48 bytes alone in a message, 32 per pose in a round of 20 (≤ 100); a loop
//! closure 96 bytes alone in a message (≤ 100); a verification feature 38 bytes (pixel,
//! disparity, 32-byte ORB descriptor) after a 20-byte camera, so the front-end's packet of
//! at most 500 features is ≤ 19.1 kB (target ≤ 20 kB; the paper's was 59.5 kB).

mod backend;
mod codec;
mod error;
mod message;
mod supersede;
mod types;

pub use backend::{
    GraphEdge, Route, SeparatorGraph, TeamMap, Trajectory, MAX_GRAPH_EDGES, MAX_TRAJECTORY_POSES,
};
pub use codec::{f16_from_f32, f32_from_f16};
pub use error::WireError;
pub use message::Descriptors;
pub use message::{
    Ack, Body, Estimate, Header, Hello, Kind, LoopClosure, LoopClosures, Match, Matches, Message,
    PoseEstimate, PoseEstimates, SolveStop, Stage, VerificationFeatures, ESTIMATES_CONVERGED,
    ESTIMATES_STOP_MASK, MAX_ACK_RANGES, MAX_DESCRIPTORS, MAX_FEATURES, MAX_LOOP_CLOSURES,
    MAX_MATCHES, MAX_MESSAGE_BYTES, MAX_POSE_ESTIMATES, WIRE_VERSION,
};
pub use supersede::Slot;
pub use types::{
    CompactPose, Descriptor, Information, Pose, QuantizeError, RelaxedRotation, RobotId,
    VerificationCamera, VerificationFeature, COMPACT_POSE_MIN_BYTES, COMPACT_QUATERNION_MAX,
    COMPACT_QUATERNION_STEPS, COMPACT_ROTATION_ERROR_RAD, COMPACT_TRANSLATION_STEP_M,
    DESCRIPTOR_DIM, DISPARITY_STEPS, FEATURE_BYTES, INFORMATION_BYTES, MAX_COMPACT_TRANSLATION_M,
    MAX_ROBOT_ID_LEN, PIXEL_STEPS, POSE_BYTES, RELAXED_ROTATION_BYTES, RELAXED_ROTATION_STEP,
    VERIFICATION_CAMERA_BYTES,
};
