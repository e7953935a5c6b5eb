//! The channel's two promises beyond plain pub-sub: a sleeping receiver is woken for every
//! sample (no lost wake-up between its last look at the queue and going to sleep), and a
//! receiver that connects late on a reliable topic (a consumer restarted after a crash)
//! is handed what was sent before, in order.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use doorslam_ipc::{create_node, OdometryEdge, Receiver, Sender, StereoFrame, Topic};

fn edge(seq: u64) -> OdometryEdge {
    OdometryEdge {
        from: seq,
        to: seq + 1,
        ..OdometryEdge::default()
    }
}

/// Ping-pong: the sender waits until each sample was taken before sending the next, after
/// a pause from 0 to ~50 µs, so sends land at every point of the receiver's
/// look-drain-look-sleep sequence. A lost wake-up leaves the receiver asleep while the
/// sender waits for it: `recv_timeout` then returns `None` after 2 s and the test fails.
#[test]
fn sleeping_receiver_is_woken_for_every_sample() {
    const N: u64 = 3000;
    let robot = format!("wake{}", std::process::id());
    let (node, _) = create_node("channel-test-receiver").unwrap();
    let rx = Receiver::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
    let taken = Arc::new(AtomicU64::new(0));

    let sender = {
        let (robot, taken) = (robot.clone(), taken.clone());
        std::thread::spawn(move || {
            let (node, _) = create_node("channel-test-sender").unwrap();
            let tx = Sender::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
            let mut rng = 0x9E37_79B9_7F4A_7C15u64;
            for seq in 0..N {
                let deadline = Instant::now() + Duration::from_secs(10);
                while taken.load(Ordering::Acquire) < seq {
                    assert!(Instant::now() < deadline, "receiver stuck before {seq}");
                    std::hint::spin_loop();
                }
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                let pause = Instant::now() + Duration::from_nanos(rng % 50_000);
                while Instant::now() < pause {
                    std::hint::spin_loop();
                }
                tx.send_copy(&edge(seq)).unwrap();
            }
        })
    };

    for seq in 0..N {
        let sample = rx
            .recv_timeout(Duration::from_secs(2))
            .unwrap()
            .unwrap_or_else(|| panic!("sample {seq} sent but the receiver was not woken"));
        assert_eq!(sample.payload().from, seq, "samples in order");
        drop(sample);
        taken.store(seq + 1, Ordering::Release);
    }
    sender.join().unwrap();
    assert!(
        rx.recv_timeout(Duration::from_millis(50))
            .unwrap()
            .is_none(),
        "nothing beyond what was sent"
    );
}

/// A consumer that dies and comes back gets what was sent while it was gone (and what it
/// had already taken, which it must skip itself), in order, as soon as the producer
/// catches up receivers, even if the producer has nothing new to send.
#[test]
fn late_receiver_gets_the_reliable_history_but_no_old_frames() {
    let robot = format!("history{}", std::process::id());
    let (node, _) = create_node("channel-test-history").unwrap();
    let tx = Sender::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
    let frames_tx = Sender::<StereoFrame>::new(&node, &robot, Topic::Frames).unwrap();

    let first = Receiver::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
    for seq in 0..10 {
        tx.send_copy(&edge(seq)).unwrap();
    }
    for seq in 0..10 {
        let s = first.recv_timeout(Duration::from_secs(1)).unwrap().unwrap();
        assert_eq!(s.payload().from, seq);
    }
    drop(first);
    assert_eq!(tx.receivers(), 0);
    for seq in 10..15 {
        tx.send_copy(&edge(seq)).unwrap();
    }
    frames_tx
        .send_with(|slot| {
            StereoFrame::write(slot, Default::default(), &[], &[])?;
            Ok::<(), doorslam_ipc::FrameError>(())
        })
        .unwrap();

    let second = Receiver::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
    let frames_rx = Receiver::<StereoFrame>::new(&node, &robot, Topic::Frames).unwrap();
    assert!(
        second.try_recv().unwrap().is_none(),
        "history arrives when the producer updates its connections, not before"
    );
    tx.catch_up_receivers().unwrap();
    frames_tx.catch_up_receivers().unwrap();
    let mut got = Vec::new();
    while let Some(s) = second.recv_timeout(Duration::from_millis(500)).unwrap() {
        got.push(s.payload().from);
    }
    assert_eq!(
        got,
        (0..15).collect::<Vec<_>>(),
        "the whole history, in order"
    );
    assert!(
        frames_rx.try_recv().unwrap().is_none(),
        "frames have no history: a late consumer wants the next frame, not old ones"
    );
}
