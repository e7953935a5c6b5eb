//! Two robots' team links over real Zenoh sessions in one process (unique ports and team
//! name): discovery by liveliness, the whole rendezvous, departure.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use doorslam_ipc::wire::RobotId;
use doorslam_team::ledger::{Direction, Ledger, LedgerHandle};
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
        lease_ms: Some(2000),
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
