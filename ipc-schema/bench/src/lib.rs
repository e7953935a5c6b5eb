//! # doorslam-ipc-bench
//!
//! The benchmark behind `doorslam bench ipc`: the on-robot channel of `doorslam-ipc`
//! (its iceoryx2 [`Sender`](doorslam_ipc::Sender) / [`Receiver`](doorslam_ipc::Receiver),
//! subscriber polling or event-driven) side by side with an eventfd and a Unix-datagram
//! wake-up floor, Zenoh shared memory and a Unix socket, with the subscriber in a second
//! process, reporting latency, throughput, zero-copy and CPU at 30 Hz.
//!
//! A crate of its own because it needs Zenoh, which the lightweight `doorslam-ipc` (linked
//! by every service) must not pull in.
//!
//! - [`run_ipc`] is the publisher side: for every resolution, round and [`Transport`] it
//!   starts a peer process ([`IpcOptions::peer`]: the caller's binary re-executed with a
//!   hidden subcommand), measures, and returns an [`IpcReport`] (serde: the `--json` form;
//!   [`IpcReport::table`]: the human one).
//! - [`run_peer`] is that subcommand's body: it receives until the end marker and prints
//!   its [`PeerReport`]. The peer's arguments are [`PeerSpec::to_args`]; the caller parses
//!   them back into a [`PeerSpec`].

mod child;
mod error;
mod ipc;
mod measure;
mod peer;
mod report;
mod transports;

pub use error::BenchError;
pub use ipc::{run as run_ipc, IpcOptions, PeerCommand, LATENCY_PACE, PACED_HZ, RESOLUTIONS};
pub use measure::{LatencySummary, Mapping};
pub use peer::{run_peer, PeerReport, PeerSpec, PhaseReport};
pub use report::{IpcReport, Machine, ResultRow, Settings, TargetCheck};
pub use transports::{PeerEndpoint, Transport, UnknownTransport};
