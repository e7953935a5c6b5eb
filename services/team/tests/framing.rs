//! Zenoh's framing per message, measured: two Zenoh peers joined through a TCP relay that
//! counts the bytes it forwards; the bytes beyond the payloads, per message, are what the
//! ledger adds to each message's payload for its on-the-wire estimate.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use doorslam_team::ledger::ZENOH_FRAMING_BYTES;
use doorslam_team::{key_expr, open_peer, LinkConfig};
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

#[test]
fn zenoh_framing_per_message_is_what_the_ledger_adds() {
    let p1 = free_port();
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let p2 = listener.local_addr().unwrap().port();
    let publisher_side = open_peer(&LinkConfig {
        listen: vec![format!("tcp/127.0.0.1:{p1}")],
        connect: vec![],
        multicast_scouting: false,
    })
    .unwrap();
    let counter = relay(listener, p1);
    let subscriber_side = open_peer(&LinkConfig {
        listen: vec![],
        connect: vec![format!("tcp/127.0.0.1:{p2}")],
        multicast_scouting: false,
    })
    .unwrap();
    let team = format!("fr{}", std::process::id());
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
            "no route through the relay in 10 s"
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
        "zenoh framing per message: declared publisher {small:.2} B (135 B payload), {large:.2} B (4000 B payload); session.put with the key string {undeclared:.2} B (key {} chars)",
        key.len()
    );
    assert!(
        (small - large).abs() < 1.5,
        "framing depends on payload size beyond a varint: {small} vs {large}"
    );
    assert!(
        (small - ZENOH_FRAMING_BYTES as f64).abs() <= 2.0,
        "ledger::ZENOH_FRAMING_BYTES = {ZENOH_FRAMING_BYTES}, measured {small:.2}: update it"
    );
    publisher_side.close().wait().unwrap();
    subscriber_side.close().wait().unwrap();
}
