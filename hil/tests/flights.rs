//! Team flights through the synthetic town: determinism, smoothness, safety, the
//! designed closure candidates, and a radio event log that matches the positions.

use std::collections::BTreeMap;

use doorslam_hil::flights::{
    camera_for_resolution, closure_candidates, fly_team, rendezvous_events, seen_buildings,
    simulate_team, write_team, ClosureKind, Flight, FlightConfig, RangeEventKind, TeamFlight,
    OVERLAP_RADIUS_M,
};
use doorslam_hil::sensor::CameraModel;
use doorslam_hil::{StereoCamera, World};
use nalgebra::Vector3;

const SEED: u64 = 1;

fn default_team() -> (World, TeamFlight) {
    let world = World::town(SEED);
    let config = FlightConfig::default();
    let team = simulate_team(&world, &StereoCamera::euroc_like(), &config).unwrap();
    (world, team)
}

fn distance(f: &Flight, g: &Flight, k: usize) -> f64 {
    (f.poses[k].translation.vector - g.poses[k].translation.vector).norm()
}

#[test]
fn same_seed_gives_same_flights_and_events() {
    let world = World::town(SEED);
    let config = FlightConfig::default();
    let a = fly_team(&world, &config).unwrap();
    let b = fly_team(&world, &config).unwrap();
    assert_eq!(a, b);
    assert_eq!(
        rendezvous_events(&a, config.radio_range_m),
        rendezvous_events(&b, config.radio_range_m)
    );
    let other = FlightConfig {
        seed: SEED + 1,
        ..config.clone()
    };
    assert_ne!(a, fly_team(&world, &other).unwrap(), "the seed must matter");
}

#[test]
fn trajectories_are_smooth_and_at_drone_altitude() {
    let world = World::town(SEED);
    let config = FlightConfig::default();
    let dt = 1.0 / config.rate_hz;
    for (r, f) in fly_team(&world, &config).unwrap().iter().enumerate() {
        assert_eq!(f.poses.len(), config.frames);
        for k in 1..f.poses.len() - 1 {
            let p = |i: usize| f.poses[i].translation.vector;
            let accel = (p(k + 1) - 2.0 * p(k) + p(k - 1)) / (dt * dt);
            assert!(accel.norm() < 3.0, "robot {r} frame {k}: {accel:?} m/s²");
            let speed = (p(k + 1) - p(k)).norm() / dt;
            assert!(
                (1.0..=5.0).contains(&speed),
                "robot {r} frame {k}: {speed} m/s"
            );
            let turn = f.poses[k].rotation.angle_to(&f.poses[k + 1].rotation) / dt;
            assert!(turn < 0.6, "robot {r} frame {k}: {turn} rad/s");
        }
        for (k, pose) in f.poses.iter().enumerate() {
            let z = pose.translation.z;
            assert!(
                (config.min_altitude_m..=config.max_altitude_m).contains(&z),
                "robot {r} frame {k}: altitude {z}"
            );
            // Looking forward and a little down, rows level.
            let forward = pose.rotation * Vector3::z();
            let right = pose.rotation * Vector3::x();
            let pitch = (-forward.z).asin().to_degrees();
            assert!((pitch - config.pitch_down_deg).abs() < 1e-9);
            assert!(right.z.abs() < 1e-12);
        }
    }
}

#[test]
fn cameras_never_enter_a_building() {
    let world = World::town(SEED);
    for seed in [SEED, 2, 3] {
        let config = FlightConfig {
            seed,
            frames: 600,
            ..FlightConfig::default()
        };
        for f in fly_team(&world, &config).unwrap() {
            for pose in &f.poses {
                let p = pose.translation.vector;
                for b in world.buildings() {
                    let (lo, hi) = (b.bounds().min, b.bounds().max);
                    // With a margin: the near plane must not clip a wall either.
                    let inside = (0..3).all(|i| p[i] > lo[i] - 1.0 && p[i] < hi[i] + 1.0);
                    assert!(!inside, "camera at {p:?} inside {:?}", b.bounds());
                }
            }
        }
    }
}

#[test]
fn default_team_has_true_overlaps_aliases_and_rendezvous() {
    let (world, team) = default_team();
    let overlaps = team.count(ClosureKind::Overlap);
    let aliased = team.count(ClosureKind::Aliased);
    eprintln!(
        "default team: {overlaps} overlap, {aliased} aliased candidates, {} rendezvous events",
        team.events.len()
    );
    for f in &team.flights {
        eprintln!("  {} at {:.2} m/s", f.role, f.speed_mps);
    }
    assert!(overlaps >= 1 && aliased >= 1 && !team.events.is_empty());
    let camera = team.camera;
    for c in &team.closures {
        assert!(c.robot_a < c.robot_b);
        let (pa, pb) = (
            &team.flights[c.robot_a].poses[c.frame_a],
            &team.flights[c.robot_b].poses[c.frame_b],
        );
        let d = (pa.translation.vector - pb.translation.vector).norm();
        match c.kind {
            ClosureKind::Overlap => assert!(d <= OVERLAP_RADIUS_M),
            ClosureKind::Aliased => {
                // Different buildings of one design in view, far apart in the world.
                let (sa, sb) = (
                    seen_buildings(&world, &camera, pa),
                    seen_buildings(&world, &camera, pb),
                );
                let style = |i: &usize| world.buildings()[*i].style();
                assert!(sa
                    .iter()
                    .any(|a| sb.iter().any(|b| a != b && style(a) == style(b))));
            }
        }
    }
    // The candidates are a function of the flights.
    assert_eq!(
        closure_candidates(&world, &camera, &team.flights),
        team.closures
    );
}

#[test]
fn the_design_holds_for_other_seeds() {
    for seed in 2..=6 {
        let world = World::town(seed);
        let config = FlightConfig {
            seed,
            ..FlightConfig::default()
        };
        let team = simulate_team(&world, &StereoCamera::euroc_like(), &config).unwrap();
        let (o, a) = (
            team.count(ClosureKind::Overlap),
            team.count(ClosureKind::Aliased),
        );
        eprintln!(
            "seed {seed}: {o} overlap, {a} aliased, {} events",
            team.events.len()
        );
        assert!(o >= 1 && a >= 1, "seed {seed}");
    }
}

#[test]
fn event_log_matches_the_distances() {
    let (_, team) = default_team();
    let range = team.config.radio_range_m;
    let flights = &team.flights;
    // Per pair, the events in order.
    let mut per_pair: BTreeMap<(usize, usize), Vec<(usize, RangeEventKind)>> = BTreeMap::new();
    let mut last_time = 0.0;
    for e in &team.events {
        assert!(e.robot_a < e.robot_b && e.time_s >= last_time);
        assert!((e.time_s - team.config.time_of(e.frame)).abs() < 1e-12);
        last_time = e.time_s;
        per_pair
            .entry((e.robot_a, e.robot_b))
            .or_default()
            .push((e.frame, e.kind));
    }
    for a in 0..flights.len() {
        for b in a + 1..flights.len() {
            let events = per_pair.remove(&(a, b)).unwrap_or_default();
            let mut inside = false;
            let mut next = events.iter().peekable();
            for k in 0..team.config.frames {
                if let Some(&&(frame, kind)) = next.peek() {
                    if frame == k {
                        let expected = if inside {
                            RangeEventKind::Leave
                        } else {
                            RangeEventKind::Enter
                        };
                        assert_eq!(kind, expected, "pair {a}-{b} frame {k}: not alternating");
                        inside = !inside;
                        next.next();
                    }
                }
                let d = distance(&flights[a], &flights[b], k);
                assert_eq!(d <= range, inside, "pair {a}-{b} frame {k}: distance {d}");
            }
            assert!(next.next().is_none());
        }
    }
}

#[test]
fn small_team_writes_a_replayable_folder() {
    let world = World::town(SEED);
    let camera = camera_for_resolution("94x60").unwrap();
    let config = FlightConfig {
        robots: 2,
        frames: 4,
        ..FlightConfig::default()
    };
    let team = simulate_team(&world, &camera, &config).unwrap();
    let dir = std::env::temp_dir().join(format!("doorslam-flights-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    write_team(&dir, &world, &team, &CameraModel::default(), &|_, _| {}).unwrap();
    for robot in ["a", "b"] {
        let d = doorslam_dataset::Dataset::open(&dir.join(robot)).unwrap();
        assert_eq!(d.len(), 4);
        assert_eq!(d.load(3).unwrap().width, 94);
        assert!(d.truth.is_some());
        // The simulator's calib.txt reads back as the camera that rendered the images.
        let c = d.calibration().unwrap();
        assert!((c.fx - camera.fx()).abs() < 1e-6 * camera.fx(), "{c:?}");
        assert!((c.cx - camera.cx()).abs() < 1e-6, "{c:?}");
        assert!((c.baseline_m - camera.baseline()).abs() < 1e-6, "{c:?}");
    }
    // The realistic camera's settings and per-frame exposures are recorded.
    let world_txt = std::fs::read_to_string(dir.join("world.txt")).unwrap();
    for key in ["camera = \"realistic\"", "full_well_e = ", "blur = true"] {
        assert!(
            world_txt.contains(key),
            "world.txt lacks {key}:\n{world_txt}"
        );
    }
    let exposures = std::fs::read_to_string(dir.join("exposures.csv")).unwrap();
    assert!(exposures.starts_with("robot,frame,time_s,exposure_ms,gain,light,brightness,shade\n"));
    assert_eq!(exposures.lines().count(), 1 + 2 * 4, "{exposures}");
    // A shorter run into the same folder would leave frames behind: refused.
    let shorter = FlightConfig {
        frames: 2,
        ..config
    };
    let team = simulate_team(&world, &camera, &shorter).unwrap();
    let err = write_team(&dir, &world, &team, &CameraModel::Ideal, &|_, _| {}).unwrap_err();
    assert!(err.to_string().contains("image_0"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn pose_at_runs_through_the_frames_smoothly() {
    let world = World::town(SEED);
    let config = FlightConfig::default();
    for f in fly_team(&world, &config).unwrap() {
        for (k, (&t, pose)) in f.times.iter().zip(&f.poses).enumerate() {
            assert_eq!(f.pose_at(t), *pose, "frame {k}");
            // Within an exposure (a few ms) the pose moves by speed × time, no jump.
            let (a, b) = (f.pose_at(t - 0.005), f.pose_at(t + 0.005));
            let step = (b.translation.vector - a.translation.vector).norm();
            assert!(
                step <= 0.01 * f.speed_mps * 1.01 + 1e-9,
                "frame {k}: {step} m"
            );
            assert!(a.rotation.angle_to(&b.rotation) < 0.01, "frame {k}");
        }
    }
}
