//! Zenoh's framing per message, measured: two Zenoh peers joined through a TCP relay that
//! counts the bytes it forwards; the bytes beyond the payloads, per message, are what the
//! ledger adds to each message's payload for its on-the-wire estimate. Over plain TCP and
//! over TLS (the team link with `[team.tls]`), and what a TLS link costs to open.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use std::path::Path;

use doorslam_ipc::wire::RobotId;
use doorslam_team::certs::{generate, CertsRequest};
use doorslam_team::ledger::{TLS_RECORD_BYTES, ZENOH_FRAMING_BYTES};
use doorslam_team::link::open_team_session;
use doorslam_team::security::{Holder, Security, TlsSection};
use doorslam_team::{key_expr, LinkConfig};
use zenoh::Wait;

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn pump(mut from: TcpStream, mut to: TcpStream, count: Arc<AtomicU64>) {
    let mut buf = [0u8; 65536];
    while let Ok(n) = from.read(&mut buf) {
        if n == 0 || to.write_all(&buf[..n]).is_err() {
            break;
        }
        count.fetch_add(n as u64, Ordering::Relaxed);
    }
}

/// Relays one connection from `listen` to `upstream`; returns the counter of bytes going
/// from upstream (the publisher) to the connecting side (the subscriber).
fn relay(listen: TcpListener, upstream: u16) -> Arc<AtomicU64> {
    let down = Arc::new(AtomicU64::new(0));
    let d = down.clone();
    std::thread::spawn(move || {
        let (client, _) = listen.accept().unwrap();
        let server = TcpStream::connect(("127.0.0.1", upstream)).unwrap();
        client.set_nodelay(true).unwrap();
        server.set_nodelay(true).unwrap();
        let (c2, s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
        std::thread::spawn(move || pump(c2, s2, Arc::new(AtomicU64::new(0))));
        pump(server, client, d);
    });
    down
}

/// Team certificates for robots a and b in `dir`: their checked TLS settings.
fn team_security(dir: &Path, team: &str) -> (Security, Security) {
    generate(
        dir,
        &CertsRequest {
            team: team.into(),
            robots: vec!["a".into(), "b".into()],
            routers: vec![],
            days: 2,
            clockless: false,
        },
    )
    .unwrap();
    let section = |r: &str| TlsSection {
        ca: dir.join("ca.pem"),
        cert: dir.join("robots").join(r).join("cert.pem"),
        key: dir.join("robots").join(r).join("key.pem"),
        robots: vec!["a".into(), "b".into()],
    };
    let check = |r: &str| {
        Security::check(&section(r), team, &Holder::Robot(RobotId::new(r).unwrap())).unwrap()
    };
    (check("a"), check("b"))
}

fn session(
    listen: Vec<String>,
    connect: Vec<String>,
    security: Option<&Security>,
) -> zenoh::Session {
    open_team_session(
        "peer",
        &LinkConfig {
            listen,
            connect,
            multicast_scouting: false,
        },
        None,
        security,
    )
    .unwrap()
}

/// Framing per message (declared publisher, 135 B and 4000 B payloads; `session.put`),
/// over TCP or TLS.
fn framing(tls: bool) -> (f64, f64, f64) {
    let dir = tempfile::tempdir().unwrap();
    let team = format!("fr{}{}", std::process::id(), if tls { "s" } else { "p" });
    let (sa, sb) = team_security(dir.path(), &team);
    let (sa, sb) = if tls {
        (Some(sa), Some(sb))
    } else {
        (None, None)
    };
    let scheme = if tls { "tls" } else { "tcp" };
    let p1 = free_port();
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let p2 = listener.local_addr().unwrap().port();
    let publisher_side = session(
        vec![format!("{scheme}/127.0.0.1:{p1}")],
        vec![],
        sa.as_ref(),
    );
    let counter = relay(listener, p1);
    let subscriber_side = session(
        vec![],
        vec![format!("{scheme}/127.0.0.1:{p2}")],
        sb.as_ref(),
    );
    let key = key_expr(&team, "b", "descriptors", "a").unwrap();
    let sub = subscriber_side.declare_subscriber(&key).wait().unwrap();
    let publisher = publisher_side
        .declare_publisher(key.clone())
        .wait()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        publisher.put(vec![0u8; 8]).wait().unwrap();
        if sub
            .recv_timeout(Duration::from_millis(50))
            .unwrap()
            .is_some()
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no route through the relay in 10 s ({scheme})"
        );
    }
    std::thread::sleep(Duration::from_millis(300));
    while sub.try_recv().unwrap().is_some() {}

    let measure = |size: usize, declared: bool| -> f64 {
        let n = 50;
        let before = counter.load(Ordering::Relaxed);
        for i in 0..n {
            let payload = vec![i as u8; size];
            if declared {
                publisher.put(payload).wait().unwrap();
            } else {
                publisher_side.put(&key, payload).wait().unwrap();
            }
            // Spaced: each message alone in its batch (the worst case).
            std::thread::sleep(Duration::from_millis(15));
        }
        for _ in 0..n {
            sub.recv_timeout(Duration::from_secs(5))
                .unwrap()
                .expect("message lost");
        }
        std::thread::sleep(Duration::from_millis(100));
        let bytes = counter.load(Ordering::Relaxed) - before;
        bytes as f64 / n as f64 - size as f64
    };
    let small = measure(135, true);
    let large = measure(4000, true);
    let undeclared = measure(135, false);
    eprintln!(
        "zenoh framing per message over {scheme}: declared publisher {small:.2} B (135 B payload), {large:.2} B (4000 B payload); session.put with the key string {undeclared:.2} B (key {} chars)",
        key.len()
    );
    publisher_side.close().wait().unwrap();
    subscriber_side.close().wait().unwrap();
    (small, large, undeclared)
}

#[test]
fn zenoh_framing_per_message_is_what_the_ledger_adds() {
    let (small, large, _) = framing(false);
    assert!(
        (small - large).abs() < 1.5,
        "framing depends on payload size beyond a varint: {small} vs {large}"
    );
    assert!(
        (small - ZENOH_FRAMING_BYTES as f64).abs() <= 2.0,
        "ledger::ZENOH_FRAMING_BYTES = {ZENOH_FRAMING_BYTES}, measured {small:.2}: update it"
    );
}

/// The same over TLS 1.3 with mutual authentication: one record per batch on top.
#[test]
fn tls_adds_one_record_per_message_to_the_framing() {
    let (small, large, _) = framing(true);
    let expected = (ZENOH_FRAMING_BYTES + TLS_RECORD_BYTES) as f64;
    assert!(
        (small - large).abs() < 1.5,
        "TLS framing depends on payload size: {small} vs {large}"
    );
    assert!(
        (small - expected).abs() <= 2.0,
        "ZENOH_FRAMING_BYTES + TLS_RECORD_BYTES = {expected}, measured {small:.2} over TLS: update ledger::TLS_RECORD_BYTES"
    );
}

/// Relays every connection to `upstream`, counting the bytes of both directions.
fn counting_relay(listen: TcpListener, upstream: u16) -> Arc<AtomicU64> {
    let both = Arc::new(AtomicU64::new(0));
    let b = both.clone();
    std::thread::spawn(move || {
        for client in listen.incoming() {
            let Ok(client) = client else { return };
            let Ok(server) = TcpStream::connect(("127.0.0.1", upstream)) else {
                return;
            };
            let (c2, s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
            let (b1, b2) = (b.clone(), b.clone());
            std::thread::spawn(move || pump(c2, s2, b1));
            std::thread::spawn(move || pump(server, client, b2));
        }
    });
    both
}

/// Time and bytes from opening a session that connects to a listening robot until the
/// link is up (the other side is among its peers), plain TCP against TLS with mutual
/// authentication; twenty connections each, on loopback through a counting relay.
#[test]
fn tls_handshake_time_and_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let team = format!("hs{}", std::process::id());
    let (sa, sb) = team_security(dir.path(), &team);
    for tls in [false, true] {
        let scheme = if tls { "tls" } else { "tcp" };
        let p1 = free_port();
        let listening = session(
            vec![format!("{scheme}/127.0.0.1:{p1}")],
            vec![],
            tls.then_some(&sa),
        );
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let p2 = listener.local_addr().unwrap().port();
        let bytes = counting_relay(listener, p1);
        let mut times = Vec::new();
        let mut sizes = Vec::new();
        for _ in 0..20 {
            let before = bytes.load(Ordering::Relaxed);
            let t0 = Instant::now();
            let s = session(
                vec![],
                vec![format!("{scheme}/127.0.0.1:{p2}")],
                tls.then_some(&sb),
            );
            while s.info().peers_zid().wait().count() == 0 {
                assert!(
                    t0.elapsed() < Duration::from_secs(5),
                    "{scheme}: no link in 5 s"
                );
                std::thread::sleep(Duration::from_micros(200));
            }
            times.push(t0.elapsed().as_secs_f64() * 1000.0);
            std::thread::sleep(Duration::from_millis(100));
            sizes.push(bytes.load(Ordering::Relaxed) - before);
            s.close().wait().unwrap();
            std::thread::sleep(Duration::from_millis(100));
        }
        times.sort_by(f64::total_cmp);
        sizes.sort();
        eprintln!(
            "session open to link up over {scheme}: median {:.1} ms (min {:.1}, max {:.1}; all {times:.1?}); bytes both ways by then and 100 ms after: median {} B",
            times[10], times[0], times[19], sizes[10]
        );
        listening.close().wait().unwrap();
    }
}
