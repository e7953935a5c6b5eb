//! The team link's delivery contract against zenoh-ext's over two real Zenoh sessions and
//! a relay that cuts the link (`doorslam team delivery-bench`): the acknowledgements
//! deliver every message once and in order through a cut longer than Zenoh's lease;
//! zenoh-ext recovers from its publisher's cache, so what was published beyond the cache
//! while the robots were apart is gone. Unique keys per run; bounded time (~30 s).

use std::time::Duration;

use doorslam_hil::delivery_bench::{run, BenchOptions, Layer};

/// 80 messages at 20 Hz; the link cut from 1 s to 4 s (the lease is 2 s: the sessions
/// close and reconnect), so ~60 messages are published while the robots are apart.
fn options(cache: usize) -> BenchOptions {
    BenchOptions {
        messages: 80,
        rate_hz: 20.0,
        cut_at: Duration::from_secs(1),
        cut_for: Duration::from_secs(3),
        cache,
        settle: Duration::from_secs(8),
        ..BenchOptions::default()
    }
}

#[test]
fn acknowledgements_deliver_everything_once_in_order_through_a_cut() {
    let r = run(Layer::Acks, &options(128)).unwrap();
    println!("{r:?}");
    assert_eq!(r.delivered, r.messages, "{r:?}");
    assert_eq!(r.duplicates, 0, "{r:?}");
    assert_eq!(r.out_of_order, 0, "{r:?}");
    assert!(
        r.resends > 0,
        "messages published in the cut are resent: {r:?}"
    );
    // Every byte of the payload crossed the relay, plus framing and acknowledgements.
    assert!(r.bytes_a_to_b > r.payload_bytes, "{r:?}");
    assert!(r.bytes_b_to_a > 0, "{r:?}");
    assert!(r.recovered_after_s.is_some(), "{r:?}");
}

#[test]
fn zenoh_ext_loses_what_its_cache_no_longer_holds() {
    // Ten samples cached, ~60 published in the cut: most cannot be recovered.
    let r = run(Layer::ZenohExt, &options(10)).unwrap();
    println!("{r:?}");
    assert!(r.delivered < r.messages - 30, "{r:?}");
    assert!(
        r.delivered >= 20,
        "what was sent before the cut arrives: {r:?}"
    );
    assert_eq!(r.duplicates, 0, "{r:?}");
    assert!(r.bytes_a_to_b > 0 && r.bytes_b_to_a > 0, "{r:?}");
}
