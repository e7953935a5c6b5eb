//! A stereo frame published by one process is received, intact, by another process.
//!
//! The test re-executes its own binary as the publisher (selected by an environment
//! variable), so the two ends share nothing but the iceoryx2 shared memory.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use doorslam_ipc::{create_node, open_frames, FrameHeader, StereoFrame};

const CHILD_ENV: &str = "DOORSLAM_IPC_TEST_PUBLISH_AS";
const W: u32 = 752;
const H: u32 = 480;
const FRAMES: u64 = 5;

fn pattern(seq: u64, side: u8) -> Vec<u8> {
    (0..(W * H) as usize)
        .map(|i| {
            ((i % W as usize) as u64 + (i / W as usize) as u64 * 3 + seq * 7 + side as u64) as u8
        })
        .collect()
}

/// Child side: publish FRAMES frames, then stay alive until the parent closes stdin
/// (so the samples outlive the reads).
fn publish(robot: &str) {
    let (node, _) = create_node("ipc-test-publisher").expect("node");
    let service = open_frames(&node, robot).expect("service");
    let publisher = service.publisher_builder().create().expect("publisher");
    for seq in 0..FRAMES {
        let mut sample = publisher.loan_uninit().expect("loan");
        let header = FrameHeader {
            seq,
            stamp_ns: 1_000_000 * seq,
            robot: 1,
            camera: 0,
            width: W,
            height: H,
            ..Default::default()
        };
        StereoFrame::write(
            sample.payload_mut(),
            header,
            &pattern(seq, 0),
            &pattern(seq, 1),
        )
        .expect("write");
        // SAFETY: `StereoFrame::write` initialized the sample.
        unsafe { sample.assume_init() }.send().expect("send");
        std::thread::sleep(Duration::from_millis(30));
    }
    let mut buf = Vec::new();
    let _ = std::io::stdin().read_to_end(&mut buf);
}

#[test]
fn stereo_frame_crosses_process_boundary() {
    if let Ok(robot) = std::env::var(CHILD_ENV) {
        publish(&robot);
        return;
    }
    let robot = format!("ipctest{}", std::process::id());
    let (node, _) = create_node("ipc-test-subscriber").expect("node");
    let service = open_frames(&node, &robot).expect("service");
    let subscriber = service.subscriber_builder().create().expect("subscriber");

    let mut child = Command::new(std::env::current_exe().unwrap())
        .args([
            "stereo_frame_crosses_process_boundary",
            "--exact",
            "--nocapture",
        ])
        .env(CHILD_ENV, &robot)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn publisher process");
    assert_ne!(child.id(), std::process::id());

    let deadline = Instant::now() + Duration::from_secs(20);
    let mut seen = Vec::new();
    while seen.len() < FRAMES as usize && Instant::now() < deadline {
        match subscriber.receive().expect("receive") {
            Some(sample) => {
                let frame = sample.payload();
                let h = *frame.header();
                assert_eq!((h.width, h.height, h.robot), (W, H, 1));
                assert_eq!(h.stamp_ns, 1_000_000 * h.seq);
                assert!(
                    frame.left_image().unwrap() == pattern(h.seq, 0).as_slice(),
                    "left image of frame {} corrupted",
                    h.seq
                );
                assert!(
                    frame.right_image().unwrap() == pattern(h.seq, 1).as_slice(),
                    "right image of frame {} corrupted",
                    h.seq
                );
                seen.push(h.seq);
            }
            None => std::thread::sleep(Duration::from_millis(2)),
        }
    }
    drop(child.stdin.take());
    let out = child.wait_with_output().expect("wait publisher");
    assert!(
        out.status.success(),
        "publisher process failed: {}\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // The subscriber buffer holds 2 frames and frames may be dropped oldest-first, but
    // with a reader this fast all 5 arrive, in order.
    assert_eq!(seen, (0..FRAMES).collect::<Vec<_>>(), "frames received");
}

#[test]
fn oversized_or_mismatched_frames_are_rejected() {
    let mut slot = Box::<StereoFrame>::new_uninit();
    let big = FrameHeader {
        width: 4000,
        height: 10,
        ..Default::default()
    };
    assert!(StereoFrame::write(&mut slot, big, &[], &[])
        .unwrap_err()
        .to_string()
        .contains("exceeds"));
    let hdr = FrameHeader {
        width: 4,
        height: 2,
        ..Default::default()
    };
    let err = StereoFrame::write(&mut slot, hdr, &[0; 8], &[0; 7]).unwrap_err();
    assert!(err.to_string().contains("right image has 7 bytes"), "{err}");
    StereoFrame::write(&mut slot, hdr, &[1; 8], &[2; 8]).unwrap();
    // SAFETY: written just above.
    let frame = unsafe { slot.assume_init() };
    assert_eq!(frame.left_image().unwrap(), &[1; 8]);
    assert_eq!(frame.right_image().unwrap(), &[2; 8]);
}
