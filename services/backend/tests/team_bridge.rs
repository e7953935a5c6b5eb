//! The back-end's side of the team (`service::team::TeamBridge`) with the team link played
//! in-process: each message handed over is re-headed as the protocol would send it (the
//! sender's team-link epoch, a sequence per kind) and given to the peer's bridge. Two
//! robots with exact odometry and exact closures must end with the true poses in the
//! team's frame (robot a's first keyframe), and keep them through restarts of a team link
//! and of a back-end.

use std::collections::BTreeMap;

use doorslam_backend::distributed::AgentOptions;
use doorslam_backend::service::output::Outputs;
use doorslam_backend::service::{BackendState, TeamBridge};
use doorslam_geometry::{key, TangentMatrix, SE3};
use doorslam_ipc::wire::{Header, Message, RobotId};
use doorslam_ipc::EnvelopeEvent;
use nalgebra::{Translation3, UnitQuaternion, Vector3};

const N: u64 = 12;

/// True pose of keyframe `i` of robot `r`: two parallel lines 2 m apart, gently turning.
fn truth(r: u8, i: u64) -> SE3 {
    let s = i as f64;
    SE3::from_parts(
        Translation3::new(s * 1.0, 2.0 * f64::from(r), 0.1 * s),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.05 * s + 0.3 * f64::from(r)),
    )
}

fn information() -> TangentMatrix {
    TangentMatrix::from_diagonal(&nalgebra::Vector6::new(1e4, 1e4, 1e4, 1e2, 1e2, 1e2))
}

/// One robot: its bridge and what the in-process "team link" knows of it.
struct Robot {
    r: u8,
    bridge: TeamBridge,
    team_epoch: u64,
    /// Sequence per kind of the messages this robot's link sent.
    sequences: BTreeMap<&'static str, u64>,
}

impl Robot {
    fn new(r: u8, backend_epoch: u64, team_epoch: u64) -> Self {
        Self::with_options(r, backend_epoch, team_epoch, AgentOptions::default())
    }

    fn with_options(r: u8, backend_epoch: u64, team_epoch: u64, options: AgentOptions) -> Self {
        let id = RobotId::new(&format!("robot{r}")).unwrap();
        let mut bridge = TeamBridge::new(r, id, backend_epoch, options);
        // Its odometry, starting at the identity in its own frame (it does not know where
        // it is relative to the other robot).
        let origin = truth(r, 0).inverse();
        for i in 0..N {
            let k = key::symbol(r, i).unwrap();
            bridge.add_pose(k, origin * truth(r, i)).unwrap();
            if i > 0 {
                let z = truth(r, i - 1).inverse() * truth(r, i);
                bridge
                    .add_odometry(key::symbol(r, i - 1).unwrap(), k, z, information())
                    .unwrap();
            }
        }
        Self {
            r,
            bridge,
            team_epoch,
            sequences: BTreeMap::new(),
        }
    }

    fn add_true_closures(&mut self) {
        for (i, j) in [(3, 2), (6, 6), (9, 10)] {
            let (a, b) = (key::symbol(0, i).unwrap(), key::symbol(1, j).unwrap());
            let z = truth(0, i).inverse() * truth(1, j);
            self.bridge.add_closure(a, b, z, information()).unwrap();
        }
    }

    fn announce(&mut self, peer: &Robot) {
        self.bridge
            .on_envelope(
                EnvelopeEvent::PeerPresent as u32,
                u32::from(peer.r),
                peer.team_epoch,
                &[],
            )
            .unwrap();
    }
}

/// Gives `dst` the messages `src`'s bridge handed over, as the team link carries them.
fn carry(src: &mut Robot, dst: &mut Robot, messages: Vec<(u8, Vec<u8>)>) -> usize {
    let mut moved = 0;
    for (peer, bytes) in messages {
        assert_eq!(peer, dst.r);
        let m = Message::decode(&bytes).unwrap();
        let kind = m.kind().name();
        let seq = src.sequences.entry(kind).or_insert(0);
        let sent = Message::new(
            Header {
                sender: RobotId::new(&format!("robot{}", src.r)).unwrap(),
                epoch: src.team_epoch,
                sequence: *seq,
            },
            m.body,
        );
        *seq += 1;
        dst.bridge
            .on_envelope(
                EnvelopeEvent::Message as u32,
                u32::from(src.r),
                0,
                &sent.encode().unwrap(),
            )
            .unwrap();
        moved += 1;
    }
    moved
}

/// One round: both step, and every message crosses as the team link would carry it.
fn round(x: &mut Robot, y: &mut Robot) -> usize {
    let mut moved = 0;
    for from in [0, 1] {
        let (src, dst) = if from == 0 {
            (&mut *x, &mut *y)
        } else {
            (&mut *y, &mut *x)
        };
        src.bridge.step().unwrap();
        let out = src.bridge.outgoing().unwrap();
        moved += carry(src, dst, out);
    }
    moved
}

fn settle(x: &mut Robot, y: &mut Robot) -> usize {
    let mut rounds = 0;
    while rounds < 50 {
        rounds += 1;
        let moved = round(x, y);
        if moved == 0 && x.bridge.agent().converged() && y.bridge.agent().converged() {
            break;
        }
    }
    rounds
}

fn max_error(robot: &Robot) -> f64 {
    robot
        .bridge
        .estimate()
        .map(|(k, p)| {
            let t = truth(key::robot(k).unwrap(), key::index(k));
            (p.translation.vector - t.translation.vector).norm() + p.rotation.angle_to(&t.rotation)
        })
        .fold(0.0, f64::max)
}

/// Robots a and b (epoch 1, team epoch 1), each with the true closures between them.
fn two_robots() -> (Robot, Robot) {
    let mut a = Robot::new(0, 1, 1);
    let mut b = Robot::new(1, 1, 1);
    a.add_true_closures();
    b.add_true_closures();
    (a, b)
}

/// backend.json's `team` of robots a (the team's solver) and b once the pair settled, the
/// solver limited to `max_iterations`.
fn team_status(max_iterations: usize) -> [serde_json::Value; 2] {
    let options = AgentOptions {
        solver: doorslam_backend::SolverOptions {
            max_iterations,
            ..doorslam_backend::SolverOptions::default()
        },
        ..AgentOptions::default()
    };
    let mut a = Robot::with_options(0, 1, 1, options.clone());
    let mut b = Robot::with_options(1, 1, 1, options);
    // Closures that disagree (decimetres apart): the optimum has a cost, so a solve is not
    // over in one iteration by reaching zero.
    for (n, (i, j)) in [(3, 2), (6, 6), (9, 10)].into_iter().enumerate() {
        let (ka, kb) = (key::symbol(0, i).unwrap(), key::symbol(1, j).unwrap());
        let off = 0.3 * n as f64;
        let z = truth(0, i).inverse() * truth(1, j) * SE3::translation(off, -off, 0.5 * off);
        for r in [&mut a, &mut b] {
            r.bridge.add_closure(ka, kb, z, information()).unwrap();
        }
    }
    a.announce(&b);
    b.announce(&a);
    assert!(settle(&mut a, &mut b) < 50, "no settling in 50 rounds");
    assert!(a.bridge.agent().solves_team());
    assert!(!b.bridge.agent().solves_team());
    [a, b].map(|r| {
        let state = BackendState::new(0, 10).unwrap().with_team(r.bridge);
        serde_json::to_value(Outputs::status(&state)).unwrap()["team"].clone()
    })
}

#[test]
fn the_status_says_why_the_solver_stopped_and_a_cut_solve_is_not_converged() {
    // On the solver and on the robot it sends estimates to (the stop rides in their flags).
    for cut in team_status(1) {
        assert_eq!(cut["settled"], true, "{cut}");
        assert_eq!(cut["converged"], false, "{cut}");
        assert_eq!(cut["stop_reason"], "max_iterations", "{cut}");
    }
    // Both on the same solve: the one a handed down to b.
    let [a, b] = team_status(100);
    assert!(a["round"].as_u64().is_some_and(|n| n > 0), "{a}");
    assert_eq!(a["round"], b["round"], "{a}\n{b}");
    assert_eq!(a["rounds_handed_down"]["b"], b["round"], "{a}");
    assert_eq!(b["rounds_handed_down"], serde_json::json!({}), "{b}");
    for full in [a, b] {
        assert_eq!(full["converged"], true, "{full}");
        assert!(
            full["stop_reason"]
                .as_str()
                .is_some_and(|r| r.starts_with("converged_")),
            "{full}"
        );
    }
}

#[test]
fn two_robots_reach_the_true_team_estimate_through_the_relay() {
    let (mut a, mut b) = two_robots();
    a.announce(&b);
    b.announce(&a);
    let rounds = settle(&mut a, &mut b);
    assert!(rounds < 50, "no convergence in 50 rounds");
    assert!(a.bridge.agent().anchored() && b.bridge.agent().anchored());
    assert!(max_error(&a) < 1e-3, "a: {}", max_error(&a));
    assert!(max_error(&b) < 1e-3, "b: {}", max_error(&b));
    // No acknowledgement crossed the radio: the relay only carries graphs.
    assert_eq!(a.bridge.agent_stats().resent, 0);
    assert!(a.bridge.stats().messages_out > 0 && b.bridge.stats().messages_in > 0);
}

#[test]
fn a_restarted_back_end_gets_the_team_estimate_back() {
    let (mut a, mut b) = two_robots();
    a.announce(&b);
    b.announce(&a);
    settle(&mut a, &mut b);
    assert!(max_error(&b) < 1e-3);

    // b's back-end restarts (its journal gives it the same graph, a new epoch); its team
    // link starts a new epoch too, and a hears b again with it.
    let mut b = Robot::new(1, 2, 2);
    b.add_true_closures();
    b.announce(&a);
    a.announce(&b);
    assert!(max_error(&b) > 0.5, "b starts from its odometry frame");
    let rounds = settle(&mut a, &mut b);
    assert!(rounds < 50);
    assert!(max_error(&b) < 1e-3, "b after restart: {}", max_error(&b));
    assert!(max_error(&a) < 1e-3);
}

#[test]
fn a_restarted_team_link_makes_the_back_end_send_again() {
    let (mut a, mut b) = two_robots();
    // The team links announce themselves; then a's link restarts before b heard anything.
    for r in [&mut a, &mut b] {
        let e = r.team_epoch;
        assert!(r
            .bridge
            .on_envelope(EnvelopeEvent::TeamStarted as u32, u32::from(r.r), e, &[])
            .unwrap());
    }
    // The same announcement again is no news: no answer (the two ends would ping-pong).
    assert!(!a
        .bridge
        .on_envelope(EnvelopeEvent::TeamStarted as u32, 0, 1, &[])
        .unwrap());
    a.announce(&b);
    b.announce(&a);
    // a's messages of the first round are lost with its old team link.
    a.bridge.step().unwrap();
    assert!(!a.bridge.outgoing().unwrap().is_empty());
    a.team_epoch = 2;
    a.sequences.clear();
    assert!(a
        .bridge
        .on_envelope(EnvelopeEvent::TeamStarted as u32, 0, 2, &[])
        .unwrap());
    assert_eq!(a.bridge.stats().team_restarts, 1);
    // Peers are present again once their Hello comes through the new link.
    a.announce(&b);
    b.announce(&a);
    let rounds = settle(&mut a, &mut b);
    assert!(rounds < 50);
    assert!(max_error(&b) < 1e-3, "b: {}", max_error(&b));
}

#[test]
fn the_rounds_tell_estimates_still_on_the_radio_that_converged_cannot() {
    let (mut a, mut b) = two_robots();
    a.announce(&b);
    b.announce(&a);
    assert!(settle(&mut a, &mut b) < 50);
    let before = a.bridge.agent().team_round().unwrap();
    assert_eq!(b.bridge.agent().team_round(), Some(before));
    assert_eq!(a.bridge.agent().rounds_handed_down(), [(1, before)].into());

    // a's own loop closure, 0.3 m off the truth: a solves again, which moves b too (only
    // a's graph changed, so b has nothing new of its own to wait for). The team link
    // takes a's estimates for b and has not delivered them yet (a resend on a lossy
    // radio can be seconds away).
    let (i, j) = (key::symbol(0, 2).unwrap(), key::symbol(0, 10).unwrap());
    let z = truth(0, 2).inverse() * truth(0, 10) * SE3::translation(0.3, 0.0, 0.0);
    a.bridge.add_odometry(i, j, z, information()).unwrap();
    let b_before: Vec<SE3> = b.bridge.estimate().map(|(_, p)| *p).collect();
    let mut on_the_radio = Vec::new();
    for _ in 0..50 {
        a.bridge.step().unwrap();
        on_the_radio.extend(a.bridge.outgoing().unwrap());
        b.bridge.step().unwrap();
        let out = b.bridge.outgoing().unwrap();
        carry(&mut b, &mut a, out);
        if a.bridge.agent().rounds_handed_down()[&1] > before && a.bridge.agent().converged() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let handed = a.bridge.agent().rounds_handed_down()[&1];
    assert!(
        handed > before,
        "a solved again and handed b's estimates over"
    );
    // Both back-ends' own word: settled, converged (a handed everything to the link,
    // b holds a solve of its latest graph) ...
    assert!(a.bridge.agent().converged() && b.bridge.agent().converged());
    // ... while b's estimate is still the older solve's, and the rounds say so.
    assert_eq!(b.bridge.agent().team_round(), Some(before));
    let b_now: Vec<SE3> = b.bridge.estimate().map(|(_, p)| *p).collect();
    assert_eq!(b_now, b_before);

    // Delivered: b settles on the solve a handed down, and its estimate moves with it.
    carry(&mut a, &mut b, on_the_radio);
    assert!(settle(&mut a, &mut b) < 50);
    let round = a.bridge.agent().team_round();
    assert_eq!(b.bridge.agent().team_round(), round);
    assert_eq!(
        a.bridge.agent().rounds_handed_down()[&1],
        round.unwrap(),
        "a handed down its last solve"
    );
    let moved = b
        .bridge
        .estimate()
        .zip(&b_before)
        .map(|((_, p), q)| (p.translation.vector - q.translation.vector).norm())
        .fold(0.0, f64::max);
    assert!(
        moved > 0.01,
        "b's estimate moved by {moved} m with a's new solve"
    );
}

#[test]
fn bad_envelopes_are_refused_and_counted() {
    let mut a = Robot::new(0, 1, 1);
    assert!(a.bridge.on_envelope(99, 1, 1, &[]).is_err());
    assert!(a
        .bridge
        .on_envelope(EnvelopeEvent::Message as u32, 1, 1, b"not a message")
        .is_err());
    assert!(a
        .bridge
        .on_envelope(EnvelopeEvent::PeerPresent as u32, 200, 1, &[])
        .is_err());
    assert!(
        a.bridge
            .on_envelope(EnvelopeEvent::PeerPresent as u32, 0, 1, &[])
            .is_err(),
        "this robot itself is no peer"
    );
    assert_eq!(a.bridge.stats().bad_envelopes, 4);
}
