//! Two Zenoh peers on loopback exchange a message (no multicast, explicit endpoints).

use std::time::{Duration, Instant};

use doorslam_team::{key_expr, open_peer, LinkConfig};
use zenoh::Wait;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

#[test]
fn two_peers_exchange_a_message_over_loopback() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let alpha = open_peer(&LinkConfig {
        listen: vec![endpoint.clone()],
        connect: vec![],
        multicast_scouting: false,
    })
    .unwrap();
    let beta = open_peer(&LinkConfig {
        listen: vec![],
        connect: vec![endpoint],
        multicast_scouting: false,
    })
    .unwrap();

    // Unique per process so parallel test runs on one machine never cross.
    let to = format!("b{}", std::process::id());
    let key = key_expr("loopback", &to, "hello", "a").unwrap();
    let sub = beta
        .declare_subscriber(format!("doorslam/loopback/{to}/**"))
        .wait()
        .unwrap();

    let payload: Vec<u8> = (0..=255u8).collect();
    let deadline = Instant::now() + Duration::from_secs(10);
    let received = loop {
        // Resend until routing between the two peers is established.
        alpha.put(&key, payload.clone()).wait().unwrap();
        if let Some(sample) = sub.recv_timeout(Duration::from_millis(100)).unwrap() {
            break sample;
        }
        assert!(
            Instant::now() < deadline,
            "no message over loopback within 10 s"
        );
    };
    assert_eq!(received.key_expr().as_str(), key);
    assert_eq!(received.payload().to_bytes().as_ref(), payload.as_slice());

    alpha.close().wait().unwrap();
    beta.close().wait().unwrap();
}

#[test]
fn bad_endpoints_and_ids_are_clear_errors() {
    let err = open_peer(&LinkConfig {
        listen: vec!["nonsense".into()],
        connect: vec![],
        multicast_scouting: false,
    })
    .unwrap_err();
    assert!(err.to_string().contains("nonsense"), "{err}");
    assert!(key_expr("t", "B/../x", "hello", "a")
        .unwrap_err()
        .to_string()
        .contains("B/../x"));
    // The wire header's id rule: at most 32 characters.
    let long = "a".repeat(33);
    assert!(key_expr("t", "b", "hello", &long).is_err());
    assert!(key_expr("t", "b", "hello", &"a".repeat(32)).is_ok());
    assert!(key_expr("t", "b", "he/llo", "a")
        .unwrap_err()
        .to_string()
        .contains("kind"));
}
