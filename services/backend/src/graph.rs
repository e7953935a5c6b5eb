//! Pose graphs: poses keyed by `u64`, between-factors with information matrices.
//!
//! The graph only holds problems the solver can take as they are: every edge joins two
//! distinct existing poses and has a finite, symmetric information matrix that is positive
//! definite unless the caller explicitly chose otherwise ([`InformationCheck::AsIs`]). The
//! edge list is private so that this holds for every graph, not just for those built
//! carefully; [`check_information`] holds the rules, shared with the g2o reader.

use std::collections::BTreeMap;

use crate::lie::{LieGroup, TangentMatrix};

/// GTSAM's multi-robot key convention: `key = (robot_char << 56) | index`.
pub mod key {
    /// The key of pose `index` of robot `robot` (0 = 'a', 1 = 'b', ...).
    pub fn symbol(robot: u8, index: u64) -> u64 {
        ((b'a' + robot) as u64) << 56 | (index & ((1 << 56) - 1))
    }
    /// The robot (0 = 'a') of a multi-robot key, or `None` for a plain single-robot index.
    pub fn robot(key: u64) -> Option<u8> {
        let c = (key >> 56) as u8;
        c.is_ascii_lowercase().then(|| c - b'a')
    }
    /// The per-robot index of a key.
    pub fn index(key: u64) -> u64 {
        if robot(key).is_some() {
            key & ((1 << 56) - 1)
        } else {
            key
        }
    }
    /// `a12`-style label for messages, or the plain number.
    pub fn label(key: u64) -> String {
        match robot(key) {
            Some(r) => format!("{}{}", (b'a' + r) as char, index(key)),
            None => key.to_string(),
        }
    }
}

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

/// `z ≈ Xᵢ⁻¹ Xⱼ` with information `Ω` (rotation-first tangent order, see [`crate::lie`]).
#[derive(Debug, Clone, PartialEq)]
pub struct BetweenFactor<G> {
    /// Index of pose i in the graph.
    pub i: usize,
    /// Index of pose j in the graph.
    pub j: usize,
    pub measured: G,
    pub information: TangentMatrix,
}

/// How strictly [`PoseGraph::add_edge_with`] (and the g2o reader) checks an information
/// matrix. Finiteness and symmetry are always required: a NaN poisons the cost, and the
/// solver reads only the lower triangle, so an asymmetric matrix would silently become a
/// different one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum InformationCheck {
    /// Also positive definite (the default): an indefinite Ω makes rᵀΩr negative in some
    /// directions, so the cost is not a sum of squares and Gauss-Newton's normal equations
    /// may be singular or indefinite.
    #[default]
    PositiveDefinite,
    /// Use the matrix as written even if it is indefinite or singular: published benchmark
    /// files (SE-Sync's cubicle) contain such matrices and other solvers accept them.
    /// Levenberg-Marquardt's damping keeps its steps defined; Gauss-Newton may fail.
    AsIs,
}

/// Why an information matrix was refused by [`check_information`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InformationError {
    #[error("information matrix entry ({row}, {col}) is {value}, not finite")]
    NonFinite { row: usize, col: usize, value: f64 },
    #[error(
        "information matrix is not symmetric: entries ({row}, {col}) and ({col}, {row}) are {a} and {b}"
    )]
    NotSymmetric {
        row: usize,
        col: usize,
        a: f64,
        b: f64,
    },
    #[error("information matrix is not positive definite")]
    NotPositiveDefinite,
}

/// Relative tolerance of the symmetry check, against the largest entry: a matrix computed
/// as `AᵀA` or as an inverse is symmetric only to rounding.
pub const SYMMETRY_TOLERANCE: f64 = 1e-9;

/// The one definition of an acceptable information matrix, for the graph API and the g2o
/// reader alike: the leading `dim × dim` block (the rest is padding, see [`crate::lie`])
/// must be finite, symmetric to [`SYMMETRY_TOLERANCE`] and, with
/// [`InformationCheck::PositiveDefinite`], have a Cholesky factorization.
pub fn check_information(
    information: &TangentMatrix,
    dim: usize,
    check: InformationCheck,
) -> Result<(), InformationError> {
    let dim = dim.min(6);
    let mut scale = 0.0f64;
    for col in 0..dim {
        for row in 0..dim {
            let value = information[(row, col)];
            if !value.is_finite() {
                return Err(InformationError::NonFinite { row, col, value });
            }
            scale = scale.max(value.abs());
        }
    }
    for col in 0..dim {
        for row in col + 1..dim {
            let (a, b) = (information[(row, col)], information[(col, row)]);
            if (a - b).abs() > SYMMETRY_TOLERANCE * scale {
                return Err(InformationError::NotSymmetric { row, col, a, b });
            }
        }
    }
    if check == InformationCheck::PositiveDefinite
        && information
            .view((0, 0), (dim, dim))
            .into_owned()
            .cholesky()
            .is_none()
    {
        return Err(InformationError::NotPositiveDefinite);
    }
    Ok(())
}

/// Eigenvalues of a repaired matrix are at least this fraction of its largest one: small
/// enough to stay close to the original, large enough for the condition number (1e8) to
/// leave the Cholesky factorization well defined.
pub const NEAREST_PD_FLOOR: f64 = 1e-8;

/// The nearest positive-definite matrix to the (symmetrized) leading `dim × dim` block:
/// symmetric eigen-decomposition with the eigenvalues clamped to [`NEAREST_PD_FLOOR`]
/// times the largest magnitude (the Frobenius-nearest PSD matrix clamps to 0, which is not
/// definite). The padding is zeroed. `None` if an entry is not finite or all are zero: then
/// there is no scale to repair towards.
pub fn nearest_positive_definite(information: &TangentMatrix, dim: usize) -> Option<TangentMatrix> {
    let dim = dim.min(6);
    let block = information.view((0, 0), (dim, dim)).into_owned();
    if block.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let sym = (&block + block.transpose()) * 0.5;
    let eig = sym.symmetric_eigen();
    let largest = eig.eigenvalues.amax();
    if largest <= 0.0 {
        return None;
    }
    let floor = NEAREST_PD_FLOOR * largest;
    let clamped = eig.eigenvalues.map(|l| l.max(floor));
    let v = &eig.eigenvectors;
    let repaired = v * nalgebra::DMatrix::from_diagonal(&clamped) * v.transpose();
    let mut out = TangentMatrix::zeros();
    for c in 0..dim {
        for r in 0..dim {
            // Average the mirror entries: the product is symmetric only to rounding.
            out[(r, c)] = 0.5 * (repaired[(r, c)] + repaired[(c, r)]);
        }
    }
    Some(out)
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
pub fn between_residual<G: LieGroup>(xi: &G, xj: &G, z: &G) -> crate::lie::Tangent {
    z.inverse().compose(&xi.inverse().compose(xj)).log()
}

/// The residual and its Jacobians w.r.t. right perturbations of Xᵢ and Xⱼ:
/// `∂r/∂δⱼ = Jr⁻¹(r)` and `∂r/∂δᵢ = -Jr⁻¹(r) Ad(Xⱼ⁻¹ Xᵢ)`.
pub fn between_linearized<G: LieGroup>(
    xi: &G,
    xj: &G,
    z: &G,
) -> (crate::lie::Tangent, TangentMatrix, TangentMatrix) {
    let xij = xi.inverse().compose(xj);
    let r = z.inverse().compose(&xij).log();
    let jr_inv = G::right_jacobian_inv(&r);
    let jj = jr_inv;
    let ji = -(jr_inv * xij.inverse().adjoint());
    (r, ji, jj)
}
