//! The eval module against evo's own results: the result archives stored in evo's test
//! data (`shared/data/trajectories/evo/res_files/*.zip`: `stats.json` + the per-pair
//! `error_array`) and the numbers printed in evo's `doc/performance.md` (quoted in
//! `shared/data/trajectories/evo/README.md`). Plus bad-input messages and an Umeyama
//! property test.
//!
//! Data: `shared/data` beside the repository, or `$DOORSLAM_DATA`.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use doorslam_backend::eval::*;
use nalgebra::{Isometry3, Point3, Similarity3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;

fn data_dir() -> PathBuf {
    match std::env::var_os("DOORSLAM_DATA") {
        Some(dir) => PathBuf::from(dir),
        None => PathBuf::from(concat!(".", "/../../../shared/data")),
    }
}

fn evo_file(name: &str) -> PathBuf {
    let path = data_dir().join("trajectories/evo").join(name);
    assert!(
        path.exists(),
        "missing test data {} (set DOORSLAM_DATA)",
        path.display()
    );
    path
}

/// One evo result archive: its `stats.json` and `error_array` (a `.npy` of f64).
struct EvoResult {
    stats: BTreeMap<String, f64>,
    errors: Vec<f64>,
}

fn read_evo_result(name: &str) -> EvoResult {
    let file = std::fs::File::open(evo_file(&format!("res_files/{name}.zip"))).unwrap();
    let mut zip = zip::ZipArchive::new(file).unwrap();
    let mut json = String::new();
    zip.by_name("stats.json")
        .unwrap()
        .read_to_string(&mut json)
        .unwrap();
    let stats: BTreeMap<String, f64> = serde_json::from_str(&json).unwrap();
    let mut npy = Vec::new();
    zip.by_name("error_array.npz")
        .unwrap()
        .read_to_end(&mut npy)
        .unwrap();
    EvoResult {
        stats,
        errors: parse_npy_f64(&npy),
    }
}

/// A 1-D little-endian f64 `.npy` (format version 1 or 2): magic, header length, a Python
/// dict header, then the raw values. (evo names it `.npz` but stores a plain `.npy`.)
fn parse_npy_f64(bytes: &[u8]) -> Vec<f64> {
    assert_eq!(&bytes[..6], b"\x93NUMPY", "not a .npy");
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        _ => (
            u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize,
            12,
        ),
    };
    let header = std::str::from_utf8(&bytes[start..start + header_len]).unwrap();
    assert!(header.contains("'descr': '<f8'"), "{header}");
    assert!(header.contains("'fortran_order': False"), "{header}");
    let shape = header.split("'shape': (").nth(1).unwrap();
    let n: usize = shape.split(',').next().unwrap().trim().parse().unwrap();
    let data = &bytes[start + header_len..];
    assert_eq!(data.len(), 8 * n);
    data.chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

fn assert_close(what: &str, got: f64, want: f64, tol: f64) {
    assert!(
        (got - want).abs() <= tol,
        "{what}: got {got:.12}, evo {want:.12}, diff {:.3e} > {tol:e}",
        (got - want).abs()
    );
}

/// Every statistic evo stores, each within `tol` except `sse`, within `sse_tol`.
fn assert_stats(name: &str, got: &ErrorStats, evo: &EvoResult, tol: f64, sse_tol: f64) {
    let s = &evo.stats;
    let ours = [
        ("rmse", got.rmse),
        ("mean", got.mean),
        ("median", got.median),
        ("std", got.std),
        ("min", got.min),
        ("max", got.max),
    ];
    let worst = ours
        .iter()
        .map(|(k, v)| (v - s[*k]).abs())
        .fold(0.0, f64::max);
    let sse_diff = (got.sse - s["sse"]).abs();
    eprintln!("{name}: max |stat - evo| {worst:.2e} m, |sse - evo| {sse_diff:.2e} m²");
    for (k, v) in ours {
        assert_close(&format!("{name} {k}"), v, s[k], tol);
    }
    assert_close(&format!("{name} sse"), got.sse, s["sse"], sse_tol);
    assert_eq!(got.pairs, evo.errors.len(), "{name} pairs");
}

/// Pose-by-pose errors against evo's `error_array`.
fn assert_errors(name: &str, got: &[f64], evo: &[f64], tol: f64) {
    assert_eq!(got.len(), evo.len(), "{name} error count");
    let worst = got
        .iter()
        .zip(evo)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    eprintln!(
        "{name}: max |error - evo error| {worst:.2e} m over {} errors",
        got.len()
    );
    for (k, (a, b)) in got.iter().zip(evo).enumerate() {
        assert_close(&format!("{name} error[{k}]"), *a, *b, tol);
    }
}

fn kitti00(estimate: &str) -> (Trajectory, Trajectory) {
    let reference = read_kitti(evo_file("KITTI_00_gt.txt")).unwrap();
    let estimate = read_kitti(evo_file(estimate)).unwrap();
    associate_by_index(&reference, &estimate).unwrap()
}

fn check_kitti_ape(estimate: &str, archive: &str) {
    let evo = read_evo_result(archive);
    let start = Instant::now();
    let (reference, estimate) = kitti00(estimate);
    let read = start.elapsed();
    let ate = absolute_trajectory_error(&reference, &estimate, Alignment::Se3).unwrap();
    let total = start.elapsed();
    eprintln!(
        "{archive}: read+associate {:.1} ms, ATE (Umeyama + errors + stats) {:.2} ms",
        read.as_secs_f64() * 1e3,
        (total - read).as_secs_f64() * 1e3
    );
    assert_eq!(ate.stats.pairs, 4541); // KITTI 00 has 4541 images (README table)
    assert_stats(archive, &ate.stats, &evo, 1e-6, 1e-6);
    assert_errors(archive, &ate.errors, &evo.errors, 1e-6);
}

#[test]
fn kitti00_orb_ape_matches_evo() {
    check_kitti_ape("KITTI_00_ORB.txt", "orb_ape");
}

#[test]
fn kitti00_sptam_ape_matches_evo() {
    check_kitti_ape("KITTI_00_SPTAM.txt", "sptam_ape");
}

/// evo multiplies KITTI's raw 3x4 rows, whose rotation blocks are off SO(3) by up to
/// 2e-7 (the ground truth prints 7 digits); we project them to the nearest rotation.
/// Over a 10 m pair that moves each RPE error by up to ~1e-6 m (1.2e-6 measured), the
/// statistics by less than 3e-7 m, and the sum of ~350 squared errors by ~5e-7 relative.
fn check_kitti_rpe(estimate: &str, archive: &str, pairs: usize) {
    let evo = read_evo_result(archive);
    let (reference, estimate) = kitti00(estimate);
    let rpe = relative_pose_error(&reference, &estimate, RpeDelta::Meters(10.0)).unwrap();
    assert_eq!(rpe.stats.pairs, pairs);
    let sse_tol = 1e-6 * evo.stats["sse"];
    assert_stats(archive, &rpe.stats, &evo, 1e-6, sse_tol);
    assert_errors(archive, &rpe.errors, &evo.errors, 2e-6);
    // Consecutive pairs: each starts where the previous one ended.
    assert!(rpe.pairs.windows(2).all(|w| w[0].1 == w[1].0));
}

#[test]
fn kitti00_orb_rpe_10m_matches_evo() {
    check_kitti_rpe("KITTI_00_ORB.txt", "orb_rpe", 353);
}

#[test]
fn kitti00_sptam_rpe_10m_matches_evo() {
    check_kitti_rpe("KITTI_00_SPTAM.txt", "sptam_rpe", 355);
}

#[test]
fn tum_fr2_desk_ate_matches_evo_doc() {
    let reference = read_tum(evo_file("fr2_desk_groundtruth.txt")).unwrap();
    let estimate = read_tum(evo_file("fr2_desk_ORB.txt")).unwrap();
    assert_eq!((reference.len(), estimate.len()), (20957, 2893)); // README table
    let (reference, estimate) =
        associate_by_timestamp(&reference, &estimate, DEFAULT_MAX_TIME_DIFF).unwrap();
    let ate = absolute_trajectory_error(&reference, &estimate, Alignment::Se3).unwrap();
    // evo doc/performance.md prints 6 decimals (rounding error <= 5e-7).
    let s = ate.stats;
    assert_close("rmse", s.rmse, 0.008119, 1e-6);
    assert_close("mean", s.mean, 0.007492, 1e-6);
    assert_close("median", s.median, 0.007415, 1e-6);
    assert_close("std", s.std, 0.003129, 1e-6);
    assert_close("min", s.min, 0.000350, 1e-6);
    assert_close("max", s.max, 0.024300, 1e-6);
    assert_close("sse", s.sse, 0.143305, 1e-6);
    // The doc gives no pair count, but sse / rmse² = 0.143305 / 0.008119² = 2173.98
    // (±0.3 from the rounding of both): 2174 pairs.
    assert_eq!(s.pairs, 2174);
}

#[test]
fn kitti_times_file_gives_seconds() {
    let t = read_kitti_with_times(
        evo_file("KITTI_00_gt.txt"),
        evo_file("KITTI_00_gt_times.txt"),
    )
    .unwrap();
    assert_eq!(t.len(), 4541);
    // First and last line of KITTI_00_gt_times.txt: 0.000000e+00, 4.705816e+02.
    assert_eq!(t.timestamps()[0], 0.0);
    assert_eq!(t.timestamps()[4540], 470.5816);
    // Without times, stamps are the pose indices.
    let plain = read_kitti(evo_file("KITTI_00_gt.txt")).unwrap();
    assert_eq!(plain.timestamps()[4540], 4540.0);
}

#[test]
fn euroc_reader_puts_w_first_and_converts_ns() {
    let t = read_euroc(evo_file("V102_groundtruth.csv")).unwrap();
    // 16702 poses (README table). First data row: 1403715524907143168,0.515356,1.996773,
    // 0.971104,0.161996,0.789985,-0.205376,0.554528,... (q_w first).
    assert_eq!(t.len(), 16702);
    assert_close("stamp", t.timestamps()[0] - 1403715524.0, 0.907143168, 1e-6);
    let p = t.poses()[0];
    assert_eq!(
        p.translation.vector,
        Vector3::new(0.515356, 1.996773, 0.971104)
    );
    let q = p.rotation.quaternion();
    let n = (0.161996f64.powi(2) + 0.789985f64.powi(2) + 0.205376f64.powi(2) + 0.554528f64.powi(2))
        .sqrt();
    assert_close("q_w", q.w, 0.161996 / n, 1e-12);
    assert_close("q_x", q.i, 0.789985 / n, 1e-12);
    assert_close("q_z", q.k, 0.554528 / n, 1e-12);
    // The TUM estimate of the same sequence associates with it by timestamp.
    let estimate = read_tum(evo_file("V102.txt")).unwrap();
    let (r, e) = associate_by_timestamp(&t, &estimate, DEFAULT_MAX_TIME_DIFF).unwrap();
    assert_eq!(r.len(), e.len());
    assert!(r.len() <= estimate.len() && !r.is_empty());
    for (a, b) in r.timestamps().iter().zip(e.timestamps()) {
        assert!((a - b).abs() <= DEFAULT_MAX_TIME_DIFF);
    }
}

#[test]
fn format_is_guessed_from_extension_and_content() {
    let cases = [
        ("KITTI_00_ORB.txt", TrajectoryFormat::Kitti),
        ("fr2_desk_groundtruth.txt", TrajectoryFormat::Tum),
        ("V102.txt", TrajectoryFormat::Tum),
        ("V102_groundtruth.csv", TrajectoryFormat::Euroc),
    ];
    for (file, format) in cases {
        assert_eq!(
            TrajectoryFormat::from_path(evo_file(file)).unwrap(),
            format,
            "{file}"
        );
    }
    assert_eq!(
        "TUM".parse::<TrajectoryFormat>().unwrap(),
        TrajectoryFormat::Tum
    );
    assert!("g2o".parse::<TrajectoryFormat>().is_err());
}

fn temp_file(name: &str, content: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::File::create(&path)
        .unwrap()
        .write_all(content.as_bytes())
        .unwrap();
    (dir, path)
}

fn error_of(result: Result<Trajectory, EvalError>) -> String {
    result.unwrap_err().to_string()
}

/// Reading `text` as file `name` fails with a message containing `want`.
fn assert_read_error(name: &str, text: &str, format: TrajectoryFormat, want: &str) {
    let (_dir, path) = temp_file(name, text);
    let msg = error_of(read_trajectory(&path, format));
    assert!(msg.contains(want), "{name}: {msg:?} lacks {want:?}");
}

const KITTI_IDENTITY: &str = "1 0 0 0 0 1 0 0 0 0 1 0";

#[test]
fn truncated_kitti_line_names_file_and_line() {
    let text = format!("# header\n{KITTI_IDENTITY}\n\n1 0 0 0 0 1 0 0 0 0 1\n");
    let want = "truncated.txt:4: expected 12 fields, found 11";
    assert_read_error("truncated.txt", &text, TrajectoryFormat::Kitti, want);
}

#[test]
fn nan_in_tum_names_file_line_and_field() {
    let text = "# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 0 nan 0 0 0 0 1\n";
    let want = "nan.tum:3: field 3: \"nan\" is not finite";
    assert_read_error("nan.tum", text, TrajectoryFormat::Tum, want);
}

#[test]
fn other_bad_lines_are_reported() {
    use TrajectoryFormat::{Euroc, Kitti, Tum};
    let tum = "1.0 0 0 0 0 0 0 1\n1.1 0 0 x 0 0 0 1\n";
    assert_read_error("a.tum", tum, Tum, "a.tum:2: field 4: cannot parse \"x\"");
    let zero_quaternion = "1.0 0 0 0 0 0 0 0\n";
    assert_read_error(
        "b.tum",
        zero_quaternion,
        Tum,
        "b.tum:1: quaternion has norm 0",
    );
    let short_csv = "#ts,x\n1,0,0,0,1,0,0\n";
    let want = "c.csv:2: expected at least 8 fields, found 7";
    assert_read_error("c.csv", short_csv, Euroc, want);
    let scaled = "2 0 0 0 0 2 0 0 0 0 2 0\n";
    assert_read_error(
        "d.txt",
        scaled,
        Kitti,
        "d.txt:1: 3x3 block is not a rotation",
    );
    assert_read_error("e.txt", "# only a comment\n\n", Kitti, "e.txt: no poses");
    // Columns after the 8th are ignored, the first 8 are checked.
    let inf_csv = "1,0,0,0,1,0,0,0,extra,columns\n2,0,0,0,inf,0,0,0\n";
    assert_read_error(
        "f.csv",
        inf_csv,
        Euroc,
        "f.csv:2: field 5: \"inf\" is not finite",
    );
    let msg = error_of(read_tum(Path::new("/nonexistent/x.tum")));
    assert!(msg.contains("cannot read /nonexistent/x.tum"), "{msg}");
}

#[test]
fn kitti_times_count_must_match() {
    let (_d1, poses) = temp_file(
        "poses.txt",
        &format!("{KITTI_IDENTITY}\n{KITTI_IDENTITY}\n"),
    );
    let (_d2, times) = temp_file("times.txt", "0.0\n");
    let msg = error_of(read_kitti_with_times(&poses, &times));
    assert!(msg.contains("times.txt: 1 timestamps for 2 poses"), "{msg}");
}

#[test]
fn wrong_length_association_names_both_lengths() {
    let (reference, estimate) = kitti00("KITTI_00_ORB.txt");
    let short = Trajectory::from_poses(estimate.poses()[..100].to_vec());
    let msg = associate_by_index(&reference, &short)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("reference has 4541 poses, estimate has 100"),
        "{msg}"
    );
    let msg = absolute_trajectory_error(&reference, &short, Alignment::Se3)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("4541") && msg.contains("100"), "{msg}");
    // Stamps 0..99 s against 1000.5.. s: nothing within 10 ms.
    let far = Trajectory::new(
        (0..100).map(|k| 1000.5 + k as f64).collect(),
        short.poses().to_vec(),
    );
    let msg = associate_by_timestamp(&short, &far.unwrap(), 0.01)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("no timestamps"), "{msg}");
}

/// Hand-made: the reference moves 1 m along x per frame, the estimate 1.1 m; every
/// consecutive-frame RPE is then |1.1 - 1| = 0.1 m, and over 2 frames 0.2 m.
#[test]
fn rpe_in_frames_on_a_hand_made_trajectory() {
    let line = |step: f64| {
        Trajectory::from_poses(
            (0..11)
                .map(|k| Isometry3::translation(step * k as f64, 0.0, 0.0))
                .collect(),
        )
    };
    let (reference, estimate) = (line(1.0), line(1.1));
    let rpe = relative_pose_error(&reference, &estimate, RpeDelta::default()).unwrap();
    assert_eq!(rpe.stats.pairs, 10);
    assert_close("rmse", rpe.stats.rmse, 0.1, 1e-12);
    assert_close("std", rpe.stats.std, 0.0, 1e-12);
    let rpe = relative_pose_error(&reference, &estimate, RpeDelta::Frames(2)).unwrap();
    assert_eq!(rpe.pairs, vec![(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]);
    assert_close("max", rpe.stats.max, 0.2, 1e-12);
    // 11 poses, 1.1 m apart on the estimate: the path reaches 2 m at poses 2, 4, 6, 8, 10.
    assert_eq!(
        pairs_by_path(estimate.poses(), 2.0),
        vec![(2, 4), (4, 6), (6, 8), (8, 10)]
    );
    assert!(relative_pose_error(&reference, &estimate, RpeDelta::Meters(100.0)).is_err());
    assert!(relative_pose_error(&reference, &estimate, RpeDelta::Frames(0)).is_err());
}

/// A Sim(3)-transformed copy of the ground truth aligns back to zero error.
#[test]
fn sim3_alignment_undoes_a_scaled_copy() {
    let reference = read_kitti(evo_file("KITTI_00_gt.txt")).unwrap();
    let s = Similarity3::from_parts(
        Translation3::new(5.0, -2.0, 30.0),
        UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0),
        0.25,
    );
    let moved = apply_alignment(&reference, &s);
    let ate = absolute_trajectory_error(&reference, &moved, Alignment::Sim3).unwrap();
    assert!(ate.stats.max < 1e-9, "{:?}", ate.stats);
    assert_close("scale", ate.alignment.scaling(), 4.0, 1e-12);
    let ate = absolute_trajectory_error(&reference, &moved, Alignment::Se3).unwrap();
    assert!(ate.stats.rmse > 1.0); // without scale the copy cannot be matched
}

#[test]
fn umeyama_rejects_collinear_points() {
    let x: Vec<Point3<f64>> = (0..5).map(|k| Point3::new(k as f64, 0.0, 0.0)).collect();
    let msg = umeyama(&x, &x, false).unwrap_err().to_string();
    assert!(msg.contains("degenerate"), "{msg}");
}

fn point() -> impl Strategy<Value = Point3<f64>> {
    (-10.0..10.0, -10.0..10.0, -10.0..10.0).prop_map(|(x, y, z)| Point3::new(x, y, z))
}

proptest! {
    // Failing inputs are printed; there is no lib.rs beside tests/ to persist them next to.
    #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn umeyama_recovers_a_random_transform(
        points in proptest::collection::vec(point(), 4..30),
        axis_angle in (-3.0..3.0, -3.0..3.0, -3.0..3.0),
        t in (-100.0..100.0, -100.0..100.0, -100.0..100.0),
        scale in 0.01f64..100.0,
        with_scale: bool,
    ) {
        let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(axis_angle.0, axis_angle.1, axis_angle.2));
        let c = if with_scale { scale } else { 1.0 };
        let truth = Similarity3::from_parts(Translation3::new(t.0, t.1, t.2), rotation, c);
        let moved: Vec<Point3<f64>> = points.iter().map(|p| truth * p).collect();
        let fit = umeyama(&points, &moved, with_scale).unwrap();
        prop_assert!(fit.isometry.rotation.angle_to(&rotation) < 1e-9);
        prop_assert!((fit.isometry.translation.vector - truth.isometry.translation.vector).norm() < 1e-9);
        prop_assert!((fit.scaling() - c).abs() < 1e-9);
    }
}
