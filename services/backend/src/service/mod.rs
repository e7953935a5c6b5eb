//! The back-end service of one robot: receives keyframes and odometry edges over iceoryx2,
//! checks each one ([`input`]), journals it (fsync) before applying it, keeps the pose
//! graph, re-optimizes it warm-started every few keyframes and publishes the latest pose
//! estimate.
//!
//! All decisions live in the plain state machine [`state::BackendState`]; this loop only
//! moves samples in and out. Ordering: keyframe ids should arrive consecutively. A
//! keyframe or odometry edge already in the graph is skipped and counted as a duplicate: a
//! restarted back-end is first handed the publishers' history (see
//! `doorslam_ipc::channel`), most of which it journaled before it died. A gap is logged
//! (it means an upstream service lost data) and accepted.
//!
//! The journal is opened for this robot's id (see [`crate::journal`]): another robot's
//! journal or a newer format stops the service with the file untouched; corruption found on
//! the way is logged as an error with the side file now holding the unread bytes.

pub mod input;
pub mod state;

use std::path::{Path, PathBuf};
use std::time::Duration;

use doorslam_geometry::pose_to_array;
use doorslam_ipc::{
    create_node, Keyframe, Lifecycle, OdometryEdge, PoseEstimate, Receiver, Sender, Topic,
};
use serde::Deserialize;

use crate::journal::{Journal, JournalError, Recovery};
pub use state::{Append, BackendReport, BackendState, Outcome};

/// Failures of the back-end service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    Ipc(#[from] doorslam_ipc::IpcError),
    #[error(transparent)]
    Journal(#[from] JournalError),
    #[error("robot index {0} is outside 0..52 (multi-robot keys use 'a'..'z', then 'A'..'Z')")]
    Robot(u32),
    #[error("backend config: {0}")]
    Config(String),
}

/// `[backend]` of `robot.toml`. Unknown keys are errors: a typo must not be ignored.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackendSection {
    /// Where the back-end keeps its journal (`<state_dir>/<robot id>/backend.journal`).
    #[serde(default = "default_state_dir")]
    pub state_dir: PathBuf,
    /// Re-optimize after this many new keyframes.
    #[serde(default = "default_optimize_every")]
    pub optimize_every: usize,
}

fn default_state_dir() -> PathBuf {
    PathBuf::from("/var/lib/doorslam")
}
fn default_optimize_every() -> usize {
    10
}

impl Default for BackendSection {
    fn default() -> Self {
        Self {
            state_dir: default_state_dir(),
            optimize_every: default_optimize_every(),
        }
    }
}

impl BackendSection {
    pub fn validate(&self) -> Result<(), ServiceError> {
        if self.optimize_every == 0 {
            return Err(ServiceError::Config(
                "backend.optimize_every must be >= 1".into(),
            ));
        }
        Ok(())
    }

    /// The settings of the back-end of robot `robot` (index `robot_index` in the team).
    pub fn for_robot(&self, robot: &str, robot_index: u32) -> BackendConfig {
        BackendConfig {
            robot: robot.to_string(),
            robot_index,
            state_dir: self.state_dir.join(robot),
            optimize_every: self.optimize_every,
        }
    }
}

/// Settings of one back-end process.
#[derive(Debug, Clone, PartialEq)]
pub struct BackendConfig {
    /// Robot id (service names) and index (keys: 'a' + index).
    pub robot: String,
    pub robot_index: u32,
    /// The journal lives at `<state_dir>/backend.journal`; its header names `robot`, so
    /// the back-end of one robot never resumes from another's.
    pub state_dir: PathBuf,
    /// Re-optimize after this many new keyframes.
    pub optimize_every: usize,
}

/// Logs what happened to one sample (rejections name robot, topic and field).
fn log_outcome(topic: Topic, id: u64, outcome: &Outcome) {
    match outcome {
        Outcome::Rejected(e) => tracing::error!("backend: rejected: {e}"),
        Outcome::AcceptedAfterGap { expected, got } => tracing::warn!(
            topic = topic.as_str(),
            expected,
            got,
            "backend: keyframe ids not consecutive (upstream lost data)"
        ),
        Outcome::Accepted => tracing::debug!(topic = topic.as_str(), id, "backend: accepted"),
        Outcome::Duplicate | Outcome::Waiting => {}
    }
}

/// Logs what opening the journal found; corruption is an error: records after the bad
/// spot are not in the graph until someone restores them from the side file.
fn log_recovery(path: &Path, recovery: &Recovery, report: &BackendReport) {
    let journal = path.display();
    if recovery.torn_header_bytes > 0 {
        tracing::warn!(
            %journal,
            torn_header_bytes = recovery.torn_header_bytes,
            "backend: journal header was torn at creation (no records yet), rewrote it"
        );
    } else if recovery.fresh {
        tracing::info!(%journal, "backend: started a new journal");
    }
    if recovery.truncated_bytes > 0 {
        tracing::warn!(
            %journal,
            torn_tail_bytes = recovery.truncated_bytes,
            "backend: cut a torn last record off the journal"
        );
    }
    if let Some(c) = &recovery.corruption {
        tracing::error!(
            %journal,
            offset = c.offset,
            preserved_bytes = c.bytes,
            preserved_to = %c.preserved.as_deref().unwrap_or(Path::new("")).display(),
            reason = %c.reason,
            "backend: journal corrupt: kept the records before the bad one, moved it and \
             everything after it into the side file, continuing without them"
        );
    }
    if report.rejected_from_journal > 0 {
        tracing::error!(
            %journal,
            entries = report.rejected_from_journal,
            "backend: journal entries fail the input checks (written by an older build): skipped"
        );
    }
    tracing::info!(
        %journal,
        keyframes = report.recovered_keyframes,
        edges = report.recovered_edges,
        torn_tail_bytes = report.truncated_bytes,
        preserved_bytes = report.preserved_bytes,
        "backend: recovered graph from journal"
    );
}

fn feed_keyframe(
    state: &mut BackendState,
    journal: &mut Journal,
    kf: &Keyframe,
) -> Result<(), ServiceError> {
    let outcome = state.on_keyframe(kf, journal)?;
    log_outcome(Topic::Keyframes, kf.id, &outcome);
    Ok(())
}

/// Feeds every queued keyframe, then every queued odometry edge, to the state machine;
/// whether there was any.
fn drain(
    keyframes: &Receiver<Keyframe>,
    odometry: &Receiver<OdometryEdge>,
    state: &mut BackendState,
    journal: &mut Journal,
) -> Result<bool, ServiceError> {
    let mut any = false;
    while let Some(sample) = keyframes.try_recv()? {
        any = true;
        feed_keyframe(state, journal, sample.payload())?;
    }
    while let Some(sample) = odometry.try_recv()? {
        any = true;
        let e = sample.payload();
        let outcome = state.on_odometry(e, journal)?;
        log_outcome(Topic::Odometry, e.to, &outcome);
    }
    Ok(any)
}

/// Runs until SIGTERM/SIGINT. The journal is replayed first, so a restarted back-end
/// resumes with the graph it had.
pub fn run(config: &BackendConfig) -> Result<BackendReport, ServiceError> {
    let mut state = BackendState::new(config.robot_index, config.optimize_every)
        .ok_or(ServiceError::Robot(config.robot_index))?;
    let path = config.state_dir.join("backend.journal");
    let (mut journal, recovery) = Journal::open(&path, &config.robot)?;
    state.recover(&recovery);
    log_recovery(&path, &recovery, state.report());
    let recovered = state.report().clone();

    let (node, cleaned) = create_node("doorslam-backend")?;
    if cleaned > 0 {
        tracing::warn!(cleaned, "backend: removed shared memory of dead processes");
    }
    let keyframes = Receiver::<Keyframe>::new(&node, &config.robot, Topic::Keyframes)?;
    let odometry = Receiver::<OdometryEdge>::new(&node, &config.robot, Topic::Odometry)?;
    let estimates = Sender::<PoseEstimate>::new(&node, &config.robot, Topic::Estimates)?;
    let mut lifecycle = Lifecycle::new();
    lifecycle.ready(&format!(
        "{} keyframes recovered",
        recovered.recovered_keyframes
    ));
    tracing::info!(robot = %config.robot, "backend: ready (subscribed to keyframes and odometry)");

    while lifecycle.keep_going(&node) {
        // Sleep until a keyframe arrives (or 100 ms pass), then take everything queued.
        let woken = keyframes.recv_timeout(Duration::from_millis(100))?;
        let mut progressed = woken.is_some();
        if let Some(sample) = woken {
            feed_keyframe(&mut state, &mut journal, sample.payload())?;
        }
        progressed |= drain(&keyframes, &odometry, &mut state, &mut journal)?;
        if progressed && state.optimization_due() {
            match state.optimize() {
                Ok(s) => tracing::info!(
                    poses = state.graph().len(),
                    chi2 = s.final_chi2,
                    "backend: optimized"
                ),
                Err(e) => tracing::warn!("backend: optimization skipped: {e}"),
            }
            if let Some((keyframe, pose)) = state.latest_estimate() {
                let est = PoseEstimate {
                    robot: config.robot_index,
                    reserved: 0,
                    keyframe,
                    stamp_ns: 0,
                    pose: pose_to_array(&pose),
                };
                estimates.send_copy(&est)?;
            }
        }
    }
    lifecycle.stopping();
    // Whatever reached the queues before the stop is journaled: producers stop first
    // (`doorslam up` and the systemd units stop in reverse start order), so this is all
    // they sent.
    drain(&keyframes, &odometry, &mut state, &mut journal)?;
    tracing::info!(report = ?state.report(), pending_edges = state.pending(), "backend: stopped");
    Ok(state.report().clone())
}
