//! Closures pairwise PCM cannot check: a closure alone between two robots (or a robot pair
//! whose closures are all mutually inconsistent) has no second closure of its pair to close
//! a cycle with, so plain PCM with `min_clique = 2` rejects it and `min_clique = 1` keeps it
//! blindly. Through a third robot it can be checked: with closures `c₁` between robots α
//! and γ and `c₂` between β and γ that PCM already confirmed (in a clique of at least
//! `min_clique`), the singleton `c₀` between α and β closes the cycle
//!
//! `T = c₀ · odo_β(v₀ → v₂) · c₂ · odo_γ(w₂ → w₁) · c₁⁻¹ · odo_α(u₁ → u₀)`
//!
//! which is the identity when all three are right. Its error `e = Log(T)` with the six
//! factors' covariances propagated (as in the pairwise test, eq. 1 of the paper) gives the
//! squared Mahalanobis norm, tested against the same `γ = χ²₆(p)`.
//!
//! A candidate is confirmed when most of the cycles it closes are consistent (at least one,
//! and more than half): with confirmed `c₁`, `c₂`, a right `c₀` passes nearly every cycle and
//! a wrong one nearly none. Cycles are taken through the confirmed closures nearest to the
//! candidate's ends along each trajectory (shortest odometry, so the tightest test), at
//! most [`NEAREST`] per side and third robot. Confirmed candidates confirm others in turn
//! (repeated until nothing changes). Between candidates of one pair that pass, only a set
//! that is pairwise consistent is kept (most consistent cycles first).
//!
//! The same cycles also check pairs that do hold a clique: three robots whose three cliques
//! contradict each other have one pair set aside, by trust rather than size
//! ([`contradicted_pairs`]).
//!
//! Nothing here needs more than what PCM already has: every robot's odometry and the
//! closures. In the distributed back-end the robot that solves the separator graph holds
//! both (the condensed graphs), so the check costs no message.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{Isometry3, Matrix6};

use super::pcm::{Closure, Odometry, PairProblem};
use doorslam_geometry::key;
use doorslam_geometry::{LieGroup, Tangent};

/// Confirmed closures nearest to a candidate's end, per side and third robot.
pub const NEAREST: usize = 8;

/// A robot pair, lower robot first.
pub type Pair = (Option<u8>, Option<u8>);

/// Squared Mahalanobis norm of the error of the cycle `F₁ ⋯ Fₙ` (each factor a relative
/// pose with its covariance, right perturbations), or `None` if the covariance of the
/// error is singular.
pub fn cycle_mahalanobis2(factors: &[(Isometry3<f64>, Matrix6<f64>)]) -> Option<f64> {
    let n = factors.len();
    if n == 0 {
        return None;
    }
    // after[k] = F_{k+1} ⋯ F_n.
    let mut after = vec![Isometry3::identity(); n];
    for k in (0..n - 1).rev() {
        after[k] = factors[k + 1].0 * after[k + 1];
    }
    let t = factors[0].0 * after[0];
    let mut sigma = Matrix6::zeros();
    for ((_, s), a) in factors.iter().zip(&after) {
        let ad = a.inverse().adjoint();
        sigma += ad * s * ad.transpose();
    }
    let e: Tangent = t.log();
    let jr_inv = Isometry3::right_jacobian_inv(&e);
    let sigma_e = jr_inv * sigma * jr_inv.transpose();
    let inv = sigma_e.cholesky()?.inverse();
    Some(e.dot(&(inv * e)))
}

/// `c` oriented to start at a pose of robot `from`.
fn from_robot(c: &Closure, from: Option<u8>) -> Closure {
    if key::robot(c.u) == from {
        c.clone()
    } else {
        c.reversed()
    }
}

/// Squared Mahalanobis norm of the cycle `c₀` (α→β), `c₂` (β→γ), `c₁` (γ→α) through the
/// three robots' odometry, or `None` if an odometry leg does not connect.
pub fn triple_mahalanobis2(
    odo: &Odometry,
    c0: &Closure,
    c1: &Closure,
    c2: &Closure,
) -> Option<f64> {
    let (alpha, beta) = (key::robot(c0.u), key::robot(c0.v));
    let c2 = from_robot(c2, beta);
    let gamma = key::robot(c2.v);
    let c1 = from_robot(c1, gamma);
    if key::robot(c1.v) != alpha {
        return None;
    }
    let reversed_z1 = (c1.measured, c1.covariance);
    let factors = [
        (c0.measured, c0.covariance),
        odo.between(c0.v, c2.u)?,
        (c2.measured, c2.covariance),
        odo.between(c2.v, c1.u)?,
        reversed_z1,
        odo.between(c1.v, c0.u)?,
    ];
    cycle_mahalanobis2(&factors)
}

fn pair_of(a: Option<u8>, b: Option<u8>) -> Pair {
    if a <= b {
        (a, b)
    } else {
        (b, a)
    }
}

/// The end of `c` on robot `r`.
fn end_on(c: &Closure, r: Option<u8>) -> u64 {
    if key::robot(c.u) == r {
        c.u
    } else {
        c.v
    }
}

/// Up to `NEAREST` of `confirmed`, nearest (by index) to `pose` along its robot.
fn nearest<'a>(confirmed: &[&'a Closure], pose: u64) -> Vec<&'a Closure> {
    let r = key::robot(pose);
    let mut v: Vec<&Closure> = confirmed.to_vec();
    v.sort_by_key(|c| {
        (
            key::index(end_on(c, r)).abs_diff(key::index(pose)),
            c.u,
            c.v,
        )
    });
    v.truncate(NEAREST);
    v
}

/// (consistent, checked) cycles of candidate `c0` through the confirmed closures.
fn cycles_of(
    odo: &Odometry,
    c0: &Closure,
    confirmed: &BTreeMap<Pair, Vec<&Closure>>,
    robots: &BTreeSet<Option<u8>>,
    gamma: f64,
) -> (usize, usize) {
    let (alpha, beta) = (key::robot(c0.u), key::robot(c0.v));
    let (mut consistent, mut checked) = (0, 0);
    for &third in robots.iter().filter(|r| **r != alpha && **r != beta) {
        let (Some(v1), Some(v2)) = (
            confirmed.get(&pair_of(alpha, third)),
            confirmed.get(&pair_of(beta, third)),
        ) else {
            continue;
        };
        for c1 in nearest(v1, c0.u) {
            for c2 in nearest(v2, c0.v) {
                if let Some(d2) = triple_mahalanobis2(odo, c0, c1, c2) {
                    checked += 1;
                    consistent += usize::from(d2 <= gamma);
                }
            }
        }
    }
    (consistent, checked)
}

/// Robot pairs whose accepted clique a 3-robot cycle contradicts and that are set aside.
///
/// Three robots whose three pairs each hold an accepted clique close cycles through all
/// three; when most of those cycles fail, one pair's clique is wrong, and geometry alone
/// cannot say which. Size must not decide: a teammate that controls its own trajectory
/// (a valid certificate, a hostile or broken robot) can make its closures with two others
/// as many and as mutually consistent as it likes, so the sets of closures through it would
/// outweigh the true closures between the other two and move one relative to the other.
/// What it can always do — lie about where it is itself — a set-aside pair still lets it
/// do; what it must not do is bend the others.
///
/// So a contradicted triangle is broken by setting aside one pair, chosen by trust, not
/// size: first a pair no consistent triangle corroborates, in the order of the robot it
/// does not touch (lowest first); all corroborated, the one not touching the triangle's
/// lowest robot. Triangles are taken in the order of their robots, so those of the team's
/// lowest robot come first — in the distributed back-end the robot that runs PCM (the
/// team's solver, whose own data it knows to be its own): for it the pair of the two
/// others goes, and with one hostile robot among them that pair is one of the hostile
/// robot's, whichever side it lies about. The others keep their closures with the lowest
/// robot, so each is placed by its own evidence with it.
///
/// The limit: with one hostile robot among three robots none of which is the lowest of a
/// triangle the team's lowest robot is part of, and no consistent triangle to tell the
/// honest pair, the pair of the two higher robots goes — honest if the hostile one is
/// the lowest of the three.
pub fn contradicted_pairs(
    problems: &BTreeMap<Pair, PairProblem>,
    odo: &Odometry,
    gamma: f64,
    min_clique: usize,
) -> BTreeSet<Pair> {
    let accepted: BTreeMap<Pair, Vec<&Closure>> = problems
        .iter()
        .filter(|(k, p)| k.0 != k.1 && !p.accepted(min_clique).is_empty())
        .map(|(k, p)| {
            let kept = p.accepted(min_clique).iter().map(|&i| &p.closures[i]);
            (*k, kept.collect())
        })
        .collect();
    let robots: BTreeSet<Option<u8>> = accepted.keys().flat_map(|(a, b)| [*a, *b]).collect();
    let robots: Vec<Option<u8>> = robots.into_iter().collect();
    // Every triangle of accepted pairs, in robot order, with its verdict.
    let mut triangles: Vec<([Option<u8>; 3], bool)> = Vec::new();
    for (i, &r0) in robots.iter().enumerate() {
        for (j, &r1) in robots.iter().enumerate().skip(i + 1) {
            for &r2 in robots.iter().skip(j + 1) {
                let (p01, p02, p12) = (pair_of(r0, r1), pair_of(r0, r2), pair_of(r1, r2));
                let (Some(c01), Some(c02), Some(c12)) =
                    (accepted.get(&p01), accepted.get(&p02), accepted.get(&p12))
                else {
                    continue;
                };
                // The closures of the pair of the two higher robots, through the lowest.
                let view = BTreeMap::from([(p01, c01.clone()), (p02, c02.clone())]);
                let within = BTreeSet::from([r0, r1, r2]);
                let (mut ok, mut all) = (0, 0);
                for c0 in c12 {
                    let (o, a) = cycles_of(odo, c0, &view, &within, gamma);
                    ok += o;
                    all += a;
                }
                if all > 0 {
                    triangles.push(([r0, r1, r2], 2 * ok > all));
                }
            }
        }
    }
    let corroborated: BTreeSet<Pair> = triangles
        .iter()
        .filter(|(_, consistent)| *consistent)
        .flat_map(|([r0, r1, r2], _)| [pair_of(*r0, *r1), pair_of(*r0, *r2), pair_of(*r1, *r2)])
        .collect();
    let mut aside = BTreeSet::new();
    for ([r0, r1, r2], _) in triangles.iter().filter(|(_, consistent)| !consistent) {
        // Opposite r0, r1, r2 in turn.
        let pairs = [pair_of(*r1, *r2), pair_of(*r0, *r2), pair_of(*r0, *r1)];
        if pairs.iter().any(|p| aside.contains(p)) {
            continue;
        }
        let pick = pairs
            .iter()
            .find(|p| !corroborated.contains(*p))
            .unwrap_or(&pairs[0]);
        aside.insert(*pick);
    }
    aside
}

/// Closures of the pairs PCM left without an accepted clique that 3-robot cycles confirm:
/// (pair, index into its closures), with the number of consistent cycles each passed.
pub fn confirm_through_cycles(
    problems: &BTreeMap<Pair, PairProblem>,
    odo: &Odometry,
    gamma: f64,
    min_clique: usize,
    aside: &BTreeSet<Pair>,
) -> BTreeMap<Pair, Vec<usize>> {
    let robots: BTreeSet<Option<u8>> = problems.keys().flat_map(|(a, b)| [*a, *b]).collect();
    let mut confirmed: BTreeMap<Pair, Vec<usize>> = problems
        .iter()
        .filter(|(k, p)| !p.accepted(min_clique).is_empty() && !aside.contains(k))
        .map(|(k, p)| (*k, p.accepted(min_clique).to_vec()))
        .collect();
    let mut added: BTreeMap<Pair, Vec<usize>> = BTreeMap::new();
    loop {
        let view: BTreeMap<Pair, Vec<&Closure>> = confirmed
            .iter()
            .map(|(k, idx)| (*k, idx.iter().map(|&i| &problems[k].closures[i]).collect()))
            .collect();
        let mut progress = BTreeMap::new();
        for (pair, p) in problems {
            // A pair set aside by a contradicted triangle stays aside.
            if confirmed.contains_key(pair) || pair.0 == pair.1 || aside.contains(pair) {
                continue;
            }
            // Candidates that pass, most consistent cycles first.
            let mut passing: Vec<(usize, usize)> = p
                .closures
                .iter()
                .enumerate()
                .filter_map(|(i, c)| {
                    let (ok, all) = cycles_of(odo, c, &view, &robots, gamma);
                    (ok >= 1 && 2 * ok > all).then_some((ok, i))
                })
                .collect();
            passing.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
            let mut kept: Vec<usize> = Vec::new();
            for (_, i) in passing {
                if kept.iter().all(|&k| p.consistent(k, i)) {
                    kept.push(i);
                }
            }
            if !kept.is_empty() {
                kept.sort_unstable();
                progress.insert(*pair, kept);
            }
        }
        if progress.is_empty() {
            return added;
        }
        for (pair, kept) in progress {
            confirmed.insert(pair, kept.clone());
            added.insert(pair, kept);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::outliers::pcm::pairwise_mahalanobis2;
    use crate::PoseGraph;
    use doorslam_geometry::key::symbol;

    #[test]
    fn a_four_factor_cycle_is_the_pairwise_test() {
        // Two robots, a straight line each, two closures; the pairwise test and the generic
        // cycle agree.
        let step = Isometry3::translation(1.0, 0.0, 0.0);
        let info = Matrix6::identity() * 100.0;
        let mut g = PoseGraph::<Isometry3<f64>>::new();
        for r in 0..2u8 {
            for i in 0..5 {
                g.add_pose(
                    symbol(r, i).unwrap(),
                    Isometry3::translation(i as f64, r as f64, 0.0),
                );
            }
            for i in 0..4 {
                let (a, b) = (5 * r as usize + i, 5 * r as usize + i + 1);
                g.add_edge(a, b, step, info).unwrap();
            }
        }
        let odo = Odometry::from_graph(&g).unwrap();
        let closure = |i: u64, j: u64, dx: f64| Closure {
            u: symbol(0, i).unwrap(),
            v: symbol(1, j).unwrap(),
            measured: Isometry3::translation(j as f64 - i as f64 + dx, 1.0, 0.0),
            covariance: Matrix6::identity() * 0.01,
        };
        let (c1, c2) = (closure(1, 1, 0.0), closure(3, 2, 0.3));
        let want = pairwise_mahalanobis2(&odo, &c1, &c2).unwrap();
        let (a, sa) = odo.between(c1.u, c2.u).unwrap();
        let (c, sc) = odo.between(c2.v, c1.v).unwrap();
        let r = c1.reversed();
        let got = cycle_mahalanobis2(&[
            (a, sa),
            (c2.measured, c2.covariance),
            (c, sc),
            (r.measured, r.covariance),
        ])
        .unwrap();
        assert!((got - want).abs() < 1e-9 * want.max(1.0), "{got} vs {want}");
        assert!(want > 0.0);
    }
}
