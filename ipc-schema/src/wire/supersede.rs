//! Which messages carry *state* and how a newer one absorbs an older one still waiting to
//! be sent: the team link keeps, per peer, kind and [`Slot`], one message in flight and at
//! most one waiting behind it, merged with [`Body::supersede`]. So however often the
//! distributed back-end updates a separator estimate or a graph, what waits to be sent is
//! bounded by the slots, and the peer, which gets every message it is sent in order
//! exactly once, ends with the same state as if it had received every update.
//!
//! State kinds and their slots: [`PoseEstimates`] per robot of its keys, [`SeparatorGraph`]
//! per origin robot, [`Route`] one, [`TeamMap`] one for the request and one per chunk of a
//! reply (its first key). The other kinds (the rendezvous') are streams: each message is
//! news, none replaces another.

use std::collections::{BTreeMap, BTreeSet};

use super::backend::{GraphEdge, SeparatorGraph, TeamMap, MAX_GRAPH_EDGES};
use super::message::{Body, PoseEstimates, MAX_POSE_ESTIMATES};
use doorslam_geometry::key;

/// The state a message is about, within its kind: (tag, id).
pub type Slot = (u8, u64);

/// Key pairs of graph edges.
fn pairs(edges: &[GraphEdge]) -> BTreeSet<(u64, u64)> {
    edges.iter().map(|e| (e.key_a, e.key_b)).collect()
}

/// `older` then `newer` as one message, if `newer` updates the version `older` makes.
/// Applying an update drops the edges of the pairs it removes or rewrites, then adds its
/// edges; composing two keeps that: the pairs either one removed or rewrote (and the
/// second does not rewrite again) are removed from the first's base.
fn compose(older: &SeparatorGraph, newer: &SeparatorGraph) -> Option<SeparatorGraph> {
    if newer.origin != older.origin || newer.version <= older.version {
        return None;
    }
    if newer.base == 0 {
        return Some(newer.clone());
    }
    if newer.base != older.version {
        return None;
    }
    let rewritten: BTreeSet<(u64, u64)> = newer
        .removed
        .iter()
        .copied()
        .chain(pairs(&newer.edges))
        .collect();
    let edges: Vec<GraphEdge> = older
        .edges
        .iter()
        .filter(|e| !rewritten.contains(&(e.key_a, e.key_b)))
        .chain(&newer.edges)
        .cloned()
        .collect();
    let removed: Vec<(u64, u64)> = if older.base == 0 {
        Vec::new()
    } else {
        let kept = pairs(&edges);
        let gone: BTreeSet<(u64, u64)> = older
            .removed
            .iter()
            .copied()
            .chain(newer.removed.iter().copied())
            .chain(pairs(&older.edges))
            .filter(|p| !kept.contains(p))
            .collect();
        gone.into_iter().collect()
    };
    (edges.len() <= MAX_GRAPH_EDGES && removed.len() <= MAX_GRAPH_EDGES).then_some(SeparatorGraph {
        origin: older.origin,
        version: newer.version,
        base: older.base,
        removed,
        edges,
    })
}

/// `older`'s estimates updated by `newer`'s, if both are of one frame and stage (else the
/// newer replaces: the receiver drops estimates of another frame anyway).
fn merge_estimates(older: &PoseEstimates, newer: &PoseEstimates) -> Option<PoseEstimates> {
    if older.anchor != newer.anchor || older.stage != newer.stage {
        return Some(newer.clone());
    }
    let mut values: BTreeMap<u64, _> = older.estimates.iter().map(|e| (e.key, e.clone())).collect();
    values.extend(newer.estimates.iter().map(|e| (e.key, e.clone())));
    (values.len() <= MAX_POSE_ESTIMATES).then(|| PoseEstimates {
        estimates: values.into_values().collect(),
        ..newer.clone()
    })
}

impl Body {
    /// The state this message carries (`None`: a stream kind, every message is news).
    pub fn slot(&self) -> Option<Slot> {
        match self {
            Body::PoseEstimates(p) => Some((
                0,
                p.estimates
                    .first()
                    .and_then(|e| key::robot(e.key))
                    .map_or(0, u64::from),
            )),
            Body::SeparatorGraph(g) => Some((0, u64::from(g.origin))),
            Body::Route(_) => Some((0, 0)),
            Body::TeamMap(TeamMap::Request { .. }) => Some((0, 0)),
            Body::TeamMap(TeamMap::Trajectory(t)) => {
                Some((1, t.poses.first().map_or(0, |(k, _)| *k)))
            }
            _ => None,
        }
    }

    /// Makes this message (waiting to be sent) carry `newer` too: afterwards the peer,
    /// given only this message, ends as it would after this one and `newer` in order.
    /// `Err(newer)` when they cannot be one message (other kinds or slots, a graph update
    /// of another version, a result beyond the message limits): both must be sent.
    pub fn supersede(&mut self, newer: Body) -> Result<(), Body> {
        if self.kind() != newer.kind() || self.slot().is_none() || self.slot() != newer.slot() {
            return Err(newer);
        }
        let merged = match (&*self, &newer) {
            (Body::SeparatorGraph(a), Body::SeparatorGraph(b)) => {
                compose(a, b).map(Body::SeparatorGraph)
            }
            (Body::PoseEstimates(a), Body::PoseEstimates(b)) => {
                merge_estimates(a, b).map(Body::PoseEstimates)
            }
            // A route, a request or a reply chunk: the newer one is the whole state.
            _ => Some(newer.clone()),
        };
        match merged {
            Some(m) => {
                *self = m;
                Ok(())
            }
            None => Err(newer),
        }
    }
}
