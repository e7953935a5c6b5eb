//! Two robots' team links over real Zenoh sessions in one process (unique ports and team
//! name): discovery by liveliness, the whole rendezvous, departure.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use doorslam_ipc::wire::RobotId;
use doorslam_team::ledger::{Direction, Ledger, LedgerHandle};
use doorslam_team::link::LinkMode;
use doorslam_team::protocol::{Identity, ProtocolConfig};
use doorslam_team::standin::{EchoBackend, SimPlaces, SimWorld, TruthVerifier};
use doorslam_team::zenoh_link::{ZenohLink, ZenohLinkConfig};
use doorslam_team::{LinkConfig, Node, Pieces};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn robot(
    team: &str,
    id: &str,
    index: u8,
    listen: Vec<String>,
    connect: Vec<String>,
) -> (Node, ZenohLink) {
    let world = SimWorld::default();
    let id = RobotId::new(id).unwrap();
    let place = SimPlaces::new(world, index, 50);
    place.created().store(60, Ordering::Release);
    let node = Node::new(
        Identity {
            id: id.clone(),
            robot: index,
            epoch: 1,
        },
        ProtocolConfig {
            retransmit_ms: 300,
            ..ProtocolConfig::default()
        },
        LedgerHandle::new(Ledger::new(id.as_str(), team, 1, 752 * 480)),
        Pieces {
            place: Box::new(place),
            verifier: Box::new(TruthVerifier::from_world(world)),
            backend: Box::new(EchoBackend::new(index)),
        },
    );
    let link = ZenohLink::open(&ZenohLinkConfig {
        team: team.into(),
        me: id,
        link: LinkConfig {
            listen,
            connect,
            multicast_scouting: false,
        },
        mode: LinkMode::Peer,
        lease_ms: Some(2000),
        security: None,
    })
    .unwrap();
    (node, link)
}

#[test]
fn two_zenoh_peers_discover_each_other_and_complete_a_rendezvous() {
    let team = format!("zt{}", std::process::id());
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let (mut a, mut la) = robot(&team, "a", 0, vec![endpoint.clone()], vec![]);
    let (mut b, mut lb) = robot(&team, "b", 1, vec![], vec![endpoint]);
    let ida = RobotId::new("a").unwrap();
    let idb = RobotId::new("b").unwrap();
    let start = Instant::now();
    let now = || start.elapsed().as_millis() as u64;
    let done = |a: &Node, b: &Node| {
        let delivered = b
            .session(&ida)
            .map_or(0, |s| s.delivered_descriptors().len());
        let acked = a.session(&idb).is_some_and(|s| {
            s.unacknowledged(doorslam_ipc::wire::Kind::Descriptors)
                .is_empty()
                && s.unacknowledged(doorslam_ipc::wire::Kind::LoopClosures)
                    .is_empty()
        });
        delivered == 60 && acked && a.session(&idb).unwrap().stats().closures_accepted > 0
    };
    while !done(&a, &b) {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "rendezvous incomplete after 30 s: a {:?}, b {:?}",
            a.session(&idb).map(|s| s.stats().clone()),
            b.session(&ida).map(|s| s.stats().clone())
        );
        a.step(&mut la, now(), Duration::from_millis(5));
        b.step(&mut lb, now(), Duration::from_millis(5));
    }
    let sa = a.session(&idb).unwrap().stats().clone();
    let sb = b.session(&ida).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, 60);
    assert_eq!(sb.descriptors_redelivered, 0);
    // The ledgers count exactly what the links handed to Zenoh.
    assert_eq!(
        a.ledger().lock().total(Direction::Sent).payload_bytes,
        la.published_bytes()
    );
    assert_eq!(
        b.ledger().lock().total(Direction::Sent).payload_bytes,
        lb.published_bytes()
    );
    assert!(sa.closures_accepted > 0);

    // b leaves: its token goes with its session, a sees the departure.
    lb.close().unwrap();
    drop(b);
    let left = Instant::now();
    while a.session(&idb).unwrap().is_connected() {
        assert!(
            left.elapsed() < Duration::from_secs(10),
            "departure not seen in 10 s"
        );
        a.step(&mut la, now(), Duration::from_millis(20));
    }
    la.close().unwrap();
}

/// The clean-link rate target, on loopback (one process, two sessions): 1,000
/// descriptor messages per second for 5 s, paced, through `ZenohLink`; none may be lost.
#[test]
fn a_thousand_descriptor_messages_per_second_arrive_without_loss() {
    use doorslam_ipc::wire::{Descriptor, Descriptors, Header, Kind, Message};
    use doorslam_team::{Link, LinkEvent};
    let team = format!("zr{}", std::process::id());
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let open = |id: &str, listen: Vec<String>, connect: Vec<String>| {
        ZenohLink::open(&ZenohLinkConfig {
            team: team.clone(),
            me: RobotId::new(id).unwrap(),
            link: LinkConfig {
                listen,
                connect,
                multicast_scouting: false,
            },
            mode: LinkMode::Peer,
            lease_ms: None,
            security: None,
        })
        .unwrap()
    };
    let mut la = open("a", vec![endpoint.clone()], vec![]);
    let mut lb = open("b", vec![], vec![endpoint]);
    let idb = RobotId::new("b").unwrap();
    // Wait until each sees the other's token (routes are up).
    let start = Instant::now();
    while !la
        .poll_events(Duration::from_millis(20))
        .iter()
        .any(|e| matches!(e, LinkEvent::PeerAppeared(p) if *p == idb))
    {
        assert!(start.elapsed() < Duration::from_secs(10), "no discovery");
    }
    std::thread::sleep(Duration::from_millis(300));
    let _ = lb.poll_events(Duration::ZERO);
    let n = 5000u64;
    let world = SimWorld::default();
    let values = world.descriptor(0, 0);
    let messages: Vec<Vec<u8>> = (0..n)
        .map(|i| {
            let key = doorslam_geometry::key::symbol(0, i).unwrap();
            Message::new(
                Header {
                    sender: RobotId::new("a").unwrap(),
                    epoch: 1,
                    sequence: i,
                },
                Descriptors {
                    robot: 0,
                    keyframes: i..i + 1,
                    descriptors: vec![Descriptor::quantize(key, &values).unwrap()],
                },
            )
            .encode()
            .unwrap()
        })
        .collect();
    let mut received = std::collections::BTreeSet::new();
    let t0 = Instant::now();
    for (i, m) in messages.iter().enumerate() {
        // Paced at 1 ms per message.
        let due = t0 + Duration::from_micros(1000 * i as u64);
        while Instant::now() < due {
            for e in lb.poll_events(Duration::ZERO) {
                if let LinkEvent::Message { bytes, .. } = e {
                    received.insert(Message::decode(&bytes).unwrap().header.sequence);
                }
            }
            std::thread::yield_now();
        }
        la.publish(&idb, Kind::Descriptors, m).unwrap();
    }
    let sent_s = t0.elapsed().as_secs_f64();
    let deadline = Instant::now() + Duration::from_secs(10);
    while (received.len() as u64) < n && Instant::now() < deadline {
        for e in lb.poll_events(Duration::from_millis(20)) {
            if let LinkEvent::Message { bytes, .. } = e {
                received.insert(Message::decode(&bytes).unwrap().header.sequence);
            }
        }
    }
    eprintln!(
        "{n} descriptor messages of {} B sent in {sent_s:.2} s ({:.0}/s), {} received",
        messages[0].len(),
        n as f64 / sent_s,
        received.len()
    );
    assert!(n as f64 / sent_s >= 950.0, "could not send at 1000/s");
    assert_eq!(received.len() as u64, n, "messages lost on a clean link");
    la.close().unwrap();
    lb.close().unwrap();
}
