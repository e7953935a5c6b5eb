//! Pose graphs: poses keyed by `u64`, between-factors with information matrices.
//!
//! The graph only holds problems the solver can take as they are: every edge joins two
//! distinct existing poses and has a finite, symmetric information matrix that is positive
//! definite unless the caller explicitly chose otherwise ([`InformationCheck::AsIs`]). The
//! edge list is private so that this holds for every graph, not just for those built
//! carefully; `doorslam_geometry::check_information` holds the rules, shared with the g2o
//! reader and the back-end service's input checks.

use std::collections::BTreeMap;

use doorslam_geometry::information::{check_information, InformationCheck, InformationError};
use doorslam_geometry::{key, LieGroup, TangentMatrix};

/// What an edge is, for per-class robust kernels and for PCM.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum EdgeClass {
    /// Consecutive poses of one robot.
    Odometry,
    /// Non-consecutive poses of one robot.
    IntraLoop,
    /// Poses of two different robots.
    InterLoop,
}

/// `z ≈ Xᵢ⁻¹ Xⱼ` with information `Ω` (rotation-first tangent order, see [`doorslam_geometry::lie`]).
#[derive(Debug, Clone, PartialEq)]
pub struct BetweenFactor<G> {
    /// Index of pose i in the graph.
    pub i: usize,
    /// Index of pose j in the graph.
    pub j: usize,
    pub measured: G,
    pub information: TangentMatrix,
}

/// Why [`PoseGraph::add_edge`] refused an edge; nothing was added.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EdgeError {
    #[error("edge from pose {label} (index {index}) to itself")]
    SelfLoop { index: usize, label: String },
    #[error("pose index {index} is out of range: the graph has {len} poses")]
    UnknownPose { index: usize, len: usize },
    #[error("edge {from} -> {to}: the measurement is not finite")]
    NonFiniteMeasurement { from: String, to: String },
    #[error("edge {from} -> {to}: {source}")]
    Information {
        from: String,
        to: String,
        #[source]
        source: InformationError,
    },
}

/// A pose graph: poses (dense indices, each with its original key) and between-factors.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseGraph<G> {
    keys: Vec<u64>,
    poses: Vec<G>,
    index: BTreeMap<u64, usize>,
    edges: Vec<BetweenFactor<G>>,
}

impl<G: LieGroup> Default for PoseGraph<G> {
    fn default() -> Self {
        Self {
            keys: Vec::new(),
            poses: Vec::new(),
            index: BTreeMap::new(),
            edges: Vec::new(),
        }
    }
}

impl<G: LieGroup> PoseGraph<G> {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a pose, or overwrites the estimate of an existing key; returns its index.
    pub fn add_pose(&mut self, key: u64, pose: G) -> usize {
        if let Some(&i) = self.index.get(&key) {
            self.poses[i] = pose;
            return i;
        }
        self.keys.push(key);
        self.poses.push(pose);
        self.index.insert(key, self.poses.len() - 1);
        self.poses.len() - 1
    }

    /// Adds a between-factor on two existing, distinct poses (by index) with a positive-
    /// definite information matrix; returns the new edge's index.
    pub fn add_edge(
        &mut self,
        i: usize,
        j: usize,
        measured: G,
        information: TangentMatrix,
    ) -> Result<usize, EdgeError> {
        self.add_edge_with(
            i,
            j,
            measured,
            information,
            InformationCheck::PositiveDefinite,
        )
    }

    /// [`Self::add_edge`] with an explicit information check: `InformationCheck::AsIs`
    /// accepts indefinite matrices (still finite and symmetric).
    pub fn add_edge_with(
        &mut self,
        i: usize,
        j: usize,
        measured: G,
        information: TangentMatrix,
        check: InformationCheck,
    ) -> Result<usize, EdgeError> {
        for index in [i, j] {
            if index >= self.len() {
                return Err(EdgeError::UnknownPose {
                    index,
                    len: self.len(),
                });
            }
        }
        if i == j {
            // Its two Jacobian blocks would land on one diagonal block, which the solver's
            // pattern has no off-diagonal slot for; and it constrains nothing.
            return Err(EdgeError::SelfLoop {
                index: i,
                label: key::label(self.keys[i]),
            });
        }
        let names = || (key::label(self.keys[i]), key::label(self.keys[j]));
        if measured.log().iter().any(|v| !v.is_finite()) {
            let (from, to) = names();
            return Err(EdgeError::NonFiniteMeasurement { from, to });
        }
        check_information(&information, G::DIM, check).map_err(|source| {
            let (from, to) = names();
            EdgeError::Information { from, to, source }
        })?;
        self.edges.push(BetweenFactor {
            i,
            j,
            measured,
            information,
        });
        Ok(self.edges.len() - 1)
    }

    /// The between-factors, in the order they were added.
    pub fn edges(&self) -> &[BetweenFactor<G>] {
        &self.edges
    }

    /// Keeps only the edges for which `keep` is true (in order). Removing edges cannot make
    /// an edge invalid, so this is the one mutation of the edge list besides adding.
    pub fn retain_edges(&mut self, keep: impl FnMut(&BetweenFactor<G>) -> bool) {
        self.edges.retain(keep);
    }

    pub fn len(&self) -> usize {
        self.poses.len()
    }
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }
    pub fn keys(&self) -> &[u64] {
        &self.keys
    }
    pub fn poses(&self) -> &[G] {
        &self.poses
    }
    pub fn poses_mut(&mut self) -> &mut [G] {
        &mut self.poses
    }
    pub fn index_of(&self, key: u64) -> Option<usize> {
        self.index.get(&key).copied()
    }

    /// Class of an edge from its keys.
    pub fn edge_class(&self, e: &BetweenFactor<G>) -> EdgeClass {
        let (a, b) = (self.keys[e.i], self.keys[e.j]);
        if key::robot(a) != key::robot(b) {
            EdgeClass::InterLoop
        } else if key::index(a).abs_diff(key::index(b)) == 1 {
            EdgeClass::Odometry
        } else {
            EdgeClass::IntraLoop
        }
    }

    /// Which poses are connected to pose `start` through edges (in either direction).
    pub fn reachable_from(&self, start: usize) -> Vec<bool> {
        let mut adj = vec![Vec::new(); self.len()];
        for e in &self.edges {
            adj[e.i].push(e.j);
            adj[e.j].push(e.i);
        }
        let mut seen = vec![false; self.len()];
        if start >= self.len() {
            return seen;
        }
        let mut stack = vec![start];
        seen[start] = true;
        while let Some(a) = stack.pop() {
            for &b in &adj[a] {
                if !seen[b] {
                    seen[b] = true;
                    stack.push(b);
                }
            }
        }
        seen
    }

    /// χ² = Σ rᵀ Ω r with r = Log(Z⁻¹ Xᵢ⁻¹ Xⱼ) (twice GTSAM's `graph.error`).
    pub fn chi2(&self) -> f64 {
        self.edges.iter().map(|e| self.edge_chi2(e)).sum()
    }

    /// rᵀ Ω r of one edge at the current estimate.
    pub fn edge_chi2(&self, e: &BetweenFactor<G>) -> f64 {
        let r = between_residual(&self.poses[e.i], &self.poses[e.j], &e.measured);
        r.dot(&(e.information * r))
    }
}

/// `r = Log(Z⁻¹ Xᵢ⁻¹ Xⱼ)`.
pub fn between_residual<G: LieGroup>(xi: &G, xj: &G, z: &G) -> doorslam_geometry::Tangent {
    z.inverse().compose(&xi.inverse().compose(xj)).log()
}

/// The residual and its Jacobians w.r.t. right perturbations of Xᵢ and Xⱼ:
/// `∂r/∂δⱼ = Jr⁻¹(r)` and `∂r/∂δᵢ = -Jr⁻¹(r) Ad(Xⱼ⁻¹ Xᵢ)`.
pub fn between_linearized<G: LieGroup>(
    xi: &G,
    xj: &G,
    z: &G,
) -> (doorslam_geometry::Tangent, TangentMatrix, TangentMatrix) {
    let xij = xi.inverse().compose(xj);
    let r = z.inverse().compose(&xij).log();
    let jr_inv = G::right_jacobian_inv(&r);
    let jj = jr_inv;
    let ji = -(jr_inv * xij.inverse().adjoint());
    (r, ji, jj)
}
