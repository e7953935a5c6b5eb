//! Pose graphs: poses keyed by `u64`, between-factors with information matrices.

use std::collections::BTreeMap;

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

/// A pose graph: poses (dense indices, each with its original key) and between-factors.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseGraph<G> {
    keys: Vec<u64>,
    poses: Vec<G>,
    index: BTreeMap<u64, usize>,
    pub edges: Vec<BetweenFactor<G>>,
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

    /// Adds a between-factor on two existing poses (by index).
    pub fn add_edge(&mut self, i: usize, j: usize, measured: G, information: TangentMatrix) {
        self.edges.push(BetweenFactor {
            i,
            j,
            measured,
            information,
        });
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
    pub fn edges(&self) -> &[BetweenFactor<G>] {
        &self.edges
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
