//! Stereo VO at drone speed (issue #28's acceptance): a flight at 5 m/s through the
//! simulated town, imaged by the realistic camera (noise, auto-exposure, motion blur),
//! keeps its end-point drift under 1 % without a single loss, its odometry edges'
//! information is consistent (NEES), and a frame of another place is a loss, never a pose.
//!
//! The front-end before this issue (frame-to-keyframe descriptor matching) lost this
//! flight's kind 11-46 times per 500 m (BENCHMARKS.md).

use std::sync::OnceLock;

use doorslam_dataset::StereoCalibration;
use doorslam_frontend::{FrameResult, Gray, LostReason, StereoVo, TrackState, VoConfig};
use doorslam_geometry::{LieGroup, SE3};
use doorslam_hil::flights::{simulate_team, FlightConfig, TeamCamera};
use doorslam_hil::sensor::{CameraModel, SensorModel};
use doorslam_hil::{render_stereo, StereoCamera, World};

const FRAMES: usize = 250;
const RATE_HZ: f64 = 10.0;
/// The town and flight (seed 6: not one the odometry was tuned on), planned at 5.5 m/s:
/// each drone flies its own speed within ±15 %, this one 5.0 m/s.
const SEED: u64 = 6;
const PLANNED_SPEED_MPS: f64 = 5.5;

struct Flight {
    camera: StereoCamera,
    left: Vec<Vec<u8>>,
    right: Vec<Vec<u8>>,
    truth: Vec<SE3>,
    world: World,
}

fn flight() -> &'static Flight {
    static FLIGHT: OnceLock<Flight> = OnceLock::new();
    FLIGHT.get_or_init(|| {
        let world = World::town(SEED);
        let config = FlightConfig {
            robots: 1,
            frames: FRAMES,
            rate_hz: RATE_HZ,
            seed: SEED,
            speed_mps: PLANNED_SPEED_MPS,
            ..FlightConfig::default()
        };
        let camera = StereoCamera::euroc_like();
        let team = simulate_team(&world, &camera, &config).expect("plan a flight");
        let imaging = TeamCamera::new(
            &world,
            &team,
            CameraModel::Realistic(SensorModel::default()),
        )
        .expect("a valid camera model");
        let (mut left, mut right) = (Vec::new(), Vec::new());
        for k in 0..FRAMES {
            let pair = imaging.render(0, k).expect("render").expect("frame exists");
            left.push(pair.left.pixels().to_vec());
            right.push(pair.right.pixels().to_vec());
        }
        Flight {
            camera,
            left,
            right,
            truth: team.flights[0].poses.clone(),
            world,
        }
    })
}

fn calibration(c: &StereoCamera) -> StereoCalibration {
    c.stereo_calibration()
}

/// The simulator's rig is calibrated exactly: no shared calibration errors in the edges'
/// information, and its disparities are better than a real rig's
/// (deploy/vo-simulated-rig.toml, the same settings).
fn simulated_rig() -> VoConfig {
    VoConfig {
        scale_sigma: 0.0,
        rotation_sigma_deg: 0.0,
        rotation_sigma_deg_per_m: 0.0,
        translation_sigma_m: 0.0,
        translation_sigma_per_m: 0.0,
        disparity_sigma_px: 0.25,
        ..VoConfig::default()
    }
}

fn stamp(n: usize) -> u64 {
    (n as f64 / RATE_HZ * 1e9).round() as u64
}

fn process(vo: &mut StereoVo, n: usize, frame: u64, left: &[u8], right: &[u8]) -> FrameResult {
    let c = &flight().camera;
    let (w, h) = (c.width() as usize, c.height() as usize);
    vo.process(
        frame,
        stamp(n),
        &Gray::new(w, h, left).unwrap(),
        &Gray::new(w, h, right).unwrap(),
    )
    .unwrap()
}

fn whole_flight() -> &'static (Vec<FrameResult>, doorslam_frontend::VoStats) {
    static RUN: OnceLock<(Vec<FrameResult>, doorslam_frontend::VoStats)> = OnceLock::new();
    RUN.get_or_init(|| {
        let f = flight();
        let mut vo = StereoVo::new(calibration(&f.camera), simulated_rig()).unwrap();
        let results = (0..FRAMES)
            .map(|k| process(&mut vo, k, k as u64, &f.left[k], &f.right[k]))
            .collect();
        (results, vo.stats())
    })
}

fn path_length(poses: &[SE3]) -> f64 {
    poses
        .windows(2)
        .map(|w| (w[1].translation.vector - w[0].translation.vector).norm())
        .sum()
}

#[test]
fn a_5_mps_flight_keeps_its_drift_under_1_percent_without_a_loss() {
    let f = flight();
    let (results, stats) = whole_flight();
    let distance = path_length(&f.truth);
    let speed = distance / ((FRAMES - 1) as f64 / RATE_HZ);
    assert!(
        (4.9..6.5).contains(&speed),
        "the flight is meant to be at drone speed: {speed:.2} m/s"
    );
    assert_eq!((stats.lost, stats.segments), (0, 1), "{stats:?}");
    assert!(results.iter().all(|r| r.pose.is_some()));
    let (first, last) = (results[0].pose.unwrap(), results[FRAMES - 1].pose.unwrap());
    let end_est = first.inverse() * last;
    let end_gt = f.truth[0].inverse() * f.truth[FRAMES - 1];
    let drift = (end_est.translation.vector - end_gt.translation.vector).norm() / distance;
    eprintln!(
        "{distance:.1} m at {speed:.2} m/s: {} keyframes, end-point drift {:.3} %",
        stats.keyframes,
        100.0 * drift
    );
    // Measured 0.107 % (seed 6, 250 frames; 0.16 % before the gradient-refined
    // disparities); the bound is 1 %.
    assert!(drift < 0.01, "end-point drift {:.2} %", 100.0 * drift);
}

#[test]
fn the_edges_information_is_consistent_at_speed() {
    let f = flight();
    let (results, _) = whole_flight();
    let frame_of: std::collections::HashMap<u64, usize> = results
        .iter()
        .filter_map(|r| r.keyframe.as_ref().map(|k| (k.id, k.frame as usize)))
        .collect();
    let nees: Vec<f64> = results
        .iter()
        .filter_map(|r| r.edge)
        .map(|edge| {
            let truth = f.truth[frame_of[&edge.from]].inverse() * f.truth[frame_of[&edge.to]];
            let r = (truth.inverse() * edge.relative).log();
            (r.transpose() * edge.information * r)[0]
        })
        .collect();
    let mean = nees.iter().sum::<f64>() / nees.len().max(1) as f64;
    eprintln!(
        "edge NEES mean {mean:.2} over {} edges (expected 6)",
        nees.len()
    );
    assert!(nees.len() >= 30, "only {} edges", nees.len());
    // Measured 4.99 over 46 edges (5.21 with the parabola's disparities and 0.5 px); the
    // issue's band is 4-9 (6 expected). The frame-to-keyframe refinement's information
    // without the window's adjustment is 2-3× more confident than its errors on these
    // flights.
    assert!((4.0..=9.0).contains(&mean), "mean NEES {mean:.2}");
}

#[test]
fn a_frame_of_another_place_is_a_loss_never_a_pose() {
    let f = flight();
    let c = &f.camera;
    // The next frame comes from another town (another seed), or from the same town 150 m
    // further on, 0.1 s after the last: no overlap with what was tracked.
    let elsewhere = World::town(SEED + 100);
    let other_town = render_stereo(&elsewhere, c, &f.truth[20]);
    let later = render_stereo(&f.world, c, &f.truth[FRAMES - 1]);
    for (name, jump) in [("another town", &other_town), ("150 m on", &later)] {
        let mut vo = StereoVo::new(calibration(c), VoConfig::default()).unwrap();
        for k in 0..10 {
            let r = process(&mut vo, k, k as u64, &f.left[k], &f.right[k]);
            assert!(r.pose.is_some(), "{name}: frame {k}: {r:?}");
        }
        let r = process(&mut vo, 10, 10, jump.left.pixels(), jump.right.pixels());
        eprintln!("{name}: {:?} ({:?})", r.state, r.lost_reason);
        assert_eq!(r.state, TrackState::Lost, "{name}: {r:?}");
        assert!(r.pose.is_none() && r.edge.is_none() && r.keyframe.is_none());
        assert!(
            matches!(
                r.lost_reason,
                Some(LostReason::TrackingFailed { .. } | LostReason::Unpredicted { .. })
            ),
            "{name}: {:?}",
            r.lost_reason
        );
        // The next frame starts a new segment at once, linked to the old one.
        let next = process(&mut vo, 11, 11, &f.left[11], &f.right[11]);
        assert_eq!(next.state, TrackState::Initialized, "{name}: {next:?}");
        assert_eq!(next.segment, 1);
        assert!(next.link.is_some());
        let stats = vo.stats();
        assert_eq!(stats.lost, 1);
        assert_eq!(
            stats.lost_by_reason.tracking_failed + stats.lost_by_reason.unpredicted,
            1,
            "{stats:?}"
        );
    }
}
