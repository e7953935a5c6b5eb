//! The front-end service's state machine, without iceoryx2: frames checked against the
//! calibration, keyframe ids and poses continuing across restarts (of the camera and of
//! the process), segment links published as edges, the keyframe written in place, the
//! resume and status files, and the `[frontend]` section of robot.toml.

use std::sync::OnceLock;

use doorslam_dataset::StereoCalibration;
use doorslam_frontend::keyframe::OdometryEdge;
use doorslam_frontend::service::{
    fill_keyframe, ipc_edge, Calibration, CalibrationSource, Files, FrontendSection, FrontendState,
    Refusal, Restart, Resume, Step,
};
use doorslam_frontend::{TrackState, VoConfig};
use doorslam_geometry::{LieGroup, SE3};
use doorslam_hil::flights::one_robot_flight;
use doorslam_hil::render_stereo;
use doorslam_ipc::FrameHeader;

const FRAMES: usize = 40;
const RATE_HZ: f64 = 10.0;

struct Flight {
    width: u32,
    height: u32,
    left: Vec<Vec<u8>>,
    right: Vec<Vec<u8>>,
    calib: StereoCalibration,
}

fn flight() -> &'static Flight {
    static FLIGHT: OnceLock<Flight> = OnceLock::new();
    FLIGHT.get_or_init(|| {
        let (world, team) = one_robot_flight(3, FRAMES, RATE_HZ).expect("plan a flight");
        let camera = team.camera;
        let (mut left, mut right) = (Vec::new(), Vec::new());
        for pose in &team.flights[0].poses {
            let pair = render_stereo(&world, &camera, pose);
            left.push(pair.left.pixels().to_vec());
            right.push(pair.right.pixels().to_vec());
        }
        Flight {
            width: camera.width(),
            height: camera.height(),
            left,
            right,
            calib: camera.stereo_calibration(),
        }
    })
}

fn calibration() -> Calibration {
    let f = flight();
    Calibration {
        stereo: f.calib,
        width: f.width,
        height: f.height,
    }
}

fn header(seq: u64, k: usize) -> FrameHeader {
    let f = flight();
    FrameHeader {
        seq,
        stamp_ns: (k as f64 / RATE_HZ * 1e9).round() as u64,
        robot: 2,
        camera: 0,
        width: f.width,
        height: f.height,
        ..FrameHeader::default()
    }
}

fn state(resume: Option<Resume>) -> FrontendState {
    FrontendState::new(calibration(), VoConfig::default(), 2, resume).unwrap()
}

/// Feeds flight frames `frames` (as sequence numbers `seq0..`), black where `blank(k)`.
fn feed(
    state: &mut FrontendState,
    seq0: u64,
    frames: impl Iterator<Item = usize>,
    blank: &dyn Fn(usize) -> bool,
) -> Vec<Step> {
    let f = flight();
    let black = vec![0u8; (f.width * f.height) as usize];
    frames
        .enumerate()
        .map(|(n, k)| {
            let (l, r) = match blank(k) {
                true => (&black, &black),
                false => (&f.left[k], &f.right[k]),
            };
            state.on_frame(&header(seq0 + n as u64, k), l, r).unwrap()
        })
        .collect()
}

/// Whether the edges join every keyframe into one connected graph.
fn connected(ids: &[u64], edges: &[(u64, u64)]) -> bool {
    let mut component: std::collections::BTreeMap<u64, u64> = ids.iter().map(|&i| (i, i)).collect();
    fn root(c: &std::collections::BTreeMap<u64, u64>, mut i: u64) -> u64 {
        while c[&i] != i {
            i = c[&i];
        }
        i
    }
    for &(a, b) in edges {
        let (ra, rb) = (root(&component, a), root(&component, b));
        component.insert(ra, rb);
    }
    let roots: std::collections::BTreeSet<u64> = ids.iter().map(|&i| root(&component, i)).collect();
    roots.len() == 1
}

#[test]
fn blank_frames_lose_the_track_and_the_new_segment_is_linked_by_an_edge() {
    let mut s = state(None);
    let steps = feed(&mut s, 0, 0..FRAMES, &|k| (15..20).contains(&k));
    assert_eq!(steps[15].state, TrackState::Lost);
    assert!(steps[15].lost.is_some());
    assert!(steps[20].new_segment);
    let ids: Vec<u64> = steps
        .iter()
        .filter_map(|s| s.keyframe.as_ref().map(|k| k.id))
        .collect();
    assert_eq!(
        ids,
        (0..ids.len() as u64).collect::<Vec<_>>(),
        "consecutive ids"
    );
    let edges: Vec<(u64, u64)> = steps
        .iter()
        .flat_map(|s| s.edges.iter().map(|e| (e.from, e.to)))
        .collect();
    let first_of_new = steps[20].keyframe.as_ref().unwrap();
    assert_eq!(first_of_new.segment, 1);
    assert_eq!(steps[20].links, 1);
    assert_eq!(steps[20].edges[0].to, first_of_new.id);
    assert!(connected(&ids, &edges), "one graph: {ids:?} {edges:?}");
    let snap = s.snapshot();
    assert_eq!(
        (snap.lost, snap.lost_frames, snap.segments, snap.links),
        (1, 5, 2, 1)
    );
    assert_eq!(snap.keyframes as usize, ids.len());
    assert_eq!(snap.edges as usize, edges.len());
    assert_eq!(snap.state, "tracking");
    assert!(snap.last_lost_reason.unwrap().contains("unusable image"));
    assert!(snap.cpu_ms_per_frame_median > 0.0 && snap.timing_frames == FRAMES);
}

#[test]
fn frames_of_another_size_or_robot_are_refused_and_counted() {
    let mut s = state(None);
    let f = flight();
    let mut h = header(0, 0);
    h.width -= 2;
    let n = (h.width * h.height) as usize;
    let err = s
        .on_frame(&h, &f.left[0][..n], &f.right[0][..n])
        .unwrap_err();
    assert!(matches!(err, Refusal::Size { .. }), "{err}");
    assert!(
        err.to_string().contains("750x480") && err.to_string().contains("752x480"),
        "{err}"
    );
    let mut h = header(1, 0);
    h.robot = 5;
    let err = s.on_frame(&h, &f.left[0], &f.right[0]).unwrap_err();
    assert!(err.to_string().contains("robot 5"), "{err}");
    let h = header(2, 0);
    let err = s.on_frame(&h, &f.left[0], &f.right[0][1..]).unwrap_err();
    assert!(err.to_string().contains("right image"), "{err}");
    let snap = s.snapshot();
    assert_eq!(
        (snap.refused_frames, snap.frames, snap.state),
        (3, 0, "waiting")
    );
    // Refusals change nothing: the next good frame starts the odometry as the first would.
    let steps = feed(&mut s, 3, 0..3, &|_| false);
    assert_eq!(steps[0].keyframe.as_ref().unwrap().id, 0);
    assert_eq!(steps[0].dropped, 0);
}

#[test]
fn a_restarted_process_continues_ids_and_links_its_first_keyframe() {
    let before = SE3::translation(5.0, -1.0, 2.0);
    let resume = Resume {
        keyframe: 41,
        stamp_ns: 0,
        pose: before,
        edge: None,
    };
    let mut s = state(Some(resume));
    let steps = feed(&mut s, 0, 0..10, &|_| false);
    let kf = steps[0].keyframe.as_ref().unwrap();
    // 42 may have reached the back-end from the process that died: never reused.
    assert_eq!(kf.id, 43);
    // The new odometry starts where the last keyframe was.
    assert!((kf.pose.inverse() * before).log().norm() < 1e-12);
    assert_eq!(steps[0].links, 1);
    let link = steps[0].edges[0];
    assert_eq!((link.from, link.to), (41, 43));
    // Weak: σ 2 m per second lost, at least one second.
    assert!((link.information[(3, 3)] - 0.25).abs() < 1e-12);
    // Later keyframes continue from there, and later edges carry the robot's ids.
    let later: Vec<_> = steps.iter().flat_map(|s| s.edges.iter()).skip(1).collect();
    assert!(
        later.iter().all(|e| e.from >= 43 && e.to == e.from + 1),
        "{later:?}"
    );
    assert_eq!(
        s.resume().unwrap().keyframe,
        43 + s.snapshot().keyframes - 1
    );
}

#[test]
fn a_camera_restart_starts_a_new_odometry_linked_to_the_last_keyframe() {
    let mut s = state(None);
    let first = feed(&mut s, 0, 0..12, &|_| false);
    let last = s.resume().unwrap();
    // The replay starts over: sequence numbers and stamps go back.
    let second = feed(&mut s, 0, 0..6, &|_| false);
    assert_eq!(
        second[0].restart,
        Some(Restart::CameraRestarted {
            seq: 0,
            last_seq: 11
        })
    );
    let kf = second[0].keyframe.as_ref().unwrap();
    assert_eq!(kf.id, last.keyframe + 1);
    assert_eq!(second[0].edges[0].from, last.keyframe);
    let mut ids: Vec<u64> = first
        .iter()
        .chain(&second)
        .filter_map(|s| s.keyframe.as_ref().map(|k| k.id))
        .collect();
    let edges: Vec<(u64, u64)> = first
        .iter()
        .chain(&second)
        .flat_map(|s| s.edges.iter().map(|e| (e.from, e.to)))
        .collect();
    assert!(connected(&ids, &edges));
    ids.dedup();
    assert_eq!(ids, (0..ids.len() as u64).collect::<Vec<_>>());
    let snap = s.snapshot();
    assert_eq!(
        (snap.camera_restarts, snap.segments, snap.frames),
        (1, 2, 18)
    );
}

#[test]
fn keyframes_are_written_in_place_with_every_feature() {
    let mut s = state(None);
    let steps = feed(&mut s, 0, 0..1, &|_| false);
    let kf = steps[0].keyframe.as_ref().unwrap();
    assert!(kf.features.len() > 100);
    // A loaned sample holds garbage from its last use.
    let mut slot = Box::new(std::mem::MaybeUninit::<doorslam_ipc::Keyframe>::uninit());
    // SAFETY: writing bytes into the MaybeUninit's own storage.
    unsafe { std::ptr::write_bytes(slot.as_mut_ptr(), 0xA5, 1) };
    let out = doorslam_ipc::Keyframe::zeroed_in(&mut slot);
    fill_keyframe(out, 2, kf);
    assert_eq!((out.robot, out.id, out.frame_seq), (2, 0, 0));
    assert_eq!(
        out.source,
        doorslam_ipc::KeyframeSource::VisualOdometry as u32
    );
    assert_eq!(out.n_features as usize, kf.features.len());
    for (a, b) in out.features.iter().zip(&kf.features) {
        assert_eq!(
            (a.uv, a.point, a.descriptor),
            (b.pixel, b.point, b.descriptor)
        );
    }
    assert!(out.features[kf.features.len()..]
        .iter()
        .all(|f| *f == doorslam_ipc::Feature::default()));
    assert_eq!(out.pose, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
}

#[test]
fn edges_keep_their_information_on_the_channel() {
    let mut s = state(None);
    let steps = feed(&mut s, 0, 0..FRAMES, &|_| false);
    let e = steps
        .iter()
        .flat_map(|s| s.edges.iter())
        .next()
        .expect("an edge");
    let out = ipc_edge(2, 7, e);
    let info = doorslam_geometry::information::matrix_from_upper(&out.information);
    assert!((info - e.information).norm() <= 1e-9 * e.information.norm());
    assert_eq!(
        (out.robot, out.from, out.to, out.stamp_ns),
        (2, e.from, e.to, 7)
    );
}

#[test]
fn the_resume_file_round_trips_and_a_bad_one_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let files = Files::in_dir(&tmp.path().join("robot"));
    assert_eq!(files.read_resume().unwrap(), None);
    let r = Resume {
        keyframe: 17,
        stamp_ns: 123,
        pose: SE3::translation(1.0, 2.0, 3.0),
        edge: None,
    };
    files.write_resume(&r).unwrap();
    let back = files.read_resume().unwrap().unwrap();
    assert_eq!((back.keyframe, back.stamp_ns), (17, 123));
    assert!((back.pose.inverse() * r.pose).log().norm() < 1e-12);
    std::fs::write(&files.resume, "{\"keyframe\": 3}").unwrap();
    let err = files.read_resume().unwrap_err().to_string();
    assert!(
        err.contains("frontend.resume") && err.contains("stamp_ns"),
        "{err}"
    );
}

#[test]
fn the_resume_state_keeps_the_edge_into_the_last_keyframe_for_a_restart() {
    let resume = Resume {
        keyframe: 41,
        stamp_ns: 0,
        pose: SE3::translation(5.0, -1.0, 2.0),
        edge: None,
    };
    let mut s = state(Some(resume));
    let mut keyframes = 0;
    for k in 0..FRAMES {
        let step = feed(&mut s, k as u64, k..k + 1, &|_| false).remove(0);
        let Some(kf) = &step.keyframe else { continue };
        keyframes += 1;
        let r = s.resume().unwrap();
        assert_eq!(r.keyframe, kf.id);
        // The edge into it as published: the restart link (from 41) for the first
        // keyframe of this process, its odometry for the next ones.
        let edge = r.edge.expect("the edge into the last keyframe");
        assert_eq!(edge.to, kf.id);
        assert!(
            step.edges.contains(&edge),
            "{edge:?} not in {:?}",
            step.edges
        );
        if keyframes == 1 {
            assert_eq!(edge.from, 41);
        } else {
            assert!(edge.from > 41 && edge.from < kf.id, "{edge:?}");
        }
    }
    assert!(keyframes >= 2, "the flight makes keyframes");
}

#[test]
fn the_resume_file_keeps_the_edge_and_reads_files_without_one() {
    let tmp = tempfile::tempdir().unwrap();
    let files = Files::in_dir(&tmp.path().join("robot"));
    let edge = OdometryEdge {
        from: 16,
        to: 17,
        relative: SE3::translation(0.0, 0.0, 3.0),
        information: doorslam_geometry::TangentMatrix::from_diagonal(&nalgebra::Vector6::new(
            1e4, 2e4, 3e4, 1e2, 2e2, 3e2,
        )),
    };
    let r = Resume {
        keyframe: 17,
        stamp_ns: 123,
        pose: SE3::translation(1.0, 2.0, 3.0),
        edge: Some(edge),
    };
    files.write_resume(&r).unwrap();
    let back = files.read_resume().unwrap().unwrap().edge.unwrap();
    assert_eq!((back.from, back.to), (16, 17));
    assert!((back.relative.inverse() * edge.relative).log().norm() < 1e-12);
    assert!((back.information - edge.information).norm() < 1e-9);
    // A file of before the edge was kept: no edge, not an error.
    let old = r#"{"keyframe":17,"stamp_ns":123,"pose":[1,2,3,0,0,0,1]}"#;
    std::fs::write(&files.resume, old).unwrap();
    assert_eq!(files.read_resume().unwrap().unwrap().edge, None);
    // A bad edge is named.
    for (edge, what) in [
        (
            r#"{"from":17,"relative":[0,0,3,0,0,0,1],"information":[]}"#,
            "not from an earlier one",
        ),
        (
            r#"{"from":16,"relative":[0,0,3,0,0,0,1],"information":[1,2,3]}"#,
            "3 values",
        ),
    ] {
        let text =
            format!(r#"{{"keyframe":17,"stamp_ns":123,"pose":[1,2,3,0,0,0,1],"edge":{edge}}}"#);
        std::fs::write(&files.resume, text).unwrap();
        let err = files.read_resume().unwrap_err().to_string();
        assert!(
            err.contains("frontend.resume") && err.contains(what),
            "{err}"
        );
    }
}

#[test]
fn the_frontend_section_takes_vo_fields_and_refuses_unknown_keys() {
    #[derive(serde::Deserialize)]
    struct Robot {
        frontend: FrontendSection,
    }
    let ok: Robot = toml::from_str(
        "[frontend]\ncalibration = \"/etc/calib.txt\"\nimage_size = [640, 480]\nmax_features = 500\ndetector = \"fast\"\nthreads = 1\n",
    )
    .unwrap();
    assert_eq!(ok.frontend.vo.max_features, 500);
    assert_eq!(ok.frontend.image_size, Some([640, 480]));
    ok.frontend.validate().unwrap();
    let err = toml::from_str::<Robot>("[frontend]\nmax_featurs = 500\n")
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("max_featurs"), "{err}");
    let too_many: Robot = toml::from_str("[frontend]\nmax_features = 2000\n").unwrap();
    let err = too_many.frontend.validate().unwrap_err().to_string();
    assert!(err.contains("max_features = 2000"), "{err}");
    let bad_vo: Robot = toml::from_str("[frontend]\nmin_inliers = 2\n").unwrap();
    let err = bad_vo.frontend.validate().unwrap_err().to_string();
    assert!(err.contains("min_inliers"), "{err}");
}

#[test]
fn calibration_errors_name_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let section = FrontendSection::default();
    let err = section
        .calibration_source(None, [752, 480])
        .unwrap_err()
        .to_string();
    assert!(err.contains("frontend.calibration"), "{err}");

    let missing = tmp.path().join("nope.txt");
    let source = CalibrationSource::File {
        path: missing.clone(),
        width: 752,
        height: 480,
    };
    let err = Calibration::load(&source).unwrap_err().to_string();
    assert!(err.contains("nope.txt"), "{err}");

    let malformed = tmp.path().join("calib.txt");
    std::fs::write(&malformed, "P0: 1 2 3\n").unwrap();
    let source = CalibrationSource::File {
        path: malformed.clone(),
        width: 752,
        height: 480,
    };
    let err = Calibration::load(&source).unwrap_err().to_string();
    assert!(err.contains("calib.txt:1") && err.contains("P0"), "{err}");

    // A calibration for a larger image: its principal point is outside this one.
    std::fs::write(
        &malformed,
        "P0: 700 0 600 0 0 700 180 0 0 0 1 0\nP1: 700 0 600 -350 0 700 180 0 0 0 1 0\n",
    )
    .unwrap();
    let source = CalibrationSource::File {
        path: malformed,
        width: 320,
        height: 240,
    };
    let err = Calibration::load(&source).unwrap_err().to_string();
    assert!(
        err.contains("principal point") && err.contains("320x240"),
        "{err}"
    );

    // A dataset folder without calib.txt.
    let data = tmp.path().join("seq");
    std::fs::create_dir_all(data.join("image_0")).unwrap();
    std::fs::create_dir_all(data.join("image_1")).unwrap();
    let px = vec![7u8; 64 * 48];
    for side in ["image_0", "image_1"] {
        doorslam_dataset::write_gray_png(&data.join(side).join("000000.png"), 64, 48, &px).unwrap();
    }
    let err = Calibration::load(&CalibrationSource::Dataset(data.clone()))
        .unwrap_err()
        .to_string();
    assert!(err.contains("calib.txt"), "{err}");
    std::fs::write(
        data.join("calib.txt"),
        "P0: 50 0 32 0 0 50 24 0 0 0 1 0\nP1: 50 0 32 -25 0 50 24 0 0 0 1 0\n",
    )
    .unwrap();
    let c = Calibration::load(&CalibrationSource::Dataset(data)).unwrap();
    assert_eq!((c.width, c.height, c.stereo.baseline_m), (64, 48, 0.5));
}
