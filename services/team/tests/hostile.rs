//! A hostile teammate: robot z holds a place in the team (its certificate is in the roster,
//! so the access control lets it publish as itself) and turns against it. After an honest
//! first meeting it floods robots a and b with a million messages built from its own
//! real traffic: garbage, truncated and bit-flipped messages, replays, stale epochs,
//! sequence jumps, messages claiming another sender or another kind, loop closures with
//! NaN and absurd poses, and descriptor floods. Meanwhile a and b have their own meeting.
//!
//! What must hold (issue #33): no panic; a and b complete their exchange; every message
//! of z is accounted for in the ledgers (delivered or dropped by reason, never silently
//! lost); nothing non-finite reaches a back-end; the process's memory stays flat while a
//! million messages go by.

use std::sync::atomic::Ordering;

use doorslam_ipc::wire::{Kind, Message, RobotId};
use doorslam_team::emulate::Bus;

const HOSTILE_MESSAGES: u64 = 1_000_000;
/// Messages z injects between two steps of the honest robots.
const BURST: u64 = 2_000;
const KEYFRAMES: u64 = 40;

mod common;
use common::hostile::{assert_attacker_accounted, closures_with_pose_value, met, rss_kb, Forger};
use common::{config, robot, run, Robot};

/// Loop closures with z each robot handed to its back-end.
fn closures_of_z(robots: &[&Robot]) -> Vec<u64> {
    robots
        .iter()
        .map(|r| {
            r.backend
                .lock()
                .unwrap()
                .closures
                .get("z")
                .copied()
                .unwrap_or(0)
        })
        .collect()
}

#[test]
fn a_hostile_teammate_cannot_crash_stall_or_flood_the_team() {
    let bus = Bus::new(0.0, 11);
    let mut a = robot(&bus, "a", 0, 0);
    let mut b = robot(&bus, "b", 1, 0);
    let mut z = robot(&bus, "z", 2, 0);
    let (ida, idb, idz) = (a.id.clone(), b.id.clone(), z.id.clone());
    let mut now = 0;

    // 1. z meets a and b honestly (its real traffic is what it will forge from).
    for r in [&a, &b, &z] {
        r.created.store(KEYFRAMES / 2, Ordering::Release);
    }
    bus.join(&ida, &idz);
    bus.join(&idb, &idz);
    for _ in 0..3000 {
        if met(&z.node, &a.node, KEYFRAMES / 2) && met(&z.node, &b.node, KEYFRAMES / 2) {
            break;
        }
        run(&mut [&mut a, &mut b, &mut z], &mut now, 1);
    }
    assert!(
        met(&z.node, &a.node, KEYFRAMES / 2) && met(&z.node, &b.node, KEYFRAMES / 2),
        "z's honest meetings: with a {:?}, with b {:?}",
        z.node.session(&ida).map(|s| s.stats().clone()),
        z.node.session(&idb).map(|s| s.stats().clone())
    );
    run(&mut [&mut a, &mut b, &mut z], &mut now, 50);
    let honest: Vec<(RobotId, Message)> = bus
        .published(&idz)
        .into_iter()
        .filter_map(|(to, bytes)| Some((to, Message::decode(&bytes).ok()?)))
        .collect();
    let sent_to = |r: &RobotId| honest.iter().filter(|(to, _)| to == r).count() as u64;
    let honest_to_a = sent_to(&ida);
    let honest_to_b = sent_to(&idb);
    // Well-formed descriptor messages for the flood: the ones z received in its meetings
    // (it plays β to both), sent again under its own name.
    let received_by_z = |kind: Kind| -> Vec<Message> {
        [&ida, &idb]
            .iter()
            .flat_map(|r| bus.published(r))
            .filter_map(|(to, bytes)| (to == idz).then(|| Message::decode(&bytes).ok()).flatten())
            .filter(|m| m.kind() == kind)
            .map(|mut m| {
                m.header.sender = idz.clone();
                m
            })
            .collect()
    };
    let descriptors = received_by_z(Kind::Descriptors);
    // Closures for the NaN and absurd poses: the ones a and b verified with z.
    let closures = received_by_z(Kind::LoopClosures);
    // A NaN pose never decodes, whatever else the message gets right.
    if let Some(c) = closures.first() {
        let nan = closures_with_pose_value(c, f32::NAN).expect("the pose's bytes are found");
        assert!(Message::decode(&nan).is_err(), "a NaN closure pose decoded");
    }
    let closures_before = closures_of_z(&[&a, &b]);

    // 2. z turns hostile (its node stops; its token stays), a and b fly on: new keyframes,
    //    a meeting of their own, under the attack.
    a.created.store(KEYFRAMES, Ordering::Release);
    b.created.store(KEYFRAMES, Ordering::Release);
    bus.join(&ida, &idb);
    let mut forger = Forger::new(
        0x05ee_d0fa_77ac,
        honest.iter().map(|(_, m)| m.clone()).collect(),
        descriptors,
        closures,
        ida.clone(),
    );
    let mut injected = [0u64; 2];
    let rss_start = rss_kb();
    let mut rss_after_warmup = 0;
    let mut sent = 0u64;
    while sent < HOSTILE_MESSAGES {
        for _ in 0..BURST {
            let forgery = forger.next();
            let to = if forger.rng.below(2) == 0 { &ida } else { &idb };
            injected[usize::from(to == &idb)] += 1;
            bus.inject(to, &idz, forgery.kind, forgery.bytes);
            sent += 1;
        }
        run(&mut [&mut a, &mut b], &mut now, 1);
        if sent == 100_000 {
            rss_after_warmup = rss_kb();
        }
    }
    // The honest meeting finishes (it may need steps after the attack's last burst, but
    // not the attack's end: it ran all along).
    let steps_during_attack = (HOSTILE_MESSAGES / BURST) as usize;
    for _ in 0..3000 {
        if met(&a.node, &b.node, KEYFRAMES) {
            break;
        }
        run(&mut [&mut a, &mut b], &mut now, 1);
    }
    let rss_end = rss_kb();
    println!(
        "hostile: {sent} messages ({:?}; {} bit flips claim a newer epoch), {steps_during_attack} steps under attack; \
         RSS {rss_start} kB at the start, {rss_after_warmup} kB after 100k, {rss_end} kB at the end",
        forger.by_what, forger.epoch_claims
    );
    assert!(
        met(&a.node, &b.node, KEYFRAMES),
        "a and b did not complete their meeting under the attack: a {:?}, b {:?}",
        a.node.session(&idb).map(|s| s.stats().clone()),
        b.node.session(&ida).map(|s| s.stats().clone())
    );
    for (r, honest_to, injected) in [
        (&a, honest_to_a, injected[0]),
        (&b, honest_to_b, injected[1]),
    ] {
        let ledger = r.node.ledger().lock().to_file();
        assert_attacker_accounted(r.id.as_str(), &ledger, honest_to, injected);
        // The honest exchange with a and b was not refused for z's sake.
        let d = &ledger.dropped;
        let honest_peer = if r.id == ida { "b" } else { "a" };
        assert!(
            d.iter()
                .filter(|d| d.peer == honest_peer && d.reason != "duplicate")
                .all(|d| d.messages == 0),
            "{}: honest messages dropped: {d:?}",
            r.id
        );
        // Bounded state: the peer's verification packets stay within the cache.
        let s = r.node.session(&idz).unwrap().stats().clone();
        assert!(
            s.features_held as usize <= config().features_cache,
            "{}: {} packets of z held",
            r.id,
            s.features_held
        );
    }
    // Nothing forged got through to a back-end (a new, well-formed closure of z would, and
    // the back-end's PCM judges it: the rendezvous tests).
    let closures_after = closures_of_z(&[&a, &b]);
    println!("closures of z handed to the back-ends: before {closures_before:?}, after {closures_after:?}");
    // Every forged closure was undecodable (NaN), stale, or a copy of a sequence already
    // delivered (absurd values under an old sequence number): none is new to a back-end.
    assert_eq!(
        closures_after, closures_before,
        "forged closures reached a back-end"
    );
    // Memory: flat after warm-up (the attack carried ~1 GB of payload through the robots).
    assert!(
        rss_end < rss_after_warmup + 32 * 1024,
        "memory grew from {rss_after_warmup} kB to {rss_end} kB under the attack"
    );
}
