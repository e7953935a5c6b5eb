//! # doorslam-ipc
//!
//! The types that cross process boundaries *inside* one robot, over iceoryx2 shared
//! memory. Every type here is `#[repr(C)]`, fixed-size and [`ZeroCopySend`]: a publisher
//! loans an uninitialized sample, writes it in place once, and subscribers read the
//! publisher's memory. A stereo pair is never serialized or copied between processes.
//! The messages that cross *between* robots are the exception, in [`wire`].
//!
//! - [`shm`]: the payload types ([`StereoFrame`], ...) and their compile-time maxima.
//! - [`service`]: service names per robot (`doorslam/<robot>/<topic>`), opening the
//!   services with the settings every process must agree on, and stale-resource cleanup.
//!
//! - [`channel`]: typed senders/receivers with event notification, the back-pressure
//!   policy (frames lossy, everything else reliable) and crash recovery (history).
//! - [`wire`]: the inter-robot messages (Zenoh): versioned header, compact layouts,
//!   bounded decoding that validates with `doorslam-geometry`'s rules.
//!
//! Poses and information matrices travel as plain arrays (`[x y z qx qy qz qw]`, the
//! 21-value upper triangle); their conversions and the rules they must satisfy live in
//! `doorslam-geometry` (`pose`, `information`); the shared-memory types use no math from
//! it, the wire messages validate with it.

pub mod channel;
pub mod lifecycle;
pub mod service;
pub mod shm;
pub mod wire;

pub use channel::{Receiver, Sender, RELIABLE_BUFFER, RELIABLE_HISTORY};
pub use lifecycle::{sd_notify, Lifecycle};
pub use service::{
    cleanup_dead_nodes, create_node, open_frames, service_name, FramePublisher, FrameSubscriber,
    IpcError, Topic,
};
pub use shm::{
    EnvelopeEvent, EnvelopeTooLong, Feature, FrameError, FrameHeader, ImageWriter, Keyframe,
    KeyframeSource, LoopClosure, OdometryEdge, PlaceDescriptor, PoseEstimate, StereoFrame,
    WireEnvelope, FRAME_HAS_TRUTH, MAX_DESCRIPTOR_DIM, MAX_ENVELOPE_BYTES, MAX_FRAME_HEIGHT,
    MAX_FRAME_PIXELS, MAX_FRAME_WIDTH, MAX_KEYFRAME_FEATURES, SCHEMA_VERSION,
};

/// Re-exported so service crates use the exact iceoryx2 this schema was built against.
pub use iceoryx2;
