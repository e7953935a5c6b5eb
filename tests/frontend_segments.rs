//! Lost → re-initialized → one connected graph in the back-end: the front-end service's
//! state machine runs on a rendered flight with blank frames and, later, a second of
//! dropped frames; what it would publish goes, as the same shared-memory types, into the
//! back-end's state machine, which must optimize one connected graph (the segment links
//! join the segments). Without the links the same graph is refused as disconnected, so the
//! test would catch links that are missing or wrong.

use doorslam_backend::journal::Entry;
use doorslam_backend::service::BackendState;
use doorslam_frontend::service::{fill_keyframe, ipc_edge, Calibration, FrontendState, Step};
use doorslam_frontend::{TrackState, VoConfig};
use doorslam_geometry::SE3;
use doorslam_hil::flights::one_robot_flight;
use doorslam_hil::render_stereo;
use doorslam_ipc::FrameHeader;

const FRAMES: usize = 60;
const RATE_HZ: f64 = 10.0;
/// Frames replaced by black images (a covered lens), and frames never delivered.
const BLANK: std::ops::Range<usize> = 15..20;
const DROPPED: std::ops::Range<usize> = 35..46;

struct Run {
    steps: Vec<Step>,
    truth: Vec<SE3>,
}

fn run_frontend() -> Run {
    let (world, team) = one_robot_flight(3, FRAMES, RATE_HZ).expect("plan a flight");
    let camera = team.camera;
    let truth = team.flights[0].poses.clone();
    let calibration = Calibration {
        stereo: camera.stereo_calibration(),
        width: camera.width(),
        height: camera.height(),
    };
    let mut state = FrontendState::new(calibration, VoConfig::default(), 0, None).unwrap();
    let black = vec![0u8; (camera.width() * camera.height()) as usize];
    let mut steps = Vec::new();
    for (k, pose) in truth.iter().enumerate() {
        if DROPPED.contains(&k) {
            continue;
        }
        let pair = render_stereo(&world, &camera, pose);
        let (l, r) = match BLANK.contains(&k) {
            true => (black.as_slice(), black.as_slice()),
            false => (pair.left.pixels(), pair.right.pixels()),
        };
        let header = FrameHeader {
            seq: k as u64,
            stamp_ns: (k as f64 / RATE_HZ * 1e9).round() as u64,
            width: camera.width(),
            height: camera.height(),
            ..FrameHeader::default()
        };
        steps.push(state.on_frame(&header, l, r).unwrap());
    }
    Run { steps, truth }
}

/// Feeds what the front-end published to a back-end, optimizing when due and at the end;
/// returns it and the result of the last optimization.
fn backend(steps: &[Step], with_links: bool) -> (BackendState, Result<(), String>) {
    let mut backend = BackendState::new(0, 2).unwrap();
    let mut journal: Vec<Entry> = Vec::new();
    let mut last = Ok(());
    for step in steps {
        if let Some(kf) = &step.keyframe {
            let mut slot = Box::new(std::mem::MaybeUninit::<doorslam_ipc::Keyframe>::uninit());
            fill_keyframe(doorslam_ipc::Keyframe::zeroed_in(&mut slot), 0, kf);
            // SAFETY: zeroed_in initialized the value and fill_keyframe wrote its fields.
            let sample = unsafe { slot.assume_init() };
            backend.on_keyframe(&sample, &mut journal).unwrap();
        }
        // A step's links come first among its edges.
        for e in step
            .edges
            .iter()
            .skip(if with_links { 0 } else { step.links })
        {
            backend
                .on_odometry(&ipc_edge(0, 0, e), &mut journal)
                .unwrap();
        }
        if backend.optimization_due() {
            last = backend.optimize().map(|_| ()).map_err(|e| e.to_string());
        }
    }
    last = backend
        .optimize()
        .map(|_| ())
        .map_err(|e| e.to_string())
        .and(last);
    (backend, last)
}

#[test]
fn blank_and_dropped_frames_start_segments_that_the_backend_keeps_in_one_graph() {
    let Run { steps, truth } = run_frontend();
    let lost = |range: std::ops::Range<usize>| {
        steps
            .iter()
            .filter(|s| range.contains(&(s.seq as usize)))
            .all(|s| s.state == TrackState::Lost)
    };
    assert!(lost(BLANK), "blank frames have no pose");
    let new_segments: Vec<u64> = steps
        .iter()
        .filter(|s| s.new_segment)
        .map(|s| s.seq)
        .collect();
    assert_eq!(
        new_segments,
        vec![0, BLANK.end as u64, DROPPED.end as u64],
        "re-initialized after the blank frames and after the gap"
    );
    let links: usize = steps.iter().map(|s| s.links).sum();
    assert_eq!(links, 2, "one link per new segment after the first");

    // Without the links: two of the segments float free, and the back-end says so.
    let (_, without) = backend(&steps, false);
    let err = without.expect_err("segments without links are disconnected");
    assert!(err.contains("not connected"), "{err}");

    // With them: one connected graph, every optimization succeeds.
    let (backend, result) = backend(&steps, true);
    result.expect("one connected graph");
    let report = backend.report();
    assert_eq!(report.failed_optimizations, 0, "{report:?}");
    assert!(report.optimizations >= 3, "{report:?}");
    let keyframes = steps.iter().filter(|s| s.keyframe.is_some()).count();
    assert_eq!(report.accepted_keyframes, keyframes);
    assert_eq!(report.gaps, 0);
    assert_eq!(backend.pending(), 0, "every edge found its keyframes");

    // The back-end's trajectory against the truth (both relative to the first pose): the
    // segment links only guess the motion over the time lost (constant velocity), so the
    // bound is looser than the odometry's drift, but it must be the same trajectory.
    let frame_of: std::collections::HashMap<u64, usize> = steps
        .iter()
        .filter_map(|s| s.keyframe.as_ref().map(|k| (k.id, k.frame as usize)))
        .collect();
    let estimate: Vec<(u64, SE3)> = backend.trajectory().map(|(id, _, p)| (id, *p)).collect();
    let (id0, first) = estimate[0];
    let t0 = truth[frame_of[&id0]];
    let mut worst: f64 = 0.0;
    for (id, pose) in &estimate {
        let est = first.inverse() * pose;
        let gt = t0.inverse() * truth[frame_of[id]];
        worst = worst.max((est.translation.vector - gt.translation.vector).norm());
    }
    let distance: f64 = truth
        .windows(2)
        .map(|w| (w[1].translation.vector - w[0].translation.vector).norm())
        .sum();
    eprintln!(
        "{keyframes} keyframes, 3 segments over {distance:.1} m: worst keyframe position error {worst:.2} m"
    );
    assert!(worst < 2.0, "worst keyframe position error {worst:.2} m");
}
