//! The back-end service of one robot: receives keyframes and odometry edges over iceoryx2,
//! journals each one (fsync) before applying it, keeps the pose graph, re-optimizes it
//! warm-started every few keyframes and publishes the latest pose estimate.
//!
//! Ordering: keyframe ids must arrive consecutively. A keyframe or odometry edge already in
//! the graph is skipped and counted as a duplicate: a restarted back-end is first handed
//! the publishers' history (see `doorslam_ipc::channel`), most of which it journaled before
//! it died. A gap is logged (it means an upstream service lost data) and accepted.

use std::path::PathBuf;
use std::time::Duration;

use doorslam_ipc::{
    create_node, matrix_from_upper, pose_from_array, pose_to_array, Keyframe, Lifecycle,
    OdometryEdge, PoseEstimate, Receiver, Sender, Topic,
};
use nalgebra::Isometry3;

use crate::graph::{check_information, key, InformationCheck, InformationError, PoseGraph};
use crate::journal::{Entry, Journal, JournalError};
use crate::solver::{Optimizer, SolverOptions};

/// Failures of the back-end service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    Ipc(#[from] doorslam_ipc::IpcError),
    #[error(transparent)]
    Journal(#[from] JournalError),
    #[error("optimizer: {0}")]
    Solve(#[from] crate::solver::SolveError),
    #[error("robot index {0} is outside 0..26 (multi-robot keys use 'a' + index)")]
    Robot(u32),
}

/// Settings of the back-end service.
#[derive(Debug, Clone, PartialEq)]
pub struct BackendConfig {
    /// Robot id (service names) and index (keys: 'a' + index).
    pub robot: String,
    pub robot_index: u32,
    /// The journal lives at `<state_dir>/backend.journal`.
    pub state_dir: PathBuf,
    /// Re-optimize after this many new keyframes.
    pub optimize_every: usize,
}

/// What the service did, for its exit log and for tests.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BackendReport {
    pub recovered_keyframes: usize,
    pub recovered_edges: usize,
    pub truncated_bytes: u64,
    pub accepted_keyframes: usize,
    pub accepted_edges: usize,
    /// Keyframes and edges received again (history handed to a restarted back-end).
    pub duplicates: usize,
    pub gaps: usize,
    /// Odometry edges refused by the graph (non-finite measurement or information that is
    /// not symmetric positive definite): logged and dropped, not journaled.
    pub rejected_edges: usize,
}

/// The graph being built, with the bookkeeping of ids.
struct State {
    robot: u8,
    graph: PoseGraph<Isometry3<f64>>,
    next_id: Option<u64>,
    /// Odometry edges in the graph, by (from, to) keyframe id.
    odometry: std::collections::HashSet<(u64, u64)>,
}

impl State {
    /// Whether the graph would take this odometry entry's information matrix (the check
    /// `add_edge` does), so the commonest bad edge is refused before it is journaled.
    fn validate(&self, e: &Entry) -> Result<(), InformationError> {
        match e {
            Entry::Odometry { information, .. } => check_information(
                &matrix_from_upper(information),
                6,
                InformationCheck::PositiveDefinite,
            ),
            Entry::Keyframe { .. } => Ok(()),
        }
    }

    /// Applies an entry; returns false for a duplicate, an edge to unknown poses, or an
    /// edge the graph refuses (logged: a journal written by an older version may hold one).
    fn apply(&mut self, e: &Entry) -> bool {
        match e {
            Entry::Keyframe { id, pose, .. } => {
                let k = key::symbol(self.robot, *id);
                if self.graph.index_of(k).is_some() {
                    return false;
                }
                self.graph.add_pose(k, pose_from_array(pose));
                self.next_id = Some(self.next_id.map_or(id + 1, |n| n.max(id + 1)));
                true
            }
            Entry::Odometry {
                from,
                to,
                relative,
                information,
            } => {
                let (a, b) = (
                    self.graph.index_of(key::symbol(self.robot, *from)),
                    self.graph.index_of(key::symbol(self.robot, *to)),
                );
                match (a, b) {
                    (Some(a), Some(b)) if !self.odometry.contains(&(*from, *to)) => {
                        match self.graph.add_edge(
                            a,
                            b,
                            pose_from_array(relative),
                            matrix_from_upper(information),
                        ) {
                            Ok(_) => {
                                // Only now: a refused edge must not make a corrected
                                // retransmission look like a duplicate.
                                self.odometry.insert((*from, *to));
                                true
                            }
                            Err(err) => {
                                tracing::warn!(from, to, "backend: odometry edge refused: {err}");
                                false
                            }
                        }
                    }
                    _ => false,
                }
            }
        }
    }
}

/// Runs until SIGTERM/SIGINT. The journal is replayed first, so a restarted back-end
/// resumes with the graph it had.
pub fn run(config: &BackendConfig) -> Result<BackendReport, ServiceError> {
    let robot = u8::try_from(config.robot_index)
        .ok()
        .filter(|r| *r < 26)
        .ok_or(ServiceError::Robot(config.robot_index))?;
    let (mut journal, recovery) = Journal::open(&config.state_dir.join("backend.journal"))?;
    let mut state = State {
        robot,
        graph: PoseGraph::new(),
        next_id: None,
        odometry: Default::default(),
    };
    let mut report = BackendReport {
        truncated_bytes: recovery.truncated_bytes,
        ..Default::default()
    };
    for e in &recovery.entries {
        if state.apply(e) {
            match e {
                Entry::Keyframe { .. } => report.recovered_keyframes += 1,
                Entry::Odometry { .. } => report.recovered_edges += 1,
            }
        }
    }
    tracing::info!(
        journal = %journal.path().display(),
        keyframes = report.recovered_keyframes,
        edges = report.recovered_edges,
        torn_tail_bytes = report.truncated_bytes,
        "backend: recovered graph from journal"
    );

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
        report.recovered_keyframes
    ));
    tracing::info!(robot = %config.robot, "backend: ready (subscribed to keyframes and odometry)");

    let mut optimizer: Option<Optimizer> = None;
    let mut since_optimized = 0usize;
    // Odometry edges waiting for a keyframe they refer to (the two channels are separate,
    // so an edge can overtake the keyframe sent just before it).
    let mut pending: std::collections::VecDeque<Entry> = std::collections::VecDeque::new();
    while lifecycle.keep_going(&node) {
        let mut progressed = false;
        let mut next = keyframes.recv_timeout(Duration::from_millis(100))?;
        while let Some(kf) = next {
            let kf = kf.payload();
            progressed = true;
            let entry = Entry::Keyframe {
                id: kf.id,
                stamp_ns: kf.stamp_ns,
                pose: kf.pose,
            };
            if state.graph.index_of(key::symbol(robot, kf.id)).is_some() {
                report.duplicates += 1;
            } else {
                if let Some(n) = state.next_id.filter(|n| *n != kf.id) {
                    report.gaps += 1;
                    tracing::warn!(
                        expected = n,
                        got = kf.id,
                        "backend: keyframe ids not consecutive (upstream lost data)"
                    );
                }
                journal.append(&entry)?;
                state.apply(&entry);
                report.accepted_keyframes += 1;
                since_optimized += 1;
                tracing::debug!(id = kf.id, "backend: keyframe accepted");
            }
            next = keyframes.try_recv()?;
        }
        while let Some(edge) = odometry.try_recv()? {
            let e = edge.payload();
            progressed = true;
            pending.push_back(Entry::Odometry {
                from: e.from,
                to: e.to,
                relative: e.relative,
                information: e.information,
            });
        }
        let known = |state: &State, id: u64| state.graph.index_of(key::symbol(robot, id)).is_some();
        let mut waiting = std::collections::VecDeque::new();
        while let Some(entry) = pending.pop_front() {
            let Entry::Odometry { from, to, .. } = entry else {
                continue;
            };
            if state.odometry.contains(&(from, to)) {
                report.duplicates += 1;
            } else if known(&state, from) && known(&state, to) {
                if let Err(err) = state.validate(&entry) {
                    tracing::warn!(from, to, "backend: odometry edge refused: {err}");
                    report.rejected_edges += 1;
                    continue;
                }
                journal.append(&entry)?;
                if state.apply(&entry) {
                    report.accepted_edges += 1;
                } else {
                    report.rejected_edges += 1;
                }
            } else {
                waiting.push_back(entry);
            }
        }
        if waiting.len() > 10_000 {
            tracing::warn!(
                waiting = waiting.len(),
                "backend: odometry edges waiting for keyframes that never came"
            );
        }
        pending = waiting;
        if progressed && since_optimized >= config.optimize_every && !state.graph.edges().is_empty()
        {
            // A graph in the middle of being built may be disconnected: try again later.
            let result = match optimizer.as_mut() {
                Some(opt) => opt.optimize(&mut state.graph, &SolverOptions::default()),
                None => Optimizer::new(&state.graph, 0).and_then(|opt| {
                    optimizer
                        .insert(opt)
                        .optimize(&mut state.graph, &SolverOptions::default())
                }),
            };
            match result {
                Ok(s) => tracing::info!(
                    poses = state.graph.len(),
                    chi2 = s.final_chi2,
                    "backend: optimized"
                ),
                Err(e) => tracing::warn!("backend: optimization skipped: {e}"),
            }
            since_optimized = 0;
            if let Some((&k, p)) = state.graph.keys().last().zip(state.graph.poses().last()) {
                let est = PoseEstimate {
                    robot: config.robot_index,
                    reserved: 0,
                    keyframe: key::index(k),
                    stamp_ns: 0,
                    pose: pose_to_array(p),
                };
                estimates.send_copy(&est)?;
            }
        }
    }
    lifecycle.stopping();
    tracing::info!(?report, "backend: stopped");
    Ok(report)
}
