//! The candidate chain: which (query, candidate) keyframe pairs are worth a verification
//! packet (paper §III-B/§III-C, with more than one candidate per query).
//!
//! For every received descriptor (a query), in the order its robot made them:
//! 1. **top-k**: its [`ChainConfig::top_k`] nearest keyframes in the [`MatchIndex`], nearer
//!    than [`ChainConfig::max_distance`] (the match threshold of the descriptor in use): a
//!    true match ranked second, behind a look-alike, still reaches verification;
//! 2. **temporal confirmation**: a pair `(q_i, c_j)` goes on only when at least
//!    [`ChainConfig::min_support`] of the query's temporal neighbours `q_{i±1..=window}`
//!    rank, among their own top-k, a keyframe of `c`'s robot within
//!    [`ChainConfig::max_gap`] ids of `j`: consecutive keyframes matching consecutive
//!    keyframes. A look-alike seen once, or a place matched to different places from one
//!    keyframe to the next, costs no packet. A pair waits while its neighbours may still
//!    come (a robot's descriptors arrive in id order, in batches); it is dropped once a
//!    keyframe of the query's robot beyond the window has been ranked without enough
//!    support, or when [`CandidateChain::flush`] ends the flight.
//!
//! [`ChainStats`] counts what each stage keeps. The same chain serves the rendezvous (a
//! peer's descriptors against this robot's keyframes), a robot's own loops (its own
//! descriptors against its older keyframes: the index's temporal exclusion keeps the recent
//! ones out) and `doorslam place eval --verify`.

use std::collections::{BTreeMap, BTreeSet};

use doorslam_geometry::key;
use doorslam_ipc::wire::{Descriptor, Match};
use serde::{Deserialize, Serialize};

use crate::index::MatchIndex;

/// Pairs waiting for their temporal neighbours, at most (the oldest is dropped beyond).
pub const MAX_PENDING: usize = 4096;

/// How candidates are chosen (`[place]` `top_k`, `temporal_window`, ... in robot.toml).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChainConfig {
    /// Candidates per query (nearest first).
    pub top_k: usize,
    /// Largest descriptor distance of a candidate (int8 wire form).
    pub max_distance: f32,
    /// Temporal neighbours of a query looked at, in ids on each side.
    pub window: u64,
    /// Neighbours that must agree; 0: no temporal check.
    pub min_support: usize,
    /// A neighbour agrees when one of its candidates is within this many ids of the
    /// pair's candidate (same robot).
    pub max_gap: u64,
}

impl ChainConfig {
    /// Top-k below `max_distance` only, no temporal check.
    pub fn top_k_only(top_k: usize, max_distance: f32) -> Self {
        Self {
            top_k,
            max_distance,
            window: 0,
            min_support: 0,
            max_gap: 0,
        }
    }

    /// Checks the values; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.top_k == 0 || self.top_k > 64 {
            return Err(format!("top_k = {}: from 1 to 64", self.top_k));
        }
        if !(self.max_distance.is_finite() && self.max_distance > 0.0 && self.max_distance <= 2.0) {
            return Err(format!(
                "max_distance = {}: a distance of unit vectors, in (0, 2]",
                self.max_distance
            ));
        }
        if self.min_support as u64 > 2 * self.window {
            return Err(format!(
                "min_support = {}: at most the {} neighbours a window of {} has",
                self.min_support,
                2 * self.window,
                self.window
            ));
        }
        Ok(())
    }
}

/// What each stage kept, summed over the chain's life.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChainStats {
    /// Descriptors ranked against the index.
    pub queries: u64,
    /// (query, candidate) pairs in a query's top-k and below the distance bound.
    pub ranked: u64,
    /// Pairs confirmed by their temporal neighbours: what goes to verification.
    pub confirmed: u64,
    /// Pairs the temporal check dropped (no support once the window was complete, at the
    /// end, or beyond [`MAX_PENDING`]).
    pub unconfirmed: u64,
}

/// One candidate of a query.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Ranked {
    candidate: u64,
    distance: f32,
}

/// The chain's state: every query's candidates (the neighbours of later queries need
/// them), and the pairs waiting for support.
#[derive(Debug, Clone)]
pub struct CandidateChain {
    config: ChainConfig,
    ranked: BTreeMap<u64, Vec<Ranked>>,
    /// Highest query id ranked per robot (a window is complete once it is passed).
    newest: BTreeMap<u8, u64>,
    /// Waiting pairs, by (query, candidate), with their distance; in arrival order.
    pending: BTreeMap<(u64, u64), (u64, f32)>,
    arrivals: u64,
    sent: BTreeSet<(u64, u64)>,
    stats: ChainStats,
}

impl CandidateChain {
    pub fn new(config: ChainConfig) -> Self {
        Self {
            config,
            ranked: BTreeMap::new(),
            newest: BTreeMap::new(),
            pending: BTreeMap::new(),
            arrivals: 0,
            sent: BTreeSet::new(),
            stats: ChainStats::default(),
        }
    }

    pub fn config(&self) -> &ChainConfig {
        &self.config
    }

    pub fn stats(&self) -> &ChainStats {
        &self.stats
    }

    /// Pairs waiting for their temporal neighbours now.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Ranks `received` against `index` and returns every pair confirmed now (this batch's,
    /// and waiting ones its descriptors confirm), in key order; each pair once.
    pub fn push(&mut self, index: &MatchIndex, received: &[Descriptor]) -> Vec<Match> {
        for d in received {
            let candidates = index.top_k(d, self.config.top_k, self.config.max_distance);
            self.stats.queries += 1;
            self.stats.ranked += candidates.len() as u64;
            if let Some(r) = key::robot(d.key) {
                let newest = self.newest.entry(r).or_insert(key::index(d.key));
                *newest = (*newest).max(key::index(d.key));
            }
            for &(candidate, distance) in &candidates {
                if !self.sent.contains(&(d.key, candidate)) {
                    self.arrivals += 1;
                    self.pending
                        .entry((d.key, candidate))
                        .or_insert((self.arrivals, distance));
                }
            }
            self.ranked.insert(
                d.key,
                candidates
                    .into_iter()
                    .map(|(candidate, distance)| Ranked {
                        candidate,
                        distance,
                    })
                    .collect(),
            );
        }
        let out = self.decide(false);
        self.bound_pending();
        out
    }

    /// Ends the flight: every waiting pair is decided with the neighbours there are.
    pub fn flush(&mut self) -> Vec<Match> {
        self.decide(true)
    }

    /// How many of the query's temporal neighbours rank a keyframe near the candidate.
    fn support(&self, query: u64, candidate: u64) -> usize {
        let (Some(robot), i) = (key::robot(query), key::index(query)) else {
            return 0;
        };
        let (c_robot, j) = (key::robot(candidate), key::index(candidate));
        let w = self.config.window;
        let (lo, hi) = (i.saturating_sub(w), i.saturating_add(w));
        let Ok(lo) = key::symbol(robot, lo) else {
            return 0;
        };
        let hi = key::symbol(robot, hi.min(key::MAX_INDEX)).unwrap_or(lo);
        self.ranked
            .range(lo..=hi)
            .filter(|(&n, _)| n != query)
            .filter(|(_, ranked)| {
                ranked.iter().any(|r| {
                    key::robot(r.candidate) == c_robot
                        && key::index(r.candidate).abs_diff(j) <= self.config.max_gap
                })
            })
            .count()
    }

    fn decide(&mut self, at_end: bool) -> Vec<Match> {
        let mut out = Vec::new();
        let pairs: Vec<((u64, u64), f32)> =
            self.pending.iter().map(|(&p, &(_, d))| (p, d)).collect();
        for ((query, candidate), distance) in pairs {
            let confirmed = self.config.min_support == 0
                || self.support(query, candidate) >= self.config.min_support;
            let complete = at_end
                || key::robot(query)
                    .and_then(|r| self.newest.get(&r))
                    .is_some_and(|&n| n > key::index(query).saturating_add(self.config.window));
            if confirmed {
                self.pending.remove(&(query, candidate));
                self.sent.insert((query, candidate));
                self.stats.confirmed += 1;
                out.push(Match {
                    query,
                    candidate,
                    distance,
                });
            } else if complete {
                self.pending.remove(&(query, candidate));
                self.stats.unconfirmed += 1;
            }
        }
        out
    }

    fn bound_pending(&mut self) {
        while self.pending.len() > MAX_PENDING {
            let oldest = self
                .pending
                .iter()
                .min_by_key(|(_, &(arrival, _))| arrival)
                .map(|(&p, _)| p);
            if let Some(p) = oldest {
                self.pending.remove(&p);
                self.stats.unconfirmed += 1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matching::random_unit_vectors;

    fn key(robot: u8, i: u64) -> u64 {
        key::symbol(robot, i).unwrap()
    }

    /// `v` moved a little: the same place seen again.
    fn nudge(v: &[f32], by: f32, seed: usize) -> Vec<f32> {
        let mut w: Vec<f32> = v
            .iter()
            .enumerate()
            .map(|(i, x)| {
                x + by
                    * if (i + seed).is_multiple_of(3) {
                        1.0
                    } else {
                        -0.5
                    }
            })
            .collect();
        let n = w.iter().map(|x| x * x).sum::<f32>().sqrt();
        w.iter_mut().for_each(|x| *x /= n);
        w
    }

    fn index_of(robot: u8, views: &[Vec<f32>]) -> MatchIndex {
        let mut index = MatchIndex::new(robot, 0.5, 5);
        for (i, v) in views.iter().enumerate() {
            index.insert_f32(i as u64, v).unwrap();
        }
        index
    }

    fn queries(robot: u8, views: &[(u64, Vec<f32>)]) -> Vec<Descriptor> {
        views
            .iter()
            .map(|(i, v)| Descriptor::quantize(key(robot, *i), v).unwrap())
            .collect()
    }

    #[test]
    fn top_k_recovers_a_true_match_ranked_second() {
        // Robot b's keyframe 12 is the place robot a's keyframe 3 sees; b's keyframe 30 is
        // a look-alike (another copy of the building) that the descriptor ranks first.
        let places = random_unit_vectors(40, 128, 11);
        let mut own = places.clone();
        own[12] = nudge(&places[12], 0.01, 0);
        let query = nudge(&places[12], 0.01, 1);
        own[30] = nudge(&query, 0.003, 2);
        let index = index_of(1, &own);
        let q = queries(0, &[(3, query)]);
        let ranked = index.top_k(&q[0], 2, 0.5);
        assert_eq!(ranked.len(), 2, "{ranked:?}");
        assert_eq!(ranked[0].0, key(1, 30), "the look-alike is nearest");
        assert_eq!(ranked[1].0, key(1, 12), "the true match is second");
        let mut top1 = CandidateChain::new(ChainConfig::top_k_only(1, 0.5));
        let m = top1.push(&index, &q);
        assert!(m.iter().all(|m| m.candidate != key(1, 12)), "{m:?}");
        let mut top2 = CandidateChain::new(ChainConfig::top_k_only(2, 0.5));
        let m = top2.push(&index, &q);
        assert!(m.iter().any(|m| m.candidate == key(1, 12)), "{m:?}");
        assert_eq!(top2.stats().ranked, 2);
        assert_eq!(top2.stats().confirmed, 2);
    }

    #[test]
    fn a_temporally_inconsistent_candidate_is_not_sent_to_verification() {
        // Robot a's keyframes 10..=14 see robot b's places 20..=24 in order. Keyframe 12
        // also looks like b's keyframe 60 (a look-alike), ranked first, but its neighbours
        // match near 20..24, never near 60.
        let places = random_unit_vectors(80, 128, 21);
        let index = index_of(1, &places);
        let mut seen: Vec<(u64, Vec<f32>)> = (0..5u64)
            .map(|k| (10 + k, nudge(&places[20 + k as usize], 0.02, k as usize)))
            .collect();
        let mix: Vec<f32> = places[60]
            .iter()
            .zip(&places[22])
            .map(|(a, b)| 0.8 * a + 0.6 * b)
            .collect();
        seen[2].1 = nudge(&mix, 0.0, 0);
        let config = ChainConfig {
            top_k: 2,
            max_distance: 1.0,
            window: 2,
            min_support: 2,
            max_gap: 3,
        };
        let mut chain = CandidateChain::new(config.clone());
        let mut sent = chain.push(&index, &queries(0, &seen[..3]));
        // Keyframe 12 waits for its later neighbours (13, 14) before a decision.
        assert!(chain.pending() > 0);
        sent.extend(chain.push(&index, &queries(0, &seen[3..])));
        sent.extend(chain.flush());
        let pairs: Vec<(u64, u64)> = sent.iter().map(|m| (m.query, m.candidate)).collect();
        assert!(
            pairs.contains(&(key(0, 12), key(1, 22))),
            "the consistent pair goes on: {pairs:?}"
        );
        assert!(
            !pairs.contains(&(key(0, 12), key(1, 60))),
            "the inconsistent one does not: {pairs:?}"
        );
        let stats = chain.stats();
        assert!(stats.unconfirmed >= 1, "{stats:?}");
        assert_eq!(stats.confirmed + stats.unconfirmed, stats.ranked);
        // Without the temporal check the look-alike is sent.
        let mut plain = CandidateChain::new(ChainConfig::top_k_only(2, 1.0));
        let all = plain.push(&index, &queries(0, &seen));
        assert!(all
            .iter()
            .any(|m| (m.query, m.candidate) == (key(0, 12), key(1, 60))));
        // A pair is sent once, however often its query comes again.
        assert!(plain.push(&index, &queries(0, &seen)).is_empty());
    }

    #[test]
    fn bad_configurations_are_named() {
        let ok = ChainConfig {
            top_k: 3,
            max_distance: 0.5,
            window: 2,
            min_support: 1,
            max_gap: 3,
        };
        assert!(ok.validate().is_ok());
        let e = ChainConfig {
            top_k: 0,
            ..ok.clone()
        }
        .validate()
        .unwrap_err();
        assert!(e.contains("top_k"), "{e}");
        let e = ChainConfig {
            max_distance: f32::NAN,
            ..ok.clone()
        }
        .validate()
        .unwrap_err();
        assert!(e.contains("max_distance"), "{e}");
        let e = ChainConfig {
            min_support: 5,
            ..ok
        }
        .validate()
        .unwrap_err();
        assert!(e.contains("min_support"), "{e}");
    }
}
