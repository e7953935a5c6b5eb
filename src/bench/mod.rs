//! Benchmarks of the on-robot pipeline, run by `doorslam bench`.
//!
//! `ipc`: the intra-robot transports side by side (iceoryx2 polling and event-driven,
//! an eventfd wake-up floor, Zenoh shared memory, a Unix socket), with the subscriber in
//! a second process, reporting latency, throughput, zero-copy and CPU at 30 Hz.

mod child;
mod ipc;
mod measure;
pub mod pcm_sweep;
mod peer;
mod report;
mod transports;

pub use ipc::{run as run_ipc, IpcOptions, LATENCY_PACE, PACED_HZ, RESOLUTIONS};
pub use peer::{run_peer, PeerReport, PeerSpec};
pub use report::{IpcReport, Machine, ResultRow, Settings, TargetCheck};
pub use transports::{PeerEndpoint, Transport};
