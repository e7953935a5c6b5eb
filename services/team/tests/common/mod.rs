//! Robots on the in-process link emulation, shared by the protocol tests (`protocol.rs`,
//! `hostile.rs`), and the hostile teammate's forgeries ([`hostile`], also used over real
//! Zenoh by `hostile_zenoh.rs`), and plain Zenoh link configs ([`zenoh_config`]: `zenoh_team.rs`,
//! `presence_bytes.rs`). Each test binary uses a part of it, hence the `dead_code`
//! allowance.
#![allow(dead_code)]

pub mod hostile;
pub mod tls;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use doorslam_ipc::wire::RobotId;
use doorslam_team::emulate::{Bus, EmulatedLink};
use doorslam_team::ledger::{Ledger, LedgerHandle};
use doorslam_team::link::LinkMode;
use doorslam_team::protocol::{Identity, ProtocolConfig};
use doorslam_team::standin::{BackendLog, EchoBackend, SimPlaces, SimWorld, TruthVerifier};
use doorslam_team::zenoh_link::ZenohLinkConfig;
use doorslam_team::{LinkConfig, Node, Pieces};

/// A test robot's Zenoh link: a peer on plain TCP, no multicast scouting (concurrent test
/// runs never find each other), the given endpoints and lease.
pub fn zenoh_config(
    team: &str,
    id: &str,
    listen: Vec<String>,
    connect: Vec<String>,
    lease_ms: Option<u64>,
) -> ZenohLinkConfig {
    ZenohLinkConfig {
        team: team.into(),
        me: RobotId::new(id).unwrap(),
        link: LinkConfig {
            listen,
            connect,
            multicast_scouting: false,
        },
        mode: LinkMode::Peer,
        lease_ms,
        security: None,
    }
}

pub struct Robot {
    pub id: RobotId,
    pub node: Node,
    pub link: EmulatedLink,
    pub created: Arc<AtomicU64>,
    pub backend: Arc<Mutex<BackendLog>>,
}

pub fn config() -> ProtocolConfig {
    ProtocolConfig {
        retransmit_ms: 200,
        descriptor_batch: 16,
        batch_linger_ms: 100,
        window: 4,
        receive_window: 64,
        features_cache: 512,
        ..ProtocolConfig::default()
    }
}

pub fn robot(bus: &Bus, id: &str, index: u8, keyframes: u64) -> Robot {
    robot_in_epoch(bus, id, index, keyframes, 1)
}

pub fn robot_in_epoch(bus: &Bus, id: &str, index: u8, keyframes: u64, epoch: u64) -> Robot {
    let world = SimWorld::default();
    let id = RobotId::new(id).unwrap();
    let place = SimPlaces::new(world, index, 20);
    let created = place.created();
    created.store(keyframes, Ordering::Release);
    let backend = EchoBackend::new(index);
    let log = backend.log.clone();
    let me = Identity {
        id: id.clone(),
        robot: index,
        epoch,
    };
    let ledger = LedgerHandle::new(Ledger::new(id.as_str(), "test", epoch, 752 * 480));
    let node = Node::new(
        me,
        config(),
        ledger,
        Pieces {
            place: Box::new(place),
            verifier: Box::new(TruthVerifier::from_world(world)),
            backend: Box::new(backend),
        },
    );
    Robot {
        link: bus.link(&id),
        id,
        node,
        created,
        backend: log,
    }
}

/// Steps both robots `steps` times, 10 ms of local time each, from `*now`.
pub fn run(robots: &mut [&mut Robot], now: &mut u64, steps: usize) {
    for _ in 0..steps {
        for r in robots.iter_mut() {
            r.node.step(&mut r.link, *now, Duration::ZERO);
        }
        *now += 10;
    }
}
