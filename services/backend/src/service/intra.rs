//! A robot's own loop closures (the team link's intra-robot chain: its new keyframes against
//! its older ones, verified by PnP): every candidate the back-end received, PCM among them
//! (`doorslam pcm --intra` semantics: one problem for the robot, the odometry chained
//! with its covariances, cliques of at least `min_clique`), and which of them the graph
//! holds. A wrong closure (a look-alike building, a facade shifted by one window) is
//! consistent with no true one, so it stays out of the clique while the true closures of a
//! revisit confirm each other.

use std::collections::{BTreeSet, HashSet};

use doorslam_geometry::{key, SE3};

use super::input::ClosureInput;
use crate::graph::{EdgeClass, PoseGraph};
use crate::outliers::pcm::{Pcm, PcmError, Scope};

/// The intra-robot closures of one back-end.
#[derive(Debug, Clone)]
pub struct IntraLoops {
    pcm: Pcm,
    candidates: Vec<ClosureInput>,
    seen: HashSet<(u64, u64)>,
    /// Keys of the candidates the last PCM run kept.
    kept: BTreeSet<(u64, u64)>,
}

impl IntraLoops {
    /// PCM with consistency probability `p` and smallest clique `min_clique` (the
    /// `[backend]` PCM settings).
    pub fn new(p: f64, min_clique: usize) -> Result<Self, PcmError> {
        let mut pcm = Pcm::new(p, Scope::IntraRobot)?;
        pcm.min_clique = min_clique.max(1);
        Ok(Self {
            pcm,
            candidates: Vec::new(),
            seen: HashSet::new(),
            kept: BTreeSet::new(),
        })
    }

    /// Candidates received (copies of one pair count once).
    pub fn candidates(&self) -> &[ClosureInput] {
        &self.candidates
    }

    /// Whether the pair is known already (either direction).
    pub fn contains(&self, c: &ClosureInput) -> bool {
        self.seen.contains(&(c.key_a, c.key_b))
    }

    /// A new candidate (both keyframes are in the graph: checked by the caller).
    pub fn add(&mut self, c: ClosureInput) {
        self.seen.insert((c.key_a, c.key_b));
        self.seen.insert((c.key_b, c.key_a));
        self.candidates.push(c);
    }

    /// The candidates PCM keeps now (a subset of [`Self::candidates`]).
    pub fn kept(&self) -> impl Iterator<Item = &ClosureInput> {
        self.candidates
            .iter()
            .filter(|c| self.kept.contains(&(c.key_a, c.key_b)))
    }

    /// Runs PCM over every candidate with `graph`'s odometry (its intra-loop edges, the
    /// closures it holds, left out: they are candidates here); returns whether the kept
    /// set changed.
    pub fn check(&mut self, graph: &PoseGraph<SE3>) -> Result<bool, PcmError> {
        if self.candidates.is_empty() {
            return Ok(false);
        }
        let mut g = PoseGraph::new();
        for (&k, p) in graph.keys().iter().zip(graph.poses()) {
            g.add_pose(k, *p);
        }
        for e in graph.edges() {
            if graph.edge_class(e) == EdgeClass::Odometry {
                // The same indices: the poses were added in the same order.
                let _ = g.add_edge(e.i, e.j, e.measured, e.information);
            }
        }
        for c in &self.candidates {
            let (Some(i), Some(j)) = (g.index_of(c.key_a), g.index_of(c.key_b)) else {
                continue;
            };
            let _ = g.add_edge(i, j, c.relative, c.information);
        }
        let summary = self.pcm.run(&g)?;
        // PCM orients closures (lower index first); map back to the pairs as received.
        let kept: BTreeSet<(u64, u64)> = summary
            .inliers
            .iter()
            .flat_map(|&(u, v)| [(u, v), (v, u)])
            .filter(|p| self.seen.contains(p))
            .collect();
        let kept: BTreeSet<(u64, u64)> = self
            .candidates
            .iter()
            .map(|c| (c.key_a, c.key_b))
            .filter(|p| kept.contains(p))
            .collect();
        let changed = kept != self.kept;
        self.kept = kept;
        Ok(changed)
    }
}

/// Whether a closure joins two keyframes of one robot.
pub fn is_intra(c: &ClosureInput) -> bool {
    key::robot(c.key_a) == key::robot(c.key_b)
}
