//! # doorslam-team
//!
//! The link between robots: Zenoh in peer-to-peer mode. Only compact, versioned messages
//! cross it (descriptors, keypoints for verification, relative poses, separator
//! estimates), and every byte goes through the bandwidth ledger (next wave).
//!
//! Landed so far: [`link`], opening a peer session from a typed config and the key
//! expressions robots publish under.

pub mod link;

pub use link::{key_expr, open_peer, LinkConfig, TeamError};

/// Re-exported so callers use the exact Zenoh this crate was built against.
pub use zenoh;
