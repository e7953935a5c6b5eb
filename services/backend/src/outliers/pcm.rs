//! Pairwise Consistency Maximization (Mangelson et al. 2018; DOOR-SLAM §III-C).
//!
//! Two loop closures between the same two trajectories, `z₁` from pose `u₁` (robot α) to
//! `v₁` (robot β) and `z₂` from `u₂` to `v₂`, close a cycle with the odometry of each robot:
//!
//! `T = (x̂ᵤ₁⁻¹ x̂ᵤ₂) · z₂ · (x̂ᵥ₂⁻¹ x̂ᵥ₁) · z₁⁻¹`,   `e = Log(T)`   (paper eq. 1)
//!
//! which is the identity if both closures are right. With the covariances of the four
//! factors propagated to `e` (first order, right perturbations: factor k contributes
//! `Ad((F_{k+1}⋯F₄)⁻¹) Σₖ Ad(⋯)ᵀ`, then `Jr⁻¹(e)` maps to the tangent of `e`), the pair is
//! consistent when the squared Mahalanobis norm `eᵀΣₑ⁻¹e ≤ γ`, `γ = χ²₆ quantile(p)`.
//! The largest mutually consistent set is a maximum clique of the consistency graph.
//!
//! Odometric estimates come from the robots' odometry edges alone (consecutive keys),
//! chained with their covariances; the relative odometry between two poses of a robot is
//! then O(1) from prefix products: `Σᵤᵥ = Σ₀ᵥ − Ad(Tᵤᵥ⁻¹) Σ₀ᵤ Ad(Tᵤᵥ⁻¹)ᵀ`.
//! Each robot pair is its own problem; new closures are checked only against the existing
//! ones and the clique search warm-starts from the previous clique.
//!
//! Copies of one closure (same keys, same measurement to [`DUPLICATE_D2`], in either
//! direction) count once: a lossy radio retransmits, and two copies are perfectly
//! consistent with each other, so without this a single wrong closure sent twice would
//! pass `min_clique = 2` on its own. The first copy is the candidate; later ones, in the
//! same batch or in a later [`Pcm::run`], are listed in [`PcmSummary::duplicates`] and
//! share its verdict (inliers are reported by keys).

use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Matrix6};

use super::max_clique::{maximum_clique, CliqueOptions, ConsistencyGraph};
use crate::graph::{EdgeClass, PoseGraph};
use crate::robust::chi2_quantile;
use doorslam_geometry::key;
use doorslam_geometry::{LieGroup, Tangent};

/// Failures of PCM.
#[derive(Debug, thiserror::Error)]
pub enum PcmError {
    #[error("PCM threshold p = {0} must be a probability strictly between 0 and 1")]
    Threshold(f64),
    #[error("no candidate closures: {0}")]
    NoCandidates(String),
    #[error(
        "information matrix of the edge {a} -> {b} is not positive definite: PCM needs its \
         inverse as a covariance (read the file with --information nearest-pd to repair it)"
    )]
    Covariance { a: String, b: String },
}

/// A loop-closure candidate between pose `u` (first trajectory) and `v` (second).
#[derive(Debug, Clone, PartialEq)]
pub struct Closure {
    pub u: u64,
    pub v: u64,
    /// `z ≈ Xᵤ⁻¹ Xᵥ`.
    pub measured: Isometry3<f64>,
    pub covariance: Matrix6<f64>,
}

impl Closure {
    /// The same closure seen from the other side: `z⁻¹`, covariance `Ad(z) Σ Ad(z)ᵀ`.
    pub fn reversed(&self) -> Self {
        let ad = self.measured.adjoint();
        Closure {
            u: self.v,
            v: self.u,
            measured: self.measured.inverse(),
            covariance: ad * self.covariance * ad.transpose(),
        }
    }
}

/// A pose relative to the start of its odometry segment: (segment, T₀ₘ, Σ₀ₘ at m).
type ChainEntry = (usize, Isometry3<f64>, Matrix6<f64>);
/// A relative pose with its covariance.
type Uncertain = (Isometry3<f64>, Matrix6<f64>);

/// One robot's odometry: cumulative pose and covariance of each pose from the start of
/// its segment (a gap in the odometry chain starts a new segment).
#[derive(Debug, Clone, Default)]
pub struct Odometry {
    /// Per robot: index -> (segment, T₀ₘ, Σ₀ₘ at m).
    chains: BTreeMap<Option<u8>, BTreeMap<u64, ChainEntry>>,
    /// The steps chained so far: (robot, index) -> measurement to index + 1 and its
    /// covariance (the first odometry edge between the two poses).
    steps: HashMap<(Option<u8>, u64), Uncertain>,
}

impl Odometry {
    /// Chains the odometry edges (consecutive indices of one robot) of `graph`.
    pub fn from_graph(graph: &PoseGraph<Isometry3<f64>>) -> Result<Self, PcmError> {
        let mut odo = Odometry::default();
        odo.update(graph)?;
        Ok(odo)
    }

    /// Brings the chains up to `graph`, a graph that holds every pose and odometry edge of
    /// the graphs this was built from, and maybe more (odometry edges never change once in
    /// a graph): only what is new costs. A robot's chain is recomputed from the first index
    /// whose pose or step is new, so a keyframe appended at the end costs one step and a
    /// gap filled in the middle rechains the rest of that robot's flight. The chains are
    /// then those of [`Self::from_graph`] on `graph`.
    pub fn update(&mut self, graph: &PoseGraph<Isometry3<f64>>) -> Result<(), PcmError> {
        let keys = graph.keys();
        // Per robot: the first index to chain again, and the indices new to its chain.
        let mut from: BTreeMap<Option<u8>, u64> = BTreeMap::new();
        let mark = |from: &mut BTreeMap<Option<u8>, u64>, robot, index| {
            let f = from.entry(robot).or_insert(index);
            *f = (*f).min(index);
        };
        for e in graph.edges() {
            if graph.edge_class(e) != EdgeClass::Odometry {
                continue;
            }
            let (a, b) = (keys[e.i], keys[e.j]);
            let lower = (key::robot(a), key::index(a).min(key::index(b)));
            if self.steps.contains_key(&lower) {
                // The first edge between two poses is their step (as in `from_graph`).
                continue;
            }
            let c = closure_of(a, b, e.measured, &e.information)?;
            let c = if key::index(c.u) < key::index(c.v) {
                c
            } else {
                c.reversed()
            };
            self.steps.insert(lower, (c.measured, c.covariance));
            mark(&mut from, lower.0, lower.1 + 1);
        }
        let mut new: BTreeMap<Option<u8>, Vec<u64>> = BTreeMap::new();
        for &k in keys {
            let (robot, index) = (key::robot(k), key::index(k));
            if !self.chains.entry(robot).or_default().contains_key(&index) {
                mark(&mut from, robot, index);
                new.entry(robot).or_default().push(index);
            }
        }
        for (robot, first) in from {
            let chain = self.chains.entry(robot).or_default();
            let mut indices: Vec<u64> = chain.range(first..).map(|(&m, _)| m).collect();
            indices.extend(new.remove(&robot).unwrap_or_default());
            indices.sort_unstable();
            indices.dedup();
            // Segments only need to differ: the new ones number after the last one kept.
            let mut prev: Option<(u64, ChainEntry)> =
                chain.range(..first).next_back().map(|(&m, &e)| (m, e));
            let mut segment = prev.map_or(0, |(_, (s, _, _))| s);
            for m in indices {
                let (t, s) = match prev {
                    Some((p, (_, t, s))) if p + 1 == m => match self.steps.get(&(robot, p)) {
                        Some((z, sz)) => {
                            let ad = z.inverse().adjoint();
                            (t * z, ad * s * ad.transpose() + sz)
                        }
                        None => {
                            segment += 1;
                            (Isometry3::identity(), Matrix6::zeros())
                        }
                    },
                    _ => {
                        segment += 1;
                        (Isometry3::identity(), Matrix6::zeros())
                    }
                };
                let entry = (segment, t, s);
                chain.insert(m, entry);
                prev = Some((m, entry));
            }
        }
        Ok(())
    }

    /// Odometric `x̂ᵤ⁻¹ x̂ᵥ` of two poses of one robot and its covariance, if both lie on
    /// the same odometry segment.
    pub fn between(&self, u: u64, v: u64) -> Option<(Isometry3<f64>, Matrix6<f64>)> {
        let chain = self.chains.get(&key::robot(u))?;
        if key::robot(u) != key::robot(v) {
            return None;
        }
        let &(su, tu, cu) = chain.get(&key::index(u))?;
        let &(sv, tv, cv) = chain.get(&key::index(v))?;
        if su != sv {
            return None;
        }
        if key::index(u) <= key::index(v) {
            let t = tu.inverse() * tv;
            let ad = t.inverse().adjoint();
            Some((t, cv - ad * cu * ad.transpose()))
        } else {
            let t = tv.inverse() * tu;
            let ad = t.inverse().adjoint();
            let forward = cu - ad * cv * ad.transpose();
            let back = t.adjoint();
            Some((t.inverse(), back * forward * back.transpose()))
        }
    }
}

fn closure_of(a: u64, b: u64, z: Isometry3<f64>, info: &Matrix6<f64>) -> Result<Closure, PcmError> {
    let covariance = info
        .cholesky()
        .map(|c| c.inverse())
        .ok_or_else(|| PcmError::Covariance {
            a: key::label(a),
            b: key::label(b),
        })?;
    Ok(Closure {
        u: a,
        v: b,
        measured: z,
        covariance,
    })
}

/// Squared Mahalanobis norm of the cycle error of two closures (paper eq. 1), or `None`
/// if the odometry does not connect their endpoints.
pub fn pairwise_mahalanobis2(odo: &Odometry, c1: &Closure, c2: &Closure) -> Option<f64> {
    let (a, sa) = odo.between(c1.u, c2.u)?;
    let (c, sc) = odo.between(c2.v, c1.v)?;
    let (b, sb) = (c2.measured, c2.covariance);
    let d = c1.measured.inverse();
    let ad_z1 = c1.measured.adjoint();
    let sd = ad_z1 * c1.covariance * ad_z1.transpose();
    // Σ_T = Σₖ Ad((Fₖ₊₁⋯F₄)⁻¹) Σₖ Ad(⋯)ᵀ for T = A·B·C·D.
    let cd = c * d;
    let bcd = b * cd;
    let prop = |after: &Isometry3<f64>, s: &Matrix6<f64>| {
        let ad = after.inverse().adjoint();
        ad * s * ad.transpose()
    };
    let sigma_t = prop(&bcd, &sa) + prop(&cd, &sb) + prop(&d, &sc) + sd;
    let e: Tangent = (a * bcd).log();
    let jr_inv = Isometry3::right_jacobian_inv(&e);
    let sigma_e = jr_inv * sigma_t * jr_inv.transpose();
    let inv = sigma_e.cholesky()?.inverse();
    Some(e.dot(&(inv * e)))
}

/// The closures between one pair of trajectories, their consistency graph and clique.
#[derive(Debug, Clone, Default)]
pub struct PairProblem {
    pub closures: Vec<Closure>,
    graph: ConsistencyGraph,
    clique: Vec<usize>,
    exact: bool,
}

impl PairProblem {
    /// Adds closures, checking each new one against all others (old and new), then
    /// re-solves the maximum clique warm-started from the previous one.
    pub fn add(&mut self, new: Vec<Closure>, odo: &Odometry, gamma: f64, budget: Option<Duration>) {
        for c in new {
            let v = self.graph.add_vertex();
            for (w, other) in self.closures.iter().enumerate() {
                if pairwise_mahalanobis2(odo, other, &c).is_some_and(|d2| d2 <= gamma) {
                    // Both indices exist: add_edge cannot fail here.
                    let _ = self.graph.add_edge(v, w);
                }
            }
            self.closures.push(c);
        }
        let result = maximum_clique(
            &self.graph,
            &CliqueOptions {
                initial: Some(self.clique.clone()),
                time_budget: budget,
            },
        );
        self.clique = result.vertices;
        self.exact = result.exact;
    }

    /// Indices (into `closures`) of the maximum clique.
    pub fn inliers(&self) -> &[usize] {
        &self.clique
    }

    /// The clique if it has at least `min_clique` closures, else nothing: a lone closure
    /// (or too few) between two robots cannot be checked against anything.
    pub fn accepted(&self, min_clique: usize) -> &[usize] {
        if self.clique.len() >= min_clique {
            &self.clique
        } else {
            &[]
        }
    }
    pub fn exact(&self) -> bool {
        self.exact
    }
    /// Whether closures `a` and `b` (indices into `closures`) are pairwise consistent.
    pub fn consistent(&self, a: usize, b: usize) -> bool {
        self.graph.has_edge(a, b)
    }
    pub fn consistent_pairs(&self) -> usize {
        self.graph.edge_count()
    }
}

/// Which closures PCM considers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scope {
    /// Closures between different robots, one problem per robot pair.
    InterRobot,
    /// Non-consecutive closures within each robot, one problem per robot.
    IntraRobot,
}

/// PCM over a whole graph: one [`PairProblem`] per robot pair (or per robot).
#[derive(Debug, Clone)]
pub struct Pcm {
    pub gamma: f64,
    pub scope: Scope,
    pub budget: Option<Duration>,
    /// Smallest clique accepted per robot pair (default 2: a single closure between two
    /// robots is consistent with itself by definition and proves nothing; it is kept
    /// waiting until a second, consistent one arrives).
    pub min_clique: usize,
    /// Check the closures of pairs left without an accepted clique through 3-robot cycles,
    /// and set aside the clique of a pair a triangle of accepted cliques contradicts
    /// ([`super::cycles`]); off by default (plain PCM).
    pub cycles: bool,
    pub problems: BTreeMap<(Option<u8>, Option<u8>), PairProblem>,
}

/// Two closures between the same keys are copies of one when their measurements differ by
/// a squared Mahalanobis distance `eᵀ(Σ₁ + Σ₂)⁻¹e` below this, `e = Log(z₁⁻¹ z₂)`: a
/// thousandth of a standard deviation. That absorbs the rounding of a text round trip or of
/// reversing a closure, while two real measurements of one place differ by O(1).
pub const DUPLICATE_D2: f64 = 1e-6;

/// Whether `b` is a copy of `a` (both oriented the same way, see [`DUPLICATE_D2`]).
fn is_copy(a: &Closure, b: &Closure) -> bool {
    if a.u != b.u || a.v != b.v {
        return false;
    }
    if a.measured == b.measured {
        return true;
    }
    let e: Tangent = (a.measured.inverse() * b.measured).log();
    match (a.covariance + b.covariance).cholesky() {
        Some(c) => e.dot(&c.solve(&e)) <= DUPLICATE_D2,
        None => false,
    }
}

/// Summary of a PCM run.
#[derive(Debug, Clone, PartialEq)]
pub struct PcmSummary {
    /// Distinct candidate closures over all runs (copies count once).
    pub closures: usize,
    /// Indices into this run's `graph.edges()` of candidate edges that copy an earlier
    /// edge of the same graph (see the module docs): not candidates of their own, their
    /// keys are in `inliers` exactly when the closure they copy is kept.
    pub duplicates: Vec<usize>,
    pub consistent_pairs: usize,
    /// Kept closures as (key, key), in the direction they were given.
    pub inliers: Vec<(u64, u64)>,
    pub clique_size: usize,
    /// Of the kept closures, those confirmed through 3-robot cycles ([`Pcm::cycles`]).
    pub cycle_confirmed: usize,
    /// Closures of accepted cliques set aside because a 3-robot cycle contradicts their
    /// pair ([`super::cycles::contradicted_pairs`]; with [`Pcm::cycles`]): not kept.
    pub set_aside: usize,
    pub exact: bool,
    pub time_s: f64,
}

impl Pcm {
    /// `p`: probability that a consistent pair passes with honest covariances.
    pub fn new(p: f64, scope: Scope) -> Result<Self, PcmError> {
        let gamma = chi2_quantile(p, 6).ok_or(PcmError::Threshold(p))?;
        Ok(Self {
            gamma,
            scope,
            budget: None,
            min_clique: 2,
            cycles: false,
            problems: BTreeMap::new(),
        })
    }

    /// Runs PCM on the candidate edges of `graph` (all at once; call again with a larger
    /// graph to add the new closures incrementally). Returns the summary over all pairs.
    pub fn run(&mut self, graph: &PoseGraph<Isometry3<f64>>) -> Result<PcmSummary, PcmError> {
        let start = Instant::now();
        let odo = Odometry::from_graph(graph)?;
        let mut s = self.run_with(graph, &odo)?;
        s.time_s = start.elapsed().as_secs_f64();
        Ok(s)
    }

    /// [`Self::run`] with the odometry chained already (a caller that checks a growing
    /// graph again and again keeps it with [`Odometry::update`]); `graph` then needs only
    /// the poses the candidate edges join.
    pub fn run_with(
        &mut self,
        graph: &PoseGraph<Isometry3<f64>>,
        odo: &Odometry,
    ) -> Result<PcmSummary, PcmError> {
        let start = Instant::now();
        let keys = graph.keys();
        let wanted = match self.scope {
            Scope::InterRobot => EdgeClass::InterLoop,
            Scope::IntraRobot => EdgeClass::IntraLoop,
        };
        let mut new: BTreeMap<(Option<u8>, Option<u8>), Vec<Closure>> = BTreeMap::new();
        let mut total = 0;
        // Closures stored by earlier runs and the ones of this graph so far, by keys: an
        // edge that copies one of this graph is a duplicate; one that matches only a stored
        // closure is that closure, handed in again with the grown graph.
        let mut stored: BTreeMap<(u64, u64), Vec<&Closure>> = BTreeMap::new();
        for p in self.problems.values() {
            for c in &p.closures {
                stored.entry((c.u, c.v)).or_default().push(c);
            }
        }
        let mut this_run: BTreeMap<(u64, u64), Vec<Closure>> = BTreeMap::new();
        let mut duplicates = Vec::new();
        for (n, e) in graph.edges().iter().enumerate() {
            if graph.edge_class(e) != wanted {
                continue;
            }
            total += 1;
            let c = closure_of(keys[e.i], keys[e.j], e.measured, &e.information)?;
            // Orient every closure of a pair the same way (lower robot, then lower index first).
            let c = if (key::robot(c.u), key::index(c.u)) <= (key::robot(c.v), key::index(c.v)) {
                c
            } else {
                c.reversed()
            };
            let seen = this_run.entry((c.u, c.v)).or_default();
            if seen.iter().any(|k| is_copy(k, &c)) {
                duplicates.push(n);
                continue;
            }
            seen.push(c.clone());
            let known = stored
                .get(&(c.u, c.v))
                .is_some_and(|ks| ks.iter().any(|k| is_copy(k, &c)));
            if !known {
                new.entry((key::robot(c.u), key::robot(c.v)))
                    .or_default()
                    .push(c);
            }
        }
        if total == 0 {
            return Err(PcmError::NoCandidates(match self.scope {
                Scope::InterRobot => "the graph has no inter-robot edges (keys must follow the multi-robot convention (robot_char << 56) | index); use --intra for single-robot loop closures".into(),
                Scope::IntraRobot => "the graph has no loop closures between non-consecutive poses of one robot".into(),
            }));
        }
        for (pair, mut closures) in new {
            // In key order, whatever the order of the graph's edges: the maximum clique
            // search breaks ties between cliques of one size by vertex order, so the same
            // closures give the same verdicts wherever PCM runs (offline on a merged
            // file, or inside the distributed loop on the condensed graphs).
            closures.sort_by_key(|c| (key::index(c.u), key::index(c.v)));
            self.problems
                .entry(pair)
                .or_default()
                .add(closures, odo, self.gamma, self.budget);
        }
        let mut s = PcmSummary {
            closures: 0,
            duplicates,
            consistent_pairs: 0,
            inliers: Vec::new(),
            clique_size: 0,
            cycle_confirmed: 0,
            set_aside: 0,
            exact: true,
            time_s: 0.0,
        };
        let cycles = self.cycles && self.scope == Scope::InterRobot;
        let aside = if cycles {
            super::cycles::contradicted_pairs(&self.problems, odo, self.gamma, self.min_clique)
        } else {
            Default::default()
        };
        for (pair, p) in &self.problems {
            s.closures += p.closures.len();
            s.consistent_pairs += p.consistent_pairs();
            s.exact &= p.exact();
            if aside.contains(pair) {
                s.set_aside += p.accepted(self.min_clique).len();
                continue;
            }
            s.clique_size += p.accepted(self.min_clique).len();
            s.inliers.extend(
                p.accepted(self.min_clique)
                    .iter()
                    .map(|&k| (p.closures[k].u, p.closures[k].v)),
            );
        }
        if cycles {
            let added = super::cycles::confirm_through_cycles(
                &self.problems,
                odo,
                self.gamma,
                self.min_clique,
                &aside,
            );
            for (pair, kept) in added {
                let p = &self.problems[&pair];
                s.cycle_confirmed += kept.len();
                s.clique_size += kept.len();
                s.inliers
                    .extend(kept.iter().map(|&k| (p.closures[k].u, p.closures[k].v)));
            }
        }
        s.time_s = start.elapsed().as_secs_f64();
        Ok(s)
    }
}
