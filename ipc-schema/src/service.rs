//! iceoryx2 services of one robot: names, settings and housekeeping.

use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;

use crate::shm::StereoFrame;

/// Errors of the intra-robot transport. iceoryx2's own errors are kept as text
/// with the service they concern, so a log line says which service failed.
#[derive(Debug, thiserror::Error)]
pub enum IpcError {
    #[error("invalid iceoryx2 service name {name:?}: {reason}")]
    Name { name: String, reason: String },
    #[error("iceoryx2 node: {0}")]
    Node(String),
    #[error("iceoryx2 service {service:?}: {reason}")]
    Service { service: String, reason: String },
    #[error("iceoryx2 service {service:?} was created by a process built with another doorslam-ipc schema (this build: v{}); restart all services of the robot from the same build", crate::shm::SCHEMA_VERSION)]
    SchemaMismatch { service: String },
    #[error("iceoryx2 service {service:?}: every sample is in flight (receivers hold them all); nothing was sent")]
    NoRoom { service: String },
    #[error("iceoryx2 service {service:?}: could not fill the sample: {reason}")]
    Payload { service: String, reason: String },
    #[error("iceoryx2 domain {domain:?} (environment variable DOORSLAM_IPC_DOMAIN): {reason}")]
    Domain { domain: String, reason: String },
}

/// The topics one robot publishes internally.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Topic {
    Frames,
    Keyframes,
    Odometry,
    Descriptors,
    Closures,
    Estimates,
    /// Team link → back-end: peers present/absent and the back-end messages they sent
    /// ([`crate::WireEnvelope`]).
    TeamIn,
    /// Back-end → team link: the back-end's messages for each peer.
    TeamOut,
}

impl Topic {
    pub fn as_str(self) -> &'static str {
        match self {
            Topic::Frames => "frames",
            Topic::Keyframes => "keyframes",
            Topic::Odometry => "odometry",
            Topic::Descriptors => "descriptors",
            Topic::Closures => "closures",
            Topic::Estimates => "estimates",
            Topic::TeamIn => "team-in",
            Topic::TeamOut => "team-out",
        }
    }

    /// Samples a subscriber buffers and a publisher keeps for late subscribers, as
    /// (buffer, history). Frames: the two newest, no history. The relay between the team
    /// link and the back-end carries large envelopes (256 KiB each, see
    /// [`crate::WireEnvelope`]) and keeps no history: both ends announce themselves when
    /// they (re)start instead, and an envelope replayed to a restarted process would be
    /// handled twice. Everything else: [`crate::RELIABLE_BUFFER`] and half of it.
    pub fn buffers(self) -> (usize, usize) {
        match self {
            Topic::Frames => (2, 0),
            Topic::TeamIn | Topic::TeamOut => (64, 0),
            _ => (crate::RELIABLE_BUFFER, crate::RELIABLE_HISTORY),
        }
    }

    /// Whether a slow consumer may lose samples (only camera frames: newest wins).
    pub fn lossy(self) -> bool {
        matches!(self, Topic::Frames)
    }
}

/// `doorslam/<robot>/<topic>`: one namespace per robot, so several simulated robots
/// can share one machine (HIL) without seeing each other's frames.
pub fn service_name(robot: &str, topic: Topic) -> String {
    format!("doorslam/{robot}/{}", topic.as_str())
}

/// Opens (or creates) the stereo-frame service of `robot`.
///
/// Every process must agree on these settings (the same as [`crate::channel`] uses for
/// [`Topic::Frames`]), so they are set in one place:
/// frames are the one stream where the newest data wins, hence `safe_overflow`
/// (a slow subscriber loses its oldest frame, the camera never blocks).
pub fn open_frames(
    node: &Node<ipc::Service>,
    robot: &str,
) -> Result<PortFactory<ipc::Service, StereoFrame, ()>, IpcError> {
    crate::channel::open::<StereoFrame>(node, robot, Topic::Frames).map(|(_, pubsub, _)| pubsub)
}

/// Creates a node, named after the process's role, after removing the shared memory
/// left behind by processes that died (a crashed service must be restartable).
/// Returns the node and how many dead nodes were cleaned up.
///
/// iceoryx2's own logging is limited to errors: doorslam configures its services in
/// code, so iceoryx2's "no config file was loaded" warning is expected noise.
pub fn create_node(role: &str) -> Result<(Node<ipc::Service>, u64), IpcError> {
    set_log_level(LogLevel::Error);
    let node_name: NodeName = role
        .try_into()
        .map_err(|e| IpcError::Node(format!("invalid node name {role:?}: {e:?}")))?;
    let mut config = Config::default();
    if let Some(prefix) = domain_prefix_from_env()? {
        config.global.prefix = prefix;
    }
    let node = NodeBuilder::new()
        .name(&node_name)
        .config(&config)
        .create::<ipc::Service>()
        .map_err(|e| IpcError::Node(format!("{e:?}")))?;
    let cleaned = cleanup_dead_nodes(&node);
    Ok((node, cleaned))
}

/// The environment variable that puts a process in an iceoryx2 domain of its own.
///
/// Processes see each other's services only within one domain: every file iceoryx2
/// creates is prefixed `iox2_<domain>_`. Unset, a process is in the default domain (the
/// one `doorslam up` and the systemd units use). Two teams simulated on one machine at
/// once (e.g. two `doorslam demo` runs, or tests in parallel) each set their own, so their
/// robots `a` never share a frame service.
pub const DOMAIN_ENV: &str = "DOORSLAM_IPC_DOMAIN";

/// The file prefix of the domain named by [`DOMAIN_ENV`], if set (non-empty).
fn domain_prefix_from_env(
) -> Result<Option<iceoryx2_bb_system_types::file_name::FileName>, IpcError> {
    match std::env::var(DOMAIN_ENV) {
        Ok(d) if d.is_empty() => Ok(None),
        Ok(d) => domain_prefix(&d).map(Some),
        Err(std::env::VarError::NotPresent) => Ok(None),
        Err(std::env::VarError::NotUnicode(_)) => Err(IpcError::Domain {
            domain: format!("{:?}", std::env::var_os(DOMAIN_ENV)),
            reason: "not valid UTF-8".into(),
        }),
    }
}

/// The iceoryx2 file prefix of `domain`: letters, digits, `-` and `_`, at most 32 bytes.
fn domain_prefix(domain: &str) -> Result<iceoryx2_bb_system_types::file_name::FileName, IpcError> {
    let bad = |reason: &str| IpcError::Domain {
        domain: domain.to_string(),
        reason: reason.to_string(),
    };
    if domain.len() > 32 {
        return Err(bad("longer than 32 bytes"));
    }
    if !domain
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
    {
        return Err(bad("only letters, digits, '-' and '_' are allowed"));
    }
    let prefix = format!("iox2_{domain}_");
    iceoryx2_bb_system_types::file_name::FileName::new(prefix.as_bytes())
        .map_err(|e| bad(&format!("{e:?}")))
}

/// Removes stale resources of dead nodes; returns how many were cleaned.
pub fn cleanup_dead_nodes(node: &Node<ipc::Service>) -> u64 {
    node.try_cleanup_dead_nodes().cleanups
}

/// Type aliases so service crates need not spell out iceoryx2's generics.
pub type FramePublisher = Publisher<ipc::Service, StereoFrame, ()>;
pub type FrameSubscriber = Subscriber<ipc::Service, StereoFrame, ()>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_domain_is_a_file_prefix_and_a_bad_one_is_named() {
        let p = domain_prefix("demo4242").unwrap();
        assert_eq!(p.as_bytes(), b"iox2_demo4242_");
        for bad in ["a/b", "two words", &"x".repeat(33)] {
            let e = domain_prefix(bad).unwrap_err().to_string();
            assert!(
                e.contains(&format!("{bad:?}")) && e.contains(DOMAIN_ENV),
                "{e}"
            );
        }
    }
}
