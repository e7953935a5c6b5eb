//! The back-end's logic as a plain state machine fed by values: de-duplication, gap
//! handling, odometry edges waiting for their keyframes, journaling before applying, and
//! when to optimize. The iceoryx2 loop ([`super::run`]) only moves samples in and out, so
//! all of this is tested without shared memory.

use std::collections::{BTreeMap, HashSet, VecDeque};

use doorslam_geometry::information::upper_from_matrix;
use doorslam_geometry::{key, pose_to_array, SE3};
use doorslam_ipc::{Keyframe, LoopClosure, OdometryEdge};

use super::input::{
    check_journaled_closure, check_journaled_keyframe, check_journaled_odometry, check_keyframe,
    check_odometry, check_own_closure, ClosureInput, InputError, KeyframeInput, OdometryInput,
};
use super::intra::{is_intra, IntraLoops, DEFAULT_INTRA_PCM_WINDOW};
use super::team::TeamBridge;
use crate::graph::PoseGraph;
use crate::journal::{Entry, JournalError, Recovery};
use crate::solver::{Optimizer, SolveError, SolverOptions, Summary};

/// Odometry edges may overtake their keyframe (two channels), so a few wait; an edge that
/// still waits when this many queue up refers to a keyframe that will not come.
pub const MAX_PENDING_EDGES: usize = 4096;

/// PCM of the robot's own loops by default: the `[backend]` defaults (`pcm_threshold`,
/// `pcm_min_clique`).
pub const INTRA_PCM_THRESHOLD: f64 = 0.99;
pub const INTRA_MIN_CLIQUE: usize = 2;

/// Where accepted entries go before they are applied (the journal; a `Vec` in tests).
pub trait Append {
    fn append(&mut self, entry: &Entry) -> Result<(), JournalError>;
}

impl Append for crate::journal::Journal {
    fn append(&mut self, entry: &Entry) -> Result<(), JournalError> {
        crate::journal::Journal::append(self, entry)
    }
}

impl Append for Vec<Entry> {
    fn append(&mut self, entry: &Entry) -> Result<(), JournalError> {
        self.push(entry.clone());
        Ok(())
    }
}

/// What happened to one received sample.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Journaled and in the graph.
    Accepted,
    /// Journaled and in the graph, but ids skipped `expected..got` (upstream lost data).
    AcceptedAfterGap { expected: u64, got: u64 },
    /// Already in the graph (history handed to a restarted back-end): skipped.
    Duplicate,
    /// An odometry edge whose keyframes have not all arrived: held until they do.
    Waiting,
    /// Refused by the input checks: not journaled.
    Rejected(InputError),
}

/// Counters of everything the back-end did, for its exit log and for tests.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BackendReport {
    pub recovered_keyframes: usize,
    pub recovered_edges: usize,
    /// Journal entries that fail today's input checks (written by an older build).
    pub rejected_from_journal: usize,
    /// Bytes of a torn last record cut off the journal.
    pub truncated_bytes: u64,
    /// Bytes of a corrupt journal moved into a side file, and that file.
    pub preserved_bytes: u64,
    pub preserved_to: Option<std::path::PathBuf>,
    pub accepted_keyframes: usize,
    pub accepted_edges: usize,
    /// Keyframes and edges received again (history handed to a restarted back-end).
    pub duplicates: usize,
    pub gaps: usize,
    /// Samples refused by the input checks (see [`super::input`]).
    pub rejected: usize,
    /// Edges dropped after waiting for keyframes that never came.
    pub expired_edges: usize,
    /// Inter-robot loop closures from the team link in the graph (recovered included).
    pub accepted_closures: usize,
    pub recovered_closures: usize,
    /// Closures dropped after waiting for a keyframe of this robot that never came.
    pub expired_closures: usize,
    /// Keyframes, edges or closures the distributed back-end refused (logged).
    pub team_refused: usize,
    /// This robot's own loop closures (the team link's intra-robot chain): received (and
    /// recovered), in the graph now (PCM's clique), and taken out again when PCM changed
    /// its mind (the distributed back-end keeps what it was given).
    pub intra_closures: usize,
    pub intra_kept: usize,
    pub intra_retracted: usize,
    /// Own loop candidates that left PCM's window (`[backend] intra_pcm_window`) with their
    /// last verdict: kept (they stay in the graph) and rejected (forgotten).
    pub intra_frozen_kept: usize,
    pub intra_frozen_rejected: usize,
    pub optimizations: usize,
    pub failed_optimizations: usize,
}

/// One robot's graph and its bookkeeping.
pub struct BackendState {
    robot: u8,
    robot_index: u32,
    optimize_every: usize,
    graph: PoseGraph<SE3>,
    /// Stamp of each keyframe, by its index in the graph.
    stamps: Vec<u64>,
    next_id: Option<u64>,
    /// Odometry edges in the graph, by (from, to) keyframe id.
    odometry: HashSet<(u64, u64)>,
    pending: VecDeque<OdometryInput>,
    /// Inter-robot closures in the graph, by (key, key) both ways, and as received.
    closures: HashSet<(u64, u64)>,
    closure_list: Vec<ClosureInput>,
    /// Closures whose keyframe of this robot has not arrived yet.
    pending_closures: VecDeque<ClosureInput>,
    /// Keyframe id → (stamp, pose as received): the odometry alone, for comparison.
    received: BTreeMap<u64, (u64, SE3)>,
    since_optimized: usize,
    optimizer: Option<Optimizer>,
    /// The distributed back-end, when this robot is part of a team.
    team: Option<TeamBridge>,
    /// Own loop closures, PCM among them, and the ones the graph holds (by keys).
    intra: IntraLoops,
    intra_in_graph: std::collections::BTreeSet<(u64, u64)>,
    report: BackendReport,
}

impl BackendState {
    /// An empty graph for robot `robot_index` (below 52: keys are `key::robot_char(index)`).
    pub fn new(robot_index: u32, optimize_every: usize) -> Option<Self> {
        let robot = key::robot_index(robot_index).ok()?;
        Some(Self {
            robot,
            robot_index,
            optimize_every: optimize_every.max(1),
            graph: PoseGraph::new(),
            stamps: Vec::new(),
            next_id: None,
            odometry: HashSet::new(),
            pending: VecDeque::new(),
            closures: HashSet::new(),
            closure_list: Vec::new(),
            pending_closures: VecDeque::new(),
            received: BTreeMap::new(),
            since_optimized: 0,
            optimizer: None,
            team: None,
            intra: IntraLoops::new(
                INTRA_PCM_THRESHOLD,
                INTRA_MIN_CLIQUE,
                DEFAULT_INTRA_PCM_WINDOW,
            )
            .ok()?,
            intra_in_graph: Default::default(),
            report: BackendReport::default(),
        })
    }

    /// PCM of the robot's own loop closures with probability `p` and smallest clique
    /// `min_clique` (`[backend] pcm_threshold`, `pcm_min_clique`) over the newest `window`
    /// candidates (`intra_pcm_window`).
    pub fn with_intra_pcm(
        mut self,
        p: f64,
        min_clique: usize,
        window: usize,
    ) -> Result<Self, crate::outliers::pcm::PcmError> {
        self.intra = IntraLoops::new(p, min_clique, window)?;
        Ok(self)
    }

    /// The robot's own loop closures in PCM's window, and how many the graph holds.
    pub fn intra_closures(&self) -> (&[ClosureInput], usize) {
        (self.intra.candidates(), self.intra_in_graph.len())
    }

    /// Adds the distributed back-end: every keyframe, edge and closure (recovered ones
    /// too: add it before [`Self::recover`]) is also given to it.
    pub fn with_team(mut self, bridge: TeamBridge) -> Self {
        self.team = Some(bridge);
        self
    }

    pub fn team(&self) -> Option<&TeamBridge> {
        self.team.as_ref()
    }
    pub fn team_mut(&mut self) -> Option<&mut TeamBridge> {
        self.team.as_mut()
    }

    /// Keyframe id → (stamp, pose as the front-end sent it).
    pub fn received_poses(&self) -> &BTreeMap<u64, (u64, SE3)> {
        &self.received
    }

    /// The inter-robot closures taken (before the distributed back-end's PCM).
    pub fn closures(&self) -> &[ClosureInput] {
        &self.closure_list
    }

    /// Closures waiting for a keyframe of this robot.
    pub fn pending_closures(&self) -> usize {
        self.pending_closures.len()
    }

    /// This robot's key letter number (0 = 'a').
    pub fn robot(&self) -> u8 {
        self.robot
    }
    pub fn graph(&self) -> &PoseGraph<SE3> {
        &self.graph
    }
    pub fn report(&self) -> &BackendReport {
        &self.report
    }
    /// Edges received but waiting for a keyframe.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    fn key(&self, id: u64) -> u64 {
        // Ids were checked against key::MAX_INDEX on entry, so this cannot fail.
        key::symbol(self.robot, id).unwrap_or(u64::MAX)
    }
    fn has_keyframe(&self, id: u64) -> bool {
        self.graph.index_of(self.key(id)).is_some()
    }

    /// Rebuilds the graph from what [`crate::journal::Journal::open`] recovered.
    pub fn recover(&mut self, recovery: &Recovery) {
        self.report.truncated_bytes = recovery.truncated_bytes;
        if let Some(c) = &recovery.corruption {
            self.report.preserved_bytes = c.bytes;
            self.report.preserved_to = c.preserved.clone();
        }
        self.replay(&recovery.entries);
    }

    /// Rebuilds the graph from journaled entries. An entry that fails today's checks (a
    /// journal written before they existed) is counted and skipped, never applied.
    pub fn replay(&mut self, entries: &[Entry]) {
        for e in entries {
            let checked = match e {
                Entry::Keyframe { id, stamp_ns, pose } => {
                    check_journaled_keyframe(self.robot_index, *id, pose).map(|(id, pose)| {
                        if !self.has_keyframe(id) {
                            self.insert_keyframe(&KeyframeInput {
                                id,
                                stamp_ns: *stamp_ns,
                                pose,
                                source: doorslam_ipc::KeyframeSource::VisualOdometry,
                            });
                            self.report.recovered_keyframes += 1;
                        }
                    })
                }
                Entry::Odometry {
                    from,
                    to,
                    relative,
                    information,
                } => check_journaled_odometry(self.robot_index, *from, *to, relative, information)
                    .map(|edge| {
                        if self.can_insert_edge(&edge) {
                            self.insert_edge(edge);
                            self.report.recovered_edges += 1;
                        }
                    }),
                Entry::Closure {
                    key_a,
                    key_b,
                    relative,
                    information,
                    inliers,
                } => check_journaled_closure(
                    self.robot_index,
                    *key_a,
                    *key_b,
                    relative,
                    information,
                    *inliers,
                )
                .map(|c| {
                    if self.can_insert_closure(&c) {
                        self.insert_closure(c);
                        self.report.recovered_closures += 1;
                    }
                }),
            };
            if let Err(e) = checked {
                tracing::error!("backend: journal entry skipped: {e}");
                self.report.rejected_from_journal += 1;
            }
        }
        self.apply_intra();
        // The optimizer is rebuilt lazily for the recovered graph.
        self.since_optimized = self.optimize_every;
    }

    /// A keyframe sample: checked, de-duplicated, journaled, applied; then any edge that
    /// waited for it.
    pub fn on_keyframe(
        &mut self,
        kf: &Keyframe,
        journal: &mut impl Append,
    ) -> Result<Outcome, JournalError> {
        let input = match check_keyframe(kf, self.robot_index) {
            Ok(i) => i,
            Err(e) => return Ok(self.rejected(e)),
        };
        if self.has_keyframe(input.id) {
            self.report.duplicates += 1;
            return Ok(Outcome::Duplicate);
        }
        journal.append(&Entry::Keyframe {
            id: input.id,
            stamp_ns: input.stamp_ns,
            pose: pose_to_array(&input.pose),
        })?;
        let outcome = match self.next_id.filter(|n| *n != input.id) {
            Some(expected) => {
                self.report.gaps += 1;
                Outcome::AcceptedAfterGap {
                    expected,
                    got: input.id,
                }
            }
            None => Outcome::Accepted,
        };
        self.insert_keyframe(&input);
        self.report.accepted_keyframes += 1;
        self.since_optimized += 1;
        self.flush_pending(journal)?;
        Ok(outcome)
    }

    /// An inter-robot loop closure from the team link: checked, de-duplicated (either
    /// direction), then journaled and applied once this robot's keyframe is in the graph.
    pub fn on_closure(
        &mut self,
        lc: &LoopClosure,
        journal: &mut impl Append,
    ) -> Result<Outcome, JournalError> {
        let input = match check_own_closure(lc, self.robot_index) {
            Ok(i) => i,
            Err(e) => return Ok(self.rejected(e)),
        };
        let pair = (input.key_a, input.key_b);
        if self.closures.contains(&pair)
            || self.intra.contains(&input)
            || self
                .pending_closures
                .iter()
                .any(|c| (c.key_a, c.key_b) == pair || (c.key_b, c.key_a) == pair)
        {
            self.report.duplicates += 1;
            return Ok(Outcome::Duplicate);
        }
        if self.can_insert_closure(&input) {
            self.journal_closure(&input, journal)?;
            let intra = is_intra(&input);
            self.insert_closure(input);
            if intra {
                self.apply_intra();
            } else {
                self.report.accepted_closures += 1;
            }
            return Ok(Outcome::Accepted);
        }
        if self.pending_closures.len() >= MAX_PENDING_EDGES {
            if let Some(old) = self.pending_closures.pop_front() {
                self.report.expired_closures += 1;
                tracing::warn!(
                    closure = %format!("{} - {}", key::label(old.key_a), key::label(old.key_b)),
                    "backend: loop closure dropped after waiting for a keyframe that never came"
                );
            }
        }
        self.pending_closures.push_back(input);
        Ok(Outcome::Waiting)
    }

    /// An odometry edge sample: checked, de-duplicated, then journaled and applied once
    /// both keyframes are in the graph (held until then).
    pub fn on_odometry(
        &mut self,
        edge: &OdometryEdge,
        journal: &mut impl Append,
    ) -> Result<Outcome, JournalError> {
        let input = match check_odometry(edge, self.robot_index) {
            Ok(i) => i,
            Err(e) => return Ok(self.rejected(e)),
        };
        if self.odometry.contains(&(input.from, input.to))
            || self
                .pending
                .iter()
                .any(|p| (p.from, p.to) == (input.from, input.to))
        {
            self.report.duplicates += 1;
            return Ok(Outcome::Duplicate);
        }
        if self.can_insert_edge(&input) {
            self.journal_edge(&input, journal)?;
            self.insert_edge(input);
            self.report.accepted_edges += 1;
            return Ok(Outcome::Accepted);
        }
        if self.pending.len() >= MAX_PENDING_EDGES {
            // The oldest waiter is the one least likely to ever see its keyframe.
            if let Some(old) = self.pending.pop_front() {
                self.report.expired_edges += 1;
                tracing::warn!(
                    from = old.from,
                    to = old.to,
                    "backend: odometry edge dropped after waiting for keyframes that never came"
                );
            }
        }
        self.pending.push_back(input);
        Ok(Outcome::Waiting)
    }

    /// Whether enough new keyframes arrived since the last optimization.
    pub fn optimization_due(&self) -> bool {
        self.since_optimized >= self.optimize_every && !self.graph.edges().is_empty()
    }

    /// Re-optimizes the graph warm-started from the current estimate (the optimizer's
    /// symbolic factorization is kept while the pattern allows). A failure (a graph in the
    /// middle of being built may be disconnected) leaves the estimate as it was.
    pub fn optimize(&mut self) -> Result<Summary, SolveError> {
        self.since_optimized = 0;
        let opts = SolverOptions::default();
        let result = match self.optimizer.as_mut() {
            Some(opt) => opt.optimize(&mut self.graph, &opts),
            None => Optimizer::new(&self.graph, 0)
                .and_then(|opt| self.optimizer.insert(opt).optimize(&mut self.graph, &opts)),
        };
        match &result {
            Ok(_) => self.report.optimizations += 1,
            Err(_) => self.report.failed_optimizations += 1,
        }
        result
    }

    /// The newest keyframe's id and pose estimate.
    pub fn latest_estimate(&self) -> Option<(u64, SE3)> {
        let (&k, p) = self.graph.keys().last().zip(self.graph.poses().last())?;
        Some((key::index(k), *p))
    }

    /// Every keyframe's id, stamp and current estimate, in the order they arrived.
    pub fn trajectory(&self) -> impl Iterator<Item = (u64, u64, &SE3)> {
        self.graph
            .keys()
            .iter()
            .zip(&self.stamps)
            .zip(self.graph.poses())
            .map(|((&k, &stamp_ns), pose)| (key::index(k), stamp_ns, pose))
    }

    fn rejected(&mut self, e: InputError) -> Outcome {
        self.report.rejected += 1;
        Outcome::Rejected(e)
    }

    fn insert_keyframe(&mut self, input: &KeyframeInput) {
        let k = self.key(input.id);
        let i = self.graph.add_pose(k, input.pose);
        self.stamps.resize(self.stamps.len().max(i + 1), 0);
        self.stamps[i] = input.stamp_ns;
        self.received.insert(input.id, (input.stamp_ns, input.pose));
        self.next_id = Some(self.next_id.map_or(input.id + 1, |n| n.max(input.id + 1)));
        if let Some(team) = self.team.as_mut() {
            if let Err(e) = team.add_pose(k, input.pose) {
                self.report.team_refused += 1;
                tracing::error!(
                    "backend: distributed back-end refused keyframe {}: {e}",
                    input.id
                );
            }
        }
    }

    /// Whether this robot's keyframe of the closure is in the graph (both, for one of its
    /// own loops) and the closure is new.
    fn can_insert_closure(&self, c: &ClosureInput) -> bool {
        if is_intra(c) {
            return self.graph.index_of(c.key_a).is_some()
                && self.graph.index_of(c.key_b).is_some()
                && !self.intra.contains(c);
        }
        let own = if key::robot(c.key_a) == Some(self.robot) {
            c.key_a
        } else {
            c.key_b
        };
        self.graph.index_of(own).is_some() && !self.closures.contains(&(c.key_a, c.key_b))
    }

    fn journal_closure(
        &mut self,
        c: &ClosureInput,
        journal: &mut impl Append,
    ) -> Result<(), JournalError> {
        journal.append(&Entry::Closure {
            key_a: c.key_a,
            key_b: c.key_b,
            relative: pose_to_array(&c.relative),
            information: upper_from_matrix(&c.information),
            inliers: u64::from(c.inliers),
        })
    }

    /// Records a closure whose keyframe of this robot is in the graph; the local graph
    /// holds this robot's poses only, so an inter-robot closure goes to the distributed
    /// back-end; one of the robot's own loops becomes a PCM candidate ([`Self::apply_intra`]
    /// puts the consistent ones in the graph).
    fn insert_closure(&mut self, c: ClosureInput) {
        if is_intra(&c) {
            self.report.intra_closures += 1;
            self.intra.add(c);
            return;
        }
        self.closures.insert((c.key_a, c.key_b));
        self.closures.insert((c.key_b, c.key_a));
        self.closure_list.push(c.clone());
        if let Some(team) = self.team.as_mut() {
            if let Err(e) = team.add_closure(c.key_a, c.key_b, c.relative, c.information) {
                self.report.team_refused += 1;
                tracing::error!(
                    "backend: distributed back-end refused closure {} - {}: {e}",
                    key::label(c.key_a),
                    key::label(c.key_b)
                );
            }
        }
    }

    /// PCM over the robot's own loop closures; the graph then holds exactly the kept ones
    /// (a closure PCM drops again is taken out by rebuilding the graph's edges; the
    /// distributed back-end, which cannot take an edge back, keeps it and the count says so).
    fn apply_intra(&mut self) {
        let checked = match self.intra.check(&self.graph) {
            Ok(c) if c.changed => c,
            Ok(_) => return,
            Err(e) => {
                tracing::error!("backend: PCM of the robot's own loops: {e}");
                return;
            }
        };
        (
            self.report.intra_frozen_kept,
            self.report.intra_frozen_rejected,
        ) = self.intra.frozen();
        let kept: std::collections::BTreeSet<(u64, u64)> =
            self.intra.kept().map(|c| (c.key_a, c.key_b)).collect();
        // Only the window's verdicts can change: a frozen kept closure stays.
        let dropped: Vec<(u64, u64)> = self
            .intra
            .candidates()
            .iter()
            .map(|c| (c.key_a, c.key_b))
            .filter(|p| self.intra_in_graph.contains(p) && !kept.contains(p))
            .collect();
        if !dropped.is_empty() {
            self.report.intra_retracted += dropped.len();
            tracing::warn!(
                closures = dropped.len(),
                "backend: PCM dropped own loop closures it had kept; taken out of the graph"
            );
            let mut graph = PoseGraph::new();
            for (&k, p) in self.graph.keys().iter().zip(self.graph.poses()) {
                graph.add_pose(k, *p);
            }
            let keys = self.graph.keys().to_vec();
            for e in self.graph.edges() {
                let pair = (keys[e.i], keys[e.j]);
                if dropped.contains(&pair) {
                    continue;
                }
                let _ = graph.add_edge(e.i, e.j, e.measured, e.information);
            }
            self.graph = graph;
            self.optimizer = None;
            for p in &dropped {
                self.intra_in_graph.remove(p);
            }
        }
        let new: Vec<ClosureInput> = checked
            .frozen_kept
            .iter()
            .chain(self.intra.kept())
            .filter(|c| !self.intra_in_graph.contains(&(c.key_a, c.key_b)))
            .cloned()
            .collect();
        for c in new {
            let (Some(i), Some(j)) = (self.graph.index_of(c.key_a), self.graph.index_of(c.key_b))
            else {
                continue;
            };
            match self.graph.add_edge(i, j, c.relative, c.information) {
                Ok(_) => {
                    self.intra_in_graph.insert((c.key_a, c.key_b));
                    self.since_optimized = self.optimize_every;
                    if let Some(team) = self.team.as_mut() {
                        if let Err(e) =
                            team.add_odometry(c.key_a, c.key_b, c.relative, c.information)
                        {
                            self.report.team_refused += 1;
                            tracing::error!(
                                "backend: distributed back-end refused own loop {} - {}: {e}",
                                key::label(c.key_a),
                                key::label(c.key_b)
                            );
                        }
                    }
                }
                Err(e) => tracing::error!(
                    "backend: own loop {} - {} refused by the graph: {e}",
                    key::label(c.key_a),
                    key::label(c.key_b)
                ),
            }
        }
        self.report.intra_kept = self.intra_in_graph.len();
    }

    fn can_insert_edge(&self, e: &OdometryInput) -> bool {
        self.has_keyframe(e.from)
            && self.has_keyframe(e.to)
            && !self.odometry.contains(&(e.from, e.to))
    }

    fn journal_edge(
        &mut self,
        e: &OdometryInput,
        journal: &mut impl Append,
    ) -> Result<(), JournalError> {
        journal.append(&Entry::Odometry {
            from: e.from,
            to: e.to,
            relative: pose_to_array(&e.relative),
            information: upper_from_matrix(&e.information),
        })
    }

    /// Adds an edge whose keyframes are in the graph (checked by the caller).
    fn insert_edge(&mut self, e: OdometryInput) {
        let (Some(a), Some(b)) = (
            self.graph.index_of(self.key(e.from)),
            self.graph.index_of(self.key(e.to)),
        ) else {
            return;
        };
        // The input checks enforce what add_edge checks (distinct keyframes, finite
        // measurement, positive-definite information), so a refusal here is a bug: logged.
        match self.graph.add_edge(a, b, e.relative, e.information) {
            Ok(_) => {
                self.odometry.insert((e.from, e.to));
                let (ka, kb) = (self.key(e.from), self.key(e.to));
                if let Some(team) = self.team.as_mut() {
                    if let Err(err) = team.add_odometry(ka, kb, e.relative, e.information) {
                        self.report.team_refused += 1;
                        tracing::error!(
                            from = e.from,
                            to = e.to,
                            "backend: distributed back-end refused odometry edge: {err}"
                        );
                    }
                }
            }
            Err(err) => tracing::error!(
                from = e.from,
                to = e.to,
                "backend: odometry edge refused by the graph: {err}"
            ),
        }
    }

    /// Applies every waiting edge whose keyframes have arrived.
    fn flush_pending(&mut self, journal: &mut impl Append) -> Result<(), JournalError> {
        let mut waiting = VecDeque::with_capacity(self.pending.len());
        while let Some(e) = self.pending.pop_front() {
            if self.can_insert_edge(&e) {
                self.journal_edge(&e, journal)?;
                self.insert_edge(e);
                self.report.accepted_edges += 1;
            } else {
                waiting.push_back(e);
            }
        }
        self.pending = waiting;
        let mut waiting = VecDeque::with_capacity(self.pending_closures.len());
        let mut intra = false;
        while let Some(c) = self.pending_closures.pop_front() {
            if self.can_insert_closure(&c) {
                self.journal_closure(&c, journal)?;
                if is_intra(&c) {
                    intra = true;
                } else {
                    self.report.accepted_closures += 1;
                }
                self.insert_closure(c);
            } else {
                waiting.push_back(c);
            }
        }
        self.pending_closures = waiting;
        if intra {
            self.apply_intra();
        }
        Ok(())
    }
}
