//! The condensed refinement: each robot condenses its trajectory onto its separator poses,
//! the condensed graphs spread through the team, every robot solves the small separator
//! graph of its connected team (the same input everywhere, so the same answer), then
//! re-solves its own interior poses with its separators fixed.
//!
//! Why: block Gauss-Seidel between robots (the paper's DGS, and stage 3's block-coordinate
//! descent) converges slowly when trajectories overlap strongly: a neighbour tied to me by
//! many closures follows my last estimate, and I follow it back, so each step moves both
//! by a fraction of the remaining error (BENCHMARKS.md measures it). Condensing removes the
//! iteration instead of accelerating it.
//!
//! Condensing is exact where it is made and iterated to the joint optimum: a robot's
//! trajectory between two consecutive separators is a chain whose cost depends only on
//! the separators' relative pose; with its interior solved given the separators
//! ([`solve_interior`]), the chain's Gauss-Newton system with every interior pose
//! eliminated (the Schur complement, all its edges, parallel ones included) is one
//! quadratic in that relative pose, sent as the between-factor with the same gradient and
//! Hessian there ([`condense`]). Where the team's solution moves the separators, the robot
//! solves its interior again and condenses there; a segment travels again only when the
//! factor the team holds would cost more than a small fraction of the χ²
//! ([`model_change`]). At a fixed point the interior's gradient is zero and the separators'
//! is that of the whole problem: the centralized optimum. Intra-robot loop closures travel
//! as they are (their ends become separators); an inter-robot closure travels in the graph
//! of the lower of its two robots, once.

use std::collections::{BTreeMap, BTreeSet};

use doorslam_geometry::{key, reverse_measurement, LieGroup, Tangent, TangentMatrix, SE3};

use super::local::{prior_through, OwnClosure, OwnEdge};
use super::DpgoError;
use crate::graph::{between_linearized, PoseGraph};
use crate::init::Chordal;
use crate::outliers::{Pcm, Scope};
use crate::solver::{optimize, SolverOptions, Summary};
use doorslam_ipc::wire::{CompactPose, Information};

/// A relative-pose constraint of a condensed graph: `z ≈ X_a⁻¹ X_b`, rotation-first
/// information.
#[derive(Debug, Clone, PartialEq)]
pub struct CondensedEdge {
    pub a: u64,
    pub b: u64,
    pub z: SE3,
    pub information: TangentMatrix,
}

/// The separators of a robot: its first pose, the first pose after each gap in its
/// odometry, and the own end of every closure and intra-robot loop.
pub(crate) fn separators(
    n_poses: usize,
    edges: &[OwnEdge],
    closures: &[OwnClosure],
) -> BTreeSet<usize> {
    let mut s: BTreeSet<usize> = closures.iter().map(|c| c.own).collect();
    let consecutive = |e: &OwnEdge| e.i.abs_diff(e.j) == 1;
    for e in edges.iter().filter(|e| !consecutive(e)) {
        s.insert(e.i);
        s.insert(e.j);
    }
    let mut linked = vec![false; n_poses];
    for e in edges.iter().filter(|e| consecutive(e)) {
        linked[e.i.max(e.j)] = true;
    }
    for (p, l) in linked.iter().enumerate() {
        if !l {
            s.insert(p);
        }
    }
    s
}

/// The edges between poses `p` and `p + 1` (odometry and any parallel edge).
fn chain_edges(edges: &[OwnEdge], n_poses: usize) -> Vec<Vec<&OwnEdge>> {
    let mut out: Vec<Vec<&OwnEdge>> = vec![Vec::new(); n_poses];
    for e in edges.iter().filter(|e| e.i.abs_diff(e.j) == 1) {
        out[e.i.min(e.j)].push(e);
    }
    out
}

/// `z`, `Ω` of edge `e` seen from pose `from` (exact: reversing a between-factor keeps its
/// cost, see [`reverse_measurement`]).
fn oriented(e: &OwnEdge, from: usize) -> (SE3, TangentMatrix) {
    if e.i == from {
        (e.z, e.information)
    } else {
        reverse_measurement(&e.z, &e.information)
    }
}

/// The Gauss-Newton model of one chain segment on the perturbation `ε` of its end
/// (`X_t Exp(ε)`, the start held where it is): `χ²(ε) ≈ c + 2 gᵀ ε + εᵀ H ε`, with every
/// interior pose eliminated (Schur complement, one step at a time along the chain).
#[derive(Debug, Clone)]
pub(crate) struct SegmentModel {
    h: TangentMatrix,
    g: Tangent,
}

/// One edge of a condensed graph, and for a condensed chain segment the model it matches.
#[derive(Debug, Clone)]
pub(crate) struct Condensed {
    pub edge: CondensedEdge,
    pub model: Option<SegmentModel>,
}

/// The χ² a held factor `held` of a segment could cost against the segment's model `m` at
/// the relative pose `t_bar`: with `Δ` the difference of their gradients there, `ΔᵀH⁻¹Δ`
/// (what the solve's step is off by, in χ² units). Zero for the factor made from `m`.
pub(crate) fn model_change(held: &CondensedEdge, t_bar: &SE3, m: &SegmentModel) -> f64 {
    let r = held.z.inverse().compose(t_bar).log();
    let g = SE3::right_jacobian_inv(&r).transpose() * held.information * r;
    let d = g - m.g;
    match m.h.cholesky() {
        Some(c) => d.dot(&c.solve(&d)),
        None => f64::INFINITY,
    }
}

/// `e` as it travels (and as every robot holding it sees it): pose and information
/// rounded to the wire's steps.
pub(crate) fn quantized(origin: u8, e: &CondensedEdge) -> Result<CondensedEdge, DpgoError> {
    let bad = |reason: String| DpgoError::BadMessage {
        from: origin,
        reason: format!("edge {} -> {}: {reason}", key::label(e.a), key::label(e.b)),
    };
    let z = *CompactPose::quantize(&e.z)
        .map_err(|x| bad(x.to_string()))?
        .se3();
    let information = *Information::from_matrix(&e.information)
        .map_err(|x| bad(x.to_string()))?
        .matrix();
    Ok(CondensedEdge {
        a: e.a,
        b: e.b,
        z,
        information,
    })
}

/// Eliminates the chain `s → s+1 → … → t` at the estimate `poses`: the edges between
/// consecutive poses (all of them, parallel ones included) linearized where the poses are.
fn segment_model(
    poses: &[SE3],
    chain: &[Vec<&OwnEdge>],
    s: usize,
    t: usize,
) -> Option<SegmentModel> {
    // The quadratic on the current end p, interior before it eliminated (None at s: fixed).
    let mut model: Option<SegmentModel> = None;
    for (p, steps) in chain.iter().enumerate().take(t).skip(s) {
        let (mut a_pp, mut a_pq, mut a_qq) = (
            TangentMatrix::zeros(),
            TangentMatrix::zeros(),
            TangentMatrix::zeros(),
        );
        let (mut b_p, mut b_q) = (Tangent::zeros(), Tangent::zeros());
        for e in steps {
            let (r, ji, jj) = between_linearized(&poses[e.i], &poses[e.j], &e.z);
            let (jp, jq) = if e.i == p { (ji, jj) } else { (jj, ji) };
            let om = e.information;
            a_pp += jp.transpose() * om * jp;
            a_pq += jp.transpose() * om * jq;
            a_qq += jq.transpose() * om * jq;
            b_p += jp.transpose() * om * r;
            b_q += jq.transpose() * om * r;
        }
        model = Some(match model {
            None => SegmentModel { h: a_qq, g: b_q },
            Some(m) => {
                // Eliminate δp: M = H_p + A_pp.
                let chol = (m.h + a_pp).cholesky()?;
                let m_inv_a = chol.solve(&a_pq);
                let m_inv_b = chol.solve(&(m.g + b_p));
                SegmentModel {
                    h: a_qq - a_pq.transpose() * m_inv_a,
                    g: b_q - a_pq.transpose() * m_inv_b,
                }
            }
        });
    }
    model
}

/// The between-factor `(z, Ω)` with the same gradient and Gauss-Newton Hessian as `m` at
/// the current relative pose `t_bar = X_s⁻¹ X_t`: with `μ = H⁻¹ g`, `z = T̄ Exp(−μ)` (the
/// model's minimum) and `Ω = Jr(μ)ᵀ H Jr(μ)`. Its residual at `T̄` is `Log(z⁻¹ T̄) = μ`, its
/// Jacobian `Jr⁻¹(μ)`, and `Jr⁻¹(μ) μ = μ`, so `JᵀΩr = H μ = g` and `JᵀΩJ = H` exactly.
fn factor_of(t_bar: &SE3, m: &SegmentModel) -> Option<(SE3, TangentMatrix)> {
    let chol = m.h.cholesky()?;
    let mu = chol.solve(&m.g);
    let z = t_bar.compose(&SE3::exp(&(-mu)));
    let jr = SE3::right_jacobian(&mu);
    let om = jr.transpose() * m.h * jr;
    Some((z, (om + om.transpose()) * 0.5))
}

/// This robot's condensed graph at the estimate `poses` (`keys[p]` names pose `p`), whose
/// interior must be at its optimum given the separators ([`solve_interior`]): per chain
/// segment between consecutive separators, the between-factor matching the segment's
/// Schur complement there ([`factor_of`]); a segment of one step keeps its edges as they are
/// (exact); intra-robot loops as they are; inter-robot closures once, from the lower robot,
/// and also those with a robot below `resend_below` (the team's solver, so such a robot is
/// not in the team: when the solver left, its graph lives on only as a standby copy without
/// the closures the robots above it hold, and they send them again, see
/// [`trajectory_copy`]). A segment of at most `raw_steps` steps (at least one) is sent as
/// its odometry edges, exact (its inner poses become poses of the separator graph): cheaper
/// on the wire than one factor with its own information when the odometry shares one.
///
/// At the odometry's zero residual this is the classic compounding (`z` the composed
/// odometry, `Ω` the compounded information). At any other estimate it is the segment's
/// exact local model there, so a solve whose separators equal the estimate's is a
/// stationary point of the whole problem (the interior's gradient is zero, the separators'
/// is the condensed factors' plus the closures'): relinearized where the team's solution
/// puts the separators, the condensed graphs iterate to the centralized optimum.
pub(crate) fn condense(
    robot: u8,
    keys: &[u64],
    poses: &[SE3],
    edges: &[OwnEdge],
    closures: &[OwnClosure],
    resend_below: u8,
    raw_steps: usize,
) -> Result<Vec<Condensed>, DpgoError> {
    let seps = separators(keys.len(), edges, closures);
    let chain = chain_edges(edges, keys.len());
    let singular = |s: usize, t: usize| DpgoError::Information {
        from: key::label(keys[s]),
        to: key::label(keys[t]),
        source: doorslam_geometry::information::InformationError::NotPositiveDefinite,
    };
    let mut out = Vec::new();
    for &s in &seps {
        // Follow the chain to the next separator; a chain that ends before one (a gap)
        // leaves its poses hanging from s: they constrain no separator.
        let mut t = s;
        while t + 1 < keys.len() && !chain[t].is_empty() {
            t += 1;
            if seps.contains(&t) {
                break;
            }
        }
        if t == s || !seps.contains(&t) {
            continue;
        }
        if t - s <= raw_steps.max(1) {
            for p in s..t {
                for e in &chain[p] {
                    let (z, information) = oriented(e, p);
                    out.push(Condensed {
                        edge: CondensedEdge {
                            a: keys[p],
                            b: keys[p + 1],
                            z,
                            information,
                        },
                        model: None,
                    });
                }
            }
            continue;
        }
        let model = segment_model(poses, &chain, s, t).ok_or_else(|| singular(s, t))?;
        let t_bar = poses[s].inverse().compose(&poses[t]);
        let (z, information) = factor_of(&t_bar, &model).ok_or_else(|| singular(s, t))?;
        out.push(Condensed {
            edge: CondensedEdge {
                a: keys[s],
                b: keys[t],
                z,
                information,
            },
            model: Some(model),
        });
    }
    // Intra-robot loops as they are.
    let exact = |a: u64, b: u64, z: SE3, information: TangentMatrix| Condensed {
        edge: CondensedEdge {
            a,
            b,
            z,
            information,
        },
        model: None,
    };
    for e in edges.iter().filter(|e| e.i.abs_diff(e.j) != 1) {
        out.push(exact(keys[e.i], keys[e.j], e.z, e.information));
    }
    // Closures, once: from the lower robot (or from this one when the lower robot is out
    // of the team and its graph a standby copy without them).
    for c in closures {
        if key::robot(c.other).is_some_and(|o| robot < o || o < resend_below) {
            out.push(exact(keys[c.own], c.other, c.z, c.information));
        }
    }
    Ok(out)
}

/// The edges of a team's separator graph, every closure once and seen from its lower
/// robot. A closure lives in the graph of the lower of its two robots; the higher one sends
/// it too only while the lower robot is out of its team (`condense`'s `resend_below`), when
/// the solver holds the lower robot's graph as a standby copy without its closures to
/// higher robots ([`trajectory_copy`]). Such a closure is kept (reversed, exactly: the
/// cost is the same) when the lower robot's graph is held and does not carry the same key
/// pair (a full graph held from elsewhere does), and dropped when the lower robot's graph
/// is not held at all or does not hold its pose (it would hang on a pose nothing else
/// constrains; a copy leaves out the ends of closures PCM rejected, `team::own_copy`).
pub(crate) fn team_edges(graphs: &BTreeMap<u8, &[CondensedEdge]>) -> Vec<CondensedEdge> {
    let pair = |e: &CondensedEdge| (e.a.min(e.b), e.a.max(e.b));
    // Per graph: the closures it carries with higher robots, and its own poses.
    type Held = (BTreeSet<(u64, u64)>, BTreeSet<u64>);
    let held: BTreeMap<u8, Held> = graphs
        .iter()
        .map(|(o, edges)| {
            let pairs = edges
                .iter()
                .filter(|e| key::robot(e.b).is_some_and(|b| b > *o))
                .map(pair)
                .collect();
            let own = edges
                .iter()
                .flat_map(|e| [e.a, e.b])
                .filter(|k| key::robot(*k) == Some(*o))
                .collect();
            (*o, (pairs, own))
        })
        .collect();
    let mut out = Vec::new();
    for (o, edges) in graphs {
        for e in edges.iter() {
            match key::robot(e.b) {
                Some(lower) if lower < *o => {
                    // Kept on a pose the lower robot's graph holds (a copy condensed past
                    // the ends of closures PCM rejected holds no such pose).
                    let keep = held.get(&lower).is_some_and(|(pairs, own)| {
                        !pairs.contains(&pair(e)) && own.contains(&e.b)
                    });
                    if keep {
                        let (z, information) = reverse_measurement(&e.z, &e.information);
                        out.push(CondensedEdge {
                            a: e.b,
                            b: e.a,
                            z,
                            information,
                        });
                    }
                }
                _ => out.push(e.clone()),
            }
        }
    }
    out
}

/// What a solver's standby holds of the graph `edges` of robot `origin`: its trajectory
/// (condensed segments and intra-robot loops) and its closures with lower robots, not its
/// closures with higher ones: those robots hold them too and send them again once
/// `origin` is out of their team (`condense`'s `resend_below`), so the copy costs the
/// trajectory alone.
pub(crate) fn trajectory_copy(origin: u8, edges: &[CondensedEdge]) -> Vec<CondensedEdge> {
    edges
        .iter()
        .filter(|e| key::robot(e.b).is_some_and(|b| b <= origin))
        .cloned()
        .collect()
}

/// PCM settings inside the loop: probability threshold, smallest clique per robot pair,
/// and whether closures left without a clique are checked through 3-robot cycles.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PcmSettings {
    pub threshold: f64,
    pub min_clique: usize,
    pub cycles: bool,
}

/// PCM on the separator graph: the inter-robot closures it keeps, as (key, key) both ways.
///
/// Free of extra messages: the condensed graphs every robot holds already carry what PCM
/// needs — the closures, and between consecutive separators the compounded odometry with
/// its covariance, which is exactly the relative odometry PCM chains along a trajectory.
/// Separators are renumbered per robot (the k-th separator gets index k) so the super-edges
/// are "odometry" to PCM; every robot runs the same check on the same graph.
pub(crate) fn pcm_inliers(
    graphs: &BTreeMap<u8, &[CondensedEdge]>,
    settings: PcmSettings,
) -> Result<BTreeSet<(u64, u64)>, DpgoError> {
    let mut all = team_edges(graphs);
    all.sort_by_key(|e| (e.a, e.b));
    let all: Vec<&CondensedEdge> = all.iter().collect();
    let keys: BTreeSet<u64> = all.iter().flat_map(|e| [e.a, e.b]).collect();
    let mut rank: BTreeMap<u64, u64> = BTreeMap::new();
    let mut back: BTreeMap<u64, u64> = BTreeMap::new();
    let mut next: BTreeMap<u8, u64> = BTreeMap::new();
    for k in &keys {
        let r = key::robot(*k).ok_or_else(|| DpgoError::NoRobot(key::label(*k)))?;
        let n = next.entry(r).or_insert(0);
        let renamed = key::symbol(r, *n).map_err(|_| DpgoError::NoRobot(key::label(*k)))?;
        *n += 1;
        rank.insert(*k, renamed);
        back.insert(renamed, *k);
    }
    let mut g = PoseGraph::<SE3>::new();
    for k in rank.values() {
        g.add_pose(*k, SE3::identity());
    }
    let mut has_closure = false;
    for e in &all {
        let (a, b) = (rank[&e.a], rank[&e.b]);
        // A super-edge between non-consecutive separators (a gap in between) or an
        // intra-robot loop is not odometry to PCM; it is left out of its chains.
        let same = key::robot(a) == key::robot(b);
        if same && key::index(a).abs_diff(key::index(b)) != 1 {
            continue;
        }
        has_closure |= !same;
        let (i, j) = (
            g.index_of(a).unwrap_or_default(),
            g.index_of(b).unwrap_or_default(),
        );
        g.add_edge(i, j, e.z, e.information)?;
    }
    if !has_closure {
        return Ok(BTreeSet::new());
    }
    let mut pcm = Pcm::new(settings.threshold, Scope::InterRobot)
        .map_err(|e| DpgoError::Pcm(e.to_string()))?;
    pcm.min_clique = settings.min_clique;
    pcm.cycles = settings.cycles;
    let s = pcm.run(&g).map_err(|e| DpgoError::Pcm(e.to_string()))?;
    Ok(s.inliers
        .iter()
        .flat_map(|&(u, v)| {
            let (a, b) = (back[&u], back[&v]);
            [(a, b), (b, a)]
        })
        .collect())
}

/// What a solve of the separator graph gives.
#[derive(Debug, Clone)]
pub(crate) struct SeparatorSolve {
    /// Separator estimates of the connected part, in its frame.
    pub estimates: BTreeMap<u64, SE3>,
    /// Inter-robot closures (key, key) PCM rejected.
    pub rejected: Vec<(u64, u64)>,
    /// Per separator, the Gauss-Newton Hessian block of its own perturbation at the
    /// solution (Σ JᵀΩJ over the edges that touch it): moving it alone by `δ` costs
    /// `δᵀ D δ` of χ², which decides whether a change is worth sending.
    pub stiffness: BTreeMap<u64, TangentMatrix>,
    /// The solver's summary (`None`: nothing to solve, one pose).
    pub summary: Option<Summary>,
}

/// Solves the separator graph of the team `graphs` (origin → edges) that contains pose
/// `mine`: chordal initialization and Levenberg-Marquardt with the lowest key of that
/// connected part (the lowest robot's first pose) fixed at the identity — the team frame.
pub(crate) fn solve_separators(
    graphs: &BTreeMap<u8, &[CondensedEdge]>,
    mine: u64,
    pcm: Option<PcmSettings>,
    options: &SolverOptions,
) -> Result<SeparatorSolve, DpgoError> {
    let mut g = PoseGraph::<SE3>::new();
    let inliers = pcm.map(|p| pcm_inliers(graphs, p)).transpose()?;
    let inter = |e: &CondensedEdge| key::robot(e.a) != key::robot(e.b);
    let mut rejected = Vec::new();
    let edges = team_edges(graphs);
    let mut all: Vec<&CondensedEdge> = edges
        .iter()
        .filter(|e| {
            let keep = !inter(e) || inliers.as_ref().is_none_or(|i| i.contains(&(e.a, e.b)));
            if !keep {
                rejected.push((e.a, e.b));
            }
            keep
        })
        .collect();
    // Canonical order: every robot builds the same graph from the same input.
    all.sort_by_key(|e| (e.a, e.b));
    let mut keys: BTreeSet<u64> = all.iter().flat_map(|e| [e.a, e.b]).collect();
    keys.insert(mine);
    for k in &keys {
        g.add_pose(*k, SE3::identity());
    }
    for e in &all {
        let (i, j) = (
            g.index_of(e.a).unwrap_or_default(),
            g.index_of(e.b).unwrap_or_default(),
        );
        g.add_edge(i, j, e.z, e.information)?;
    }
    // The connected part that holds `mine`; its lowest key anchors.
    let start = g.index_of(mine).unwrap_or_default();
    let mut part = reachable_part(&g, start)?;
    let anchor = 0; // keys were added in ascending order: the lowest robot's first pose.
    let mut summary = None;
    if part.len() > 1 {
        SE3::chordal(&mut part, anchor)?;
        summary = Some(optimize(&mut part, anchor, options)?);
    }
    let mut stiffness: BTreeMap<u64, TangentMatrix> = BTreeMap::new();
    for e in part.edges() {
        let (_, ji, jj) = between_linearized(&part.poses()[e.i], &part.poses()[e.j], &e.measured);
        for (p, j) in [(e.i, ji), (e.j, jj)] {
            *stiffness
                .entry(part.keys()[p])
                .or_insert_with(TangentMatrix::zeros) += j.transpose() * e.information * j;
        }
    }
    Ok(SeparatorSolve {
        estimates: part
            .keys()
            .iter()
            .copied()
            .zip(part.poses().iter().copied())
            .collect(),
        rejected,
        stiffness,
        summary,
    })
}

/// The poses of `g` connected to pose `start` (same order, same values) and their edges.
pub(crate) fn reachable_part(
    g: &PoseGraph<SE3>,
    start: usize,
) -> Result<PoseGraph<SE3>, DpgoError> {
    let reach = g.reachable_from(start);
    let mut part = PoseGraph::<SE3>::new();
    for (p, k) in g.keys().iter().enumerate() {
        if reach[p] {
            part.add_pose(*k, g.poses()[p]);
        }
    }
    for e in g.edges() {
        if reach[e.i] && reach[e.j] {
            let (i, j) = (
                part.index_of(g.keys()[e.i]).unwrap_or_default(),
                part.index_of(g.keys()[e.j]).unwrap_or_default(),
            );
            part.add_edge(i, j, e.measured, e.information)?;
        }
    }
    Ok(part)
}

/// The robot's interior poses with its separators fixed at `fixed`: Levenberg-Marquardt on
/// its own edges, the terms touching a fixed pose rewritten exactly as between-factors from
/// the origin. Returns every own pose (separators at their fixed value).
pub(crate) fn solve_interior(
    poses: &[SE3],
    edges: &[OwnEdge],
    fixed: &[Option<SE3>],
) -> Result<Vec<SE3>, DpgoError> {
    let mut g = PoseGraph::<SE3>::new();
    g.add_pose(u64::MAX, SE3::identity());
    let mut node = vec![None; poses.len()];
    for (p, x) in poses.iter().enumerate() {
        if fixed[p].is_none() {
            node[p] = Some(g.add_pose(p as u64, *x));
        }
    }
    for e in edges {
        match ((node[e.i], fixed[e.i]), (node[e.j], fixed[e.j])) {
            ((Some(a), _), (Some(b), _)) => {
                g.add_edge(a, b, e.z, e.information)?;
            }
            ((None, Some(xs)), (Some(b), _)) => {
                // Log((X_s z)⁻¹ X_j): a between-factor from the origin, same information.
                g.add_edge(0, b, xs.compose(&e.z), e.information)?;
            }
            ((Some(a), _), (None, Some(xs))) => {
                let (m, info) = prior_through(&SE3::identity(), &xs, &e.z, &e.information);
                g.add_edge(0, a, m, info)?;
            }
            _ => {}
        }
    }
    let mut out: Vec<SE3> = poses
        .iter()
        .zip(fixed)
        .map(|(x, f)| f.unwrap_or(*x))
        .collect();
    if g.len() > 1 {
        // Interior poses no edge ties to a separator keep their estimate (the solver would
        // call them disconnected).
        let mut sub = reachable_part(&g, 0)?;
        optimize(&mut sub, 0, &SolverOptions::default())?;
        g = sub;
        for (k, x) in g.keys().iter().zip(g.poses()).skip(1) {
            out[*k as usize] = *x;
        }
    }
    Ok(out)
}

/// Whether an edge list of a received graph is well-formed for `origin`: super-edges and
/// loops between its own poses, closures from it to a higher robot, informations within
/// [`super::MAX_INFORMATION`] (the wire already refuses one that is not positive definite).
pub(crate) fn check_graph(origin: u8, edges: &[CondensedEdge]) -> Result<(), String> {
    for e in edges {
        let largest = e.information.diagonal().max();
        if largest > super::MAX_INFORMATION {
            return Err(format!(
                "edge {} -> {}: information {largest:e} beyond {:e}",
                key::label(e.a),
                key::label(e.b),
                super::MAX_INFORMATION
            ));
        }
        let (ra, rb) = (key::robot(e.a), key::robot(e.b));
        let ok = match (ra, rb) {
            (Some(a), Some(b)) if a == origin && b == origin => e.a != e.b,
            // A closure with a lower robot: sent again because that robot left (see
            // `condense`); `team_edges` keeps it only when the lower robot's graph is held
            // without it.
            (Some(a), Some(b)) if a == origin => b != origin,
            _ => false,
        };
        if !ok {
            return Err(format!(
                "edge {} -> {} does not belong in robot {}'s graph",
                key::label(e.a),
                key::label(e.b),
                key::robot_char(origin).unwrap_or('?')
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    fn pose(v: [f64; 6]) -> SE3 {
        SE3::exp(&Tangent::from_row_slice(&v))
    }

    fn info(scale: f64) -> TangentMatrix {
        let mut m = TangentMatrix::identity() * 400.0 * scale;
        for k in 3..6 {
            m[(k, k)] = 25.0 * scale;
        }
        m[(0, 4)] = 3.0;
        m[(4, 0)] = 3.0;
        m
    }

    fn edge(i: usize, j: usize, z: SE3, information: TangentMatrix) -> OwnEdge {
        OwnEdge {
            i,
            j,
            z,
            information,
            kappa: 1.0,
            tau: 1.0,
        }
    }

    /// A chain 0 → 1 → 2 → 3 → 4 with a parallel edge 1 → 2 and a reversed step 3 ← 4,
    /// and an estimate away from the odometry's zero residual (as after a team solve).
    fn chain() -> (Vec<SE3>, Vec<OwnEdge>) {
        let step = pose([0.02, -0.01, 0.1, 1.0, 0.1, 0.0]);
        let mut edges: Vec<OwnEdge> = (0..3).map(|i| edge(i, i + 1, step, info(1.0))).collect();
        edges.push(edge(
            1,
            2,
            pose([0.03, 0.0, 0.12, 1.1, 0.0, 0.05]),
            info(0.5),
        ));
        edges.push(edge(4, 3, step.inverse(), info(2.0)));
        let poses = (0..5)
            .map(|i| {
                let f = i as f64;
                pose([0.01 * f, 0.02 * f, 0.13 * f, 1.1 * f, 0.3 * f, -0.1 * f])
            })
            .collect();
        (poses, edges)
    }

    /// The Schur complement of the interior from the whole chain's dense normal equations
    /// (pose 0 fixed, variables 1..=4, pose 4's block kept).
    fn dense_schur(poses: &[SE3], edges: &[OwnEdge]) -> (TangentMatrix, Tangent) {
        let n = 4 * 6;
        let mut h = DMatrix::<f64>::zeros(n, n);
        let mut g = DMatrix::<f64>::zeros(n, 1);
        for e in edges {
            let (r, ji, jj) = between_linearized(&poses[e.i], &poses[e.j], &e.z);
            for (a, ja) in [(e.i, ji), (e.j, jj)] {
                if a == 0 {
                    continue;
                }
                let ga = ja.transpose() * e.information * r;
                for k in 0..6 {
                    g[(6 * (a - 1) + k, 0)] += ga[k];
                }
                for (b, jb) in [(e.i, ji), (e.j, jj)] {
                    if b == 0 {
                        continue;
                    }
                    let block = ja.transpose() * e.information * jb;
                    for r in 0..6 {
                        for c in 0..6 {
                            h[(6 * (a - 1) + r, 6 * (b - 1) + c)] += block[(r, c)];
                        }
                    }
                }
            }
        }
        let (ii, tt) = (0..18, 18..24);
        let h_ii = h.view((ii.start, ii.start), (18, 18)).into_owned();
        let h_it = h.view((ii.start, tt.start), (18, 6)).into_owned();
        let h_tt = h.view((tt.start, tt.start), (6, 6)).into_owned();
        let inv = h_ii.cholesky().unwrap().inverse();
        let s = &h_tt - h_it.transpose() * &inv * &h_it;
        let gs = g.rows(18, 6).into_owned() - h_it.transpose() * &inv * g.rows(0, 18);
        (
            TangentMatrix::from_fn(|r, c| s[(r, c)]),
            Tangent::from_fn(|r, _| gs[(r, 0)]),
        )
    }

    #[test]
    fn a_segment_model_is_the_schur_complement_of_every_edge() {
        let (poses, edges) = chain();
        let m = segment_model(&poses, &chain_edges(&edges, 5), 0, 4).unwrap();
        let (h, g) = dense_schur(&poses, &edges);
        assert!((m.h - h).amax() <= 1e-9 * h.amax(), "{}\n{h}", m.h);
        assert!((m.g - g).amax() <= 1e-9 * g.amax().max(1.0), "{}\n{g}", m.g);
        // Dropping the parallel edge changes it: every edge counts.
        let fewer: Vec<OwnEdge> = edges
            .iter()
            .enumerate()
            .filter(|(n, _)| *n != 3)
            .map(|(_, e)| e.clone())
            .collect();
        let m2 = segment_model(&poses, &chain_edges(&fewer, 5), 0, 4).unwrap();
        assert!((m2.h - h).amax() > 1e-3 * h.amax());
    }

    fn graph_edge(a: (u8, u64), b: (u8, u64), x: f64) -> CondensedEdge {
        CondensedEdge {
            a: key::symbol(a.0, a.1).unwrap(),
            b: key::symbol(b.0, b.1).unwrap(),
            z: SE3::translation(x, 0.0, 0.0),
            information: TangentMatrix::identity(),
        }
    }

    /// A closure a robot sends again because the lower robot left counts once: kept,
    /// reversed, over a trajectory copy of the lower robot; dropped beside the lower
    /// robot's full graph (which carries it), without any graph of the lower robot, and
    /// when the copy does not hold its pose.
    #[test]
    fn a_closure_sent_again_counts_once() {
        let chain = graph_edge((0, 0), (0, 5), 5.0);
        let closure = graph_edge((0, 5), (1, 2), 1.0);
        let again = graph_edge((1, 2), (0, 5), -1.0);
        let full = vec![chain.clone(), closure.clone()];
        let copy = trajectory_copy(0, &full);
        assert_eq!(copy, vec![chain.clone()]);
        let mine = vec![graph_edge((1, 0), (1, 2), 2.0), again.clone()];
        let closures = |graphs: BTreeMap<u8, &[CondensedEdge]>| -> Vec<CondensedEdge> {
            team_edges(&graphs)
                .into_iter()
                .filter(|e| key::robot(e.a) != key::robot(e.b))
                .collect()
        };
        let over_copy = closures(BTreeMap::from([(0, copy.as_slice()), (1, mine.as_slice())]));
        assert_eq!(over_copy.len(), 1);
        assert_eq!((over_copy[0].a, over_copy[0].b), (closure.a, closure.b));
        assert!(over_copy[0].z.inverse().compose(&closure.z).log().norm() < 1e-12);
        let beside_full = closures(BTreeMap::from([(0, full.as_slice()), (1, mine.as_slice())]));
        assert_eq!(beside_full, vec![closure.clone()]);
        assert!(closures(BTreeMap::from([(1, mine.as_slice())])).is_empty());
        let short = vec![graph_edge((0, 0), (0, 4), 4.0)];
        assert!(closures(BTreeMap::from([
            (0, short.as_slice()),
            (1, mine.as_slice())
        ]))
        .is_empty());
        // A graph may carry it (a robot's own closure), a lower robot's copy too.
        assert!(check_graph(1, &mine).is_ok());
        assert!(check_graph(1, &[graph_edge((1, 2), (1, 2), 0.0)]).is_err());
    }

    /// The between-factor of a model has the model's gradient and Gauss-Newton Hessian at
    /// the relative pose it was made at.
    #[test]
    fn the_condensed_factor_matches_the_model_where_it_was_made() {
        let (poses, edges) = chain();
        let m = segment_model(&poses, &chain_edges(&edges, 5), 0, 4).unwrap();
        assert!(
            m.g.norm() > 1.0,
            "the estimate is away from the zero residual"
        );
        let t_bar = poses[0].inverse().compose(&poses[4]);
        let (z, om) = factor_of(&t_bar, &m).unwrap();
        let (r, _, jj) = between_linearized(&SE3::identity(), &t_bar, &z);
        let g = jj.transpose() * om * r;
        let h = jj.transpose() * om * jj;
        assert!((g - m.g).amax() <= 1e-8 * m.g.amax(), "{g} vs {}", m.g);
        assert!((h - m.h).amax() <= 1e-8 * m.h.amax());
        let held = CondensedEdge {
            a: 0,
            b: 4,
            z,
            information: om,
        };
        assert!(model_change(&held, &t_bar, &m) <= 1e-12);
        // At the odometry (zero residual) it is the classic compounding: z the composition.
        let mut odo = vec![SE3::identity()];
        for e in &edges[..3] {
            odo.push(odo.last().unwrap().compose(&e.z));
        }
        odo.push(odo[3].compose(&edges[4].z.inverse()));
        let single: Vec<OwnEdge> = edges
            .iter()
            .enumerate()
            .filter(|(n, _)| *n != 3)
            .map(|(_, e)| e.clone())
            .collect();
        let m0 = segment_model(&odo, &chain_edges(&single, 5), 0, 4).unwrap();
        let (z0, _) = factor_of(&odo[4], &m0).unwrap();
        assert!(z0.inverse().compose(&odo[4]).log().norm() < 1e-9);
    }
}
