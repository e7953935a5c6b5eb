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

/// Back-pressure of camera frames: a consumer that stops reading costs the camera nothing
/// (every send returns at once) and, when it reads again, finds the newest frames: the
/// oldest were dropped.
#[test]
fn stalled_frame_consumer_never_blocks_the_camera_and_keeps_the_newest() {
    let robot = format!("stall{}", std::process::id());
    let (node, _) = create_node("channel-test-frames").unwrap();
    let stalled = Receiver::<StereoFrame>::new(&node, &robot, Topic::Frames).unwrap();
    // The camera runs on its own thread: a send that waited for the stalled consumer would
    // wait forever (it never reads), so "never blocks" is "all 200 sends finish", checked
    // with a deadline far above any scheduling delay of a loaded machine rather than a
    // per-send time.
    let (done_tx, done_rx) = std::sync::mpsc::channel();
    let (release_tx, release_rx) = std::sync::mpsc::channel::<()>();
    let camera = {
        let robot = robot.clone();
        std::thread::spawn(move || {
            let (node, _) = create_node("channel-test-frames-camera").unwrap();
            let camera = Sender::<StereoFrame>::new(&node, &robot, Topic::Frames).unwrap();
            let image = vec![7u8; 64 * 48];
            for seq in 0..200u64 {
                let header = doorslam_ipc::FrameHeader {
                    seq,
                    width: 64,
                    height: 48,
                    ..Default::default()
                };
                camera
                    .send_with(|slot| StereoFrame::write(slot, header, &image, &image))
                    .unwrap();
            }
            done_tx.send(()).unwrap();
            // Keep the sender (and its samples) alive until the consumer has looked.
            let _ = release_rx.recv();
        })
    };
    assert!(
        done_rx.recv_timeout(Duration::from_secs(60)).is_ok(),
        "the camera's sends waited for a consumer that does not read"
    );
    let mut got = Vec::new();
    while let Some(frame) = stalled.try_recv().unwrap() {
        got.push(frame.payload().header().seq);
    }
    assert_eq!(got, [198, 199], "the two newest frames, the oldest dropped");
    release_tx.send(()).unwrap();
    camera.join().unwrap();
}

/// Back-pressure of everything else: a full consumer makes the sender wait (it fills the
/// consumer's buffer, then blocks), and once the consumer reads again every sample
/// arrives, in order: nothing is dropped. The consumer has taken one sample first: iceoryx2
/// only blocks a sender for a receiver that has connected its side (it does so at every
/// receive); before that a full queue drops, so a receiver that never reads cannot
/// deadlock its senders.
#[test]
fn reliable_sender_waits_for_a_full_consumer_and_loses_nothing() {
    const N: u64 = doorslam_ipc::RELIABLE_BUFFER as u64 + 44;
    let robot = format!("full{}", std::process::id());
    let (node, _) = create_node("channel-test-full").unwrap();
    let rx = Receiver::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
    let (sent, taken) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let sender = {
        let (robot, sent, taken) = (robot.clone(), sent.clone(), taken.clone());
        std::thread::spawn(move || {
            let (node, _) = create_node("channel-test-full-sender").unwrap();
            let tx = Sender::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
            for seq in 0..N {
                tx.send_copy(&edge(seq)).unwrap();
                sent.store(seq + 1, Ordering::Release);
                while seq == 0 && taken.load(Ordering::Acquire) == 0 {
                    std::thread::sleep(Duration::from_millis(1));
                }
            }
        })
    };
    let first = rx
        .recv_timeout(Duration::from_secs(10))
        .unwrap()
        .expect("sample 0");
    assert_eq!(first.payload().from, 0);
    drop(first);
    taken.store(1, Ordering::Release);
    // The consumer stops reading: the sender fills its buffer and must then wait.
    let full = 1 + doorslam_ipc::RELIABLE_BUFFER as u64;
    let deadline = Instant::now() + Duration::from_secs(10);
    while sent.load(Ordering::Acquire) < full {
        assert!(
            Instant::now() < deadline,
            "sender stuck before the buffer was full"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(
        sent.load(Ordering::Acquire),
        full,
        "the sender waits once the consumer's buffer is full"
    );
    for seq in 1..N {
        let s = rx.recv_timeout(Duration::from_secs(5)).unwrap();
        assert_eq!(
            s.map(|s| s.payload().from),
            Some(seq),
            "every sample, in order"
        );
    }
    sender.join().unwrap();
}

/// A consumer that connects after a long run gets the history, which fills only half of
/// its queue: what the producer sends before the consumer's first receive neither blocks
/// the producer nor is dropped.
#[test]
fn history_leaves_room_for_new_samples_before_the_first_receive() {
    use doorslam_ipc::{RELIABLE_BUFFER, RELIABLE_HISTORY};
    const BEFORE: u64 = 300;
    const AFTER: u64 = 100;
    assert!(RELIABLE_HISTORY as u64 + AFTER <= RELIABLE_BUFFER as u64);
    let robot = format!("room{}", std::process::id());
    let (node, _) = create_node("channel-test-room").unwrap();
    let stage = Arc::new(AtomicU64::new(0));
    let sender = {
        let (robot, stage) = (robot.clone(), stage.clone());
        std::thread::spawn(move || {
            let (node, _) = create_node("channel-test-room-sender").unwrap();
            let tx = Sender::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
            for seq in 0..BEFORE {
                tx.send_copy(&edge(seq)).unwrap();
            }
            stage.store(1, Ordering::Release);
            while stage.load(Ordering::Acquire) < 2 {
                std::thread::sleep(Duration::from_millis(1));
            }
            tx.catch_up_receivers().unwrap();
            for seq in BEFORE..BEFORE + AFTER {
                tx.send_copy(&edge(seq)).unwrap();
            }
            assert_eq!(tx.undelivered(), 0, "samples dropped");
            stage.store(3, Ordering::Release);
        })
    };
    let deadline = Instant::now() + Duration::from_secs(10);
    while stage.load(Ordering::Acquire) < 1 {
        assert!(Instant::now() < deadline, "sender never started");
        std::thread::sleep(Duration::from_millis(1));
    }
    let rx = Receiver::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
    stage.store(2, Ordering::Release);
    let deadline = Instant::now() + Duration::from_secs(5);
    while stage.load(Ordering::Acquire) < 3 && !sender.is_finished() {
        assert!(
            Instant::now() < deadline,
            "the producer blocked: the history filled the new consumer's queue"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    sender.join().unwrap();
    let mut got = Vec::new();
    while let Some(s) = rx.try_recv().unwrap() {
        got.push(s.payload().from);
    }
    let first = BEFORE - RELIABLE_HISTORY as u64;
    assert_eq!(got, (first..BEFORE + AFTER).collect::<Vec<_>>());
}
