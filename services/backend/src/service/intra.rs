//! A robot's own loop closures (the team link's intra-robot chain: its new keyframes against
//! its older ones, verified by PnP): the candidates the back-end received, PCM among them
//! (`doorslam pcm --intra` semantics: one problem for the robot, the odometry chained
//! with its covariances, cliques of at least `min_clique`), and which of them the graph
//! holds. A wrong closure (a look-alike building, a facade shifted by one window) is
//! consistent with no true one, so it stays out of the clique while the true closures of a
//! revisit confirm each other.
//!
//! Bounded (`[backend] intra_pcm_window`): PCM runs over the newest `window` candidates
//! only, plus the newest `window / 4` closures it kept earlier as anchors (a new wrong
//! candidate is still judged against accepted ones). A candidate that leaves the window
//! keeps its last verdict (frozen): kept stays in the graph, rejected is forgotten but for
//! its pair key in `seen` (duplicates are refused; that set grows with the map, 32 bytes a
//! candidate). Without the bound, a robot that revisits its route piles up hundreds of
//! mutually consistent candidates and the maximum clique over all of them stalls the
//! back-end (the soak, BENCHMARKS).

use std::collections::{BTreeSet, HashSet, VecDeque};

use doorslam_geometry::{key, SE3};

use super::input::ClosureInput;
use crate::graph::{EdgeClass, PoseGraph};
use crate::outliers::pcm::{Odometry, Pcm, PcmError, Scope};

/// Default of `[backend] intra_pcm_window`.
pub const DEFAULT_INTRA_PCM_WINDOW: usize = 64;

/// What one [`IntraLoops::check`] changed.
#[derive(Debug, Clone, Default)]
pub struct Checked {
    /// The kept set of the window changed (or candidates were frozen).
    pub changed: bool,
    /// Candidates that left the window kept: they stay in the graph for good (the caller
    /// adds any it does not hold yet).
    pub frozen_kept: Vec<ClosureInput>,
}

/// The intra-robot closures of one back-end.
#[derive(Debug, Clone)]
pub struct IntraLoops {
    /// Settings only: never run, each check clones it (PCM stores every closure it saw,
    /// so one kept across checks would grow without bound).
    pcm: Pcm,
    window: usize,
    anchors_max: usize,
    /// The window: candidates not frozen yet, oldest first (above `window` only between
    /// [`Self::add`] and [`Self::check`]).
    candidates: Vec<ClosureInput>,
    /// How many of the oldest candidates the last PCM run judged (their verdict is in
    /// `kept`); the newer ones wait for the next run.
    decided: usize,
    /// The newest frozen kept closures, PCM's anchors.
    anchors: VecDeque<ClosureInput>,
    seen: HashSet<(u64, u64)>,
    /// Keys of the window's candidates the last PCM run kept.
    kept: BTreeSet<(u64, u64)>,
    /// A candidate arrived since the last run.
    dirty: bool,
    /// The odometry the last run saw, up to the newest keyframe any candidate joins.
    seen_odometry: Option<OdometryPrint>,
    /// The graph's odometry chained (brought up to date at each check).
    odometry: Odometry,
    frozen_kept: usize,
    frozen_rejected: usize,
}

/// What PCM's verdicts depend on besides the candidates: the odometry edges and poses up
/// to the newest keyframe a candidate or anchor joins (edges are never changed once in
/// the graph, so counts tell whether any was added there).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct OdometryPrint {
    last_index: u64,
    edges: usize,
    poses: usize,
}

impl IntraLoops {
    /// PCM with consistency probability `p` and smallest clique `min_clique` (the
    /// `[backend]` PCM settings) over the newest `window` candidates (at least 2).
    pub fn new(p: f64, min_clique: usize, window: usize) -> Result<Self, PcmError> {
        let mut pcm = Pcm::new(p, Scope::IntraRobot)?;
        pcm.min_clique = min_clique.max(1);
        let window = window.max(2);
        Ok(Self {
            pcm,
            window,
            anchors_max: window / 4,
            candidates: Vec::new(),
            decided: 0,
            anchors: VecDeque::new(),
            seen: HashSet::new(),
            kept: BTreeSet::new(),
            dirty: false,
            seen_odometry: None,
            odometry: Odometry::default(),
            frozen_kept: 0,
            frozen_rejected: 0,
        })
    }

    /// The candidates in the window (not frozen yet).
    pub fn candidates(&self) -> &[ClosureInput] {
        &self.candidates
    }

    /// Candidates that left the window kept, and rejected.
    pub fn frozen(&self) -> (usize, usize) {
        (self.frozen_kept, self.frozen_rejected)
    }

    /// Whether the pair is known already (either direction), frozen ones included.
    pub fn contains(&self, c: &ClosureInput) -> bool {
        self.seen.contains(&(c.key_a, c.key_b))
    }

    /// A new candidate (both keyframes are in the graph: checked by the caller).
    pub fn add(&mut self, c: ClosureInput) {
        self.seen.insert((c.key_a, c.key_b));
        self.seen.insert((c.key_b, c.key_a));
        self.candidates.push(c);
        self.dirty = true;
    }

    /// The window's candidates PCM keeps now (a subset of [`Self::candidates`]).
    pub fn kept(&self) -> impl Iterator<Item = &ClosureInput> {
        self.candidates
            .iter()
            .filter(|c| self.kept.contains(&(c.key_a, c.key_b)))
    }

    /// Freezes what left the window, then runs PCM over the window and the anchors with
    /// `graph`'s odometry (its intra-loop edges, the closures it holds, left out: they are
    /// candidates or anchors here). Skipped when no candidate arrived and the odometry
    /// among the candidates' keyframes is the same as at the last run (keyframes appended
    /// after them change no verdict).
    pub fn check(&mut self, graph: &PoseGraph<SE3>) -> Result<Checked, PcmError> {
        let mut out = Checked::default();
        if self.candidates.is_empty() {
            return Ok(out);
        }
        let print = self.odometry_print(graph);
        if !self.dirty && self.seen_odometry == Some(print) {
            return Ok(out);
        }
        // Only the keyframes and odometry edges new since the last check are chained: the
        // cost of a check grows with the window, not with the flight.
        self.odometry.update(graph)?;
        while self.candidates.len() > self.window {
            let n = (self.candidates.len() - self.window).min(self.window);
            if n > self.decided {
                // More arrived at once than the window holds (a journal replay): the
                // oldest are judged together before they freeze.
                self.kept = self.run(graph, self.window)?;
                self.decided = self.window;
            }
            for c in self.candidates.drain(..n) {
                let pair = (c.key_a, c.key_b);
                if self.kept.remove(&pair) {
                    self.frozen_kept += 1;
                    self.anchors.push_back(c.clone());
                    if self.anchors.len() > self.anchors_max {
                        self.anchors.pop_front();
                    }
                    out.frozen_kept.push(c);
                } else {
                    self.frozen_rejected += 1;
                }
            }
            self.decided -= n;
        }
        let kept = self.run(graph, self.candidates.len())?;
        out.changed = kept != self.kept || !out.frozen_kept.is_empty();
        self.kept = kept;
        self.decided = self.candidates.len();
        self.dirty = false;
        // After the freezing: the anchors may have changed the newest keyframe.
        self.seen_odometry = Some(self.odometry_print(graph));
        Ok(out)
    }

    /// PCM over the anchors and the oldest `n` candidates of the window, with the odometry
    /// of `graph` (chained in `self.odometry`); the keys of those candidates it keeps, as
    /// received. PCM's graph holds only the keyframes the closures join.
    fn run(&self, graph: &PoseGraph<SE3>, n: usize) -> Result<BTreeSet<(u64, u64)>, PcmError> {
        let mut g = PoseGraph::new();
        let window = &self.candidates[..n];
        for c in self.anchors.iter().chain(window) {
            let (Some(a), Some(b)) = (graph.index_of(c.key_a), graph.index_of(c.key_b)) else {
                continue;
            };
            let i = g
                .index_of(c.key_a)
                .unwrap_or_else(|| g.add_pose(c.key_a, graph.poses()[a]));
            let j = g
                .index_of(c.key_b)
                .unwrap_or_else(|| g.add_pose(c.key_b, graph.poses()[b]));
            let _ = g.add_edge(i, j, c.relative, c.information);
        }
        let mut pcm = self.pcm.clone();
        let summary = pcm.run_with(&g, &self.odometry)?;
        // PCM orients closures (lower index first); map back to the pairs as received.
        let inliers: HashSet<(u64, u64)> = summary
            .inliers
            .iter()
            .flat_map(|&(u, v)| [(u, v), (v, u)])
            .collect();
        Ok(window
            .iter()
            .map(|c| (c.key_a, c.key_b))
            .filter(|p| inliers.contains(p))
            .collect())
    }

    fn odometry_print(&self, graph: &PoseGraph<SE3>) -> OdometryPrint {
        let last_index = self
            .candidates
            .iter()
            .chain(&self.anchors)
            .flat_map(|c| [key::index(c.key_a), key::index(c.key_b)])
            .max()
            .unwrap_or(0);
        let keys = graph.keys();
        let edges = graph
            .edges()
            .iter()
            .filter(|e| {
                graph.edge_class(e) == EdgeClass::Odometry
                    && key::index(keys[e.i]).max(key::index(keys[e.j])) <= last_index
            })
            .count();
        let poses = keys
            .iter()
            .filter(|k| key::index(**k) <= last_index)
            .count();
        OdometryPrint {
            last_index,
            edges,
            poses,
        }
    }
}

/// Whether a closure joins two keyframes of one robot.
pub fn is_intra(c: &ClosureInput) -> bool {
    key::robot(c.key_a) == key::robot(c.key_b)
}
