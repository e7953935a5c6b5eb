//! What the presence checks cost on the wire: nothing for peers already met (Zenoh 1.10
//! answers a liveliness query from the session's own routing tables). Two links on
//! loopback in one process, the TCP bytes of every established loopback connection from
//! `ss` (iproute2, installed by `deploy/setup`), 5 s without checks, with 20 checks a
//! second per link, and without checks but ten 100-byte messages (which the count must
//! see, or it measures nothing). Alone in its test binary: no other test's sockets.

use std::time::{Duration, Instant};

use doorslam_ipc::wire::{Kind, RobotId};
use doorslam_team::presence::PresenceRules;
use doorslam_team::zenoh_link::ZenohLink;
use doorslam_team::Link;

mod common;
use common::zenoh_config;

/// Bytes sent by every established TCP connection on 127.0.0.1 (both ends count).
fn loopback_bytes_sent() -> u64 {
    let out = std::process::Command::new("ss")
        .args(["-tinH", "state", "established"])
        .output()
        .expect("ss (iproute2) runs");
    let text = String::from_utf8_lossy(&out.stdout);
    let lines: Vec<&str> = text.lines().collect();
    lines
        .windows(2)
        .filter(|w| w[0].contains("127.0.0.1:"))
        .filter_map(|w| {
            w[1].split_whitespace()
                .find_map(|t| t.strip_prefix("bytes_sent:"))
                .and_then(|v| v.parse::<u64>().ok())
        })
        .sum()
}

/// Bytes on the wire in 5 s between two fresh links checking every `every_ms`, sending
/// `messages` 100-byte messages b→a.
fn bytes_in_5_s(every_ms: u64, messages: usize) -> u64 {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let team = format!("pb{port}");
    let config = |id: &str, listen: Vec<String>, connect: Vec<String>| {
        zenoh_config(&team, id, listen, connect, None)
    };
    let rules = PresenceRules {
        check_every_ms: every_ms,
        ..PresenceRules::default()
    };
    let mut a = ZenohLink::open_with(&config("a", vec![endpoint.clone()], vec![]), rules).unwrap();
    let mut b = ZenohLink::open_with(&config("b", vec![], vec![endpoint]), rules).unwrap();
    let idb = RobotId::new("b").unwrap();
    let ida = RobotId::new("a").unwrap();
    // Met: each holds the other's token (and the routes) before the count starts.
    let start = Instant::now();
    let mut met = false;
    while !met || start.elapsed() < Duration::from_secs(2) {
        assert!(start.elapsed() < Duration::from_secs(10), "no discovery");
        met |= a
            .poll_events(Duration::from_millis(10))
            .iter()
            .any(|e| matches!(e, doorslam_team::LinkEvent::PeerAppeared(p) if *p == idb));
        b.poll_events(Duration::from_millis(10));
    }
    let before = loopback_bytes_sent();
    let t = Instant::now();
    let mut sent = 0;
    while t.elapsed() < Duration::from_secs(5) {
        if sent < messages {
            b.publish(&ida, Kind::Hello, &[0u8; 100]).unwrap();
            sent += 1;
        }
        a.poll_events(Duration::from_millis(10));
        b.poll_events(Duration::from_millis(10));
    }
    let after = loopback_bytes_sent();
    a.close().unwrap();
    b.close().unwrap();
    after.saturating_sub(before)
}

#[test]
fn presence_checks_of_peers_met_cost_no_bytes_on_the_wire() {
    let never = u64::MAX / 4;
    let quiet = bytes_in_5_s(never, 0);
    let checking = bytes_in_5_s(50, 0);
    let talking = bytes_in_5_s(never, 10);
    println!("5 s on loopback: quiet {quiet} B, 100 checks per link {checking} B, ten 100-B messages {talking} B");
    assert!(
        talking >= quiet + 1_000,
        "the count does not see ten 100-B messages: quiet {quiet} B, talking {talking} B"
    );
    assert!(
        checking <= quiet + 64,
        "presence checks cost bytes: quiet {quiet} B, checking {checking} B"
    );
}
