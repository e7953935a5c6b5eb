//! What the back-end leaves in its state folder for people and tools, rewritten
//! atomically (temporary file + rename) every `write_every` and when it stops:
//!
//! - `odometry.tum`: every keyframe's pose as the front-end sent it (the odometry alone),
//!   TUM format (`stamp_s x y z qx qy qz qw`, stamps from the keyframes);
//! - `team_estimate.tum`: the distributed back-end's estimate of this robot's keyframes,
//!   in the team's frame (the lowest robot's first keyframe) once anchored, TUM format;
//! - `keyframes.csv`: `id,stamp_ns` of every keyframe (keys ↔ times, e.g. for ground truth);
//! - `graph.g2o`: this robot's keyframes (odometry poses), odometry edges and the
//!   inter-robot closures it took (before PCM), multi-robot keys: the robots' files merged
//!   (`doorslam pcm a/graph.g2o b/graph.g2o ...`) are the team's graph, for a centralized
//!   reference;
//! - `backend.json`: counters ([`BackendReport`]), the relay's and the agent's, closures
//!   rejected by PCM, present peers, whether the team estimate converged.
//!
//! `doorslam eval ate team_estimate.tum groundtruth.tum --format tum` compares them.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use doorslam_geometry::key;
use serde::Serialize;

use super::state::{BackendReport, BackendState};
use super::team::BridgeStats;
use super::trajectory::tum_text;
use super::ServiceError;
use crate::g2o::{se3_edge_line, se3_vertex_line};

/// The output files of one back-end.
#[derive(Debug, Clone)]
pub struct Outputs {
    dir: PathBuf,
}

/// `backend.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Status {
    pub keyframes: usize,
    pub odometry_edges: usize,
    pub closures: usize,
    pub closures_waiting: usize,
    pub report: ReportJson,
    pub team: Option<TeamStatus>,
}

/// The counters of [`BackendReport`] that matter to an operator.
#[derive(Debug, Clone, Serialize)]
pub struct ReportJson {
    pub accepted_keyframes: usize,
    pub accepted_edges: usize,
    pub accepted_closures: usize,
    pub recovered_keyframes: usize,
    pub recovered_edges: usize,
    pub recovered_closures: usize,
    pub duplicates: usize,
    pub gaps: usize,
    pub rejected: usize,
    pub optimizations: usize,
    pub failed_optimizations: usize,
    pub team_refused: usize,
    /// Own loop closures received, kept by PCM in the graph, and dropped again.
    pub intra_closures: usize,
    pub intra_kept: usize,
    pub intra_retracted: usize,
    /// Own loop candidates frozen when they left PCM's window, kept and rejected.
    pub intra_frozen_kept: usize,
    pub intra_frozen_rejected: usize,
}

impl From<&BackendReport> for ReportJson {
    fn from(r: &BackendReport) -> Self {
        Self {
            accepted_keyframes: r.accepted_keyframes,
            accepted_edges: r.accepted_edges,
            accepted_closures: r.accepted_closures,
            recovered_keyframes: r.recovered_keyframes,
            recovered_edges: r.recovered_edges,
            recovered_closures: r.recovered_closures,
            duplicates: r.duplicates,
            gaps: r.gaps,
            rejected: r.rejected,
            optimizations: r.optimizations,
            failed_optimizations: r.failed_optimizations,
            team_refused: r.team_refused,
            intra_closures: r.intra_closures,
            intra_kept: r.intra_kept,
            intra_retracted: r.intra_retracted,
            intra_frozen_kept: r.intra_frozen_kept,
            intra_frozen_rejected: r.intra_frozen_rejected,
        }
    }
}

/// The distributed back-end's state.
#[derive(Debug, Clone, Serialize)]
pub struct TeamStatus {
    pub epoch: u64,
    pub anchored: bool,
    /// The robot (key letter) whose first keyframe is the team frame.
    pub anchor: String,
    /// Settled (nothing in flight or due, refinement done) and the team solve behind this
    /// robot's estimate met the solver's convergence test (false when it stopped on its
    /// iteration limit), on the solver and on every robot it sends estimates to.
    pub converged: bool,
    /// Nothing in flight or due and refinement done, whatever the solver's stop reason.
    pub settled: bool,
    /// Why the team solve behind this robot's estimate stopped (`converged_small_decrease`,
    /// `max_iterations`, ...): the solver's own, or the one that came down with the
    /// separator estimates; null before any solution, and with the DGS method.
    pub stop_reason: Option<String>,
    /// The team solve behind this robot's estimate: the solver's solve count that came
    /// down with its separator estimates (on the solver, its own count); null before any.
    pub round: Option<u64>,
    /// Per robot (key letter) this one hands separator estimates down to: the round of the
    /// estimates it handed to the team link for it. That robot's `round` is the same once
    /// they arrived; until then both may say `converged` while it still holds an older
    /// solve (the link delivers, the back-ends do not see it).
    pub rounds_handed_down: BTreeMap<String, u64>,
    pub present: Vec<String>,
    pub neighbors: Vec<String>,
    /// Closures PCM left out of the last solve, as key labels.
    pub rejected_closures: Vec<[String; 2]>,
    pub steps: u64,
    pub updates: u64,
    /// Back-end messages that arrived before the first closure with their sender, held
    /// until it came (`distributed::PARKED_MAX`), and of them dropped with the hold full.
    pub held_before_closure: u64,
    pub held_dropped: u64,
    pub relay: BridgeStats,
    /// `relay.refused` per peer robot (key letter) and message kind.
    pub refused_from: BTreeMap<String, BTreeMap<String, u64>>,
}

/// A robot's key letter (`a` for 0): the label of its keyframe 0 without the index.
fn letter(r: u8) -> String {
    match key::symbol(r, 0) {
        Ok(k) => {
            let mut l = key::label(k);
            l.pop();
            l
        }
        Err(_) => r.to_string(),
    }
}

impl Outputs {
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
        }
    }

    fn write_file(&self, name: &str, text: &str) -> Result<(), ServiceError> {
        let path = self.dir.join(name);
        let tmp = self.dir.join(format!(".{name}.tmp"));
        let io = |source| ServiceError::Output {
            path: path.clone(),
            source,
        };
        std::fs::write(&tmp, text).map_err(io)?;
        std::fs::rename(&tmp, &path).map_err(io)
    }

    /// The status of `state` (what `backend.json` holds).
    pub fn status(state: &BackendState) -> Status {
        let team = state.team().map(|b| {
            let a = b.agent();
            let stats = a.stats();
            TeamStatus {
                epoch: b.epoch(),
                anchored: a.anchored(),
                anchor: letter(a.anchor()),
                converged: a.converged() && a.team_stop_reason().is_none_or(|s| s.is_converged()),
                settled: a.converged(),
                stop_reason: a.team_stop_reason().map(|s| s.as_str().to_string()),
                round: a.team_round(),
                rounds_handed_down: a
                    .rounds_handed_down()
                    .into_iter()
                    .map(|(r, round)| (letter(r), round))
                    .collect(),
                present: b.present().map(letter).collect(),
                neighbors: a.neighbors().map(letter).collect(),
                rejected_closures: a
                    .rejected_closures()
                    .iter()
                    .filter(|(x, y)| x < y)
                    .map(|&(x, y)| [key::label(x), key::label(y)])
                    .collect(),
                steps: stats.steps,
                updates: stats.updates,
                held_before_closure: stats.parked,
                held_dropped: stats.parked_dropped,
                relay: b.stats(),
                refused_from: b
                    .refused_from()
                    .iter()
                    .map(|(r, kinds)| {
                        let kinds = kinds.iter().map(|(k, n)| (k.to_string(), *n));
                        (letter(*r), kinds.collect())
                    })
                    .collect(),
            }
        });
        let report = state.report();
        Status {
            keyframes: state.graph().len(),
            odometry_edges: state.graph().edges().len(),
            closures: report.accepted_closures + report.recovered_closures,
            closures_waiting: state.pending_closures(),
            report: report.into(),
            team,
        }
    }

    /// Writes the three files.
    pub fn write(&self, state: &BackendState) -> Result<(), ServiceError> {
        let received = state.received_poses();
        let odometry = tum_text(
            received
                .iter()
                .map(|(id, (stamp, pose))| (*id, *stamp, pose)),
        );
        self.write_file("odometry.tum", &odometry)?;
        let mut ids = String::from("id,stamp_ns\n");
        for (id, (stamp, _)) in received {
            let _ = writeln!(ids, "{id},{stamp}");
        }
        self.write_file("keyframes.csv", &ids)?;
        if let Some(bridge) = state.team() {
            let team = tum_text(bridge.estimate().filter_map(|(k, pose)| {
                let id = key::index(k);
                received.get(&id).map(|(stamp, _)| (id, *stamp, pose))
            }));
            self.write_file("team_estimate.tum", &team)?;
        }
        let mut g2o = String::new();
        let keys = state.graph().keys();
        for (id, (_, pose)) in received {
            if let Ok(k) = key::symbol(state.robot(), *id) {
                let _ = writeln!(g2o, "{}", se3_vertex_line(k, pose));
            }
        }
        for e in state.graph().edges() {
            let _ = writeln!(
                g2o,
                "{}",
                se3_edge_line(keys[e.i], keys[e.j], &e.measured, &e.information)
            );
        }
        for c in state.closures() {
            let _ = writeln!(
                g2o,
                "{}",
                se3_edge_line(c.key_a, c.key_b, &c.relative, &c.information)
            );
        }
        self.write_file("graph.g2o", &g2o)?;
        let json = serde_json::to_string_pretty(&Self::status(state)).map_err(|e| {
            ServiceError::Output {
                path: self.dir.join("backend.json"),
                source: std::io::Error::other(e),
            }
        })?;
        self.write_file("backend.json", &json)
    }
}
