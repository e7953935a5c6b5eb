//! # doorslam-rendezvous
//!
//! The robot's side of a rendezvous (paper §III-B, §III-C): what the team link's protocol
//! (`doorslam-team`) calls into on a real robot, and the team service process that wires
//! it to the robot's other services over iceoryx2.
//!
//! - [`pieces`]: this robot's place descriptors and their matching on the int8 wire form
//!   (place recognition's matcher), PnP-RANSAC verification of the peers' packets against
//!   own keyframes (the front-end's verifier), and the relay to the back-end (closures,
//!   peers present, the distributed back-end's messages) — plain state, tested with values;
//! - [`run`]: `doorslam service team` with those pieces: keyframes and descriptors in,
//!   closures and relayed messages out;
//! - [`store`]: own keyframes' verification packets and descriptors kept on disk, so a
//!   restarted robot still offers its keyframes from before the restart;
//! - [`features`]: own keyframes' features, a bounded number in memory, the rest read back
//!   from the store;
//! - [`own_loops`]: the robot's own loop closures, through the same candidate chain and
//!   PnP, to the back-end (PCM among them there);
//! - [`chain_eval`]: the same chain offline against ground truth (`place eval --verify`).
//!
//! A crate of its own because it composes services (front-end, place recognition, team
//! link) that do not depend on each other; only this glue does.

pub mod chain_eval;
pub mod features;
pub mod own_loops;
pub mod pieces;
pub mod run;
pub mod store;

pub use pieces::{MatchSettings, PiecesStats, Shared};
pub use run::{run, IpcSide, RendezvousSection, RobotPieces};
