//! The delivery contract of the team link (`doorslam_team::delivery`), end to end through
//! `PeerSession`: a back-end's state messages (separator graphs as chains of updates, each
//! on the version before; pose estimates) reach the peer's back-end exactly once and in
//! order per kind whatever the radio drops, reorders and duplicates, merged while they wait,
//! and never stall.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use doorslam_geometry::information::{matrix_from_upper, upper_from_diagonal};
use doorslam_geometry::{key, SE3};
use doorslam_ipc::wire::{
    Body, CompactPose, Estimate, GraphEdge, Header, Information, Kind, Message, PoseEstimate,
    PoseEstimates, RobotId, SeparatorGraph, Stage,
};
use doorslam_team::emulate::{Bus, EmulatedLink};
use doorslam_team::ledger::{Ledger, LedgerHandle};
use doorslam_team::protocol::{
    BackendExchange, BackendRefusal, Identity, Outgoing, PeerSession, ProtocolConfig, Services,
};
use doorslam_team::standin::{SimPlaces, SimWorld, TruthVerifier};
use doorslam_team::{Node, Pieces};

/// Edges of a graph as its receiver holds them, per key pair.
type Held = BTreeMap<(u64, u64), Vec<GraphEdge>>;

fn edge(robot: u8, a: u64, b: u64, x: f64) -> GraphEdge {
    let info =
        Information::from_matrix(&matrix_from_upper(&upper_from_diagonal([1.0; 6]))).unwrap();
    GraphEdge {
        key_a: key::symbol(robot, a).unwrap(),
        key_b: key::symbol(robot, b).unwrap(),
        relative: CompactPose::quantize(&SE3::translation(x, 0.0, 0.0)).unwrap(),
        information: Arc::new(info),
    }
}

/// Version `v` of robot `robot`'s graph as an update of `v - 1` (v = 1: whole): pair
/// (v % 7, v % 7 + 1) rewritten, and every fifth version pair (v % 3, 9) removed.
fn version(robot: u8, v: u64) -> SeparatorGraph {
    let (a, b) = (v % 7, v % 7 + 1);
    let removed = if v > 1 && v.is_multiple_of(5) {
        vec![(
            key::symbol(robot, v % 3).unwrap(),
            key::symbol(robot, 9).unwrap(),
        )]
    } else {
        Vec::new()
    };
    let mut edges = vec![edge(robot, a, b, v as f64)];
    if v.is_multiple_of(3) {
        edges.push(edge(robot, v % 3, 9, v as f64 + 0.5));
    }
    SeparatorGraph {
        origin: robot,
        version: v,
        base: v - 1,
        removed,
        edges,
    }
}

/// The receiver's rule: a whole graph replaces; an update of the version held drops the
/// pairs it removes or rewrites, then adds its edges. `None`: not an update of `version`.
fn apply(held: &mut (u64, Held), g: &SeparatorGraph) -> Option<()> {
    if g.base != 0 && g.base != held.0 {
        return None;
    }
    if g.base == 0 {
        held.1.clear();
    }
    for p in &g.removed {
        held.1.remove(p);
    }
    for e in &g.edges {
        held.1.remove(&(e.key_a, e.key_b));
    }
    for e in &g.edges {
        held.1
            .entry((e.key_a, e.key_b))
            .or_default()
            .push(e.clone());
    }
    held.0 = g.version;
    Some(())
}

fn estimates(robot: u8, v: u64) -> Body {
    Body::PoseEstimates(PoseEstimates {
        optimization: v,
        round: v,
        stage: Stage::Refine,
        flags: 0,
        anchor: 0,
        // Keys ascending (the wire's rule): four of six, moving with v.
        estimates: (0..4)
            .map(|i| ((v + i) % 6, i))
            .collect::<BTreeMap<u64, u64>>()
            .into_iter()
            .map(|(k, i)| PoseEstimate {
                key: key::symbol(robot, k).unwrap(),
                value: Estimate::Pose(
                    CompactPose::quantize(&SE3::translation(v as f64, i as f64, 0.0)).unwrap(),
                ),
            })
            .collect(),
    })
}

/// What a back-end received, applied by the receiver's rule.
#[derive(Debug, Default)]
struct Received {
    /// Per origin: the graph held, and its versions in the order they were applied
    /// (merged ones skip versions).
    graphs: BTreeMap<u8, (u64, Held)>,
    versions: BTreeMap<u8, Vec<u64>>,
    /// Each key's latest value (a merged message carries the newest round).
    estimates: BTreeMap<u64, CompactPose>,
    rounds: Vec<u64>,
    /// Updates that did not apply to the version held (must stay empty).
    stuck: Vec<(u64, u64)>,
}

/// A back-end sending versions 1..=`last` of its graph and a round of estimates per
/// version, one of each per call (while `sending`), and applying what it receives.
struct StateBackend {
    robot: u8,
    next: u64,
    last: u64,
    /// Also sends the graph of robot + 2, as a relay does.
    relay: bool,
    sending: Arc<Mutex<bool>>,
    got: Arc<Mutex<Received>>,
}

impl StateBackend {
    fn new(robot: u8, last: u64) -> Self {
        Self {
            robot,
            next: 1,
            last,
            relay: true,
            sending: Arc::new(Mutex::new(true)),
            got: Arc::default(),
        }
    }
}

impl BackendExchange for StateBackend {
    fn loop_closures(&mut self, _peer: &RobotId, _closures: &[doorslam_ipc::wire::LoopClosure]) {}

    fn messages_for(&mut self, _peer: &RobotId) -> Vec<Body> {
        if self.next > self.last || !*self.sending.lock().unwrap() {
            return Vec::new();
        }
        let v = self.next;
        self.next += 1;
        // Two origins (its own graph and one it relays): two slots of the kind in flight
        // at once, which the radio can reorder.
        let mut out = vec![Body::SeparatorGraph(version(self.robot, v))];
        if self.relay {
            out.push(Body::SeparatorGraph(version(self.robot + 2, v)));
        }
        out.push(estimates(self.robot, v));
        out
    }

    fn receive(
        &mut self,
        _peer: &RobotId,
        _header: &Header,
        body: Body,
    ) -> Result<(), BackendRefusal> {
        let mut got = self.got.lock().unwrap();
        match body {
            Body::SeparatorGraph(g) => {
                let held = got.graphs.entry(g.origin).or_default();
                if apply(held, &g).is_none() {
                    let v = held.0;
                    got.stuck.push((v, g.base));
                    return Err(BackendRefusal(format!(
                        "update of v{} while v{v} is held",
                        g.base
                    )));
                }
                got.versions.entry(g.origin).or_default().push(g.version);
            }
            Body::PoseEstimates(p) => {
                got.rounds.push(p.round);
                for e in p.estimates {
                    let Estimate::Pose(q) = e.value else {
                        return Err(BackendRefusal("rotation".into()));
                    };
                    got.estimates.insert(e.key, q);
                }
            }
            other => return Err(BackendRefusal(format!("kind {:?}", other.kind()))),
        }
        Ok(())
    }
}

/// What the receiver must end with after every version up to `last` (graphs of `robot`
/// and, if `relay`, of robot + 2).
fn expected(robot: u8, last: u64, relay: bool) -> Received {
    let mut want = Received::default();
    for v in 1..=last {
        for o in [robot, robot + 2].into_iter().take(1 + usize::from(relay)) {
            apply(want.graphs.entry(o).or_default(), &version(o, v)).unwrap();
        }
        let Body::PoseEstimates(p) = estimates(robot, v) else {
            unreachable!()
        };
        for e in p.estimates {
            let Estimate::Pose(q) = e.value else {
                unreachable!()
            };
            want.estimates.insert(e.key, q);
        }
    }
    want
}

fn config() -> ProtocolConfig {
    ProtocolConfig {
        retransmit_ms: 100,
        window: 4,
        receive_window: 16,
        ..ProtocolConfig::default()
    }
}

struct Robot {
    node: Node,
    link: EmulatedLink,
    got: Arc<Mutex<Received>>,
}

fn robot(bus: &Bus, id: &str, index: u8, last: u64) -> Robot {
    let world = SimWorld::default();
    let rid = RobotId::new(id).unwrap();
    let backend = StateBackend::new(index, last);
    let got = backend.got.clone();
    let node = Node::new(
        Identity {
            id: rid.clone(),
            robot: index,
            epoch: 1,
        },
        config(),
        LedgerHandle::new(Ledger::new(id, "test", 1, 752 * 480)),
        Pieces {
            place: Box::new(SimPlaces::new(world, index, 20)),
            verifier: Box::new(TruthVerifier::from_world(world)),
            backend: Box::new(backend),
        },
    );
    Robot {
        link: bus.link(&rid),
        node,
        got,
    }
}

fn done(r: &Robot, peer: u8, last: u64) -> bool {
    let got = r.got.lock().unwrap();
    let want = expected(peer, last, true);
    got.graphs == want.graphs && got.estimates == want.estimates
}

/// Drop 30 %, reorder 30 %, duplicate 10 %: both back-ends end with the other's last graph
/// and estimates, each message taken once and in order (no update ever on a version other
/// than the one held, rounds increasing), within a bounded time, and the faults happened.
#[test]
fn reordered_duplicated_dropped_state_arrives_once_in_order_and_never_stalls() {
    const LAST: u64 = 120;
    let bus = Bus::new(0.3, 29);
    bus.set_reorder_duplicate(0.3, 0.1);
    let mut a = robot(&bus, "a", 0, LAST);
    let mut b = robot(&bus, "b", 1, LAST);
    let (ida, idb) = (RobotId::new("a").unwrap(), RobotId::new("b").unwrap());
    bus.join(&ida, &idb);
    let mut now = 0u64;
    let mut steps = 0;
    while !(done(&a, 1, LAST) && done(&b, 0, LAST)) {
        if steps >= 20_000 {
            for (r, peer) in [(&a, 1u8), (&b, 0u8)] {
                let got = r.got.lock().unwrap();
                let want = expected(peer, LAST, true);
                eprintln!(
                    "graphs {} estimates {} rounds {:?} stuck {:?}",
                    got.graphs == want.graphs,
                    got.estimates == want.estimates,
                    got.rounds.last(),
                    got.stuck
                );
            }
            for (r, peer) in [(&a, &idb), (&b, &ida)] {
                let sess = r.node.session(peer).unwrap();
                eprintln!(
                    "unacked est {:?} graph {:?} stats {:?}",
                    sess.unacknowledged(Kind::PoseEstimates),
                    sess.unacknowledged(Kind::SeparatorGraph),
                    sess.stats().delivery
                );
                let l = r.node.ledger().lock();
                for reason in [
                    "duplicate",
                    "out_of_window",
                    "before_hello",
                    "invalid",
                    "backend_refused",
                    "stale_epoch",
                    "ack_epoch",
                ] {
                    eprintln!("  {reason} {}", l.dropped_count(reason));
                }
            }
            panic!("stalled");
        }
        a.node.step(&mut a.link, now, Duration::ZERO);
        b.node.step(&mut b.link, now, Duration::ZERO);
        now += 10;
        steps += 1;
    }
    for (r, peer) in [(&a, &idb), (&b, &ida)] {
        let got = r.got.lock().unwrap();
        assert!(got.stuck.is_empty(), "{:?}", got.stuck);
        assert!(got
            .versions
            .values()
            .all(|v| v.windows(2).all(|w| w[0] < w[1])));
        assert!(got.rounds.windows(2).all(|w| w[0] < w[1]));
        let ledger = r.node.ledger().lock();
        assert_eq!(ledger.dropped_count("backend_refused"), 0);
        assert!(ledger.dropped_count("duplicate") > 0);
        drop(ledger);
        let stats = r.node.session(peer).unwrap().stats().clone();
        assert!(stats.delivery.held_back > 0, "{stats:?}");
        // Versions queued while one of their slot was in flight were merged, not sent.
        assert!(stats.delivery.superseded > 0, "{stats:?}");
        assert!(stats.delivery.most_waiting <= 2 * config().window as u64 + 4);
    }
    let (reordered, duplicated) = bus.reordered_duplicated();
    assert!(
        reordered > 50 && duplicated > 10,
        "{reordered} {duplicated}"
    );
}

/// Hand-carried messages between two sessions: the test is the radio.
struct Pair {
    a: PeerSession,
    b: PeerSession,
    a_backend: StateBackend,
    b_backend: StateBackend,
    places: [SimPlaces; 2],
    verifier: TruthVerifier,
}

impl Pair {
    fn new() -> Self {
        let world = SimWorld::default();
        let (ida, idb) = (RobotId::new("a").unwrap(), RobotId::new("b").unwrap());
        let me = |id: &RobotId, robot| Identity {
            id: id.clone(),
            robot,
            epoch: 1,
        };
        let mut p = Self {
            a: PeerSession::new(me(&ida, 0), idb.clone(), config()),
            b: PeerSession::new(me(&idb, 1), ida, config()),
            a_backend: StateBackend {
                relay: false,
                ..StateBackend::new(0, 4)
            },
            b_backend: StateBackend::new(1, 0),
            places: [SimPlaces::new(world, 0, 20), SimPlaces::new(world, 1, 20)],
            verifier: TruthVerifier::from_world(world),
        };
        *p.a_backend.sending.lock().unwrap() = false;
        p.a.meeting_started();
        p.b.meeting_started();
        p
    }

    fn poll_a(&mut self, now: u64) -> Vec<Outgoing> {
        let [pa, _] = &mut self.places;
        self.a.poll(
            now,
            &mut Services {
                place: pa,
                verifier: &mut self.verifier,
                backend: &mut self.a_backend,
            },
        )
    }

    fn poll_b(&mut self, now: u64) -> Vec<Outgoing> {
        let [_, pb] = &mut self.places;
        self.b.poll(
            now,
            &mut Services {
                place: pb,
                verifier: &mut self.verifier,
                backend: &mut self.b_backend,
            },
        )
    }

    fn carry_to_b(&mut self, out: Vec<Outgoing>) {
        let [_, pb] = &mut self.places;
        for o in out {
            let m = Message::decode(&o.message.encode().unwrap()).unwrap();
            let _ = self.b.receive(
                m,
                &mut Services {
                    place: pb,
                    verifier: &mut self.verifier,
                    backend: &mut self.b_backend,
                },
            );
        }
    }

    fn carry_to_a(&mut self, out: Vec<Outgoing>) {
        let [pa, _] = &mut self.places;
        for o in out {
            let m = Message::decode(&o.message.encode().unwrap()).unwrap();
            let _ = self.a.receive(
                m,
                &mut Services {
                    place: pa,
                    verifier: &mut self.verifier,
                    backend: &mut self.a_backend,
                },
            );
        }
    }

    /// Both ways until nothing moves (no loss).
    fn settle(&mut self, now: u64) {
        for _ in 0..6 {
            let out = self.poll_a(now);
            self.carry_to_b(out);
            let out = self.poll_b(now);
            self.carry_to_a(out);
        }
    }

    /// a's back-end hands over its next version now.
    fn release(&mut self, now: u64) -> Vec<Outgoing> {
        *self.a_backend.sending.lock().unwrap() = true;
        let out = self.poll_a(now);
        *self.a_backend.sending.lock().unwrap() = false;
        out
    }
}

fn graphs(out: &[Outgoing]) -> Vec<&Message> {
    out.iter()
        .map(|o| &o.message)
        .filter(|m| m.kind() == Kind::SeparatorGraph)
        .collect()
}

/// The case of the issue: graph v2 (an update of v1) is lost while v3 (an update of v2) is
/// ready. v3 cannot overtake v2: it waits behind it (one message per slot in flight) and
/// absorbs v4 meanwhile; the resent v2 is applied, then v3∘v4 as one update of v2, and the
/// peer ends at v4, never having seen an update of a version it does not hold.
#[test]
fn a_lost_v2_keeps_v3_back_until_v2_is_through_and_the_peer_ends_at_the_newest() {
    let mut p = Pair::new();
    p.settle(0);
    assert!(p.b.peer_robot().is_some() && p.a.peer_robot().is_some());
    let out = p.release(10);
    assert_eq!(graphs(&out).len(), 1);
    p.carry_to_b(out);
    p.settle(20);
    assert_eq!(p.b_backend.got.lock().unwrap().versions[&0], vec![1]);
    // v2 goes out and is lost.
    let lost = p.release(30);
    let v2 = graphs(&lost)[0].clone();
    assert!(matches!(&v2.body, Body::SeparatorGraph(g) if g.version == 2 && g.base == 1));
    // v3 and v4 are queued while v2 is in flight: they wait, merged into one.
    let superseded = p.a.stats().delivery.superseded;
    assert!(graphs(&p.release(40)).is_empty());
    assert!(graphs(&p.release(50)).is_empty());
    assert_eq!(p.a.stats().delivery.superseded, superseded + 2);
    // b acknowledges what it has (v1); nothing settles v2.
    let acks = p.poll_b(60);
    p.carry_to_a(acks);
    assert!(graphs(&p.poll_a(70)).is_empty());
    // After the retransmission time v2 goes again, the same message.
    let resent = p.poll_a(200);
    assert_eq!(graphs(&resent), vec![&v2]);
    p.carry_to_b(resent);
    assert_eq!(p.b_backend.got.lock().unwrap().versions[&0], vec![1, 2]);
    // Once v2 is acknowledged, v3∘v4 goes as one update of v2.
    let acks = p.poll_b(210);
    p.carry_to_a(acks);
    let out = p.poll_a(220);
    let merged = graphs(&out);
    assert_eq!(merged.len(), 1);
    assert!(
        matches!(&merged[0].body, Body::SeparatorGraph(g) if g.version == 4 && g.base == 2),
        "{:?}",
        merged[0]
    );
    p.carry_to_b(out);
    p.settle(230);
    let got = p.b_backend.got.lock().unwrap();
    assert_eq!(got.versions[&0], vec![1, 2, 4]);
    assert!(got.stuck.is_empty());
    assert_eq!(got.graphs, expected(0, 4, false).graphs);
    assert_eq!(got.estimates, expected(0, 4, false).estimates);
    drop(got);
    assert!(p.a.idle() && p.b.idle());
}
