//! `doorslam sim world` end to end: the binary writes a small two-drone world, and the
//! replay reader reads every robot's sequence back with its ground truth.

use std::path::Path;
use std::process::{Command, Output};

use doorslam_dataset::Dataset;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

fn doorslam(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_doorslam"))
        .args(args)
        .output()
        .expect("the doorslam binary runs")
}

/// Poses of a TUM file (`t x y z qx qy qz qw`), with their times.
fn read_tum(path: &Path) -> Vec<(f64, Isometry3<f64>)> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            assert_eq!(v.len(), 8, "{l}");
            let q = UnitQuaternion::from_quaternion(Quaternion::new(v[7], v[4], v[5], v[6]));
            (
                v[0],
                Isometry3::from_parts(Translation3::new(v[1], v[2], v[3]), q),
            )
        })
        .collect()
}

#[test]
fn two_drone_world_round_trips_through_the_replay_reader() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("world");
    let out_str = out.to_str().unwrap();
    let run = doorslam(&[
        "sim",
        "world",
        "--robots",
        "2",
        "--frames",
        "20",
        "--resolution",
        "188x120",
        "--out",
        out_str,
        "--json",
    ]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    let stdout = String::from_utf8_lossy(&run.stdout);
    let summary: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(summary["robots"], 2);
    assert_eq!(summary["resolution"], "188x120");
    assert!(stderr.contains("20/40"), "progress on stderr: {stderr}");

    for robot in ["a", "b"] {
        let dir = out.join(robot);
        let data = Dataset::open(&dir).unwrap();
        assert_eq!(data.len(), 20);
        let pair = data.load(19).unwrap();
        assert_eq!((pair.width, pair.height), (188, 120));
        assert_ne!(pair.left, pair.right, "a stereo pair, not one image twice");
        for w in data.frames.windows(2) {
            assert!(w[1].stamp_ns > w[0].stamp_ns);
        }
        let truth = data.truth.as_ref().expect("poses.txt is read as truth");
        let tum = read_tum(&dir.join("groundtruth.tum"));
        assert_eq!(truth.len(), tum.len());
        for ((kitti, (t, pose)), frame) in truth.iter().zip(&tum).zip(&data.frames) {
            assert!((t * 1e9 - frame.stamp_ns as f64).abs() < 1e3);
            let dt = (kitti.translation.vector - pose.translation.vector).norm();
            assert!(dt < 1e-9 && kitti.rotation.angle_to(&pose.rotation) < 1e-9);
        }
        let calib = std::fs::read_to_string(dir.join("calib.txt")).unwrap();
        assert!(calib.starts_with("P0: ") && calib.contains("\nP1: "));
    }
    let events = std::fs::read_to_string(out.join("events.csv")).unwrap();
    assert!(events.starts_with("time_s,event,robot_a,robot_b\n"));
    let closures = std::fs::read_to_string(out.join("closures.csv")).unwrap();
    assert!(closures.starts_with("robot_a,frame_a,robot_b,frame_b,kind\n"));
    let world = std::fs::read_to_string(out.join("world.txt")).unwrap();
    for key in [
        "seed = 1",
        "resolution = \"188x120\"",
        "robots = 2",
        "frames = 20",
        "radio_range_m",
        "camera = \"realistic\"",
        "exposure_ms = ",
    ] {
        assert!(world.contains(key), "world.txt lacks {key}:\n{world}");
    }
    assert_eq!(summary["camera"], "realistic");
    let exposures = std::fs::read_to_string(out.join("exposures.csv")).unwrap();
    assert_eq!(exposures.lines().count(), 1 + 2 * 20);
}

/// Every image of a `sim world` output, by path relative to it.
fn images(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for robot in ["a", "b"] {
        for eye in ["image_0", "image_1"] {
            let folder = dir.join(robot).join(eye);
            let mut names: Vec<_> = std::fs::read_dir(&folder)
                .unwrap()
                .map(|e| e.unwrap().file_name().into_string().unwrap())
                .collect();
            names.sort();
            for name in names {
                let bytes = std::fs::read(folder.join(&name)).unwrap();
                out.push((format!("{robot}/{eye}/{name}"), bytes));
            }
        }
    }
    out
}

#[test]
fn camera_flags_choose_the_pixels_and_the_seed_fixes_them() {
    let tmp = tempfile::tempdir().unwrap();
    let world = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        let mut args = vec![
            "sim",
            "world",
            "--robots",
            "2",
            "--frames",
            "5",
            "--resolution",
            "188x120",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let run = doorslam(&args);
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        out
    };
    let realistic = images(&world("r1", &[]));
    assert_eq!(realistic.len(), 2 * 2 * 5);
    assert_eq!(
        realistic,
        images(&world("r2", &[])),
        "same seed, same bytes"
    );
    let ideal_dir = world("i", &["--camera", "ideal"]);
    let ideal = images(&ideal_dir);
    assert!(!ideal_dir.join("exposures.csv").exists());
    let world_txt = std::fs::read_to_string(ideal_dir.join("world.txt")).unwrap();
    assert!(world_txt.contains("camera = \"ideal\"") && !world_txt.contains("exposure_ms"));
    let differ = realistic
        .iter()
        .zip(&ideal)
        .filter(|(r, i)| r.1 != i.1)
        .count();
    assert_eq!(
        differ,
        realistic.len(),
        "the realistic camera changes every image"
    );
    // Every effect off: the realistic pipeline's pixels are the ideal camera's, up to
    // rounding from f32 instead of f64.
    let off = world(
        "off",
        &[
            "--noise-dn",
            "0",
            "--full-well-e",
            "0",
            "--exposure-walk",
            "0",
            "--shade-per-min",
            "0",
            "--blur",
            "off",
            "--vignetting",
            "0",
        ],
    );
    for robot in ["a", "b"] {
        let (a, b) = (
            Dataset::open(&off.join(robot)).unwrap(),
            Dataset::open(&ideal_dir.join(robot)).unwrap(),
        );
        for k in 0..5 {
            let (p, q) = (a.load(k).unwrap(), b.load(k).unwrap());
            for (x, y) in [(&p.left, &q.left), (&p.right, &q.right)] {
                let differ = x.iter().zip(y.iter()).filter(|(u, v)| u != v).count();
                assert!(x.iter().zip(y.iter()).all(|(u, v)| u.abs_diff(*v) <= 1));
                assert!(differ * 1000 < x.len(), "{differ} pixels differ");
            }
        }
    }
}

#[test]
fn bad_resolution_and_unwritable_out_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("w");
    let run = doorslam(&[
        "sim",
        "world",
        "--resolution",
        "640by480",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("640by480"));

    // A folder below a regular file cannot be created.
    let file = tmp.path().join("file");
    std::fs::write(&file, "not a folder").unwrap();
    let below = file.join("out");
    let run = doorslam(&[
        "sim",
        "world",
        "--robots",
        "1",
        "--frames",
        "1",
        "--resolution",
        "32x24",
        "--out",
        below.to_str().unwrap(),
    ]);
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains(below.to_str().unwrap()), "{stderr}");

    // An exposure longer than a frame (10 Hz: 100 ms) is refused by name.
    let run = doorslam(&[
        "sim",
        "world",
        "--max-exposure-ms",
        "150",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains("max_exposure_ms = 150"), "{stderr}");
}
