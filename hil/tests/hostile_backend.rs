//! A hostile teammate against the real back-end (issue #33): robots a and b fly a simulated
//! team with ground truth (`posegraph_sim`) and true closures between them; robot z holds a
//! valid place in the team (the team link delivers its messages as its own) and attacks
//! their estimate through the back-end, every robot a real `TeamBridge` (the distributed
//! agent with PCM and 3-robot cycles inside, as a robot runs it):
//!
//! - **crafted closures**: z–a and z–b closures, three times as many as the honest a–b
//!   ones, each set exactly consistent (they pass PCM pairwise), jointly claiming that b
//!   sits 5 m and 0.4 rad away from where the a–b closures put it (or, the other variant,
//!   that a does);
//! - **forged back-end messages**: a condensed graph "relayed" for b with b's chain and
//!   closures of z's choosing (and the newest version), graphs for a, graphs of z with
//!   absurd information, stale versions, updates of versions never sent, a graph of the
//!   wire's largest edge count, pose estimates for keys z does not own, a route claiming
//!   every robot in its subtree, forged acknowledgements, stale epochs.
//!
//! What must hold: no panic and no failed step; the triangle z closes with a and b is
//! broken at the solver (one of z's two closure sets rejected, whatever its size); a's and
//! b's estimates equal, to a tight bound, those of the same team where z never made the
//! rejected claims (z can lie about where z is, never move a relative to b), and the a–b
//! relative pose stays within the honest pair's own error of the honest pair's solution (z's
//! kept closures weigh as measurements of a's shape); forged messages refused (counted per
//! peer and kind by the bridge) or ignored; memory flat. With plain pairwise PCM the same
//! closures move b by metres: the test checks that too, so it fails without the fix.
//!
//! Measured figures: BENCHMARKS.md ("Against the real back-end").

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use doorslam_backend::distributed::condensed::PcmSettings;
use doorslam_backend::distributed::AgentOptions;
use doorslam_backend::service::{BridgeError, TeamBridge};
use doorslam_geometry::{key, TangentMatrix, SE3};
use doorslam_hil::posegraph_sim::{simulate, SimConfig, SimulatedTeam};
use doorslam_ipc::wire::{
    Ack, Body, CompactPose, Estimate, GraphEdge, Header, Information, Kind, Message, PoseEstimate,
    PoseEstimates, RobotId, Route, SeparatorGraph, Stage, MAX_GRAPH_EDGES,
};
use doorslam_ipc::EnvelopeEvent;
use nalgebra::{Translation3, UnitQuaternion, Vector3};

const A: u8 = 0;
const B: u8 = 1;
const Z: u8 = 25;
/// The simulated robot whose trajectory z flies (its own data, which z may report as it likes).
const Z_SIM: usize = 2;
const POSES: usize = 60;
const TEAM_EPOCH: u64 = 1;
const ROUND: Duration = Duration::from_millis(100);
/// z's closures per side, per honest a–b closure.
const OUTNUMBER: usize = 3;
/// How close (translation m + rotation rad, per pose) the attacked a and b stay to the
/// honest pair's solution: the condensed method's own convergence tolerance is ~1e-3 here
/// (measured: 8e-4 with every closure of z rejected).
const BOUND: f64 = 3e-3;

/// The robots' defaults (`[backend]`: PCM 0.99, smallest clique 2, 3-robot cycles), or
/// plain pairwise PCM.
fn options(cycles: bool) -> AgentOptions {
    AgentOptions {
        pcm: Some(PcmSettings {
            threshold: 0.99,
            min_clique: 2,
            cycles,
        }),
        ..AgentOptions::default()
    }
}

fn team() -> SimulatedTeam {
    simulate(&SimConfig {
        robots: 3,
        poses_per_robot: POSES,
        outlier_fraction: 0.0,
        closure_probability: 0.03,
        seed: 33,
        ..SimConfig::default()
    })
    .unwrap()
}

/// Where z claims b (or a) is: displaced by this in the world.
fn lie() -> SE3 {
    SE3::from_parts(
        Translation3::new(4.0, -3.0, 1.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.4),
    )
}

struct Robot {
    r: u8,
    id: RobotId,
    bridge: TeamBridge,
    /// The robot's team link: its sequence per kind.
    sequences: BTreeMap<&'static str, u64>,
}

impl Robot {
    fn new(r: u8, cycles: bool) -> Self {
        let id = RobotId::new(&key::robot_char(r).unwrap().to_string()).unwrap();
        Self {
            r,
            bridge: TeamBridge::new(r, id.clone(), 1, options(cycles)),
            id,
            sequences: BTreeMap::new(),
        }
    }

    /// The header the team link puts on this robot's next message of `kind`.
    fn header(&mut self, kind: Kind) -> Header {
        let s = self.sequences.entry(kind.name()).or_insert(0);
        *s += 1;
        Header {
            sender: self.id.clone(),
            epoch: TEAM_EPOCH,
            sequence: *s,
        }
    }

    /// Its odometry as the robot has it: poses in its own frame (first at the identity).
    fn fly(&mut self, keys: &[u64], poses: &[SE3], odometry: &[(usize, usize, SE3)]) {
        let origin = poses[0].inverse();
        for (k, x) in keys.iter().zip(poses) {
            self.bridge.add_pose(*k, origin * x).unwrap();
        }
        for &(i, j, z) in odometry {
            self.bridge
                .add_odometry(keys[i], keys[j], z, information())
                .unwrap();
        }
    }
}

/// Every measurement's information: the simulator's (σ_R = 0.01 rad, σ_t = 0.1 m), which
/// is also what z gives its crafted closures (as confident as the true ones).
fn information() -> TangentMatrix {
    SimConfig::default().information()
}

/// Robot `r` of the simulated team: its keys, odometry estimate and odometry edges.
/// Odometry edges between poses (by position in the robot's keys).
type OdometryEdges = Vec<(usize, usize, SE3)>;
/// A bridge's refusals per peer robot and message kind.
type RefusedFrom = BTreeMap<u8, BTreeMap<&'static str, u64>>;

fn honest(sim: &SimulatedTeam, r: u8) -> (Vec<u64>, Vec<SE3>, OdometryEdges) {
    let g = &sim.graph;
    let mine: Vec<usize> = (0..g.keys().len())
        .filter(|&p| key::robot(g.keys()[p]) == Some(r))
        .collect();
    let first = mine[0];
    let keys = mine.iter().map(|&p| g.keys()[p]).collect();
    let poses = mine.iter().map(|&p| g.poses()[p]).collect();
    let odometry = sim
        .odometry_edges()
        .iter()
        .filter(|e| key::robot(g.keys()[e.i]) == Some(r))
        .map(|e| (e.i - first, e.j - first, e.measured))
        .collect();
    (keys, poses, odometry)
}

/// The true a–b closures of the simulated team (key_a of robot a).
fn honest_closures(sim: &SimulatedTeam) -> Vec<(u64, u64, SE3)> {
    let g = &sim.graph;
    sim.closures
        .iter()
        .zip(sim.closure_edges())
        .filter(|(l, _)| {
            l.inlier && key::robot(l.key_a) == Some(A) && key::robot(l.key_b) == Some(B)
        })
        .map(|(_, e)| (g.keys()[e.i], g.keys()[e.j], e.measured))
        .collect()
}

/// z's closures: with a (keys a, z) and with b (keys b, z), exact, each set consistent
/// with the truth except that robot `liar_side` is displaced by [`lie`].
fn crafted_closures(sim: &SimulatedTeam, n: usize, liar_side: u8) -> Vec<(u64, u64, SE3)> {
    let truth = |r: u8, i: usize| {
        let t = sim.truth[usize::from(r)][i];
        if r == liar_side {
            lie() * t
        } else {
            t
        }
    };
    let z_truth = |k: usize| sim.truth[Z_SIM][k];
    let mut out = Vec::new();
    for side in [A, B] {
        for m in 0..n {
            let i = (m * (POSES - 1)) / n.max(1);
            let k = (7 * m + 3 * usize::from(side)) % POSES;
            let z = truth(side, i).inverse() * z_truth(k);
            out.push((
                key::symbol(side, i as u64).unwrap(),
                key::symbol(Z, k as u64).unwrap(),
                z,
            ));
        }
    }
    out
}

/// One message handed over as the team link delivers it: `m`'s body under the sender's
/// next header of its kind.
fn deliver(from: &mut Robot, to: &mut Robot, body: Body) -> Result<(), BridgeError> {
    let m = Message::new(from.header(body_kind(&body)), body);
    let bytes = m.encode().expect("the test's messages encode");
    to.bridge
        .on_envelope(EnvelopeEvent::Message as u32, u32::from(from.r), 0, &bytes)
        .map(drop)
}

fn body_kind(b: &Body) -> Kind {
    Message::new(
        Header {
            sender: RobotId::new("a").unwrap(),
            epoch: 0,
            sequence: 0,
        },
        b.clone(),
    )
    .kind()
}

fn index_of(robots: &[Robot], r: u8) -> usize {
    robots.iter().position(|x| x.r == r).unwrap()
}

fn pair(robots: &mut [Robot], i: usize, j: usize) -> (&mut Robot, &mut Robot) {
    assert_ne!(i, j);
    if i < j {
        let (l, r) = robots.split_at_mut(j);
        (&mut l[i], &mut r[0])
    } else {
        let (l, r) = robots.split_at_mut(i);
        (&mut r[0], &mut l[j])
    }
}

/// One round at `now`: every robot steps and its messages cross. Honest traffic (z's real
/// bridge included) is never refused. Returns the messages moved.
fn round(robots: &mut [Robot], now: Duration) -> usize {
    let mut moved = 0;
    for s in 0..robots.len() {
        robots[s]
            .bridge
            .step_at(now)
            .unwrap_or_else(|e| panic!("robot {}'s back-end step failed: {e}", robots[s].r));
        let out = robots[s].bridge.outgoing().unwrap();
        for (peer, bytes) in out {
            let d = index_of(robots, peer);
            let body = Message::decode(&bytes).unwrap().body;
            let (src, dst) = pair(robots, s, d);
            deliver(src, dst, body)
                .unwrap_or_else(|e| panic!("honest message {} -> {} refused: {e}", src.r, dst.r));
            moved += 1;
        }
    }
    moved
}

/// The honest robots settled (z's own agent, whose graph z's forgeries replaced, may
/// never settle: that is z's business).
fn settled(robots: &[Robot]) -> bool {
    robots
        .iter()
        .filter(|r| r.r != Z)
        .all(|r| r.bridge.agent().converged())
}

/// A team of `rs`, every pair present to each other.
fn meet(rs: &[u8], cycles: bool) -> Vec<Robot> {
    let mut robots: Vec<Robot> = rs.iter().map(|&r| Robot::new(r, cycles)).collect();
    for x in &mut robots {
        for &y in rs.iter().filter(|&&y| y != x.r) {
            x.bridge
                .on_envelope(
                    EnvelopeEvent::PeerPresent as u32,
                    u32::from(y),
                    TEAM_EPOCH,
                    &[],
                )
                .unwrap();
        }
    }
    robots
}

fn add_closures(robots: &mut [Robot], closures: &[(u64, u64, SE3)]) {
    for &(ka, kb, z) in closures {
        for r in robots.iter_mut() {
            if [key::robot(ka), key::robot(kb)].contains(&Some(r.r)) {
                r.bridge.add_closure(ka, kb, z, information()).unwrap();
            }
        }
    }
}

fn estimates(robot: &Robot) -> BTreeMap<u64, SE3> {
    robot.bridge.estimate().map(|(k, x)| (k, *x)).collect()
}

/// Largest translation + rotation difference between two estimates of the same poses.
fn largest_difference(x: &BTreeMap<u64, SE3>, y: &BTreeMap<u64, SE3>) -> f64 {
    assert_eq!(x.len(), y.len());
    x.iter()
        .map(|(k, p)| {
            let q = &y[k];
            (p.translation.vector - q.translation.vector).norm() + p.rotation.angle_to(&q.rotation)
        })
        .fold(0.0, f64::max)
}

/// Runs rounds until every robot settled (at most `max`); the rounds run.
fn settle(robots: &mut [Robot], clock: &mut Duration, max: usize) -> usize {
    for n in 0..max {
        *clock += ROUND;
        round(robots, *clock);
        if settled(robots) {
            return n;
        }
    }
    max
}

/// Resident memory of this process, kB.
fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmRSS:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}

fn edge(a: u64, b: u64, z: &SE3, information: &TangentMatrix) -> GraphEdge {
    GraphEdge {
        key_a: a,
        key_b: b,
        relative: CompactPose::quantize(z).unwrap(),
        information: Arc::new(Information::from_matrix(information).unwrap()),
    }
}

fn graph(origin: u8, version: u64, base: u64, edges: Vec<GraphEdge>) -> Body {
    Body::SeparatorGraph(SeparatorGraph {
        origin,
        version,
        base,
        removed: Vec::new(),
        edges,
    })
}

/// z's forgeries for robot `target` in round `n`: (what, message body).
fn forgeries(sim: &SimulatedTeam, target: u8, n: u64) -> Vec<(&'static str, Body)> {
    let info = information();
    let absurd = TangentMatrix::identity() * 1e30;
    let chain = |r: u8, sim_r: usize, lied: bool, info: &TangentMatrix| -> Vec<GraphEdge> {
        (0..POSES - 1)
            .map(|i| {
                let t = &sim.truth[sim_r];
                let mut rel = t[i].inverse() * t[i + 1];
                if lied && i == POSES / 2 {
                    rel *= lie();
                }
                edge(
                    key::symbol(r, i as u64).unwrap(),
                    key::symbol(r, i as u64 + 1).unwrap(),
                    &rel,
                    info,
                )
            })
            .collect()
    };
    // A newer version than any real one (the epoch bits of a robot that restarted often),
    // growing every round.
    let newest = (1 << 40) + 4 * n;
    let mut out = Vec::new();
    // A graph of b "relayed" by z: b's chain bent in the middle by the lie, stiff.
    let stiff = info * 1e4;
    let mut of_b = chain(B, 1, true, &stiff);
    for m in 0..8u64 {
        let (i, k) = (m * 7, m * 5);
        let z = (lie() * sim.truth[1][i as usize]).inverse() * sim.truth[Z_SIM][k as usize];
        of_b.push(edge(
            key::symbol(B, i).unwrap(),
            key::symbol(Z, k).unwrap(),
            &z,
            &stiff,
        ));
    }
    out.push(("relayed_graph_of_b", graph(B, newest, 0, of_b)));
    // A graph of a (the receiver's own, for a), with a closure a–b of z's making.
    let mut of_a = chain(A, 0, false, &info);
    let ab = sim.truth[0][10].inverse() * lie() * sim.truth[1][10];
    of_a.push(edge(
        key::symbol(A, 10).unwrap(),
        key::symbol(B, 10).unwrap(),
        &ab,
        &stiff,
    ));
    out.push(("relayed_graph_of_a", graph(A, newest, 0, of_a)));
    // z's own graph: stale, an update of a version never sent, the wire's largest.
    out.push((
        "stale_version",
        graph(Z, 1, 0, chain(Z, Z_SIM, false, &info)),
    ));
    out.push((
        "update_of_unknown_base",
        graph(Z, newest, 12_345, chain(Z, Z_SIM, false, &info)),
    ));
    let far = 1_000_000u64;
    let huge: Vec<GraphEdge> = (0..MAX_GRAPH_EDGES as u64)
        .map(|i| {
            edge(
                key::symbol(Z, far + i).unwrap(),
                key::symbol(Z, far + i + 1).unwrap(),
                &SE3::translation(1.0, 0.0, 0.0),
                &info,
            )
        })
        .collect();
    out.push(("largest_graph", graph(Z, newest + 1, 0, huge)));
    // Pose estimates for the target's own separators, moved by the lie, and of another
    // stage; an estimate for z's own keys from z is still not z's to give (it is no
    // parent of anyone).
    let moved: Vec<PoseEstimate> = (0..POSES as u64)
        .step_by(7)
        .map(|i| PoseEstimate {
            key: key::symbol(target, i).unwrap(),
            value: Estimate::Pose(
                CompactPose::quantize(&(lie() * sim.truth[usize::from(target)][i as usize]))
                    .unwrap(),
            ),
        })
        .collect();
    let estimates = |stage: Stage| {
        Body::PoseEstimates(PoseEstimates {
            optimization: newest,
            round: n,
            stage,
            flags: 0,
            anchor: A,
            estimates: moved.clone(),
        })
    };
    out.push(("estimates_for_keys_not_owned", estimates(Stage::Refine)));
    out.push(("estimates_of_another_stage", estimates(Stage::Pose)));
    // Routes: every robot in z's subtree; a path through the receiver (a loop).
    out.push((
        "route_claiming_every_robot",
        Body::Route(Route {
            path: vec![A, Z],
            subtree: (1u64 << key::MAX_ROBOTS) - 1,
            session: n,
        }),
    ));
    out.push((
        "route_through_the_receiver",
        Body::Route(Route {
            path: vec![A, B, Z],
            subtree: 0,
            session: n,
        }),
    ));
    out.push((
        "route_not_ending_at_its_sender",
        Body::Route(Route {
            path: vec![A, B],
            subtree: 0,
            session: n,
        }),
    ));
    // Acknowledgements of everything, for the receiver's epoch and another.
    for (what, kind, epoch) in [
        ("ack_of_every_graph", Kind::SeparatorGraph, 1),
        ("ack_of_every_estimate", Kind::PoseEstimates, 1),
        ("ack_of_a_descriptor", Kind::Descriptors, 1),
        ("ack_of_another_epoch", Kind::Route, 77),
    ] {
        out.push((
            what,
            Body::Ack(Ack {
                epoch,
                kind,
                next: u64::MAX / 2,
                received: Vec::new(),
            }),
        ));
    }
    // Information no sensor gives (10³⁰), next to the team's 10²–10⁴.
    out.push((
        "absurd_information",
        graph(Z, newest + 2, 0, chain(Z, Z_SIM, false, &absurd)),
    ));
    // Last, so that it is the graph of z the receiver keeps (newer than z's real ones): z's
    // true chain, every pose a separator. Its closures are then judged with a trajectory
    // that agrees with them, the crafted closures' best case.
    out.push((
        "own_chain_newest",
        graph(Z, newest + 3, 0, chain(Z, Z_SIM, false, &info)),
    ));
    out
}

/// What the attacked robots ended with and what the attack did.
struct Outcome {
    a: BTreeMap<u64, SE3>,
    b: BTreeMap<u64, SE3>,
    /// At the solver (a): z's closures it rejected, per side.
    rejected_with: BTreeMap<u8, usize>,
    crafted_per_side: usize,
    /// Forged messages per (what, outcome).
    tally: BTreeMap<(&'static str, &'static str), u64>,
    forged: u64,
    /// Per attacked robot: the refusals the test saw, and the bridge's count by peer and
    /// kind.
    refusals: BTreeMap<u8, (u64, RefusedFrom)>,
    rss: (u64, u64),
}

/// The number of z's closures per side.
fn crafted_per_side(sim: &SimulatedTeam) -> usize {
    (OUTNUMBER * honest_closures(sim).len()).max(8)
}

/// Robots a and b with their odometry and the true closures between them, and z (when
/// `z_closures` is given) with its trajectory, reported exactly (z's data is its own),
/// and those closures.
fn build(sim: &SimulatedTeam, z_closures: Option<&[(u64, u64, SE3)]>, cycles: bool) -> Vec<Robot> {
    let rs: &[u8] = if z_closures.is_some() {
        &[A, B, Z]
    } else {
        &[A, B]
    };
    let mut robots = meet(rs, cycles);
    for r in [A, B] {
        let (keys, poses, odometry) = honest(sim, r);
        let i = index_of(&robots, r);
        robots[i].fly(&keys, &poses, &odometry);
    }
    if let Some(crafted) = z_closures {
        let zkeys: Vec<u64> = (0..POSES as u64)
            .map(|i| key::symbol(Z, i).unwrap())
            .collect();
        let t = &sim.truth[Z_SIM];
        let zodo: Vec<(usize, usize, SE3)> = (0..POSES - 1)
            .map(|i| (i, i + 1, t[i].inverse() * t[i + 1]))
            .collect();
        let zi = index_of(&robots, Z);
        robots[zi].fly(&zkeys, t, &zodo);
        add_closures(&mut robots, crafted);
    }
    add_closures(&mut robots, &honest_closures(sim));
    robots
}

/// a's and b's estimates once the team of [`build`] settled without any forgery.
fn quiet(
    sim: &SimulatedTeam,
    z_closures: Option<&[(u64, u64, SE3)]>,
) -> (BTreeMap<u64, SE3>, BTreeMap<u64, SE3>) {
    let mut robots = build(sim, z_closures, true);
    let mut clock = Duration::ZERO;
    assert!(settle(&mut robots, &mut clock, 600) < 600);
    (
        estimates(&robots[index_of(&robots, A)]),
        estimates(&robots[index_of(&robots, B)]),
    )
}

/// Largest error of the a–b relative pose `X_a⁻¹ X_b` at the true closures' pose pairs
/// against the truth.
fn relative_error(sim: &SimulatedTeam, x: &(BTreeMap<u64, SE3>, BTreeMap<u64, SE3>)) -> f64 {
    honest_closures(sim)
        .iter()
        .map(|(ka, kb, _)| {
            let p = x.0[ka].inverse() * x.1[kb];
            let t = |k: u64| sim.truth[usize::from(key::robot(k).unwrap())][key::index(k) as usize];
            let q = t(*ka).inverse() * t(*kb);
            (p.translation.vector - q.translation.vector).norm() + p.rotation.angle_to(&q.rotation)
        })
        .fold(0.0, f64::max)
}

/// Largest difference of the a–b relative pose `X_a⁻¹ X_b` at the true closures' pose
/// pairs between two solutions (a, b).
fn relative_difference(
    sim: &SimulatedTeam,
    x: &(BTreeMap<u64, SE3>, BTreeMap<u64, SE3>),
    y: &(BTreeMap<u64, SE3>, BTreeMap<u64, SE3>),
) -> f64 {
    honest_closures(sim)
        .iter()
        .map(|(ka, kb, _)| {
            let p = x.0[ka].inverse() * x.1[kb];
            let q = y.0[ka].inverse() * y.1[kb];
            (p.translation.vector - q.translation.vector).norm() + p.rotation.angle_to(&q.rotation)
        })
        .fold(0.0, f64::max)
}

fn attack(sim: &SimulatedTeam, liar_side: u8, attack_rounds: u64, cycles: bool) -> Outcome {
    let n = crafted_per_side(sim);
    let crafted = crafted_closures(sim, n, liar_side);
    let mut robots = build(sim, Some(&crafted), cycles);
    let zi = index_of(&robots, Z);

    let mut clock = Duration::ZERO;
    let mut tally: BTreeMap<(&'static str, &'static str), u64> = BTreeMap::new();
    let mut forged = 0u64;
    let mut refused_at: BTreeMap<u8, u64> = BTreeMap::new();
    let mut rss = (0, 0);
    for step in 0..attack_rounds {
        clock += ROUND;
        round(&mut robots, clock);
        for target in [A, B] {
            let ti = index_of(&robots, target);
            for (what, body) in forgeries(sim, target, step) {
                let (z, dst) = pair(&mut robots, zi, ti);
                let before = dst.bridge.agent_stats();
                let verdict = match deliver(z, dst, body) {
                    Ok(()) if dst.bridge.agent_stats().ignored_stale > before.ignored_stale => {
                        "ignored"
                    }
                    Ok(()) => "taken",
                    Err(BridgeError::Refused { .. }) => {
                        *refused_at.entry(target).or_default() += 1;
                        "refused"
                    }
                    Err(e) => panic!("{what}: not a refusal by the agent: {e}"),
                };
                *tally.entry((what, verdict)).or_default() += 1;
                forged += 1;
            }
        }
        if step == attack_rounds / 4 {
            rss.0 = rss_kb();
        }
    }
    rss.1 = rss_kb();
    let rounds = settle(&mut robots, &mut clock, 600);
    assert!(rounds < 600, "the team did not settle after the attack");
    let ai = index_of(&robots, A);
    let solver = robots[ai].bridge.agent();
    assert!(solver.solves_team());
    let mut rejected_with = BTreeMap::new();
    for (u, v) in solver.rejected_closures() {
        if key::robot(*v) == Some(Z) {
            *rejected_with.entry(key::robot(*u).unwrap()).or_default() += 1;
        }
    }
    for s in [A, B] {
        rejected_with.entry(s).or_insert(0);
    }
    let refusals = [A, B]
        .into_iter()
        .map(|t| {
            let counted = robots[index_of(&robots, t)].bridge.refused_from().clone();
            (t, (refused_at.get(&t).copied().unwrap_or(0), counted))
        })
        .collect();
    Outcome {
        refusals,
        a: estimates(&robots[ai]),
        b: estimates(&robots[index_of(&robots, B)]),
        rejected_with,
        crafted_per_side: n,
        tally,
        forged,
        rss,
    }
}

#[test]
fn a_hostile_teammate_cannot_move_a_relative_to_b_through_the_back_end() {
    let sim = team();
    let honest_pairs = honest_closures(&sim);
    assert!(
        honest_pairs.len() >= 4,
        "{} true a-b closures",
        honest_pairs.len()
    );
    // A graph of z with an edge from a pose of a (or between a's and b's poses): the wire
    // cannot carry it, a graph's first keys are its origin's by construction.
    let claim = Message::new(
        Header {
            sender: RobotId::new("z").unwrap(),
            epoch: TEAM_EPOCH,
            sequence: 1,
        },
        graph(
            Z,
            5,
            0,
            vec![edge(
                key::symbol(A, 3).unwrap(),
                key::symbol(B, 4).unwrap(),
                &SE3::identity(),
                &information(),
            )],
        ),
    );
    assert!(claim.encode().is_err(), "a graph of z carried a's keys");
    // The honest pair alone: the reference.
    let pair_only = quiet(&sim, None);
    let (reference_a, reference_b) = pair_only.clone();

    // The crafted closures are what PCM pairwise cannot see through: with plain PCM they
    // move b (the test fails there).
    let plain = attack(&sim, B, 60, false);
    let moved = largest_difference(&plain.b, &reference_b);
    println!(
        "plain pairwise PCM: b's estimate {moved:.3} (m + rad) from the honest pair's; z's \
         closures rejected {:?} of {}",
        plain.rejected_with, plain.crafted_per_side
    );
    assert!(moved > 0.5, "the crafted closures did not bend b: {moved}");
    let plain_error = relative_error(&sim, &(plain.a.clone(), plain.b.clone()));
    println!("plain pairwise PCM: a–b relative error to the truth {plain_error:.3}");

    for (liar_side, rounds) in [(B, 400), (A, 60)] {
        let o = attack(&sim, liar_side, rounds, true);
        // The team where z never made the claims PCM set aside: z attached to the team by
        // the closures it kept alone (they may carry true information on the shape of a's
        // or b's trajectory, which is why the honest pair's own solution differs).
        let kept_side = if o.rejected_with[&A] == 0 { A } else { B };
        let kept: Vec<(u64, u64, SE3)> = crafted_closures(&sim, o.crafted_per_side, liar_side)
            .into_iter()
            .filter(|(ka, _, _)| key::robot(*ka) == Some(kept_side))
            .collect();
        let without_lie = quiet(&sim, Some(&kept));
        let (da, db) = (
            largest_difference(&o.a, &without_lie.0),
            largest_difference(&o.b, &without_lie.1),
        );
        let attacked = (o.a.clone(), o.b.clone());
        let relative = relative_difference(&sim, &attacked, &pair_only);
        let (error, honest_error) = (
            relative_error(&sim, &attacked),
            relative_error(&sim, &pair_only),
        );
        println!(
            "z lies about {}: a–b relative pose at the true closures {relative:.2e} (m + rad) \
             from the honest pair's own solution (a and b {:.2e} / {:.2e} from it); its error \
             to the truth {error:.3}, the honest pair's {honest_error:.3}",
            key::robot_char(liar_side).unwrap(),
            largest_difference(&o.a, &reference_a),
            largest_difference(&o.b, &reference_b),
        );
        // What z kept weighs as measurements of the shape of a's trajectory (true ones
        // here): against the honest pair's own solution the a–b relative pose moves within
        // that solution's own error to the truth, never by the lie (5 m, 0.4 rad).
        assert!(
            relative <= honest_error,
            "a–b relative pose moved {relative} from the honest pair's solution, whose error \
             is {honest_error}"
        );
        println!(
            "z lies about {}: {} true a-b closures, {} crafted per side; {} forged messages \
             {:?}; a's and b's estimates within {da:.2e} / {db:.2e} (m + rad) of the team's \
             without the claims set aside; z's closures rejected at the solver {:?}; RSS {} kB \
             after a quarter, \
             {} kB at the end of the attack",
            key::robot_char(liar_side).unwrap(),
            honest_pairs.len(),
            o.crafted_per_side,
            o.forged,
            o.tally,
            o.rejected_with,
            o.rss.0,
            o.rss.1
        );
        // z may lie about where z is; it must not move a relative to b.
        assert!(
            da <= BOUND && db <= BOUND,
            "z moved the honest pair: a by {da}, b by {db}"
        );
        // The triangle z closes with a and b is broken: one of z's closure sets is out.
        // The other stays: z's claim on the lowest robot (which places only z).
        let mut sides: Vec<usize> = o.rejected_with.values().copied().collect();
        sides.sort_unstable();
        assert!(
            sides == [0, o.crafted_per_side],
            "z's closures rejected per side: {:?} of {}",
            o.rejected_with,
            o.crafted_per_side
        );
        // Every forged message that reached the agent was refused or ignored (none of them
        // may move the estimate, which the bound above shows); the refusals are counted.
        let refused: u64 = o
            .tally
            .iter()
            .filter(|((_, v), _)| *v == "refused")
            .map(|(_, n)| n)
            .sum();
        assert!(refused > 0);
        // A relay's graph of a robot heard directly, absurd information: refused every time.
        for what in [
            "relayed_graph_of_a",
            "relayed_graph_of_b",
            "absurd_information",
        ] {
            let not_refused: u64 = o
                .tally
                .iter()
                .filter(|((w, v), _)| *w == what && *v != "refused")
                .map(|(_, n)| n)
                .sum();
            assert_eq!(not_refused, 0, "{what}: {:?}", o.tally);
        }
        for (t, (seen, counted)) in &o.refusals {
            // Every refusal is z's, counted by kind; nothing of the honest pair is refused.
            let of_z: u64 = counted.get(&Z).map_or(0, |k| k.values().sum());
            assert_eq!(of_z, *seen, "robot {t}: refusals counted {counted:?}");
            assert!(counted.keys().all(|r| *r == Z), "robot {t}: {counted:?}");
            println!("robot {t} refused from z: {:?}", counted.get(&Z));
        }
        // Memory: flat from a quarter of the attack to its end.
        assert!(
            o.rss.1 < o.rss.0 + 16 * 1024,
            "memory grew from {} kB to {} kB under the attack",
            o.rss.0,
            o.rss.1
        );
    }
}
