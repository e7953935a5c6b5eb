//! The one error type of the benchmark.

use std::io;

use crate::Transport;

pub(crate) type Result<T, E = BenchError> = std::result::Result<T, E>;

/// Everything that can stop a run, a case or the peer process. The source chain holds
/// the cause; [`BenchError::chain`] spells the whole chain on one line.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// An option out of its range; names the [`crate::IpcOptions`] field.
    #[error("invalid option {option}: {reason}")]
    InvalidOption {
        option: &'static str,
        reason: &'static str,
    },
    /// The process could not be pinned to the CPU it was given.
    #[error("pin the {process} to CPU {cpu}")]
    PinCpu {
        process: &'static str,
        cpu: usize,
        #[source]
        source: io::Error,
    },
    /// A transport's publisher half could not be opened.
    #[error("open the {transport} publisher")]
    OpenPublisher {
        transport: Transport,
        #[source]
        source: Box<BenchError>,
    },
    /// A system call or socket operation failed; `what` says which.
    #[error("{what}")]
    Io {
        what: String,
        #[source]
        source: io::Error,
    },
    /// The services' iceoryx2 channel (node, ports, send, receive).
    #[error(transparent)]
    Ipc(#[from] doorslam_ipc::IpcError),
    /// A received iceoryx2 frame whose header does not match its images.
    #[error("received frame")]
    Frame(#[source] doorslam_ipc::FrameError),
    /// A Zenoh session could not be opened.
    #[error(transparent)]
    Team(#[from] doorslam_team::TeamError),
    /// A Zenoh call failed (Zenoh's errors are opaque: kept as text).
    #[error("{what}: {reason}")]
    Zenoh { what: String, reason: String },
    /// A transport saw something it cannot carry on with (a malformed or oversized
    /// frame, a peer that never connected, a descriptor that was not inherited).
    #[error("{0}")]
    Transport(String),
    /// The peer process did not start, say what it should in time, or exit cleanly.
    #[error("{0}")]
    Peer(String),
    /// The peer's report line is not the JSON of a [`crate::PeerReport`] ("parse"), or
    /// the report could not be written as JSON ("serialize").
    #[error("{0} the peer's report")]
    PeerReport(&'static str, #[source] serde_json::Error),
}

impl BenchError {
    pub(crate) fn io(what: impl Into<String>) -> impl FnOnce(io::Error) -> Self {
        let what = what.into();
        move |source| BenchError::Io { what, source }
    }

    pub(crate) fn zenoh<E: std::fmt::Display>(what: impl Into<String>) -> impl FnOnce(E) -> Self {
        let what = what.into();
        move |e| BenchError::Zenoh {
            what,
            reason: e.to_string(),
        }
    }

    /// This error and its causes, outermost first, joined by ": " (what a failed case
    /// reports in its row).
    pub fn chain(&self) -> String {
        let mut s = self.to_string();
        let mut source = std::error::Error::source(self);
        while let Some(e) = source {
            s.push_str(": ");
            s.push_str(&e.to_string());
            source = e.source();
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chain_names_every_cause_once() {
        let inner = BenchError::Io {
            what: "eventfd".into(),
            source: io::Error::from_raw_os_error(libc::EMFILE),
        };
        let e = BenchError::OpenPublisher {
            transport: Transport::EventfdFloor,
            source: Box::new(inner),
        };
        let chain = e.chain();
        assert!(
            chain.starts_with("open the eventfd_floor publisher: eventfd: "),
            "{chain}"
        );
        assert_eq!(chain.matches("eventfd:").count(), 1, "{chain}");
    }
}
