//! The rendezvous protocol between two robots over the in-process link emulation (same
//! `Link` trait as Zenoh): meetings cut mid-way and resumed, loss, misbehaving peers.

use std::collections::BTreeSet;
use std::sync::atomic::Ordering;

use doorslam_geometry::key;
use doorslam_ipc::wire::{Body, Header, Hello, Kind, Message, RobotId};
use doorslam_team::emulate::Bus;
use doorslam_team::ledger::Direction;
use doorslam_team::Link;

mod common;
use common::{robot, robot_in_epoch, run, Robot};

fn step_until(
    robots: &mut [&mut Robot],
    now: &mut u64,
    limit: usize,
    done: impl Fn(&[&mut Robot]) -> bool,
) {
    for _ in 0..limit {
        if done(robots) {
            return;
        }
        run(robots, now, 1);
    }
    assert!(done(robots), "condition not reached within {limit} steps");
}

fn delivered(r: &Robot, peer: &RobotId) -> BTreeSet<u64> {
    r.node
        .session(peer)
        .map(|s| s.delivered_descriptors().clone())
        .unwrap_or_default()
}

fn all_keys(index: u8, n: u64) -> BTreeSet<u64> {
    (0..n).map(|i| key::symbol(index, i).unwrap()).collect()
}

/// Descriptors messages `robot` published from position `from` on: (sequence, keys).
fn descriptor_sends(bus: &Bus, robot: &RobotId, from: usize) -> Vec<(u64, Vec<u64>)> {
    bus.published(robot)[from..]
        .iter()
        .filter_map(|(_, bytes)| {
            let m = Message::decode(bytes).unwrap();
            match m.body {
                Body::Descriptors(d) => Some((
                    m.header.sequence,
                    d.descriptors.iter().map(|d| d.key).collect(),
                )),
                _ => None,
            }
        })
        .collect()
}

fn everything_acknowledged(r: &Robot, peer: &RobotId) -> bool {
    r.node
        .session(peer)
        .is_some_and(|s| Kind::ALL.iter().all(|&k| s.unacknowledged(k).is_empty()))
}

#[test]
fn meeting_cut_mid_exchange_resumes_without_loss_or_resending_acknowledged_data() {
    let bus = Bus::new(0.0, 7);
    let mut a = robot(&bus, "a", 0, 300);
    let mut b = robot(&bus, "b", 1, 300);
    let (ida, idb) = (a.id.clone(), b.id.clone());
    let mut now = 0;
    bus.join(&ida, &idb);
    // Stop mid-way through the descriptors.
    step_until(&mut [&mut a, &mut b], &mut now, 2000, |r| {
        delivered(r[1], &ida).len() >= 100
    });
    bus.cut(&ida, &idb);
    let got_before = delivered(&b, &ida).len();
    assert!(got_before < 300, "the cut came too late to test anything");
    let s = a.node.session(&idb).unwrap();
    let unacked_at_cut: BTreeSet<u64> = s.unacknowledged(Kind::Descriptors).into_iter().collect();
    let sent_at_cut = bus.published(&ida).len();
    let max_seq_at_cut = descriptor_sends(&bus, &ida, 0)
        .iter()
        .map(|(s, _)| *s)
        .max()
        .unwrap();

    // Out of range for 5 s: nothing is sent to the absent peer.
    run(&mut [&mut a, &mut b], &mut now, 500);
    assert_eq!(
        bus.published(&ida).len(),
        sent_at_cut,
        "published while the peer was away"
    );

    bus.join(&ida, &idb);
    step_until(&mut [&mut a, &mut b], &mut now, 5000, |r| {
        everything_acknowledged(r[0], &idb)
            && everything_acknowledged(r[1], &ida)
            && delivered(r[1], &ida).len() == 300
    });

    // Every descriptor delivered exactly once.
    assert_eq!(delivered(&b, &ida), all_keys(0, 300));
    let sb = b.node.session(&ida).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, 300);
    assert_eq!(sb.descriptors_redelivered, 0);
    // After the resumption, old sequences resent are only those unacknowledged at the cut.
    for (seq, _) in descriptor_sends(&bus, &ida, sent_at_cut) {
        assert!(
            seq > max_seq_at_cut || unacked_at_cut.contains(&seq),
            "descriptor batch {seq} was acknowledged before the cut and sent again"
        );
    }
    let sa = a.node.session(&idb).unwrap().stats().clone();
    assert_eq!(sa.descriptors_acknowledged, 300);
    assert_eq!(sa.meetings, 2);
    // Closures: α's accepted ones reached β once; the back-ends exchanged rounds.
    assert!(sa.closures_accepted > 50, "{sa:?}");
    assert!(
        sa.closures_rejected > 0,
        "aliased places must be rejected: {sa:?}"
    );
    assert_eq!(sb.closures_received, sa.closures_accepted);
    let la = a.backend.lock().unwrap().clone();
    let lb = b.backend.lock().unwrap().clone();
    assert_eq!(la.closures["b"], sa.closures_accepted);
    assert_eq!(lb.closures["a"], sa.closures_accepted);
    assert!(lb.estimates_received["a"] > 0 && la.estimates_received["b"] > 0);

    // The ledger adds up to what each robot published, and per rendezvous.
    for r in [&a, &b] {
        let ledger = r.node.ledger().lock();
        assert_eq!(
            ledger.total(Direction::Sent).payload_bytes,
            bus.published_bytes(&r.id)
        );
        let file = ledger.to_file();
        assert_eq!(file.rendezvous.len(), 2);
        assert!(file.traffic.iter().any(|t| t.rendezvous == Some(1)));
    }
}

#[test]
fn every_descriptor_arrives_once_through_30_percent_loss() {
    let bus = Bus::new(0.3, 11);
    let mut a = robot(&bus, "a", 0, 200);
    let mut b = robot(&bus, "b", 1, 200);
    let (ida, idb) = (a.id.clone(), b.id.clone());
    let mut now = 0;
    bus.join(&ida, &idb);
    step_until(&mut [&mut a, &mut b], &mut now, 20_000, |r| {
        delivered(r[1], &ida).len() == 200 && everything_acknowledged(r[0], &idb)
    });
    let sb = b.node.session(&ida).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, 200);
    assert_eq!(sb.descriptors_redelivered, 0);
    assert!(a.node.session(&idb).unwrap().stats().retransmissions > 0);
    // Lost acknowledgments make resends that arrive twice: processed once, counted.
    assert!(b.node.ledger().lock().dropped_count("duplicate") > 0);
}

#[test]
fn a_later_meeting_sends_only_descriptors_created_since() {
    let bus = Bus::new(0.0, 3);
    let mut a = robot(&bus, "a", 0, 100);
    let mut b = robot(&bus, "b", 1, 100);
    let (ida, idb) = (a.id.clone(), b.id.clone());
    let mut now = 0;
    bus.join(&ida, &idb);
    step_until(&mut [&mut a, &mut b], &mut now, 5000, |r| {
        everything_acknowledged(r[0], &idb) && delivered(r[1], &ida).len() == 100
    });
    bus.cut(&ida, &idb);
    a.created.store(150, Ordering::Release);
    run(&mut [&mut a, &mut b], &mut now, 50);
    let mark = bus.published(&ida).len();
    bus.join(&ida, &idb);
    step_until(&mut [&mut a, &mut b], &mut now, 5000, |r| {
        everything_acknowledged(r[0], &idb) && delivered(r[1], &ida).len() == 150
    });
    let keys: BTreeSet<u64> = descriptor_sends(&bus, &ida, mark)
        .into_iter()
        .flat_map(|(_, k)| k)
        .collect();
    let new: BTreeSet<u64> = (100..150).map(|i| key::symbol(0, i).unwrap()).collect();
    assert_eq!(keys, new);
}

#[test]
fn unknown_garbage_wrong_sender_and_replayed_messages_are_dropped_and_counted() {
    let bus = Bus::new(0.0, 5);
    let mut a = robot(&bus, "a", 0, 40);
    let mut b = robot(&bus, "b", 1, 40);
    let (ida, idb) = (a.id.clone(), b.id.clone());
    let mut now = 0;
    bus.join(&ida, &idb);
    step_until(&mut [&mut a, &mut b], &mut now, 3000, |r| {
        everything_acknowledged(r[0], &idb) && delivered(r[1], &ida).len() == 40
    });
    let c = RobotId::new("c").unwrap();
    let hello = |sender: &RobotId| {
        Message::new(
            Header {
                sender: sender.clone(),
                epoch: 1,
                sequence: 0,
            },
            Hello {
                robot: 2,
                heard: None,
                base: 0,
            },
        )
        .encode()
        .unwrap()
    };
    // A robot that never declared a token.
    bus.inject(&idb, &c, "hello", hello(&c));
    // Garbage and a truncated message from a present peer.
    bus.inject(&idb, &ida, "descriptors", vec![0xff; 40]);
    let first_batch = bus
        .published(&ida)
        .into_iter()
        .find(|(_, m)| Message::decode(m).unwrap().kind() == Kind::Descriptors)
        .unwrap()
        .1;
    bus.inject(
        &idb,
        &ida,
        "descriptors",
        first_batch[..first_batch.len() - 3].to_vec(),
    );
    // A message claiming another sender than its key.
    bus.inject(&idb, &ida, "hello", hello(&c));
    // A replay of a's first descriptor batch.
    bus.inject(&idb, &ida, "descriptors", first_batch.clone());
    // A message of an epoch older than the one a is in (a replay from before a restart).
    let old = Message::new(
        Header {
            sender: ida.clone(),
            epoch: 0,
            sequence: 99,
        },
        Hello {
            robot: 0,
            heard: None,
            base: 0,
        },
    );
    bus.inject(&idb, &ida, "hello", old.encode().unwrap());
    // A message under the wrong kind in its key.
    bus.inject(&idb, &ida, "matches", first_batch);
    run(&mut [&mut a, &mut b], &mut now, 3);
    let ledger = b.node.ledger().lock();
    assert_eq!(ledger.dropped_count("unknown_peer"), 1);
    assert_eq!(ledger.dropped_count("decode_error"), 2);
    assert_eq!(ledger.dropped_count("wrong_sender"), 1);
    assert_eq!(ledger.dropped_count("wrong_kind"), 1);
    assert!(ledger.dropped_count("duplicate") >= 1);
    assert_eq!(ledger.dropped_count("stale_epoch"), 1);
    drop(ledger);
    let sb = b.node.session(&ida).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, 40);
    assert_eq!(sb.descriptors_redelivered, 0);
    // The link trait is what the robots used.
    let _: &dyn Link = &a.link;
}

/// A robot that ran in a huge epoch (a bug, a corrupted epoch file: u64::MAX) and then
/// restarted in a sane, lower one (the file repaired or lost) is refused no longer than
/// until its next appearance: the first message of a meeting sets the peer's epoch again.
/// Within a meeting an older epoch is still a stale replay.
#[test]
fn an_epoch_claim_lasts_until_the_peers_next_appearance() {
    let bus = Bus::new(0.0, 13);
    // A huge epoch (the largest one a Hello can name: the epoch file never gives u64::MAX).
    let mut a = robot_in_epoch(&bus, "a", 0, 40, u64::MAX - 1);
    let mut b = robot(&bus, "b", 1, 40);
    let (ida, idb) = (a.id.clone(), b.id.clone());
    let mut now = 0;
    bus.join(&ida, &idb);
    step_until(&mut [&mut a, &mut b], &mut now, 3000, |r| {
        everything_acknowledged(r[0], &idb) && delivered(r[1], &ida).len() == 40
    });
    // a goes away and comes back in epoch 3, having forgotten everything.
    bus.cut(&ida, &idb);
    run(&mut [&mut a, &mut b], &mut now, 20);
    let mut a = robot_in_epoch(&bus, "a", 0, 60, 3);
    bus.join(&ida, &idb);
    step_until(&mut [&mut a, &mut b], &mut now, 5000, |r| {
        everything_acknowledged(r[0], &idb)
            && everything_acknowledged(r[1], &ida)
            && delivered(r[1], &ida).len() == 60
    });
    let ledger = b.node.ledger().lock();
    assert_eq!(ledger.dropped_count("stale_epoch"), 0);
    drop(ledger);
    let sb = b.node.session(&ida).unwrap().stats().clone();
    assert_eq!(sb.meetings, 2);
    // The restarted a sent its 40 old keyframes again (it forgot sending them): b takes
    // each descriptor once.
    assert_eq!(sb.descriptors_delivered, 60);
    assert_eq!(sb.descriptors_redelivered, 40);
    // Within the meeting, the old epoch is a replay and is refused.
    let replay = Message::new(
        Header {
            sender: ida.clone(),
            epoch: 2,
            sequence: 0,
        },
        Hello {
            robot: 0,
            heard: None,
            base: 0,
        },
    );
    bus.inject(&idb, &ida, "hello", replay.encode().unwrap());
    run(&mut [&mut a, &mut b], &mut now, 3);
    assert_eq!(b.node.ledger().lock().dropped_count("stale_epoch"), 1);
}

/// The epoch file is written before the link opens, incremented at every start; one at the
/// top of the range (corrupted) is refused by name, never wrapped to 0.
#[test]
fn the_epoch_file_counts_starts_and_refuses_to_wrap() {
    use doorslam_team::runner::next_epoch;
    let dir = tempfile::tempdir().unwrap();
    assert_eq!(next_epoch(dir.path()).unwrap(), 1);
    assert_eq!(next_epoch(dir.path()).unwrap(), 2);
    let file = dir.path().join("team.epoch");
    std::fs::write(&file, format!("{}\n", u64::MAX)).unwrap();
    let err = next_epoch(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("team.epoch") && err.contains("cannot be incremented"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(&file).unwrap().trim(),
        u64::MAX.to_string()
    );
    std::fs::write(&file, "seven").unwrap();
    let err = next_epoch(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("team.epoch") && err.contains("not an epoch"),
        "{err}"
    );
}
