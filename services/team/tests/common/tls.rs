//! Robots on real Zenoh sessions with the team's mutual TLS and access control, on
//! loopback: the team's certificates, a robot's `[team.tls]`, a robot's node and link.
//! Shared by the security tests (`security.rs`) and the hostile flood over TLS
//! (`hostile_zenoh.rs`).

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use doorslam_ipc::wire::RobotId;
use doorslam_team::certs::{generate, CertsRequest};
use doorslam_team::ledger::{Ledger, LedgerHandle};
use doorslam_team::link::{LinkConfig, LinkMode};
use doorslam_team::protocol::{Identity, ProtocolConfig};
use doorslam_team::security::{Holder, Security, TlsSection};
use doorslam_team::standin::{BackendLog, EchoBackend, SimPlaces, SimWorld, TruthVerifier};
use doorslam_team::zenoh_link::{ZenohLink, ZenohLinkConfig};
use doorslam_team::{Node, Pieces};

/// A TCP port nobody listens on now (the OS's pick), for a test's own endpoints.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// `robot`'s `[team.tls]` with the certificates in `dir`; the roster is `roster`.
pub fn tls(dir: &Path, robot: &str, roster: &[&str]) -> TlsSection {
    let d = dir.join("robots").join(robot);
    TlsSection {
        ca: dir.join("ca.pem"),
        cert: d.join("cert.pem"),
        key: d.join("key.pem"),
        robots: roster.iter().map(|s| s.to_string()).collect(),
    }
}

/// A team CA of `team` and certificates for `robots` in `dir`, valid for two days.
pub fn make_certs(dir: &Path, team: &str, robots: &[&str]) {
    make_certs_with(dir, team, robots, false);
}

/// As [`make_certs`]; `clockless`: valid from 1970 to 9999 (`team certs --clockless`).
pub fn make_certs_with(dir: &Path, team: &str, robots: &[&str], clockless: bool) {
    generate(
        dir,
        &CertsRequest {
            team: team.into(),
            robots: robots.iter().map(|s| s.to_string()).collect(),
            routers: vec![],
            days: 2,
            clockless,
        },
    )
    .unwrap();
}

/// `section` checked for `robot` of `team`, as a robot's start-up checks it.
pub fn checked(section: &TlsSection, team: &str, robot: &str) -> Security {
    Security::check(section, team, &Holder::Robot(RobotId::new(robot).unwrap())).unwrap()
}

/// A robot on a real Zenoh session: the stand-in places (`keyframes` of them made so
/// far: store more into `created` to fly on), the truth verifier, the echo back-end.
pub struct ZenohRobot {
    pub node: Node,
    pub link: ZenohLink,
    pub created: Arc<AtomicU64>,
    pub backend: Arc<Mutex<BackendLog>>,
}

pub fn zenoh_robot(
    team: &str,
    name: &str,
    index: u8,
    keyframes: u64,
    listen: Vec<String>,
    connect: Vec<String>,
    security: Security,
) -> ZenohRobot {
    let world = SimWorld::default();
    let me = RobotId::new(name).unwrap();
    let place = SimPlaces::new(world, index, 50);
    let created = place.created();
    created.store(keyframes, Ordering::Release);
    let backend = EchoBackend::new(index);
    let log = backend.log.clone();
    let node = Node::new(
        Identity {
            id: me.clone(),
            robot: index,
            epoch: 1,
        },
        ProtocolConfig {
            retransmit_ms: 300,
            ..ProtocolConfig::default()
        },
        LedgerHandle::new(Ledger::new(name, team, 1, 752 * 480).over_tls()),
        Pieces {
            place: Box::new(place),
            verifier: Box::new(TruthVerifier::from_world(world)),
            backend: Box::new(backend),
        },
    );
    let link = ZenohLink::open(&ZenohLinkConfig {
        team: team.into(),
        me,
        link: LinkConfig {
            listen,
            connect,
            multicast_scouting: false,
        },
        mode: LinkMode::Peer,
        lease_ms: Some(2000),
        security: Some(security),
    })
    .unwrap();
    ZenohRobot {
        node,
        link,
        created,
        backend: log,
    }
}
