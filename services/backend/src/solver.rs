//! Gauss-Newton and Levenberg-Marquardt on pose graphs, over the sparse normal equations.
//!
//! Each iteration linearizes every between-factor (`r`, `∂r/∂δᵢ`, `∂r/∂δⱼ`, see
//! [`crate::graph::between_linearized`]), adds `JᵀΩJ` and `JᵀΩr` into a block pattern built
//! once ([`crate::sparsity`]), and solves with faer's sparse Cholesky, whose symbolic
//! factorization is computed once per pattern ([`crate::linear`]). One pose (the anchor) is
//! held fixed to remove the gauge freedom. Levenberg-Marquardt damps with `λ·I` (as GTSAM
//! does by default) and adapts λ by the gain ratio (Nielsen's rule). Marquardt's `λ·diag(H)`
//! was tried first and is worse here: on long trajectories the Laplacian-like normal
//! equations have eigenvalues ~1/N² of their diagonal, so even λ = 1e-5 relative damping
//! slows the low-frequency (drift) modes — kitti_00 took 10 iterations instead of 3.

use std::time::Instant;

use faer::Mat;

use crate::graph::{between_linearized, between_residual, EdgeClass, PoseGraph};
use crate::linear::{LinearError, SparseCholesky};
use crate::robust::{gnc_tls_weight, Kernel};
use crate::sparsity::{BlockPattern, DiagonalSlot, OffDiagonalSlot};
use doorslam_geometry::{key, LieGroup, Tangent, TangentMatrix};

/// How many poses a [`SolveError::Disconnected`] names.
const DISCONNECTED_SHOWN: usize = 10;

/// Failures of the optimizer.
#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    #[error("the graph has no poses")]
    Empty,
    #[error("anchor pose index {0} is out of range")]
    Anchor(usize),
    #[error("{}", disconnected_message(.anchor, *.count, .first))]
    Disconnected {
        /// Label of the anchor pose ([`doorslam_geometry::key::label`]).
        anchor: String,
        /// How many poses no chain of edges connects to the anchor.
        count: usize,
        /// Labels of the first of them (at most 10), in index order.
        first: Vec<String>,
    },
    #[error(transparent)]
    Linear(#[from] LinearError),
    #[error(
        "the normal equations are not positive definite ({0}) although every pose is connected to \
         the anchor: an information matrix is indefinite or singular (Levenberg-Marquardt damps \
         this, Gauss-Newton cannot)"
    )]
    NotPositiveDefinite(String),
    #[error("non-finite cost after linearization (a NaN in the graph?)")]
    NonFinite,
}

fn disconnected_message(anchor: &str, count: usize, first: &[String]) -> String {
    let more = match count.saturating_sub(first.len()) {
        0 => String::new(),
        n => format!(" and {n} more"),
    };
    format!(
        "{count} pose{} not connected to the anchor {anchor} by any chain of edges ({}{more}): \
         the problem is not fully constrained (add edges, or optimize each part separately)",
        if count == 1 { " is" } else { "s are" },
        first.join(", ")
    )
}

/// Gauss-Newton or Levenberg-Marquardt.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Method {
    GaussNewton,
    #[default]
    LevenbergMarquardt,
}

/// Options of [`optimize`]; `Default` gives the settings `doorslam pgo` uses.
#[derive(Debug, Clone, PartialEq)]
pub struct SolverOptions {
    pub method: Method,
    pub max_iterations: usize,
    /// Stop when an accepted step lowers the cost by less than this fraction of it.
    pub relative_tolerance: f64,
    /// Stop when an accepted step lowers the cost (χ²) by less than this, or the cost
    /// itself is below it (GTSAM's `absoluteErrorTol`, on χ² rather than χ²/2).
    pub absolute_tolerance: f64,
    pub lambda_initial: f64,
    /// Kernel of odometry edges.
    pub odometry_kernel: Kernel,
    /// Kernel of loop closures (intra- and inter-robot).
    pub loop_kernel: Kernel,
}

impl Default for SolverOptions {
    fn default() -> Self {
        Self {
            method: Method::LevenbergMarquardt,
            max_iterations: 100,
            relative_tolerance: 1e-5,
            absolute_tolerance: 2e-5,
            lambda_initial: 1e-5,
            odometry_kernel: Kernel::None,
            loop_kernel: Kernel::None,
        }
    }
}

/// Which convergence test stopped a solve (the tolerances of [`SolverOptions`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Criterion {
    /// The cost is at most `absolute_tolerance`.
    SmallCost,
    /// An accepted step lowered the cost by at most `relative_tolerance` of it, or by at
    /// most `absolute_tolerance`.
    SmallDecrease,
    /// No step lowered the cost, but the linearized model predicted a decrease within
    /// those same tolerances: the estimate is at a minimum to numerical precision (e.g.
    /// re-solving an already optimized graph), and rounding decides the comparison.
    SmallPredictedDecrease,
}

/// Why a solve stopped. Only [`StopReason::Converged`] means the estimate is a minimum.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    Converged(Criterion),
    /// `max_iterations` linearizations without meeting a convergence test.
    MaxIterations,
    /// Levenberg-Marquardt damped up to its limit (λ > 1e10) without finding a step that
    /// lowers the cost, although the model predicted a decrease beyond the tolerances.
    NoDecrease,
    /// The step or the cost at the candidate was not finite (NaN/∞): the normal
    /// equations are numerically singular, e.g. from indefinite information matrices.
    NonFiniteStep,
    /// A Gauss-Newton step raised the cost while the model predicted a decrease: the
    /// linearization is not valid that far from the estimate (Levenberg-Marquardt would
    /// damp the step instead).
    Diverged,
    /// Graduated non-convexity ran all its rounds without its weights settling to 0/1.
    GncNotSettled,
    /// The cost is below zero: some information matrices are indefinite (used as written,
    /// [`crate::graph::InformationCheck::AsIs`]), so the objective is not a sum of squares
    /// and may decrease without bound. Stopped there: no estimate beyond is more
    /// meaningful (repair the matrices instead, e.g. `--information nearest-pd`).
    NegativeCost,
}

impl StopReason {
    /// Whether the solve met a convergence test.
    pub fn is_converged(&self) -> bool {
        matches!(self, StopReason::Converged(_))
    }

    /// A stable snake_case name, for JSON output and scripts.
    pub fn as_str(&self) -> &'static str {
        match self {
            StopReason::Converged(Criterion::SmallCost) => "converged_small_cost",
            StopReason::Converged(Criterion::SmallDecrease) => "converged_small_decrease",
            StopReason::Converged(Criterion::SmallPredictedDecrease) => {
                "converged_small_predicted_decrease"
            }
            StopReason::MaxIterations => "max_iterations",
            StopReason::NoDecrease => "no_decrease",
            StopReason::NonFiniteStep => "non_finite_step",
            StopReason::Diverged => "diverged",
            StopReason::GncNotSettled => "gnc_not_settled",
            StopReason::NegativeCost => "negative_cost",
        }
    }
}

impl std::fmt::Display for StopReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            StopReason::Converged(Criterion::SmallCost) => "converged (cost below the absolute tolerance)",
            StopReason::Converged(Criterion::SmallDecrease) => "converged (decrease below the tolerance)",
            StopReason::Converged(Criterion::SmallPredictedDecrease) => {
                "converged (at a minimum: predicted decrease below the tolerance)"
            }
            StopReason::MaxIterations => "not converged: iteration limit reached",
            StopReason::NoDecrease => "not converged: no step lowers the cost (damping limit reached)",
            StopReason::NonFiniteStep => "not converged: non-finite step (numerically singular normal equations)",
            StopReason::Diverged => "not converged: the Gauss-Newton step raised the cost (diverging; try Levenberg-Marquardt)",
            StopReason::GncNotSettled => "not converged: GNC weights did not settle",
            StopReason::NegativeCost => "not converged: the cost fell below zero (indefinite information matrices: the objective may be unbounded below)",
        })
    }
}

/// What an optimization did.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// χ² = Σ rᵀΩr before and after (without robust kernels or weights).
    pub initial_chi2: f64,
    pub final_chi2: f64,
    /// Linearizations (outer iterations), summed over GNC rounds.
    pub iterations: usize,
    /// `stop_reason.is_converged()`.
    pub converged: bool,
    pub stop_reason: StopReason,
    /// Symbolic factorizations computed (1 unless the graph's structure changed).
    pub symbolic_builds: usize,
    /// Final weight of each edge (1 without GNC; GNC's inlier weights otherwise).
    pub weights: Vec<f64>,
    pub time_s: f64,
}

/// Where one edge's blocks live in the values array.
struct EdgeSlots {
    /// Variable index of pose i and j (`None` for the anchor).
    vi: Option<usize>,
    vj: Option<usize>,
    /// The off-diagonal block (both poses variables; never the same one, see
    /// [`PoseGraph::add_edge`]).
    off: Option<OffDiagonalSlot>,
}

/// The optimizer's reusable state: pattern, offsets and the Cholesky with its symbolic
/// factorization. Keep it across calls to re-solve an updated graph warm-started.
pub struct Optimizer {
    anchor: usize,
    poses: usize,
    /// (i, j) of every edge, in edge order: the offsets in `slots` are per edge position,
    /// so they are valid exactly for a graph with this list (equal counts are not enough:
    /// replacing one edge by another keeps them and moves a block).
    structure: Vec<(usize, usize)>,
    bdim: usize,
    pattern: BlockPattern,
    slots: Vec<EdgeSlots>,
    diag: Vec<DiagonalSlot>,
    diagonal: Vec<usize>,
    linear: SparseCholesky,
}

/// Index of pose `p` among the optimized variables (`None` for the fixed anchor).
pub(crate) fn var_of(p: usize, anchor: usize) -> Option<usize> {
    use std::cmp::Ordering::*;
    match p.cmp(&anchor) {
        Less => Some(p),
        Equal => None,
        Greater => Some(p - 1),
    }
}

impl Optimizer {
    /// Prepares the pattern for `graph` with pose `anchor` held fixed.
    pub fn new<G: LieGroup>(graph: &PoseGraph<G>, anchor: usize) -> Result<Self, SolveError> {
        if graph.is_empty() {
            return Err(SolveError::Empty);
        }
        if anchor >= graph.len() {
            return Err(SolveError::Anchor(anchor));
        }
        check_connected(graph, anchor)?;
        let bdim = G::DIM;
        let n_vars = graph.len() - 1;
        let pairs = graph
            .edges()
            .iter()
            .filter_map(|e| Some((var_of(e.i, anchor)?, var_of(e.j, anchor)?)));
        let pattern = BlockPattern::new(n_vars, bdim, pairs);
        let diag = pattern.diagonal_blocks();
        let slots = graph
            .edges()
            .iter()
            .map(|e| {
                let (vi, vj) = (var_of(e.i, anchor), var_of(e.j, anchor));
                let off = match (vi, vj) {
                    (Some(a), Some(b)) => pattern.off_diagonal_block(a, b),
                    _ => None,
                };
                EdgeSlots { vi, vj, off }
            })
            .collect();
        let diagonal = pattern.diagonal_offsets();
        Ok(Self {
            anchor,
            poses: graph.len(),
            structure: graph.edges().iter().map(|e| (e.i, e.j)).collect(),
            bdim,
            pattern,
            slots,
            diag,
            diagonal,
            linear: SparseCholesky::new(),
        })
    }

    /// Whether this optimizer still matches the graph's structure: the same number of poses
    /// and the same (i, j) for every edge, in order.
    pub fn matches<G: LieGroup>(&self, graph: &PoseGraph<G>) -> bool {
        self.poses == graph.len()
            && self.structure.len() == graph.edges().len()
            && self
                .structure
                .iter()
                .zip(graph.edges())
                .all(|(&(i, j), e)| i == e.i && j == e.j)
    }

    /// Re-prepares after poses or edges were added, keeping the Cholesky (its symbolic
    /// factorization is recomputed only if the pattern changed).
    pub fn update<G: LieGroup>(&mut self, graph: &PoseGraph<G>) -> Result<(), SolveError> {
        if self.matches(graph) {
            return Ok(());
        }
        let linear = std::mem::take(&mut self.linear);
        *self = Self::new(graph, self.anchor)?;
        self.linear = linear;
        Ok(())
    }

    /// Assembles H (lower, into `values`) and g = JᵀWΩr at the current poses.
    fn linearize<G: LieGroup>(
        &self,
        graph: &PoseGraph<G>,
        weights: &[f64],
        values: &mut [f64],
        g: &mut [f64],
    ) {
        values.fill(0.0);
        g.fill(0.0);
        let d = self.bdim;
        let poses = graph.poses();
        for ((e, slot), &w) in graph.edges().iter().zip(&self.slots).zip(weights) {
            if w == 0.0 {
                continue;
            }
            let (r, ji, jj) = between_linearized(&poses[e.i], &poses[e.j], &e.measured);
            let om = e.information * w;
            let om_r = om * r;
            if let Some(a) = slot.vi {
                let om_ji = om * ji;
                self.pattern
                    .add_diagonal(values, &self.diag[a], &(ji.transpose() * om_ji));
                add_gradient(g, a, d, &(ji.transpose() * om_r));
                if let (Some(b), Some(off)) = (slot.vj, &slot.off) {
                    // Off-diagonal block rows = higher variable index.
                    let block: TangentMatrix = if b > a {
                        jj.transpose() * om_ji
                    } else {
                        ji.transpose() * (om * jj)
                    };
                    self.pattern.add_off_diagonal(values, off, &block);
                }
            }
            if let Some(b) = slot.vj {
                self.pattern
                    .add_diagonal(values, &self.diag[b], &(jj.transpose() * (om * jj)));
                add_gradient(g, b, d, &(jj.transpose() * om_r));
            }
        }
    }
}

fn add_gradient(g: &mut [f64], var: usize, d: usize, v: &Tangent) {
    for k in 0..d {
        g[var * d + k] += v[k];
    }
}

/// Fails with [`SolveError::Disconnected`] naming the poses no chain of edges connects to
/// `anchor`: their normal equations are singular (gauge freedom per component), which the
/// Cholesky factorization would report only as "not positive definite".
pub(crate) fn check_connected<G: LieGroup>(
    graph: &PoseGraph<G>,
    anchor: usize,
) -> Result<(), SolveError> {
    if anchor >= graph.len() {
        return Err(SolveError::Anchor(anchor));
    }
    let reached = graph.reachable_from(anchor);
    let mut missing = reached.iter().enumerate().filter(|(_, r)| !**r);
    let first: Vec<String> = missing
        .by_ref()
        .take(DISCONNECTED_SHOWN)
        .map(|(p, _)| key::label(graph.keys()[p]))
        .collect();
    if first.is_empty() {
        return Ok(());
    }
    Err(SolveError::Disconnected {
        anchor: key::label(graph.keys()[anchor]),
        count: first.len() + missing.count(),
        first,
    })
}

/// Kernel of each edge from its class.
fn kernels<G: LieGroup>(graph: &PoseGraph<G>, opts: &SolverOptions) -> Vec<Kernel> {
    graph
        .edges()
        .iter()
        .map(|e| match graph.edge_class(e) {
            EdgeClass::Odometry => opts.odometry_kernel,
            EdgeClass::IntraLoop | EdgeClass::InterLoop => opts.loop_kernel,
        })
        .collect()
}

/// (robust weighted cost, plain χ²) of `poses`.
fn costs<G: LieGroup>(
    graph: &PoseGraph<G>,
    poses: &[G],
    kernels: &[Kernel],
    weights: &[f64],
) -> (f64, f64) {
    let (mut robust, mut chi2) = (0.0, 0.0);
    for ((e, k), w) in graph.edges().iter().zip(kernels).zip(weights) {
        let r = between_residual(&poses[e.i], &poses[e.j], &e.measured);
        let s = r.dot(&(e.information * r));
        chi2 += s;
        // GNC's static weights stand in for its kernel.
        robust += w * if matches!(k, Kernel::Gnc { .. }) {
            s
        } else {
            k.cost(s)
        };
    }
    (robust, chi2)
}

/// Optimizes `graph` in place with pose `anchor` fixed. With a GNC loop kernel, runs
/// graduated non-convexity around the least-squares solver.
pub fn optimize<G: LieGroup>(
    graph: &mut PoseGraph<G>,
    anchor: usize,
    opts: &SolverOptions,
) -> Result<Summary, SolveError> {
    let mut opt = Optimizer::new(graph, anchor)?;
    opt.optimize(graph, opts)
}

impl Optimizer {
    /// Optimizes `graph` (which must match this optimizer's structure; see [`Self::update`]).
    pub fn optimize<G: LieGroup>(
        &mut self,
        graph: &mut PoseGraph<G>,
        opts: &SolverOptions,
    ) -> Result<Summary, SolveError> {
        self.update(graph)?;
        let start = Instant::now();
        let kernels = kernels(graph, opts);
        let initial_chi2 = graph.chi2();
        let mut weights = vec![1.0; graph.edges().len()];
        let (iterations, stop_reason) = match opts.loop_kernel {
            Kernel::Gnc { c2 } => self.gnc(graph, opts, &kernels, &mut weights, c2)?,
            _ => self.least_squares(graph, opts, &kernels, &weights, opts.max_iterations)?,
        };
        Ok(Summary {
            initial_chi2,
            final_chi2: graph.chi2(),
            iterations,
            converged: stop_reason.is_converged(),
            stop_reason,
            symbolic_builds: self.linear.symbolic_builds(),
            weights,
            time_s: start.elapsed().as_secs_f64(),
        })
    }

    /// GNC-TLS on the loop closures: weights start near 1 (convex surrogate) and are driven
    /// to 0/1 as μ grows; each round re-solves the weighted least squares warm-started.
    /// Converged when the weights settled and the last round's solve converged (the stop
    /// reason is that solve's).
    fn gnc<G: LieGroup>(
        &mut self,
        graph: &mut PoseGraph<G>,
        opts: &SolverOptions,
        kernels: &[Kernel],
        weights: &mut [f64],
        c2: f64,
    ) -> Result<(usize, StopReason), SolveError> {
        let is_gnc: Vec<bool> = kernels
            .iter()
            .map(|k| matches!(k, Kernel::Gnc { .. }))
            .collect();
        let mut total = 0;
        let (first, reason) =
            self.least_squares(graph, opts, kernels, weights, opts.max_iterations)?;
        total += first;
        let residuals = |graph: &PoseGraph<G>| -> Vec<f64> {
            graph.edges().iter().map(|e| graph.edge_chi2(e)).collect()
        };
        let s = residuals(graph);
        let max_s = s
            .iter()
            .zip(&is_gnc)
            .filter(|(_, g)| **g)
            .map(|(s, _)| *s)
            .fold(0.0, f64::max);
        if max_s <= c2 {
            return Ok((total, reason)); // every loop closure already within the threshold
        }
        let mut mu = c2 / (2.0 * max_s - c2);
        for _round in 0..100 {
            let s = residuals(graph);
            let mut changed = 0.0f64;
            for (k, w) in weights.iter_mut().enumerate() {
                if is_gnc[k] {
                    let nw = gnc_tls_weight(s[k], c2, mu);
                    changed = changed.max((nw - *w).abs());
                    *w = nw;
                }
            }
            let binary = weights
                .iter()
                .zip(&is_gnc)
                .all(|(w, g)| !*g || *w < 1e-9 || *w > 1.0 - 1e-9);
            let (it, reason) =
                self.least_squares(graph, opts, kernels, weights, opts.max_iterations)?;
            total += it;
            if binary && changed < 1e-9 {
                return Ok((total, reason));
            }
            mu *= 1.4;
        }
        Ok((total, StopReason::GncNotSettled))
    }

    /// Levenberg-Marquardt / Gauss-Newton with fixed per-edge weights and IRLS kernels.
    fn least_squares<G: LieGroup>(
        &mut self,
        graph: &mut PoseGraph<G>,
        opts: &SolverOptions,
        kernels: &[Kernel],
        static_weights: &[f64],
        max_iterations: usize,
    ) -> Result<(usize, StopReason), SolveError> {
        let n = self.pattern.dim();
        let d = self.bdim;
        let mut values = vec![0.0; self.pattern.nnz()];
        let mut damped = vec![0.0; self.pattern.nnz()];
        let mut g = vec![0.0; n];
        let mut candidate = graph.poses().to_vec();
        let mut weights = static_weights.to_vec();
        let (mut cost, _) = costs(graph, graph.poses(), kernels, static_weights);
        if !cost.is_finite() {
            return Err(SolveError::NonFinite);
        }
        let mut lambda = opts.lambda_initial;
        let mut nu = 2.0;
        let lm = opts.method == Method::LevenbergMarquardt;
        // Whether a decrease the model predicts is within the convergence tolerances.
        let negligible = |predicted: f64, cost: f64| {
            predicted <= opts.relative_tolerance * cost || predicted <= opts.absolute_tolerance
        };
        for it in 0..max_iterations {
            // A sum of squares cannot go below zero; this one can, so it has no minimum to
            // converge to (and "below the tolerance" would be true of any negative value).
            if cost < 0.0 {
                return Ok((it, StopReason::NegativeCost));
            }
            if cost <= opts.absolute_tolerance {
                return Ok((it, StopReason::Converged(Criterion::SmallCost)));
            }
            // IRLS: kernel weights at the current estimate times the static weights.
            for (k, e) in graph.edges().iter().enumerate() {
                weights[k] = static_weights[k] * kernels[k].weight(graph.edge_chi2(e));
            }
            self.linearize(graph, &weights, &mut values, &mut g);
            // The decrease predicted by this iteration's first (least damped) solve: when no
            // step lowers the cost, it tells a minimum apart from a failure.
            let mut first_predicted: Option<f64> = None;
            loop {
                damped.copy_from_slice(&values);
                if lm {
                    for &p in &self.diagonal {
                        damped[p] += lambda;
                    }
                }
                let mut delta = Mat::from_fn(n, 1, |i, _| -g[i]);
                match self
                    .linear
                    .solve_in_place(self.pattern.as_matrix(&damped), delta.as_mut())
                {
                    Ok(()) => {}
                    Err(LinearError::NotPositiveDefinite(_)) if lm && lambda < 1e10 => {
                        lambda *= nu;
                        nu *= 2.0;
                        continue;
                    }
                    // Connectivity was checked: the gauge is fixed, so the cause is in Ω.
                    Err(LinearError::NotPositiveDefinite(detail)) => {
                        return Err(SolveError::NotPositiveDefinite(detail))
                    }
                    Err(e) => return Err(e.into()),
                }
                // Candidate poses X ⊕ δ (the anchor stays).
                for (p, c) in candidate.iter_mut().enumerate() {
                    *c = match var_of(p, self.anchor) {
                        Some(v) => {
                            let mut t = Tangent::zeros();
                            for k in 0..d {
                                t[k] = delta[(v * d + k, 0)];
                            }
                            graph.poses()[p].oplus(&t)
                        }
                        None => graph.poses()[p],
                    };
                }
                let (new_cost, _) = costs(graph, &candidate, kernels, static_weights);
                // Predicted decrease of the damped linear model: -gᵀδ + λ δᵀδ.
                let mut predicted = 0.0;
                for i in 0..n {
                    predicted -= g[i] * delta[(i, 0)];
                }
                if lm {
                    predicted +=
                        lambda * (0..n).map(|i| delta[(i, 0)] * delta[(i, 0)]).sum::<f64>();
                }
                let finite = new_cost.is_finite()
                    && predicted.is_finite()
                    && (0..n).all(|i| delta[(i, 0)].is_finite());
                if finite && new_cost < cost {
                    graph.poses_mut().copy_from_slice(&candidate);
                    let decrease = cost - new_cost;
                    cost = new_cost;
                    if lm {
                        let rho = decrease / predicted.max(f64::MIN_POSITIVE);
                        lambda *= (1.0f64 / 3.0).max(1.0 - (2.0 * rho - 1.0).powi(3));
                        nu = 2.0;
                    }
                    if cost < 0.0 {
                        return Ok((it + 1, StopReason::NegativeCost));
                    }
                    if negligible(decrease, cost + decrease) {
                        return Ok((it + 1, StopReason::Converged(Criterion::SmallDecrease)));
                    }
                    break;
                }
                let first = *first_predicted.get_or_insert(predicted);
                // No decrease with this step. At a minimum, rounding decides the comparison
                // and the model predicted (almost) nothing: that is convergence. Otherwise
                // GN has no fallback, and LM gives up at its damping limit.
                let at_minimum = first.is_finite() && negligible(first, cost);
                if !lm || lambda > 1e10 {
                    let reason = if at_minimum {
                        StopReason::Converged(Criterion::SmallPredictedDecrease)
                    } else if !finite {
                        StopReason::NonFiniteStep
                    } else if lm {
                        StopReason::NoDecrease
                    } else {
                        StopReason::Diverged
                    };
                    return Ok((it + 1, reason));
                }
                lambda *= nu;
                nu *= 2.0;
            }
        }
        Ok((max_iterations, StopReason::MaxIterations))
    }
}
