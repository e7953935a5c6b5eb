//! The team link with TLS and access control, over real Zenoh sessions on loopback (unique
//! ports and team names): a peer without a team certificate cannot open a link nor inject
//! anything; a team robot cannot publish as another robot, claim its token or its epoch;
//! a certificate of the team CA outside the roster can do nothing. Each test has a
//! positive control (a team robot does get through the same listener), so a broken link
//! cannot pass for a secure one.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use doorslam_ipc::wire::{Header, Hello, Kind, Message, RobotId};
use doorslam_team::certs::{generate, CertsRequest, TeamCa, Validity};
use doorslam_team::ledger::{Ledger, LedgerHandle};
use doorslam_team::link::{LinkConfig, LinkMode};
use doorslam_team::protocol::{Identity, ProtocolConfig};
use doorslam_team::security::{Holder, Security, TlsSection};
use doorslam_team::standin::{EchoBackend, SimPlaces, SimWorld, TruthVerifier};
use doorslam_team::zenoh_link::{ZenohLink, ZenohLinkConfig};
use doorslam_team::{Node, Pieces};
use zenoh::{Session, Wait};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn id(s: &str) -> RobotId {
    RobotId::new(s).unwrap()
}

/// Certificates of `team` for `robots` in `dir`; the roster is `roster`.
fn tls(dir: &Path, robot: &str, roster: &[&str]) -> TlsSection {
    let d = dir.join("robots").join(robot);
    TlsSection {
        ca: dir.join("ca.pem"),
        cert: d.join("cert.pem"),
        key: d.join("key.pem"),
        robots: roster.iter().map(|s| s.to_string()).collect(),
    }
}

fn make_certs(dir: &Path, team: &str, robots: &[&str]) {
    generate(
        dir,
        &CertsRequest {
            team: team.into(),
            robots: robots.iter().map(|s| s.to_string()).collect(),
            routers: vec![],
            days: 2,
        },
    )
    .unwrap();
}

const KEYFRAMES: u64 = 60;

fn robot(
    team: &str,
    name: &str,
    index: u8,
    listen: Vec<String>,
    connect: Vec<String>,
    security: Security,
) -> (Node, ZenohLink) {
    let world = SimWorld::default();
    let me = id(name);
    let place = SimPlaces::new(world, index, 50);
    place.created().store(KEYFRAMES, Ordering::Release);
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
            backend: Box::new(EchoBackend::new(index)),
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
    (node, link)
}

fn checked(section: &TlsSection, team: &str, robot: &str) -> Security {
    Security::check(section, team, &Holder::Robot(id(robot))).unwrap()
}

/// A malicious session: TLS with `section`'s files, its own access control switched off
/// (it does what it likes; only the receiving side's rules can stop it).
fn rogue_tls(team: &str, section: &TlsSection, connect: &str) -> Session {
    let security = Security {
        team: team.into(),
        ca: section.ca.clone(),
        cert: section.cert.clone(),
        key: section.key.clone(),
        roster: vec![],
        expires_unix_s: i64::MAX,
    };
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"peer\"").unwrap();
    config.insert_json5("listen/endpoints", "[]").unwrap();
    config
        .insert_json5("connect/endpoints", &format!("[\"{connect}\"]"))
        .unwrap();
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    security.apply(&mut config).unwrap();
    config
        .insert_json5("access_control/enabled", "false")
        .unwrap();
    zenoh::open(config).wait().unwrap()
}

/// A session with a raw Zenoh config (intruders without team certificates).
fn raw_session(settings: &[(&str, String)]) -> Session {
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"peer\"").unwrap();
    config.insert_json5("listen/endpoints", "[]").unwrap();
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    for (k, v) in settings {
        config.insert_json5(k, v).unwrap();
    }
    zenoh::open(config).wait().unwrap()
}

/// A well-formed Hello claiming to come from `sender` in a huge epoch: if it ever reached a
/// robot, that robot would take every later real message of `sender` for a stale one.
fn forged_hello(sender: &str) -> Vec<u8> {
    Message::new(
        Header {
            sender: id(sender),
            epoch: u64::MAX,
            sequence: 0,
        },
        Hello {
            robot: 0,
            heard: None,
            base: 0,
        },
    )
    .encode()
    .unwrap()
}

/// What an intruder tries: a's token, messages as a (forged epoch), and wildcard keys.
struct Injector {
    session: Session,
    _tokens: Vec<zenoh::liveliness::LivelinessToken>,
    puts: Vec<(String, Vec<u8>)>,
}

impl Injector {
    fn new(session: Session, team: &str, tokens: &[&str], puts: Vec<(String, Vec<u8>)>) -> Self {
        let tokens = tokens
            .iter()
            .map(|r| {
                session
                    .liveliness()
                    .declare_token(format!("doorslam/{team}/alive/{r}"))
                    .wait()
                    .unwrap()
            })
            .collect();
        Self {
            session,
            _tokens: tokens,
            puts,
        }
    }

    fn inject(&self) {
        for (key, bytes) in &self.puts {
            // Errors are the point for some intruders (no route): ignored.
            let _ = self.session.put(key, bytes.clone()).wait();
        }
    }

    fn links(&self) -> usize {
        self.session.info().peers_zid().wait().count()
    }
}

fn step(nodes: &mut [(&mut Node, &mut ZenohLink)], start: Instant) {
    let now = start.elapsed().as_millis() as u64;
    for (n, l) in nodes.iter_mut() {
        n.step(*l, now, Duration::from_millis(5));
    }
}

fn rendezvous_done(a: &Node, b: &Node) -> bool {
    let (ida, idb) = (id("a"), id("b"));
    let delivered = b
        .session(&ida)
        .map_or(0, |s| s.delivered_descriptors().len() as u64);
    let acked = a.session(&idb).is_some_and(|s| {
        [Kind::Descriptors, Kind::LoopClosures]
            .iter()
            .all(|&k| s.unacknowledged(k).is_empty())
    });
    delivered == KEYFRAMES && acked
}

#[test]
fn a_peer_without_the_team_certificate_cannot_connect_or_inject() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let team = format!("sx{}", std::process::id());
    make_certs(d, &team, &["a", "b"]);
    let roster = ["a", "b"];
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let (mut b, mut lb) = robot(
        &team,
        "b",
        1,
        vec![endpoint.clone()],
        vec![],
        checked(&tls(d, "b", &roster), &team, "b"),
    );
    let tcp_endpoint = endpoint.replace("tls/", "tcp/");
    let msg_key = format!("doorslam/{team}/b/hello/a");
    let puts = vec![
        (msg_key.clone(), forged_hello("a")),
        (format!("doorslam/{team}/b/hello/*"), forged_hello("a")),
    ];

    // 1. A CA of its own ("the same team name"), a certificate for "a" signed by it.
    let rogue_dir = d.join("rogue");
    make_certs(&rogue_dir, &team, &["a"]);
    let rogue = Injector::new(
        rogue_tls(&team, &tls(&rogue_dir, "a", &roster), &endpoint),
        &team,
        &["a"],
        puts.clone(),
    );
    // 2. Plain TCP to the TLS port.
    let plain = Injector::new(
        raw_session(&[("connect/endpoints", format!("[\"{tcp_endpoint}\"]"))]),
        &team,
        &["a"],
        puts.clone(),
    );
    // 3. TLS trusting the team CA (it knows b's certificate is genuine) but with no client
    //    certificate of its own.
    let ca = d.join("ca.pem");
    let anonymous = Injector::new(
        raw_session(&[
            ("connect/endpoints", format!("[\"{endpoint}\"]")),
            (
                "transport/link/tls/root_ca_certificate",
                format!("{:?}", ca.to_str().unwrap()),
            ),
            ("transport/link/tls/verify_name_on_connect", "false".into()),
        ]),
        &team,
        &["a"],
        puts.clone(),
    );
    // 4. A self-signed certificate for "a" presented as a client certificate.
    let self_signed = TeamCa::create(&team, Validity::days_from_now(2)).unwrap();
    let (cert, key) = self_signed.issue("a", Validity::days_from_now(2)).unwrap();
    let (cp, kp) = (d.join("self.pem"), d.join("self.key"));
    std::fs::write(&cp, cert).unwrap();
    std::fs::write(&kp, key).unwrap();
    let path = |p: &PathBuf| format!("{:?}", p.to_str().unwrap());
    let self_signed = Injector::new(
        raw_session(&[
            ("connect/endpoints", format!("[\"{endpoint}\"]")),
            ("transport/link/tls/root_ca_certificate", path(&ca)),
            ("transport/link/tls/connect_certificate", path(&cp)),
            ("transport/link/tls/connect_private_key", path(&kp)),
            ("transport/link/tls/enable_mtls", "true".into()),
            ("transport/link/tls/verify_name_on_connect", "false".into()),
        ]),
        &team,
        &["a"],
        puts,
    );
    let intruders = [&rogue, &plain, &anonymous, &self_signed];

    // Three seconds of trying (Zenoh retries its connections meanwhile).
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(3) {
        for i in &intruders {
            i.inject();
        }
        step(&mut [(&mut b, &mut lb)], start);
    }
    for (name, i) in [
        "rogue CA",
        "plain TCP",
        "no client certificate",
        "self-signed",
    ]
    .iter()
    .zip(intruders.iter())
    {
        assert_eq!(i.links(), 0, "{name}: opened a link to b");
    }
    assert!(b.session(&id("a")).is_none(), "b saw a token of \"a\"");
    {
        let ledger = b.ledger().lock().to_file();
        assert!(ledger.traffic.is_empty(), "{:?}", ledger.traffic);
        assert!(ledger.dropped.is_empty(), "{:?}", ledger.dropped);
    }

    // Positive control: the real a, with its team certificate, gets through the same
    // listener and completes a rendezvous, in its own epoch (not the forged one).
    let (mut a, mut la) = robot(
        &team,
        "a",
        0,
        vec![],
        vec![endpoint],
        checked(&tls(d, "a", &roster), &team, "a"),
    );
    while !rendezvous_done(&a, &b) {
        assert!(
            start.elapsed() < Duration::from_secs(40),
            "rendezvous of the team robots incomplete: a {:?}, b {:?}",
            a.session(&id("b")).map(|s| s.stats().clone()),
            b.session(&id("a")).map(|s| s.stats().clone())
        );
        for i in &intruders {
            i.inject();
        }
        step(&mut [(&mut a, &mut la), (&mut b, &mut lb)], start);
    }
    let sb = b.session(&id("a")).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, KEYFRAMES);
    assert_eq!(sb.descriptors_redelivered, 0);
    let ledger = b.ledger().lock();
    // Not "unknown_peer": a's first message may overtake a's liveliness token (Zenoh orders
    // neither against the other); b drops it and a resends. The intruders never reach b at
    // all: they get no link (below).
    for reason in ["stale_epoch", "wrong_sender", "bad_key"] {
        assert_eq!(ledger.dropped_count(reason), 0, "{reason}");
    }
    drop(ledger);
    for i in &intruders {
        assert_eq!(i.links(), 0, "an intruder got a link while a was in");
    }
    la.close().unwrap();
    lb.close().unwrap();
}

#[test]
fn a_team_robot_cannot_publish_as_another_and_an_unlisted_certificate_can_do_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let team = format!("sy{}", std::process::id());
    // z's certificate is signed by the team CA but z is not in the roster.
    make_certs(d, &team, &["a", "b", "c", "z"]);
    let roster = ["a", "b", "c"];
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let (mut b, mut lb) = robot(
        &team,
        "b",
        1,
        vec![endpoint.clone()],
        vec![],
        checked(&tls(d, "b", &roster), &team, "b"),
    );
    let (mut a, mut la) = robot(
        &team,
        "a",
        0,
        vec![],
        vec![endpoint.clone()],
        checked(&tls(d, "a", &roster), &team, "a"),
    );
    // c, a team robot, impersonates a: a's token, a Hello with a's id and a huge epoch under
    // a's key, the same under a wildcard; and one garbage message under its own key (the
    // positive control: c's link to b works, so only the access control stops the rest).
    let c = Injector::new(
        rogue_tls(&team, &tls(d, "c", &roster), &endpoint),
        &team,
        &["a", "c"],
        vec![
            (format!("doorslam/{team}/b/hello/a"), forged_hello("a")),
            (
                format!("doorslam/{team}/b/descriptors/a"),
                forged_hello("a"),
            ),
            (format!("doorslam/{team}/b/hello/*"), forged_hello("a")),
            (format!("doorslam/{team}/b/hello/c"), vec![0xff; 8]),
        ],
    );
    let z = Injector::new(
        rogue_tls(&team, &tls(d, "z", &roster), &endpoint),
        &team,
        &["z", "a"],
        vec![
            (format!("doorslam/{team}/b/hello/z"), vec![0xff; 8]),
            (format!("doorslam/{team}/b/hello/a"), forged_hello("a")),
        ],
    );
    let start = Instant::now();
    let c_through = |b: &Node| {
        b.ledger()
            .lock()
            .to_file()
            .dropped
            .iter()
            .any(|e| e.peer == "c" && e.reason == "decode_error")
    };
    while !(rendezvous_done(&a, &b) && c_through(&b)) {
        assert!(
            start.elapsed() < Duration::from_secs(40),
            "incomplete after 40 s: rendezvous {}, c's own message through {}, b's sessions {:?}",
            rendezvous_done(&a, &b),
            c_through(&b),
            b.sessions()
                .map(|s| s.peer().to_string())
                .collect::<Vec<_>>()
        );
        c.inject();
        z.inject();
        step(&mut [(&mut a, &mut la), (&mut b, &mut lb)], start);
    }
    // A little longer with the impostors at it.
    let settle = Instant::now();
    while settle.elapsed() < Duration::from_secs(1) {
        c.inject();
        z.inject();
        step(&mut [(&mut a, &mut la), (&mut b, &mut lb)], start);
    }
    // z holds a certificate of the team CA: its link opens, but nothing it sends counts.
    assert!(
        z.links() > 0,
        "z (team CA, not in the roster) could not even connect"
    );
    assert!(c.links() > 0);
    let peers: Vec<String> = b.sessions().map(|s| s.peer().to_string()).collect();
    assert_eq!(peers, ["a", "c"], "b's peers (z's token must not count)");
    let sb = b.session(&id("a")).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, KEYFRAMES);
    assert_eq!(sb.descriptors_redelivered, 0);
    assert_eq!(sb.meetings, 1, "c's copy of a's token made a come and go");
    let ledger = b.ledger().lock().to_file();
    for e in &ledger.dropped {
        // The forged epoch would show as stale_epoch (a's real messages refused), a forged
        // header as wrong_sender, the wildcard as bad_key; z's as unknown_peer.
        assert!(
            e.peer == "c" && e.reason == "decode_error",
            "dropped at b: {e:?} (only c's own garbage should have reached b)"
        );
    }
    assert!(
        ledger
            .traffic
            .iter()
            .all(|t| t.peer == "a" || t.peer == "c"),
        "{:?}",
        ledger.traffic
    );
    la.close().unwrap();
    lb.close().unwrap();
}
