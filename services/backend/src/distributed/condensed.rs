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
//! Condensing a chain is exact to first order: between two consecutive separators the
//! odometry composes into one relative pose, and its covariance compounds as
//! `Σ₁₂ = Ad(z₂⁻¹) Σ₁ Ad(z₂⁻¹)ᵀ + Σ₂` (right-perturbation convention of the back-end's
//! residual). Intra-robot loop closures travel as they are (their ends become separators);
//! an inter-robot closure travels in the graph of the lower of its two robots, once.

use std::collections::{BTreeMap, BTreeSet};

use doorslam_geometry::information::{covariance_from_information, information_from_covariance};
use doorslam_geometry::{key, LieGroup, TangentMatrix, SE3};

use super::local::{prior_through, OwnClosure, OwnEdge};
use super::DpgoError;
use crate::graph::PoseGraph;
use crate::init::Chordal;
use crate::outliers::{Pcm, Scope};
use crate::solver::{optimize, SolverOptions};

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

/// The odometry edge from pose `p` to `p + 1`, oriented forward.
fn forward(edges: &[OwnEdge], p: usize) -> Option<(SE3, TangentMatrix)> {
    edges.iter().find_map(|e| {
        if e.i == p && e.j == p + 1 {
            Some((e.z, e.information))
        } else if e.j == p && e.i == p + 1 {
            // Reversed: z' = z⁻¹, Ω' = Ad(z)ᵀ... as in the agent's closure reversal.
            let ad = e.z.inverse().adjoint();
            let info = ad.transpose() * e.information * ad;
            Some((e.z.inverse(), (info + info.transpose()) * 0.5))
        } else {
            None
        }
    })
}

/// This robot's condensed graph (`keys[p]` names pose `p`).
pub(crate) fn condense(
    robot: u8,
    keys: &[u64],
    edges: &[OwnEdge],
    closures: &[OwnClosure],
) -> Result<Vec<CondensedEdge>, DpgoError> {
    let seps = separators(keys.len(), edges, closures);
    let mut out = Vec::new();
    let invert = |m: &TangentMatrix, what: u64| {
        covariance_from_information(m, 6).map_err(|source| DpgoError::Information {
            from: key::label(what),
            to: key::label(what),
            source,
        })
    };
    // Compose along the chain from each separator to the next: (start, z, Σ, the step's
    // own information while the chain is one step long).
    type Chain = (usize, SE3, TangentMatrix, Option<TangentMatrix>);
    let mut from: Option<Chain> = None;
    for p in 0..keys.len() {
        if seps.contains(&p) {
            if let Some((s, z, cov, single)) = from.take() {
                if s != p {
                    // One step is the odometry edge itself: its information exactly (so
                    // it repeats between edges, and the wire sends it once).
                    let information = match single {
                        Some(info) => info,
                        None => {
                            let i = information_from_covariance(&cov, 6).map_err(|source| {
                                DpgoError::Information {
                                    from: key::label(keys[s]),
                                    to: key::label(keys[p]),
                                    source,
                                }
                            })?;
                            (i + i.transpose()) * 0.5
                        }
                    };
                    out.push(CondensedEdge {
                        a: keys[s],
                        b: keys[p],
                        z,
                        information,
                    });
                }
            }
            from = Some((p, SE3::identity(), TangentMatrix::zeros(), None));
        }
        // Extend to p + 1 if the chain continues.
        match (from.take(), forward(edges, p)) {
            (Some((s, z, cov, _)), Some((step, info))) => {
                let ad = step.inverse().adjoint();
                let cov = ad * cov * ad.transpose() + invert(&info, keys[p])?;
                let single = (s == p).then_some(info);
                from = Some((s, z.compose(&step), cov, single));
            }
            _ => from = None,
        }
    }
    // Intra-robot loops as they are.
    for e in edges.iter().filter(|e| e.i.abs_diff(e.j) != 1) {
        out.push(CondensedEdge {
            a: keys[e.i],
            b: keys[e.j],
            z: e.z,
            information: e.information,
        });
    }
    // Closures, once: from the lower robot.
    for c in closures {
        if key::robot(c.other).is_some_and(|o| robot < o) {
            out.push(CondensedEdge {
                a: keys[c.own],
                b: c.other,
                z: c.z,
                information: c.information,
            });
        }
    }
    Ok(out)
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
    let mut all: Vec<&CondensedEdge> = graphs.values().copied().flatten().collect();
    all.sort_by_key(|e| (e.a, e.b));
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

/// Solves the separator graph of the team `graphs` (origin → edges) that contains pose
/// `mine`: chordal initialization and Levenberg-Marquardt with the lowest key of that
/// connected part (the lowest robot's first pose) fixed at the identity — the team frame.
/// Separator estimates, and the closures (key, key) PCM rejected.
pub(crate) type Solved = (BTreeMap<u64, SE3>, Vec<(u64, u64)>);

/// Returns the separator estimates and the closures PCM rejected.
pub(crate) fn solve_separators(
    graphs: &BTreeMap<u8, &[CondensedEdge]>,
    mine: u64,
    pcm: Option<PcmSettings>,
) -> Result<Solved, DpgoError> {
    let mut g = PoseGraph::<SE3>::new();
    let inliers = pcm.map(|p| pcm_inliers(graphs, p)).transpose()?;
    let inter = |e: &CondensedEdge| key::robot(e.a) != key::robot(e.b);
    let mut rejected = Vec::new();
    let mut all: Vec<&CondensedEdge> = graphs
        .values()
        .copied()
        .flatten()
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
    if part.len() > 1 {
        SE3::chordal(&mut part, anchor)?;
        optimize(&mut part, anchor, &SolverOptions::default())?;
    }
    Ok((
        part.keys()
            .iter()
            .copied()
            .zip(part.poses().iter().copied())
            .collect(),
        rejected,
    ))
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
/// loops between its own poses, closures from it to a higher robot.
pub(crate) fn check_graph(origin: u8, edges: &[CondensedEdge]) -> Result<(), String> {
    for e in edges {
        let (ra, rb) = (key::robot(e.a), key::robot(e.b));
        let ok = match (ra, rb) {
            (Some(a), Some(b)) if a == origin && b == origin => e.a != e.b,
            (Some(a), Some(b)) if a == origin => b > origin,
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
