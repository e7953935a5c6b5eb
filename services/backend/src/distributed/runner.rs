//! N agents in one process over an emulated link: message loss, robots that join late,
//! robots out of range for a while. Every message is encoded, counted, dropped or
//! delivered as bytes, and decoded by the receiver, as over the team link.
//!
//! The reference the result is measured against is the back-end core on the merged
//! graph (chordal initialization + Levenberg-Marquardt, `doorslam pgo`'s default) with
//! the same pose fixed, so trajectories compare without alignment.

use std::collections::{BTreeMap, BTreeSet};
use std::ops::Range;
use std::time::{Duration, Instant};

use doorslam_geometry::{key, LieGroup, TangentMatrix, SE3};
use doorslam_ipc::wire::{
    Body, CompactPose, Estimate, Header, Information, LoopClosure, LoopClosures, Message, Pose,
    PoseEstimate, PoseEstimates, RobotId, SeparatorGraph, Stage, MAX_GRAPH_EDGES,
    MAX_LOOP_CLOSURES, MAX_POSE_ESTIMATES,
};

use super::condensed::CondensedEdge;

use super::{Agent, AgentOptions, DpgoError};
use crate::graph::{EdgeClass, PoseGraph};
use crate::init::Chordal;
use crate::outliers::{Pcm, Scope};
use crate::solver::{optimize, SolverOptions};

/// A transport between the agents other than the runner's own (which drops each message
/// with [`RunOptions::drop`] and delivers the rest at once): e.g. the team link's
/// `PeerSession`s over a faulty emulated radio (`doorslam-hil`'s `dpgo_link`). The agents
/// then run with [`AgentOptions::link_delivers`] when the transport keeps its contract.
pub trait Transport {
    /// Whether robots `a` and `b` are in range this round (called every round for each
    /// pair of neighbours; a change starts or ends a meeting).
    fn presence(&mut self, a: u8, b: u8, present: bool);
    /// A message of `from`'s agent for `to`'s.
    fn send(&mut self, from: u8, to: u8, message: Message) -> Result<(), DpgoError>;
    /// One round of the radio: what arrives at the agents now, as (to, from, message).
    fn deliver(&mut self) -> Result<Vec<(u8, u8, Message)>, DpgoError>;
    /// Nothing in flight or waiting (the run may end).
    fn idle(&self) -> bool;
    /// What went on the radio: messages, bytes, and both per kind, dropped messages.
    fn sent(&self) -> TransportCounts;
}

/// What a [`Transport`] put on the radio (every copy, resends and acknowledgements
/// included).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TransportCounts {
    pub messages: u64,
    pub bytes: u64,
    pub bytes_by_kind: BTreeMap<String, u64>,
    pub messages_by_kind: BTreeMap<String, u64>,
    pub dropped: u64,
    pub resent: u64,
    pub refused: u64,
}

/// How the team is played.
#[derive(Debug, Clone, PartialEq)]
pub struct RunOptions {
    pub agent: AgentOptions,
    /// Probability that a message is lost.
    pub drop: f64,
    /// Seed of the loss draws.
    pub seed: u64,
    /// Rounds (every robot steps once per round, lowest id first: Gauss-Seidel order).
    pub max_rounds: u64,
    /// Simulated time of one round: the agents' clock reads round × this at their step
    /// (their timeouts are in seconds), so runs are deterministic whatever the machine.
    pub round: Duration,
    /// Robot → round at which it joins (its closures appear then, on both sides).
    pub join_at: BTreeMap<u8, u64>,
    /// Robot → rounds during which it is out of range of everyone.
    pub outage: BTreeMap<u8, Range<u64>>,
    /// Robot → round at which it asks its neighbours for the team map (the run goes on
    /// until the replies are in).
    pub team_map: BTreeMap<u8, u64>,
    /// Keyframes per round: each robot's poses arrive this many per round (with their
    /// odometry, and a closure once both its poses exist), as a back-end is fed while it
    /// runs; `None`: every pose from the start.
    pub stream: Option<usize>,
    /// Every this many rounds (and at each round a robot changes stage), the team's χ²
    /// and each robot's stage go into [`RunReport::trace`]: where an iterative method
    /// spends its rounds. `None`: no trace.
    pub trace_every: Option<u64>,
}

impl Default for RunOptions {
    fn default() -> Self {
        Self {
            agent: AgentOptions::default(),
            drop: 0.0,
            seed: 1,
            max_rounds: 500,
            round: Duration::from_millis(100),
            join_at: BTreeMap::new(),
            outage: BTreeMap::new(),
            team_map: BTreeMap::new(),
            stream: None,
            trace_every: None,
        }
    }
}

/// What a run did, `doorslam dpgo --json`'s fields.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RunReport {
    /// Every robot's poses as its agent ends with them (key, pose): in the team's frame
    /// for the robots connected to the anchor (`doorslam dpgo --out`).
    #[serde(skip)]
    pub estimate: Vec<(u64, SE3)>,
    /// Robot → the robot whose frame its estimate is in (anchored robots only).
    #[serde(skip)]
    pub anchors: BTreeMap<u8, u8>,
    pub method: super::Method,
    pub robots: usize,
    /// Rounds until every robot converged (or `max_rounds`).
    pub iterations: u64,
    pub messages: u64,
    /// Encoded bytes of every message sent, delivered or not.
    pub bytes: u64,
    /// Sending every robot's graph to the lowest robot and the result back, in the same
    /// encoding: each robot's odometry and closures as one `SeparatorGraph` (the encoding
    /// the condensed graphs travel in), the results as compact `PoseEstimates`.
    pub bytes_centralized: u64,
    pub bytes_ratio: f64,
    /// The same when robots talk only to robots they share closures with (as the agents
    /// do): each robot's graph and results relayed over its fewest hops to the lowest.
    pub bytes_centralized_relayed: u64,
    /// The same as `bytes_centralized` with the graphs as `LoopClosures` (82 B per edge:
    /// the baseline before the compact graph encoding).
    pub bytes_centralized_loop_closures: u64,
    /// Bytes and messages per wire kind (`Kind::name`).
    pub bytes_by_kind: BTreeMap<String, u64>,
    pub messages_by_kind: BTreeMap<String, u64>,
    pub centralized_chi2: f64,
    /// χ² of the centralized chordal initialization: DGS's two linear stages (relaxed
    /// rotations, then translations with the rotations fixed) solved exactly on the whole
    /// graph. Where DGS's stage 2 ends if its Gauss-Seidel iterations converge.
    pub centralized_two_stage_chi2: f64,
    pub distributed_chi2: f64,
    /// (distributed − centralized) / centralized.
    pub chi2_gap: f64,
    /// RMSE (m) between each pose's distributed and centralized translation.
    pub ate_to_centralized: f64,
    pub time_s: f64,
    /// Every robot settled within `max_rounds` and the team's solver met its convergence
    /// test (`stop_reason`).
    pub converged: bool,
    /// Why the team's solver stopped its last solve (`Summary::stop_reason`, e.g.
    /// `converged_small_decrease`, `max_iterations`); DGS: `dgs_converged` or
    /// `dgs_max_rounds` (its stages stop on their change thresholds).
    pub stop_reason: String,
    /// Condensed method: per robot with a teammate (wire id), the stop reason of the team
    /// solve it was told with its separator estimates (`none`: never told); `converged`
    /// needs every one of them converged.
    pub stop_reasons: BTreeMap<String, String>,
    /// Every robot settled (nothing in flight, nothing due) before `max_rounds`.
    pub settled: bool,
    pub dropped: u64,
    pub resent: u64,
    pub refused: u64,
    pub reinitializations: u64,
    pub separators: usize,
    pub poses: usize,
    /// Inter-robot closures in the team graph, and those PCM rejected inside the loop
    /// (most over the robots: they run the same check) and in the centralized oracle.
    pub closures: usize,
    pub rejected_distributed: u64,
    pub rejected_centralized: usize,
    /// Poses of other robots in the team maps that arrived (requests of `team_map`).
    pub team_map_poses: usize,
    /// The closures PCM rejected in the loop, by the lowest robot (the others run the same
    /// check on the same graph).
    #[serde(skip)]
    pub rejected_keys: Vec<(u64, u64)>,
    /// With [`RunOptions::trace_every`]: the team's χ² as the rounds go.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub trace: Vec<TracePoint>,
}

/// The team at the end of one round ([`RunOptions::trace_every`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TracePoint {
    pub round: u64,
    /// χ² of the robots' estimates on the centralized graph (a robot not yet in the
    /// anchor's frame counts where it is).
    pub chi2: f64,
    /// Stage name (`rotation`, `pose`, `refine`) → robots in it.
    pub stages: BTreeMap<String, usize>,
    /// The largest change any robot's last step made (the quantity the stages' stopping
    /// thresholds test: Frobenius norm over a robot's relaxed rotations, or m + rad over
    /// its poses).
    pub largest_change: f64,
    /// The largest angle (degrees) between a pose's rotation in the robots' estimates and in
    /// the centralized two-stage solution (the relaxed rotations DGS's first stage solves
    /// for, projected): how far the first stage is from its own fixed point.
    pub rotation_error_deg: f64,
    /// χ² with the estimates' rotations and every translation solved centrally from them:
    /// the fixed point of DGS's second stage given where the first left the rotations.
    pub translations_solved_chi2: f64,
}

/// The centralized graph with the agents' estimates in place of its poses.
fn team_graph(central: &PoseGraph<SE3>, agents: &BTreeMap<u8, Agent>) -> PoseGraph<SE3> {
    let mut team = central.clone();
    for a in agents.values() {
        for (k, x) in a.estimate() {
            if let Some(p) = team.index_of(k) {
                team.poses_mut()[p] = *x;
            }
        }
    }
    team
}

fn stage_name(s: Stage) -> &'static str {
    match s {
        Stage::Rotation => "rotation",
        Stage::Pose => "pose",
        Stage::Refine => "refine",
    }
}

/// The robot ids on the wire: the key letter.
/// (Robot ids are lower case: robots past 'z' are `r26`, `r27`, ...)
pub fn robot_id(robot: u8) -> Result<RobotId, DpgoError> {
    let id = match key::robot_char(robot) {
        Ok(c) if c.is_ascii_lowercase() => c.to_string(),
        _ => format!("r{robot}"),
    };
    RobotId::new(&id).map_err(|e| DpgoError::BadMessage {
        from: robot,
        reason: e.to_string(),
    })
}

/// `z ≈ X_a⁻¹ X_b` with its information, by key.
type Edge = (u64, u64, SE3, TangentMatrix);

/// One robot's part of a merged graph.
#[derive(Debug, Default)]
struct RobotPart {
    poses: Vec<(u64, SE3)>,
    odometry: Vec<Edge>,
}

fn robot_of(k: u64) -> Result<u8, DpgoError> {
    key::robot(k).ok_or_else(|| DpgoError::NoRobot(key::label(k)))
}

/// What a robot's agent was fed so far.
#[derive(Debug, Default)]
struct Feed {
    poses: usize,
    last: Option<u64>,
    edges: Vec<bool>,
}

impl Feed {
    /// Adds the next `stream` poses (all if `None`) and the own edges whose poses exist.
    fn feed(
        &mut self,
        a: &mut Agent,
        part: &RobotPart,
        stream: Option<usize>,
    ) -> Result<(), DpgoError> {
        let upto = stream.map_or(part.poses.len(), |n| (self.poses + n).min(part.poses.len()));
        for (k, x) in &part.poses[self.poses..upto] {
            a.add_pose(*k, *x)?;
            self.last = Some(*k);
        }
        self.poses = upto;
        self.edges.resize(part.odometry.len(), false);
        let last = self.last;
        let has = |k: u64| last.is_some_and(|l| k <= l);
        for ((i, j, z, info), added) in part.odometry.iter().zip(self.edges.iter_mut()) {
            if !*added && has(*i) && has(*j) {
                a.add_odometry(*i, *j, *z, *info)?;
                *added = true;
            }
        }
        Ok(())
    }

    /// Whether pose `k` of this robot was added (poses come in key order).
    fn has(&self, k: u64) -> bool {
        self.last.is_some_and(|l| k <= l)
    }
}

/// Splits a merged team graph by the robot of each key. Each robot's initial estimate is
/// its own odometry chained from its first pose (what a robot knows before it meets
/// anyone), in key order.
fn split(graph: &PoseGraph<SE3>) -> Result<(BTreeMap<u8, RobotPart>, Vec<Edge>), DpgoError> {
    let mut parts: BTreeMap<u8, RobotPart> = BTreeMap::new();
    let mut order: Vec<usize> = (0..graph.len()).collect();
    order.sort_by_key(|&p| graph.keys()[p]);
    for p in order {
        let k = graph.keys()[p];
        parts
            .entry(robot_of(k)?)
            .or_default()
            .poses
            .push((k, graph.poses()[p]));
    }
    let mut closures = Vec::new();
    for e in graph.edges() {
        let (a, b) = (graph.keys()[e.i], graph.keys()[e.j]);
        if graph.edge_class(e) == EdgeClass::InterLoop {
            closures.push((a, b, e.measured, e.information));
        } else {
            parts
                .entry(robot_of(a)?)
                .or_default()
                .odometry
                .push((a, b, e.measured, e.information));
        }
    }
    // Initial estimate: chain own edges from the first pose.
    for part in parts.values_mut() {
        let mut sub = PoseGraph::<SE3>::new();
        for (k, x) in &part.poses {
            sub.add_pose(*k, *x);
        }
        for (a, b, z, info) in &part.odometry {
            let (i, j) = (
                sub.index_of(*a).unwrap_or_default(),
                sub.index_of(*b).unwrap_or_default(),
            );
            sub.add_edge(i, j, *z, *info)?;
        }
        let known: Vec<bool> = (0..sub.len()).map(|p| p == 0).collect();
        crate::init::chain(&mut sub, 0, &known);
        for (slot, x) in part.poses.iter_mut().zip(sub.poses()) {
            slot.1 = *x;
        }
    }
    Ok((parts, closures))
}

/// The edge `z ≈ X_b⁻¹ X_a` of `z ≈ X_a⁻¹ X_b`: `z⁻¹`, information `Ad(z⁻¹)ᵀ Ω Ad(z⁻¹)`.
fn reversed(z: &SE3, information: &TangentMatrix) -> (SE3, TangentMatrix) {
    let ad = z.inverse().adjoint();
    let r = ad.transpose() * information * ad;
    (z.inverse(), (r + r.transpose()) * 0.5)
}

/// Bytes of the centralized alternative.
struct Centralized {
    /// Graphs as `SeparatorGraph`, results as `PoseEstimates`.
    direct: u64,
    /// The same, each robot's share multiplied by its hops to the central robot.
    relayed: u64,
    /// Graphs as `LoopClosures`.
    loop_closures: u64,
}

/// Hops from `from` to every robot over robots that share closures (who can meet).
fn hops(from: u8, closures: &[Edge]) -> Result<BTreeMap<u8, u64>, DpgoError> {
    let mut adjacent: BTreeMap<u8, BTreeSet<u8>> = BTreeMap::new();
    for c in closures {
        let (a, b) = (robot_of(c.0)?, robot_of(c.1)?);
        adjacent.entry(a).or_default().insert(b);
        adjacent.entry(b).or_default().insert(a);
    }
    let mut hops = BTreeMap::from([(from, 0)]);
    let mut queue = std::collections::VecDeque::from([from]);
    while let Some(r) = queue.pop_front() {
        let h = hops[&r];
        for &n in adjacent.get(&r).into_iter().flatten() {
            if let std::collections::btree_map::Entry::Vacant(e) = hops.entry(n) {
                e.insert(h + 1);
                queue.push_back(n);
            }
        }
    }
    Ok(hops)
}

/// Every robot but the lowest sends its edges (odometry and the closures no lower robot
/// sends), the lowest sends each its optimized poses back.
fn centralized_bytes(
    parts: &BTreeMap<u8, RobotPart>,
    closures: &[Edge],
) -> Result<Centralized, DpgoError> {
    let mut c = Centralized {
        direct: 0,
        relayed: 0,
        loop_closures: 0,
    };
    let Some(&central) = parts.keys().next() else {
        return Ok(c);
    };
    let hops = hops(central, closures)?;
    let quantize = |k: u64, e: doorslam_ipc::wire::QuantizeError| DpgoError::Quantize {
        key: key::label(k),
        source: e,
    };
    let edge = |a: u64, b: u64, z: &SE3, info: &TangentMatrix| -> Result<LoopClosure, DpgoError> {
        Ok(LoopClosure {
            key_a: a,
            key_b: b,
            relative: Pose::from_se3(z).map_err(|e| DpgoError::BadMessage {
                from: 0,
                reason: e.to_string(),
            })?,
            information: Information::from_matrix(info).map_err(|e| DpgoError::BadMessage {
                from: 0,
                reason: e.to_string(),
            })?,
            inliers: 0,
        })
    };
    for (&r, part) in parts {
        if r == central {
            continue;
        }
        let (mut total, mut total_closures) = (0u64, 0u64);
        let id = robot_id(r)?;
        let mut edges = Vec::new();
        let mut own: Vec<CondensedEdge> = Vec::new();
        for (a, b, z, info) in &part.odometry {
            edges.push(edge(*a, *b, z, info)?);
            own.push(CondensedEdge {
                a: *a,
                b: *b,
                z: *z,
                information: *info,
            });
        }
        for (a, b, z, info) in closures {
            // The central robot has its own closures; others are sent once, by the lower
            // of their two robots.
            let (ra, rb) = (robot_of(*a)?, robot_of(*b)?);
            if ra != central && rb != central && ra.min(rb) == r {
                edges.push(edge(*a, *b, z, info)?);
                let (a, b, (z, information)) = if ra == r {
                    (*a, *b, (*z, *info))
                } else {
                    (*b, *a, reversed(z, info))
                };
                own.push(CondensedEdge {
                    a,
                    b,
                    z,
                    information,
                });
            }
        }
        for (n, chunk) in own.chunks(MAX_GRAPH_EDGES).enumerate() {
            let m = Message::new(
                Header {
                    sender: id.clone(),
                    epoch: 0,
                    sequence: n as u64,
                },
                Body::SeparatorGraph(SeparatorGraph {
                    origin: r,
                    version: 1,
                    base: 0,
                    removed: Vec::new(),
                    edges: super::team::wire_edges(r, chunk)?,
                }),
            );
            total += m.encoded_len() as u64;
        }
        for (n, chunk) in edges.chunks(MAX_LOOP_CLOSURES).enumerate() {
            let m = Message::new(
                Header {
                    sender: id.clone(),
                    epoch: 0,
                    sequence: n as u64,
                },
                Body::LoopClosures(LoopClosures {
                    closures: chunk.to_vec(),
                }),
            );
            total_closures += m.encoded_len() as u64;
        }
        let estimates: Vec<PoseEstimate> = part
            .poses
            .iter()
            .map(|(k, x)| {
                Ok(PoseEstimate {
                    key: *k,
                    value: Estimate::Pose(CompactPose::quantize(x).map_err(|e| quantize(*k, e))?),
                })
            })
            .collect::<Result<_, DpgoError>>()?;
        for (n, chunk) in estimates.chunks(MAX_POSE_ESTIMATES).enumerate() {
            let m = Message::new(
                Header {
                    sender: robot_id(central)?,
                    epoch: 0,
                    sequence: n as u64,
                },
                Body::PoseEstimates(PoseEstimates {
                    optimization: 0,
                    round: 0,
                    stage: Stage::Refine,
                    flags: 0,
                    anchor: central,
                    estimates: chunk.to_vec(),
                }),
            );
            total += m.encoded_len() as u64;
            total_closures += m.encoded_len() as u64;
        }
        // A robot no closure connects would be met directly.
        c.direct += total;
        c.relayed += total * hops.get(&r).copied().unwrap_or(1).max(1);
        c.loop_closures += total_closures;
    }
    Ok(c)
}

/// Plays the team of a merged multi-robot graph and compares with the centralized optimum.
pub fn run(graph: &PoseGraph<SE3>, options: &RunOptions) -> Result<RunReport, DpgoError> {
    run_over(graph, options, None)
}

/// [`run`] over `transport` (None: the runner's own lossy delivery).
pub fn run_over(
    graph: &PoseGraph<SE3>,
    options: &RunOptions,
    mut transport: Option<&mut dyn Transport>,
) -> Result<RunReport, DpgoError> {
    let start = Instant::now();
    let (parts, closures) = split(graph)?;
    let centralized = centralized_bytes(&parts, &closures)?;
    let bytes_centralized = centralized.direct;
    // The centralized reference, same gauge: the lowest robot's first pose, at its value.
    let mut central = graph.clone();
    let anchor_key = parts
        .values()
        .next()
        .and_then(|p| p.poses.first())
        .map(|(k, _)| *k)
        .ok_or(crate::solver::SolveError::Empty)?;
    for part in parts.values() {
        for (k, x) in &part.poses {
            central.add_pose(*k, *x);
        }
    }
    // The centralized oracle on the same closures: offline PCM on the merged graph with
    // the agents' settings.
    let mut rejected_centralized = 0usize;
    let mut oracle_kept: Option<BTreeSet<(u64, u64)>> = None;
    if let Some(p) = options.agent.pcm {
        let mut pcm =
            Pcm::new(p.threshold, Scope::InterRobot).map_err(|e| DpgoError::Pcm(e.to_string()))?;
        pcm.min_clique = p.min_clique;
        pcm.cycles = p.cycles;
        let summary = pcm
            .run(&central)
            .map_err(|e| DpgoError::Pcm(e.to_string()))?;
        let keep: BTreeSet<(u64, u64)> = summary
            .inliers
            .iter()
            .flat_map(|&(a, b)| [(a, b), (b, a)])
            .collect();
        let keys = central.keys().to_vec();
        let before = central.edges().len();
        let classes: Vec<EdgeClass> = central
            .edges()
            .iter()
            .map(|e| central.edge_class(e))
            .collect();
        let mut n = 0;
        central.retain_edges(|e| {
            n += 1;
            classes[n - 1] != EdgeClass::InterLoop || keep.contains(&(keys[e.i], keys[e.j]))
        });
        rejected_centralized = before - central.edges().len();
        oracle_kept = Some(keep);
    }
    // PCM may leave robots without a kept closure: the oracle (and the comparison with
    // it) is the part of the team connected to the anchor, as each agent's frame is.
    let mut central = super::condensed::reachable_part(
        &central,
        central.index_of(anchor_key).unwrap_or_default(),
    )?;
    let anchor = central.index_of(anchor_key).unwrap_or_default();
    SE3::chordal(&mut central, anchor)?;
    let centralized_two_stage_chi2 = central.chi2();
    let two_stage_rotations: Vec<SE3> = match options.trace_every {
        Some(_) => central.poses().to_vec(),
        None => Vec::new(),
    };
    optimize(&mut central, anchor, &SolverOptions::default())?;
    let centralized_chi2 = central.chi2();

    // The agents, fed all at once or `stream` poses per round.
    let mut agents: BTreeMap<u8, Agent> = BTreeMap::new();
    for &r in parts.keys() {
        agents.insert(r, Agent::new(r, robot_id(r)?, 1, options.agent.clone()));
    }
    let mut feeds: BTreeMap<u8, Feed> = parts.keys().map(|&r| (r, Feed::default())).collect();
    let joined = |r: u8, round: u64| options.join_at.get(&r).is_none_or(|&j| round >= j);
    let in_range = |r: u8, round: u64| options.outage.get(&r).is_none_or(|o| !o.contains(&round));
    let mut closures_added = vec![false; closures.len()];
    // Deterministic loss draws: runs repeat exactly.
    let mut draws = crate::rng::SplitMix64::new(options.seed);
    let (mut messages, mut bytes, mut dropped, mut refused) = (0u64, 0u64, 0u64, 0u64);
    let mut bytes_by_kind: BTreeMap<String, u64> = BTreeMap::new();
    let mut messages_by_kind: BTreeMap<String, u64> = BTreeMap::new();
    let mut iterations = 0;
    let mut converged = false;
    let robots: Vec<u8> = agents.keys().copied().collect();
    let mut trace = Vec::new();
    let mut last_stages: Vec<Stage> = Vec::new();
    for round in 0..options.max_rounds {
        iterations = round + 1;
        for (&r, part) in &parts {
            if let (Some(a), Some(f)) = (agents.get_mut(&r), feeds.get_mut(&r)) {
                f.feed(a, part, options.stream)?;
            }
        }
        let exists = |k: u64| -> bool {
            robot_of(k)
                .ok()
                .and_then(|r| feeds.get(&r))
                .is_some_and(|f| f.has(k))
        };
        // Closures appear when both robots have joined (they met) and both poses exist.
        for (c, added) in closures.iter().zip(closures_added.iter_mut()) {
            let (ra, rb) = (robot_of(c.0)?, robot_of(c.1)?);
            if !*added && joined(ra, round) && joined(rb, round) && exists(c.0) && exists(c.1) {
                for r in [ra, rb] {
                    if let Some(a) = agents.get_mut(&r) {
                        a.add_closure(c.0, c.1, c.2, c.3)?;
                    }
                }
                *added = true;
            }
        }
        for &r in &robots {
            let neighbors: Vec<u8> = agents[&r].neighbors().collect();
            for n in &neighbors {
                let present = joined(*n, round) && in_range(*n, round) && in_range(r, round);
                if let Some(a) = agents.get_mut(&r) {
                    a.set_present(*n, present);
                }
                if let Some(t) = transport.as_deref_mut() {
                    t.presence(r, *n, present);
                }
            }
        }
        for (&r, &at) in &options.team_map {
            if at == round {
                if let Some(a) = agents.get_mut(&r) {
                    a.request_team_map();
                }
            }
        }
        for &r in &robots {
            if !joined(r, round) {
                continue;
            }
            let Some(agent) = agents.get_mut(&r) else {
                continue;
            };
            // Round r ends r + 1 rounds after the start (an agent's first step then
            // counts one round, as when the timeouts were counted in steps).
            let now = options
                .round
                .saturating_mul(u32::try_from(round + 1).unwrap_or(u32::MAX));
            agent.step(now)?;
            let neighbors: Vec<u8> = agent.neighbors().collect();
            for n in neighbors {
                if !(joined(n, round) && in_range(n, round) && in_range(r, round)) {
                    continue;
                }
                let out = agents.get_mut(&r).map(|a| a.messages_for(n)).transpose()?;
                if let Some(t) = transport.as_deref_mut() {
                    for m in out.unwrap_or_default() {
                        t.send(r, n, m)?;
                    }
                    continue;
                }
                for m in out.unwrap_or_default() {
                    let bytes_m = m.encode().map_err(|e| DpgoError::BadMessage {
                        from: r,
                        reason: e.to_string(),
                    })?;
                    messages += 1;
                    bytes += bytes_m.len() as u64;
                    *bytes_by_kind.entry(m.kind().name().into()).or_default() +=
                        bytes_m.len() as u64;
                    *messages_by_kind.entry(m.kind().name().into()).or_default() += 1;
                    if draws.next_f64() < options.drop {
                        dropped += 1;
                        continue;
                    }
                    let decoded = Message::decode(&bytes_m).map_err(|e| DpgoError::BadMessage {
                        from: r,
                        reason: e.to_string(),
                    })?;
                    if let Some(peer) = agents.get_mut(&n) {
                        if peer.receive(r, &decoded).is_err() {
                            refused += 1;
                        }
                    }
                }
            }
        }
        if let Some(t) = transport.as_deref_mut() {
            for (to, from, m) in t.deliver()? {
                if let Some(peer) = agents.get_mut(&to) {
                    if peer.receive(from, &m).is_err() {
                        refused += 1;
                    }
                }
            }
        }
        if let Some(every) = options.trace_every {
            let stages: Vec<Stage> = agents.values().map(|a| a.stage()).collect();
            if round % every.max(1) == 0 || stages != last_stages {
                let mut by_stage = BTreeMap::new();
                for s in &stages {
                    *by_stage.entry(stage_name(*s).to_string()).or_default() += 1;
                }
                let team = team_graph(&central, &agents);
                let rotation_error_deg = team
                    .poses()
                    .iter()
                    .zip(&two_stage_rotations)
                    .map(|(x, y)| x.rotation.angle_to(&y.rotation).to_degrees())
                    .fold(0.0, f64::max);
                let mut solved = team.clone();
                let translations_solved_chi2 =
                    match crate::init::translations_from_rotations(&mut solved, anchor) {
                        Ok(()) => solved.chi2(),
                        Err(_) => f64::NAN,
                    };
                trace.push(TracePoint {
                    round,
                    chi2: team.chi2(),
                    rotation_error_deg,
                    translations_solved_chi2,
                    stages: by_stage,
                    largest_change: agents
                        .values()
                        .map(|a| a.last_change())
                        .filter(|c| c.is_finite())
                        .fold(0.0, f64::max),
                });
            }
            last_stages = stages;
        }
        let link_idle = transport.as_deref().is_none_or(|t| t.idle());
        let all_joined = robots.iter().all(|&r| joined(r, round));
        let outage_over = options.outage.values().all(|o| round >= o.end);
        let maps_asked = options.team_map.values().all(|&at| round >= at);
        let all_fed = parts
            .iter()
            .all(|(r, p)| feeds.get(r).is_some_and(|f| f.poses == p.poses.len()));
        if all_joined
            && all_fed
            && outage_over
            && maps_asked
            && link_idle
            && closures_added.iter().all(|a| *a)
            && agents
                .values()
                .all(|a| a.converged() || a.neighbors().next().is_none())
        {
            converged = true;
            break;
        }
    }
    if let (Some(kept), Some(solver)) = (&oracle_kept, agents.values().find(|a| a.solves_team())) {
        let rejected: BTreeSet<(u64, u64)> = solver.rejected_closures().iter().copied().collect();
        for c in &closures {
            let in_loop = !rejected.contains(&(c.0, c.1)) && !rejected.contains(&(c.1, c.0));
            let oracle = kept.contains(&(c.0, c.1));
            if in_loop != oracle {
                tracing::debug!(
                    a = key::label(c.0),
                    b = key::label(c.1),
                    in_loop,
                    oracle,
                    "PCM verdicts differ"
                );
            }
        }
    }
    if !converged {
        for a in agents.values().filter(|a| !a.converged()) {
            tracing::debug!(robot = a.robot(), anchored = a.anchored(), "not converged");
        }
    }
    // The team's estimate against the centralized one, in the centralized frame (the
    // condensed method fixes the anchor pose at the identity, the centralized solve and
    // DGS at its initial value: one rigid transform apart, which χ² does not see).
    // χ² on the centralized oracle's graph: with PCM, the closures it kept.
    let distributed = team_graph(&central, &agents);
    let to_central = central.poses()[anchor].compose(&distributed.poses()[anchor].inverse());
    let mut sq = 0.0;
    let mut poses = 0usize;
    for a in agents.values() {
        for (k, _) in a.estimate() {
            let Some(p) = distributed.index_of(k) else {
                continue;
            };
            let x = to_central.compose(&distributed.poses()[p]);
            let c = central.poses()[p];
            sq += (x.translation.vector - c.translation.vector).norm_squared();
            poses += 1;
        }
    }
    let distributed_chi2 = distributed.chi2();
    let (stop_reason, solver_converged) = match options.agent.method {
        super::Method::Dgs => (
            if converged {
                "dgs_converged"
            } else {
                "dgs_max_rounds"
            }
            .to_string(),
            true,
        ),
        // The solve behind the solver's estimate: its own, or the one it inherited from
        // a solver that left (the solutions it holds carry that solve's stop).
        super::Method::Condensed => match agents.values().find(|a| a.solves_team()).and_then(|a| {
            a.team_stop_reason()
                .or(a.last_solve().map(|s| s.stop_reason))
        }) {
            Some(s) => (s.as_str().to_string(), s.is_converged()),
            None => ("no_solve".to_string(), false),
        },
    };
    // What every robot was told: the team converged only if each robot with a teammate
    // knows its estimate comes from a converged solve.
    let (mut stop_reasons, mut everyone_told) = (BTreeMap::new(), true);
    if options.agent.method == super::Method::Condensed {
        for a in agents.values().filter(|a| a.neighbors().next().is_some()) {
            let told = a.team_stop_reason();
            everyone_told &= told.is_some_and(|s| s.is_converged());
            let told = told.map_or("none", |s| s.as_str()).to_string();
            stop_reasons.insert(robot_id(a.robot())?.to_string(), told);
        }
    }
    let stats: Vec<_> = agents.values().map(|a| a.stats()).collect();
    let mut resent_link = 0;
    if let Some(t) = transport.as_deref() {
        let c = t.sent();
        (messages, bytes, dropped) = (c.messages, c.bytes, c.dropped);
        (bytes_by_kind, messages_by_kind) = (c.bytes_by_kind, c.messages_by_kind);
        resent_link = c.resent;
        refused += c.refused;
    }
    let separators = {
        let mut s: Vec<u64> = closures.iter().flat_map(|c| [c.0, c.1]).collect();
        s.sort_unstable();
        s.dedup();
        s.len()
    };
    Ok(RunReport {
        estimate: agents
            .values()
            .flat_map(|a| a.estimate().map(|(k, x)| (k, *x)))
            .collect(),
        anchors: agents
            .values()
            .filter(|a| a.anchored())
            .map(|a| (a.robot(), a.anchor()))
            .collect(),
        method: options.agent.method,
        robots: agents.len(),
        iterations,
        messages,
        bytes,
        bytes_centralized,
        bytes_ratio: bytes as f64 / bytes_centralized.max(1) as f64,
        bytes_centralized_relayed: centralized.relayed,
        bytes_centralized_loop_closures: centralized.loop_closures,
        bytes_by_kind,
        messages_by_kind,
        centralized_chi2,
        centralized_two_stage_chi2,
        distributed_chi2,
        chi2_gap: (distributed_chi2 - centralized_chi2) / centralized_chi2.max(f64::MIN_POSITIVE),
        ate_to_centralized: (sq / poses.max(1) as f64).sqrt(),
        time_s: start.elapsed().as_secs_f64(),
        converged: converged && solver_converged && everyone_told,
        stop_reason,
        stop_reasons,
        settled: converged,
        dropped,
        resent: resent_link + stats.iter().map(|s| s.resent).sum::<u64>(),
        refused: refused + stats.iter().map(|s| s.refused).sum::<u64>(),
        reinitializations: stats.iter().map(|s| s.reinitializations).sum(),
        separators,
        poses,
        closures: closures.len(),
        rejected_distributed: stats.iter().map(|s| s.rejected_closures).max().unwrap_or(0),
        rejected_centralized,
        team_map_poses: agents
            .values()
            .flat_map(|a| a.team_map().values())
            .map(|t| t.poses.len())
            .sum(),
        rejected_keys: agents
            .values()
            .find(|a| a.solves_team())
            .or_else(|| agents.values().next())
            .map(|a| a.rejected_closures().to_vec())
            .unwrap_or_default(),
        trace,
    })
}
