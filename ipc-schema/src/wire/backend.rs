//! The distributed back-end's own message bodies: a robot's trajectory condensed onto its
//! separators ([`SeparatorGraph`], whole or as an update), the route to the robot that
//! solves the team ([`Route`]), and the team-map request and reply ([`TeamMap`]).
//! (Separator estimates travel as `PoseEstimates`.)

use std::sync::Arc;

use super::codec::{Reader, Sink};
use super::message::{check_count, NOT_A_ROBOT};
use super::types::{CompactPose, Information, COMPACT_POSE_MIN_BYTES};
use super::WireError;
use doorslam_geometry::key;

/// Most edges (or removed key pairs) in one [`SeparatorGraph`]: 8192 edges of the largest
/// form (~110 bytes) stay below the message limit.
pub const MAX_GRAPH_EDGES: usize = 8192;
/// Most poses in one [`TeamMap`] trajectory message.
pub const MAX_TRAJECTORY_POSES: usize = 16384;

/// One relative-pose constraint of a condensed graph: `X_a⁻¹ X_b`, rotation-first
/// information. `key_a` is always a pose of the graph's origin robot.
#[derive(Debug, Clone, PartialEq)]
pub struct GraphEdge {
    pub key_a: u64,
    pub key_b: u64,
    /// Rounded as a separator estimate (≤ 0.5 mm per axis, ≤ 1e-4 rad).
    pub relative: CompactPose,
    /// Shared between edges that repeat it, as on the wire (so a decoded message takes
    /// memory in proportion to its bytes).
    pub information: Arc<Information>,
}

/// One robot's trajectory condensed onto its separator poses: relative-pose constraints
/// between separators (its odometry compounded between consecutive separators, with the
/// compounded information), its intra-robot loops, and the inter-robot closures it
/// reports. Sent towards the robot that solves the team, hop by hop, so it names its
/// `origin`, a `version` (higher replaces lower) and what it applies to:
///
/// - `base == 0`: the whole graph; `removed` is empty.
/// - `base > 0`: an update of version `base`, which the receiver must hold exactly (else it
///   ignores the message): the edges of every key pair in `removed` and of every key pair
///   that appears in `edges` are dropped, then `edges` are added. So an update carries only
///   the key pairs that changed since `base` (a new separator splits one chain edge in two).
///
/// Layout: origin (u8), version (varint), base (varint, 0 or below version), removed count
/// (varint) then per pair key a's index as a zigzag difference from the previous key a's
/// (the first from 0) and key b (as an edge's), edge count (varint), then per edge:
///
/// | bytes | field |
/// |---|---|
/// | varint | key a's index, zigzag difference from the previous edge's (first: from 0) |
/// | 1 + varint | key b: robot byte, then its index as a zigzag difference from key a's index if the robot is the origin (a chain edge: small), else the index |
/// | 13–25 | relative pose, as `CompactPose` |
/// | 1 (+ 46) | 0: the same information as the previous edge (odometry and closures of one sensor share it); 1: an `Information` follows (refused if equal to the previous one, so the encoding stays canonical) |
///
/// A chain edge is ~22 bytes with repeated information and ~68 with its own compounded
/// information, against 82 for a `LoopClosures` entry.
#[derive(Debug, Clone, PartialEq)]
pub struct SeparatorGraph {
    /// The robot (0 = 'a') whose trajectory this is.
    pub origin: u8,
    pub version: u64,
    pub base: u64,
    pub removed: Vec<(u64, u64)>,
    pub edges: Vec<GraphEdge>,
}

fn write_other_key(s: &mut impl Sink, origin: u8, a_index: u64, b: u64) -> Result<(), WireError> {
    let robot = key::robot(b)
        .ok_or_else(|| WireError::invalid("graph key b", s.offset(), "not a multi-robot key"))?;
    s.u8(robot);
    if robot == origin {
        s.zigzag(key::index(b) as i64 - a_index as i64);
    } else {
        s.varint(key::index(b));
    }
    Ok(())
}

fn read_other_key(r: &mut Reader<'_>, origin: u8, a_index: u64) -> Result<u64, WireError> {
    let offset = r.offset();
    let robot = r.u8("graph key b")?;
    let index = if robot == origin {
        let d = r.zigzag("graph key b")?;
        a_index
            .checked_add_signed(d)
            .ok_or_else(|| WireError::invalid("graph key b", offset, "index out of range"))?
    } else {
        r.varint("graph key b")?
    };
    key::symbol(robot, index).map_err(|e| WireError::invalid("graph key b", offset, e))
}

/// Key a of an edge or removed pair: the origin's, as a difference from the previous.
fn write_own_key(
    s: &mut impl Sink,
    field: &'static str,
    origin: u8,
    previous: u64,
    a: u64,
) -> Result<u64, WireError> {
    if key::robot(a) != Some(origin) {
        return Err(WireError::invalid(
            field,
            s.offset(),
            "key a is not a pose of the graph's origin robot",
        ));
    }
    let index = key::index(a);
    s.zigzag(index as i64 - previous as i64);
    Ok(index)
}

fn read_own_key(
    r: &mut Reader<'_>,
    field: &'static str,
    origin: u8,
    previous: u64,
) -> Result<(u64, u64), WireError> {
    let offset = r.offset();
    let d = r.zigzag(field)?;
    let index = previous
        .checked_add_signed(d)
        .ok_or_else(|| WireError::invalid(field, offset, "index out of range"))?;
    let k = key::symbol(origin, index).map_err(|e| WireError::invalid(field, offset, e))?;
    Ok((k, index))
}

pub(crate) fn write_graph(s: &mut impl Sink, g: &SeparatorGraph) -> Result<(), WireError> {
    if g.origin >= key::MAX_ROBOTS {
        return Err(WireError::invalid("graph origin", s.offset(), NOT_A_ROBOT));
    }
    s.u8(g.origin);
    s.varint(g.version);
    if g.base >= g.version && g.base != 0 {
        return Err(WireError::invalid(
            "graph base",
            s.offset(),
            "an update's base must be older than its version",
        ));
    }
    if g.base == 0 && !g.removed.is_empty() {
        return Err(WireError::invalid(
            "graph removed",
            s.offset(),
            "a whole graph (base 0) removes nothing",
        ));
    }
    s.varint(g.base);
    check_count(s, "graph removed count", g.removed.len(), MAX_GRAPH_EDGES)?;
    s.varint(g.removed.len() as u64);
    let mut previous = 0;
    for &(a, b) in &g.removed {
        previous = write_own_key(s, "graph removed key a", g.origin, previous, a)?;
        write_other_key(s, g.origin, previous, b)?;
    }
    check_count(s, "graph edge count", g.edges.len(), MAX_GRAPH_EDGES)?;
    s.varint(g.edges.len() as u64);
    let mut previous = 0;
    let mut information: Option<&Information> = None;
    for e in &g.edges {
        previous = write_own_key(s, "graph key a", g.origin, previous, e.key_a)?;
        write_other_key(s, g.origin, previous, e.key_b)?;
        e.relative.write(s);
        if information.is_some_and(|i| i.parts() == e.information.parts()) {
            s.u8(0);
        } else {
            s.u8(1);
            e.information.write(s);
        }
        information = Some(&e.information);
    }
    Ok(())
}

pub(crate) fn read_graph(r: &mut Reader<'_>) -> Result<SeparatorGraph, WireError> {
    let offset = r.offset();
    let origin = r.u8("graph origin")?;
    if origin >= key::MAX_ROBOTS {
        return Err(WireError::invalid("graph origin", offset, NOT_A_ROBOT));
    }
    let version = r.varint("graph version")?;
    let offset = r.offset();
    let base = r.varint("graph base")?;
    if base >= version && base != 0 {
        return Err(WireError::invalid(
            "graph base",
            offset,
            "an update's base must be older than its version",
        ));
    }
    // Smallest removed pair: key a (1), key b (2).
    let offset = r.offset();
    let n = r.count("graph removed count", MAX_GRAPH_EDGES, 3)?;
    if base == 0 && n > 0 {
        return Err(WireError::invalid(
            "graph removed",
            offset,
            "a whole graph (base 0) removes nothing",
        ));
    }
    let mut removed = Vec::with_capacity(n);
    let mut previous = 0;
    for _ in 0..n {
        let (a, index) = read_own_key(r, "graph removed key a", origin, previous)?;
        previous = index;
        removed.push((a, read_other_key(r, origin, index)?));
    }
    // Smallest edge: keys (3), pose, information tag (1).
    let n = r.count(
        "graph edge count",
        MAX_GRAPH_EDGES,
        3 + COMPACT_POSE_MIN_BYTES + 1,
    )?;
    let mut edges: Vec<GraphEdge> = Vec::with_capacity(n);
    let mut previous = 0;
    for _ in 0..n {
        let (key_a, index) = read_own_key(r, "graph key a", origin, previous)?;
        previous = index;
        let key_b = read_other_key(r, origin, index)?;
        let relative = CompactPose::read(r, "graph pose")?;
        let offset = r.offset();
        let information = match (r.u8("graph information tag")?, edges.last()) {
            (0, Some(last)) => Arc::clone(&last.information),
            (1, last) => {
                let i = Arc::new(Information::read(r, "graph information")?);
                if last.is_some_and(|l| l.information.parts() == i.parts()) {
                    return Err(WireError::invalid(
                        "graph information",
                        offset,
                        "repeats the previous edge's (must be sent as tag 0)",
                    ));
                }
                i
            }
            (t, _) => {
                return Err(WireError::invalid(
                    "graph information tag",
                    offset,
                    format!("{t} is not 0 (as the previous edge, which must exist) or 1 (new)"),
                ))
            }
        };
        edges.push(GraphEdge {
            key_a,
            key_b,
            relative,
            information,
        });
    }
    Ok(SeparatorGraph {
        origin,
        version,
        base,
        removed,
        edges,
    })
}

/// The route from the robot that solves a connected team (the lowest robot the sender
/// reaches through robots in range) to the sender, and, for the sender's parent (the next
/// robot on that route), the robots whose graphs the sender forwards — itself and those
/// that route through it. Sent to every neighbour in range when it changes.
///
/// Layout: path length (varint, 1..=52), the path's robot bytes (root first, the sender
/// last, distinct), the subtree as a bit set of robot numbers (varint), the session
/// (varint).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Route {
    /// Robots from the root (the team's solver) to the sender, both included.
    pub path: Vec<u8>,
    /// Bit r set: robot r's graph and estimates go through the sender (for its parent;
    /// empty for other neighbours).
    pub subtree: u64,
    /// Incremented by the sender each time its parent changes: what it holds may then have
    /// come from elsewhere, so a parent forgets what it knew the sender to hold.
    pub session: u64,
}

pub(crate) fn write_route(s: &mut impl Sink, r: &Route) -> Result<(), WireError> {
    if r.path.is_empty() {
        return Err(WireError::invalid("route path", s.offset(), "empty"));
    }
    check_count(
        s,
        "route path length",
        r.path.len(),
        key::MAX_ROBOTS as usize,
    )?;
    s.varint(r.path.len() as u64);
    let mut seen = 0u64;
    for &robot in &r.path {
        if robot >= key::MAX_ROBOTS || seen & (1 << robot) != 0 {
            return Err(WireError::invalid(
                "route path",
                s.offset(),
                "robot numbers must be below 52 and distinct",
            ));
        }
        seen |= 1 << robot;
        s.u8(robot);
    }
    if r.subtree >> key::MAX_ROBOTS != 0 {
        return Err(WireError::invalid(
            "route subtree",
            s.offset(),
            "bits beyond robot 51",
        ));
    }
    s.varint(r.subtree);
    s.varint(r.session);
    Ok(())
}

pub(crate) fn read_route(r: &mut Reader<'_>) -> Result<Route, WireError> {
    let offset = r.offset();
    let n = r.count("route path length", key::MAX_ROBOTS as usize, 1)?;
    if n == 0 {
        return Err(WireError::invalid("route path", offset, "empty"));
    }
    let mut path = Vec::with_capacity(n);
    let mut seen = 0u64;
    for _ in 0..n {
        let offset = r.offset();
        let robot = r.u8("route path")?;
        if robot >= key::MAX_ROBOTS || seen & (1 << robot) != 0 {
            return Err(WireError::invalid(
                "route path",
                offset,
                "robot numbers must be below 52 and distinct",
            ));
        }
        seen |= 1 << robot;
        path.push(robot);
    }
    let offset = r.offset();
    let subtree = r.varint("route subtree")?;
    if subtree >> key::MAX_ROBOTS != 0 {
        return Err(WireError::invalid(
            "route subtree",
            offset,
            "bits beyond robot 51",
        ));
    }
    let session = r.varint("route session")?;
    Ok(Route {
        path,
        subtree,
        session,
    })
}

/// A robot's latest keyframe trajectory, for a neighbour that asked for the team map.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// The robot whose first pose fixes the frame (0 = 'a').
    pub anchor: u8,
    /// The sender's estimate revision: a request naming it is answered without poses.
    pub version: u64,
    /// Poses in the whole trajectory of this version (a long one takes several messages).
    pub total: u64,
    /// Ascending keys of the sender's robot, each with its pose in the anchor's frame.
    pub poses: Vec<(u64, CompactPose)>,
}

/// The team-map request and its reply.
///
/// Layout: tag (u8): 0 = request, then the version of the receiver's trajectory the sender
/// already holds (varint, 0 = none); 1 = trajectory: anchor (u8), version (varint), total
/// (varint), robot (u8), count (varint), then per pose its index gap from the previous
/// (the first: the index; ≥ 1 after) and the pose as a `CompactPose` (as `PoseEstimates`).
#[derive(Debug, Clone, PartialEq)]
pub enum TeamMap {
    /// Asks the receiver for its trajectory, unless it is still at version `known`.
    Request {
        known: u64,
    },
    Trajectory(Trajectory),
}

pub(crate) fn write_team_map(s: &mut impl Sink, m: &TeamMap) -> Result<(), WireError> {
    match m {
        TeamMap::Request { known } => {
            s.u8(0);
            s.varint(*known);
        }
        TeamMap::Trajectory(t) => {
            s.u8(1);
            if t.anchor >= key::MAX_ROBOTS {
                return Err(WireError::invalid("map anchor", s.offset(), NOT_A_ROBOT));
            }
            s.u8(t.anchor);
            s.varint(t.version);
            s.varint(t.total);
            let robot = match t.poses.first() {
                Some((k, _)) => key::robot(*k).ok_or_else(|| {
                    WireError::invalid("map key", s.offset(), "not a multi-robot key")
                })?,
                None => 0,
            };
            s.u8(robot);
            check_count(s, "map pose count", t.poses.len(), MAX_TRAJECTORY_POSES)?;
            if t.poses.len() as u64 > t.total {
                return Err(WireError::invalid(
                    "map pose count",
                    s.offset(),
                    "more poses than the trajectory's total",
                ));
            }
            s.varint(t.poses.len() as u64);
            let mut previous: Option<u64> = None;
            for (k, pose) in &t.poses {
                let index = key::index(*k);
                let gap = match previous {
                    None => Some(index),
                    Some(p) => index.checked_sub(p).filter(|&g| g > 0),
                };
                match gap {
                    Some(gap) if key::robot(*k) == Some(robot) => s.varint(gap),
                    _ => {
                        return Err(WireError::invalid(
                            "map key",
                            s.offset(),
                            "keys must be of one robot, strictly ascending",
                        ))
                    }
                }
                previous = Some(index);
                pose.write(s);
            }
        }
    }
    Ok(())
}

pub(crate) fn read_team_map(r: &mut Reader<'_>) -> Result<TeamMap, WireError> {
    let offset = r.offset();
    match r.u8("map tag")? {
        0 => Ok(TeamMap::Request {
            known: r.varint("map known version")?,
        }),
        1 => {
            let offset = r.offset();
            let anchor = r.u8("map anchor")?;
            if anchor >= key::MAX_ROBOTS {
                return Err(WireError::invalid("map anchor", offset, NOT_A_ROBOT));
            }
            let version = r.varint("map version")?;
            let total = r.varint("map total")?;
            let offset = r.offset();
            let robot = r.u8("map robot")?;
            if robot >= key::MAX_ROBOTS {
                return Err(WireError::invalid("map robot", offset, NOT_A_ROBOT));
            }
            let offset = r.offset();
            let n = r.count(
                "map pose count",
                MAX_TRAJECTORY_POSES,
                1 + COMPACT_POSE_MIN_BYTES,
            )?;
            if n == 0 && robot != 0 {
                return Err(WireError::invalid(
                    "map robot",
                    offset - 1,
                    "must be 0 when no pose follows",
                ));
            }
            if n as u64 > total {
                return Err(WireError::invalid(
                    "map pose count",
                    offset,
                    "more poses than the trajectory's total",
                ));
            }
            let mut poses = Vec::with_capacity(n);
            let mut index: Option<u64> = None;
            for _ in 0..n {
                let offset = r.offset();
                let gap = r.varint("map key")?;
                let next = match index {
                    None => Some(gap),
                    Some(p) => p.checked_add(gap).filter(|_| gap > 0),
                };
                let k = next
                    .ok_or_else(|| {
                        WireError::invalid("map key", offset, "keys not strictly ascending")
                    })
                    .and_then(|i| {
                        key::symbol(robot, i).map_err(|e| WireError::invalid("map key", offset, e))
                    })?;
                index = next;
                poses.push((k, CompactPose::read(r, "map pose")?));
            }
            Ok(TeamMap::Trajectory(Trajectory {
                anchor,
                version,
                total,
                poses,
            }))
        }
        t => Err(WireError::invalid(
            "map tag",
            offset,
            format!("{t} is not 0 (request) or 1 (trajectory)"),
        )),
    }
}
