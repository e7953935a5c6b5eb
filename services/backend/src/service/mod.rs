//! The back-end service of one robot: receives keyframes and odometry edges over iceoryx2,
//! checks each one ([`input`]), journals it (fsync) before applying it, keeps the pose
//! graph, re-optimizes it warm-started every few keyframes, publishes the latest pose
//! estimate and writes the whole estimate to `<state_dir>/<robot>/trajectory.tum`
//! ([`trajectory`]).
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
pub mod intra;
pub mod output;
pub mod state;
pub mod team;
pub mod trajectory;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use doorslam_geometry::pose_to_array;
use doorslam_ipc::wire::RobotId;
use doorslam_ipc::{
    create_node, EnvelopeEvent, Keyframe, Lifecycle, LoopClosure, OdometryEdge, PoseEstimate,
    Receiver, Sender, Topic, WireEnvelope,
};
use serde::de::IgnoredAny;
use serde::Deserialize;

use crate::distributed::{condensed::PcmSettings, AgentOptions};
use crate::journal::{Journal, JournalError, Recovery};
pub use state::{Append, BackendReport, BackendState, Outcome};
pub use team::{BridgeError, BridgeStats, TeamBridge};

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
    #[error(transparent)]
    Epoch(#[from] doorslam_ipc::lifecycle::EpochError),
    #[error("{path}: {source}")]
    Output {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// `[backend]` of `robot.toml`. Unknown keys are errors: a typo must not be ignored.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackendSection {
    /// Where the back-end keeps its journal (`<state_dir>/<robot id>/backend.journal`).
    #[serde(default = "default_state_dir")]
    pub state_dir: PathBuf,
    /// Re-optimize after this many new keyframes.
    #[serde(default = "default_optimize_every")]
    pub optimize_every: usize,
    /// Run the distributed back-end with the team link (closures from `closures`, relay on
    /// `team-in` / `team-out`); off: this robot's odometry graph only.
    #[serde(default = "default_true")]
    pub distributed: bool,
    /// PCM inside the distributed back-end: χ² probability of the pairwise consistency
    /// test (README, `doorslam pcm`), and the smallest clique of closures kept per robot
    /// pair (2: a closure alone between two robots is not trusted).
    #[serde(default = "default_pcm_threshold")]
    pub pcm_threshold: f64,
    #[serde(default = "default_min_clique")]
    pub pcm_min_clique: usize,
    /// Check a closure left alone between two robots through 3-robot cycles over closures
    /// already kept (recall on singletons without admitting outliers); false: plain
    /// pairwise PCM.
    #[serde(default = "default_true")]
    pub pcm_cycles: bool,
    /// PCM of the robot's own loop closures runs over the newest this many candidates
    /// (plus a quarter as many kept earlier, as anchors); older ones keep their last
    /// verdict. Bounds the maximum clique, which stalled the back-end over every candidate
    /// of a route revisited for an hour.
    #[serde(default = "default_intra_pcm_window")]
    pub intra_pcm_window: usize,
    /// Write `odometry.tum`, `team_estimate.tum` and `backend.json` into the state folder
    /// this often (seconds; 0 = only when stopping).
    #[serde(default = "default_write_every_s")]
    pub write_every_s: f64,
    /// The distributed back-end's timeouts, in seconds of the robot's clock (a back-end
    /// loop turn is no fixed time, so none counts turns): a message of its own
    /// retransmission layer unacknowledged this long is lost (`resend_after_s`; unused over
    /// the team link, whose delivery contract resends), a robot converged in a stage waits
    /// this long for its neighbours and the team's solver twice this for missing graphs
    /// (`patience_s`: a graph crosses a hop per link delivery, which takes 1-16 s when the
    /// radio retransmits), a stage ends after at most `max_stage_s`.
    #[serde(default = "default_resend_after_s")]
    pub resend_after_s: f64,
    #[serde(default = "default_patience_s")]
    pub patience_s: f64,
    #[serde(default = "default_max_stage_s")]
    pub max_stage_s: f64,
    /// The team's solver copies its own graph to a standby (its lowest child), so that the
    /// robot taking over when the solver leaves keeps its trajectory and every closure it
    /// held (`doorslam dpgo`; `--no-standby-copy` turns it off). On by default: the copy is
    /// the solver's trajectory alone, sent once the solver is settled, and the robots above
    /// it send their closures with it again once it left (BENCHMARKS.md, "A standby copy
    /// on by default").
    #[serde(default = "default_standby_copy")]
    pub standby_copy: bool,
    /// Keys of before the timeouts were seconds: refused by name (`validate`), so an old
    /// robot.toml fails saying what replaces them rather than silently meaning steps.
    #[serde(default)]
    pub resend_after: Option<IgnoredAny>,
    #[serde(default)]
    pub patience: Option<IgnoredAny>,
    #[serde(default)]
    pub max_stage_steps: Option<IgnoredAny>,
}

fn default_state_dir() -> PathBuf {
    PathBuf::from("/var/lib/doorslam")
}
fn default_optimize_every() -> usize {
    10
}
fn default_true() -> bool {
    true
}
fn default_pcm_threshold() -> f64 {
    0.99
}
fn default_min_clique() -> usize {
    2
}
fn default_intra_pcm_window() -> usize {
    intra::DEFAULT_INTRA_PCM_WINDOW
}
fn default_write_every_s() -> f64 {
    1.0
}
fn default_resend_after_s() -> f64 {
    2.0
}
fn default_patience_s() -> f64 {
    5.0
}
fn default_max_stage_s() -> f64 {
    60.0
}
fn default_standby_copy() -> bool {
    true
}

impl Default for BackendSection {
    fn default() -> Self {
        Self {
            state_dir: default_state_dir(),
            optimize_every: default_optimize_every(),
            distributed: true,
            pcm_threshold: default_pcm_threshold(),
            pcm_min_clique: default_min_clique(),
            pcm_cycles: true,
            intra_pcm_window: default_intra_pcm_window(),
            write_every_s: default_write_every_s(),
            resend_after_s: default_resend_after_s(),
            patience_s: default_patience_s(),
            max_stage_s: default_max_stage_s(),
            standby_copy: default_standby_copy(),
            resend_after: None,
            patience: None,
            max_stage_steps: None,
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
        if !(self.pcm_threshold > 0.0 && self.pcm_threshold < 1.0) {
            return Err(ServiceError::Config(format!(
                "backend.pcm_threshold = {}: a probability strictly between 0 and 1",
                self.pcm_threshold
            )));
        }
        if self.pcm_min_clique == 0 {
            return Err(ServiceError::Config(
                "backend.pcm_min_clique must be >= 1".into(),
            ));
        }
        if !(8..=4096).contains(&self.intra_pcm_window) {
            return Err(ServiceError::Config(format!(
                "backend.intra_pcm_window = {}: candidates from 8 to 4096",
                self.intra_pcm_window
            )));
        }
        if !(self.write_every_s.is_finite() && (0.0..=3600.0).contains(&self.write_every_s)) {
            return Err(ServiceError::Config(format!(
                "backend.write_every_s = {}: seconds from 0 to 3600",
                self.write_every_s
            )));
        }
        for (old, given, new) in [
            (
                "resend_after",
                self.resend_after.is_some(),
                "resend_after_s",
            ),
            ("patience", self.patience.is_some(), "patience_s"),
            (
                "max_stage_steps",
                self.max_stage_steps.is_some(),
                "max_stage_s",
            ),
        ] {
            if given {
                return Err(ServiceError::Config(format!(
                    "backend.{old} counted back-end steps and is gone: use backend.{new} (seconds)"
                )));
            }
        }
        for (name, v) in [
            ("resend_after_s", self.resend_after_s),
            ("patience_s", self.patience_s),
            ("max_stage_s", self.max_stage_s),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 3600.0) {
                return Err(ServiceError::Config(format!(
                    "backend.{name} = {v}: seconds above 0, at most 3600"
                )));
            }
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
            distributed: self.distributed.then(|| AgentOptions {
                pcm: Some(PcmSettings {
                    threshold: self.pcm_threshold,
                    min_clique: self.pcm_min_clique,
                    cycles: self.pcm_cycles,
                }),
                resend_after: Duration::from_secs_f64(self.resend_after_s),
                patience: Duration::from_secs_f64(self.patience_s),
                max_stage: Duration::from_secs_f64(self.max_stage_s),
                standby_copy: self.standby_copy,
                ..AgentOptions::default()
            }),
            write_every: Duration::from_secs_f64(self.write_every_s),
            intra_pcm: (
                self.pcm_threshold,
                self.pcm_min_clique,
                self.intra_pcm_window,
            ),
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
    /// The distributed back-end's options, when it runs.
    pub distributed: Option<AgentOptions>,
    /// How often the output files are written (zero: only when stopping).
    pub write_every: Duration,
    /// PCM of the robot's own loop closures: probability, smallest clique and window.
    pub intra_pcm: (f64, usize, usize),
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

/// The relay with the team link: closures and envelopes in, envelopes out.
struct TeamPorts {
    closures: Receiver<LoopClosure>,
    team_in: Receiver<WireEnvelope>,
    team_out: Sender<WireEnvelope>,
}

impl TeamPorts {
    fn send(
        &self,
        event: EnvelopeEvent,
        peer: u32,
        epoch: u64,
        bytes: &[u8],
    ) -> Result<(), ServiceError> {
        self.team_out
            .send_with(|slot| WireEnvelope::write(slot, event, peer, epoch, bytes))?;
        Ok(())
    }

    /// Takes every queued closure and envelope; whether there was any.
    fn drain(
        &self,
        robot: u32,
        state: &mut BackendState,
        journal: &mut Journal,
    ) -> Result<bool, ServiceError> {
        let mut any = false;
        while let Some(sample) = self.closures.try_recv()? {
            any = true;
            let c = sample.payload();
            let outcome = state.on_closure(c, journal)?;
            log_outcome(Topic::Closures, c.keyframe_a, &outcome);
        }
        while let Some(sample) = self.team_in.try_recv()? {
            any = true;
            let e = sample.payload();
            let Some(bridge) = state.team_mut() else {
                continue;
            };
            match bridge.on_envelope(e.event, e.peer_robot, e.epoch, e.bytes()) {
                Ok(true) => {
                    let epoch = bridge.epoch();
                    self.send(EnvelopeEvent::BackendStarted, robot, epoch, &[])?;
                }
                Ok(false) => {}
                Err(err) => tracing::warn!("backend: team-in: {err}"),
            }
        }
        Ok(any)
    }

    /// Steps the distributed back-end and hands its messages to the team link.
    fn exchange(&self, state: &mut BackendState) -> Result<(), ServiceError> {
        let Some(bridge) = state.team_mut() else {
            return Ok(());
        };
        match bridge.step() {
            Ok(true) => tracing::debug!(
                anchored = bridge.agent().anchored(),
                rejected = bridge.agent().rejected_closures().len(),
                "backend: distributed back-end solved"
            ),
            Ok(false) => {}
            Err(e) => tracing::warn!("backend: distributed back-end step failed: {e}"),
        }
        match bridge.outgoing() {
            Ok(messages) => {
                for (peer, bytes) in messages {
                    self.send(EnvelopeEvent::Message, u32::from(peer), 0, &bytes)?;
                }
            }
            Err(e) => tracing::warn!("backend: distributed back-end messages failed: {e}"),
        }
        Ok(())
    }
}

/// Runs until SIGTERM/SIGINT. The journal is replayed first, so a restarted back-end
/// resumes with the graph it had (closures included), and the distributed back-end
/// rejoins the team with a new epoch.
pub fn run(config: &BackendConfig) -> Result<BackendReport, ServiceError> {
    let mut state = BackendState::new(config.robot_index, config.optimize_every)
        .ok_or(ServiceError::Robot(config.robot_index))?
        .with_intra_pcm(config.intra_pcm.0, config.intra_pcm.1, config.intra_pcm.2)
        .map_err(|e| ServiceError::Config(format!("backend.pcm_threshold: {e}")))?;
    let robot =
        u8::try_from(config.robot_index).map_err(|_| ServiceError::Robot(config.robot_index))?;
    if let Some(options) = &config.distributed {
        let id = RobotId::new(&config.robot)
            .map_err(|e| ServiceError::Config(format!("robot id {:?}: {e}", config.robot)))?;
        let epoch = doorslam_ipc::lifecycle::next_epoch(&config.state_dir, "backend.epoch")?;
        state = state.with_team(TeamBridge::new(robot, id, epoch, options.clone()));
    }
    let path = config.state_dir.join("backend.journal");
    let trajectory_path = config.state_dir.join("trajectory.tum");
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
    let team = match state.team() {
        Some(bridge) => {
            let ports = TeamPorts {
                closures: Receiver::new(&node, &config.robot, Topic::Closures)?,
                team_in: Receiver::new(&node, &config.robot, Topic::TeamIn)?,
                team_out: Sender::new(&node, &config.robot, Topic::TeamOut)?,
            };
            // A team link already running learns this back-end's epoch (and that whatever
            // its peers think we hold is gone if we restarted).
            ports.send(
                EnvelopeEvent::BackendStarted,
                config.robot_index,
                bridge.epoch(),
                &[],
            )?;
            Some(ports)
        }
        None => None,
    };
    let outputs = output::Outputs::new(&config.state_dir);
    let mut lifecycle = Lifecycle::new();
    lifecycle.ready(&format!(
        "{} keyframes recovered",
        recovered.recovered_keyframes
    ));
    tracing::info!(
        robot = %config.robot,
        distributed = team.is_some(),
        "backend: ready (subscribed to keyframes and odometry{})",
        if team.is_some() { ", closures and the team link" } else { "" }
    );

    let mut last_write = Instant::now();
    // Short sleeps: the team link's messages are taken within this time too.
    let wait = if team.is_some() {
        Duration::from_millis(20)
    } else {
        Duration::from_millis(100)
    };
    while lifecycle.keep_going(&node) {
        // Sleep until a keyframe arrives (or the wait ends), then take everything queued.
        let woken = keyframes.recv_timeout(wait)?;
        let mut progressed = woken.is_some();
        if let Some(sample) = woken {
            feed_keyframe(&mut state, &mut journal, sample.payload())?;
        }
        progressed |= drain(&keyframes, &odometry, &mut state, &mut journal)?;
        if let Some(ports) = &team {
            progressed |= ports.drain(config.robot_index, &mut state, &mut journal)?;
            ports.exchange(&mut state)?;
        }
        if progressed && state.optimization_due() {
            match state.optimize() {
                Ok(s) => {
                    tracing::info!(
                        poses = state.graph().len(),
                        chi2 = s.final_chi2,
                        "backend: optimized"
                    );
                    if let Err(e) = trajectory::write_tum(&trajectory_path, state.trajectory()) {
                        tracing::warn!(path = %trajectory_path.display(), "backend: cannot write the trajectory: {e}");
                    }
                }
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
        if !config.write_every.is_zero() && last_write.elapsed() >= config.write_every {
            last_write = Instant::now();
            if let Err(e) = outputs.write(&state) {
                tracing::warn!("backend: {e}");
            }
        }
    }
    lifecycle.stopping();
    // Whatever reached the queues before the stop is journaled: producers stop first
    // (`doorslam up` and the systemd units stop in reverse start order), so this is all
    // they sent.
    drain(&keyframes, &odometry, &mut state, &mut journal)?;
    if let Some(ports) = &team {
        ports.drain(config.robot_index, &mut state, &mut journal)?;
    }
    outputs.write(&state)?;
    tracing::info!(report = ?state.report(), pending_edges = state.pending(), "backend: stopped");
    Ok(state.report().clone())
}
