//! Writing a team flight to disk: one KITTI odometry folder per robot, plus the team's
//! events, closure candidates and a description of the world.
//!
//! ```text
//! <dir>/world.txt       seed, resolution, intrinsics, baseline, radio range, robots, frames,
//!                       camera model and its settings
//! <dir>/events.csv      time_s,event,robot_a,robot_b        (enter / leave)
//! <dir>/closures.csv    robot_a,frame_a,robot_b,frame_b,kind (overlap / aliased)
//! <dir>/revisits.csv    robot,frame,earlier_frame,kind        (a drone's own: overlap /
//!                       aliased with its frame at least 20 s earlier)
//! <dir>/exposures.csv   robot,frame,time_s,exposure_ms,gain,light,brightness,shade
//!                       (realistic camera only: what the auto-exposure did per frame)
//! <dir>/<r>/image_0/NNNNNN.png, image_1/NNNNNN.png, times.txt, calib.txt,
//!           poses.txt (KITTI, left camera-to-world), groundtruth.tum (t x y z qx qy qz qw)
//! ```
//! Text files come first, so a bad folder fails before any rendering.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use nalgebra::Isometry3;
use rayon::prelude::*;

use crate::image::GrayImage;
use crate::sensor::CameraModel;
use crate::world::World;

use super::imaging::TeamCamera;
use super::{ClosureKind, FlightError, TeamFlight};

/// Called after each rendered frame with (frames done, frames in total), from any thread.
pub type Progress<'a> = &'a (dyn Fn(usize, usize) + Sync);

/// A robot's folder and key name: `a` for robot 0 (GTSAM symbol convention).
pub fn robot_name(robot: usize) -> char {
    char::from(b'a' + robot.min(25) as u8)
}

fn io_error(path: &Path) -> impl Fn(std::io::Error) -> FlightError + '_ {
    move |source| FlightError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn write_text(path: PathBuf, text: &str) -> Result<(), FlightError> {
    std::fs::write(&path, text).map_err(io_error(&path))
}

fn create_dir(path: &Path) -> Result<(), FlightError> {
    std::fs::create_dir_all(path).map_err(io_error(path))
}

/// KITTI pose line: row-major [R | t]; `{:e}` is the shortest exact text of an f64.
fn kitti_line(p: &Isometry3<f64>) -> String {
    let m = p.rotation.to_rotation_matrix().into_inner();
    let t = p.translation.vector;
    let mut v = Vec::with_capacity(12);
    for row in 0..3 {
        v.extend([m[(row, 0)], m[(row, 1)], m[(row, 2)], t[row]]);
    }
    join(&v)
}

fn join(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x:e}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// File names of frame `k`: KITTI's six-digit index.
fn frame_file(k: usize) -> String {
    format!("{k:06}.png")
}

/// Refuses image folders holding PNGs this run would not overwrite: a replay would mix
/// two runs (and `times.txt` would no longer match the image count).
fn check_no_stale_frames(dir: &Path, frames: usize) -> Result<(), FlightError> {
    let entries = std::fs::read_dir(dir).map_err(io_error(dir))?;
    let stale = entries
        .filter_map(|e| e.ok())
        .filter(|e| {
            let name = e.file_name().to_string_lossy().to_ascii_lowercase();
            name.ends_with(".png")
                && !(name.len() == 10 && name[..6].parse::<usize>().is_ok_and(|k| k < frames))
        })
        .count();
    if stale > 0 {
        return Err(FlightError::StaleFrames {
            path: dir.to_path_buf(),
            count: stale,
        });
    }
    Ok(())
}

fn world_description(world: &World, team: &TeamFlight, model: &CameraModel) -> String {
    let (c, cfg) = (&team.camera, &team.config);
    let mut s =
        String::from("# doorslam sim world: synthetic stereo town, one KITTI sequence per robot\n");
    let lines = [
        format!("seed = {}", cfg.seed),
        format!("world_seed = {}", world.seed()),
        format!("resolution = \"{}x{}\"", c.width(), c.height()),
        format!("fx = {:e}", c.fx()),
        format!("fy = {:e}", c.fy()),
        format!("cx = {:e}", c.cx()),
        format!("cy = {:e}", c.cy()),
        format!("baseline_m = {:e}", c.baseline()),
        format!("radio_range_m = {:e}", cfg.radio_range_m),
        format!("robots = {}", cfg.robots),
        format!("frames = {}", cfg.frames),
        format!("rate_hz = {:e}", cfg.rate_hz),
        format!("speed_mps = {:e}", cfg.speed_mps),
        format!("min_altitude_m = {:e}", cfg.min_altitude_m),
        format!("max_altitude_m = {:e}", cfg.max_altitude_m),
        format!("pitch_down_deg = {:e}", cfg.pitch_down_deg),
        format!("plan = \"{}\"", cfg.plan.as_str()),
        format!("overlap_candidates = {}", team.count(ClosureKind::Overlap)),
        format!("aliased_candidates = {}", team.count(ClosureKind::Aliased)),
        format!(
            "own_overlap_candidates = {}",
            team.own
                .iter()
                .filter(|c| c.kind == ClosureKind::Overlap)
                .count()
        ),
        format!(
            "own_aliased_candidates = {}",
            team.own
                .iter()
                .filter(|c| c.kind == ClosureKind::Aliased)
                .count()
        ),
        format!("rendezvous_events = {}", team.events.len()),
    ];
    for line in lines {
        let _ = writeln!(s, "{line}");
    }
    let _ = writeln!(s, "camera = \"{}\"", model.name());
    if let CameraModel::Realistic(sensor) = model {
        for line in sensor.describe() {
            let _ = writeln!(s, "{line}");
        }
    }
    for (r, f) in team.flights.iter().enumerate() {
        let _ = writeln!(
            s,
            "role_{} = \"{}, {:.2} m/s\"",
            robot_name(r),
            f.role,
            f.speed_mps
        );
    }
    // Stretches of each flight over places others saw before, and over its own.
    let counts = super::overlap_counts(&team.flights);
    for r in 0..team.flights.len() {
        let others: Vec<String> = (0..team.flights.len())
            .filter(|&q| q != r)
            .map(|q| format!("{} {}", robot_name(q), counts.revisits[r][q]))
            .collect();
        let _ = writeln!(
            s,
            "revisits_{} = \"own {}, {}; crossings {}\"",
            robot_name(r),
            counts.own_revisited(r),
            others.join(", "),
            counts.crossings[r].len()
        );
    }
    s
}

/// KITTI calibration: projection matrices of the rectified left (P0) and right (P1) cameras.
fn calibration(team: &TeamFlight) -> String {
    let c = &team.camera;
    let p = |tx: f64| {
        let v = [
            c.fx(),
            0.0,
            c.cx(),
            tx,
            0.0,
            c.fy(),
            c.cy(),
            0.0,
            0.0,
            0.0,
            1.0,
            0.0,
        ];
        v.iter()
            .map(|x| format!("{x:.12e}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    format!("P0: {}\nP1: {}\n", p(0.0), p(-c.fx() * c.baseline()))
}

/// Writes everything (see the module docs) into `dir`, creating folders as needed, the
/// images through `model`. Frames render in parallel; `progress` hears about each one.
pub fn write_team(
    dir: &Path,
    world: &World,
    team: &TeamFlight,
    model: &CameraModel,
    progress: Progress<'_>,
) -> Result<(), FlightError> {
    let camera = TeamCamera::new(world, team, *model)?;
    create_dir(dir)?;
    let frames = team.config.frames;
    for (r, flight) in team.flights.iter().enumerate() {
        let root = dir.join(robot_name(r).to_string());
        for sub in ["image_0", "image_1"] {
            create_dir(&root.join(sub))?;
            check_no_stale_frames(&root.join(sub), frames)?;
        }
        let mut times = String::new();
        let mut kitti = String::new();
        let mut tum = String::from("# t x y z qx qy qz qw\n");
        for (t, p) in flight.times.iter().zip(&flight.poses) {
            let (x, q) = (p.translation.vector, p.rotation.quaternion());
            let _ = writeln!(times, "{t:.9}"); // nanoseconds, as replay stamps frames
            let _ = writeln!(kitti, "{}", kitti_line(p));
            let _ = writeln!(tum, "{}", join(&[*t, x.x, x.y, x.z, q.i, q.j, q.k, q.w]));
        }
        write_text(root.join("times.txt"), &times)?;
        write_text(root.join("poses.txt"), &kitti)?;
        write_text(root.join("groundtruth.tum"), &tum)?;
        write_text(root.join("calib.txt"), &calibration(team))?;
    }
    let mut events = String::from("time_s,event,robot_a,robot_b\n");
    for e in &team.events {
        let _ = writeln!(
            events,
            "{:.6},{},{},{}",
            e.time_s,
            e.kind.as_str(),
            robot_name(e.robot_a),
            robot_name(e.robot_b)
        );
    }
    write_text(dir.join("events.csv"), &events)?;
    let mut closures = String::from("robot_a,frame_a,robot_b,frame_b,kind\n");
    for c in &team.closures {
        let _ = writeln!(
            closures,
            "{},{},{},{},{}",
            robot_name(c.robot_a),
            c.frame_a,
            robot_name(c.robot_b),
            c.frame_b,
            c.kind.as_str()
        );
    }
    write_text(dir.join("closures.csv"), &closures)?;
    let mut own = String::from("robot,frame,earlier_frame,kind\n");
    for c in &team.own {
        let _ = writeln!(
            own,
            "{},{},{},{}",
            robot_name(c.robot_a),
            c.frame_a,
            c.frame_b,
            c.kind.as_str()
        );
    }
    write_text(dir.join("revisits.csv"), &own)?;
    write_text(
        dir.join("world.txt"),
        &world_description(world, team, model),
    )?;
    let exposures_csv = dir.join("exposures.csv");
    if matches!(model, CameraModel::Realistic(_)) {
        write_text(exposures_csv, &exposures(team, &camera))?;
    } else if exposures_csv.exists() {
        // An earlier realistic run's exposures would describe other images.
        std::fs::remove_file(&exposures_csv).map_err(io_error(&exposures_csv))?;
    }

    let jobs: Vec<(usize, usize)> = team
        .flights
        .iter()
        .enumerate()
        .flat_map(|(r, f)| (0..f.poses.len()).map(move |k| (r, k)))
        .collect();
    let done = AtomicUsize::new(0);
    jobs.par_iter().try_for_each(|&(r, k)| {
        let Some(pair) = camera.render(r, k)? else {
            return Ok(());
        };
        let root = dir.join(robot_name(r).to_string());
        write_png(&root.join("image_0").join(frame_file(k)), &pair.left)?;
        write_png(&root.join("image_1").join(frame_file(k)), &pair.right)?;
        progress(done.fetch_add(1, Ordering::Relaxed) + 1, jobs.len());
        Ok(())
    })
}

/// `exposures.csv`: the realistic camera's exposure of every frame.
fn exposures(team: &TeamFlight, camera: &TeamCamera<'_>) -> String {
    let mut s = String::from("robot,frame,time_s,exposure_ms,gain,light,brightness,shade\n");
    for (r, flight) in team.flights.iter().enumerate() {
        for (k, t) in flight.times.iter().enumerate() {
            if let Some(e) = camera.exposure(r, k) {
                let _ = writeln!(
                    s,
                    "{},{k},{t:.6},{:.4},{:.4},{:.5},{:.5},{}",
                    robot_name(r),
                    e.exposure_s * 1e3,
                    e.gain,
                    e.light,
                    e.brightness,
                    u8::from(e.shade)
                );
            }
        }
    }
    s
}

/// 8-bit grayscale PNG with fast compression: rendering, not zlib, should dominate.
fn write_png(path: &Path, image: &GrayImage) -> Result<(), FlightError> {
    let io = io_error(path);
    let png_err = |e: png::EncodingError| FlightError::Io {
        path: path.to_path_buf(),
        source: std::io::Error::other(e),
    };
    let file = std::fs::File::create(path).map_err(&io)?;
    let mut encoder =
        png::Encoder::new(std::io::BufWriter::new(file), image.width(), image.height());
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder.write_header().map_err(png_err)?;
    writer.write_image_data(image.pixels()).map_err(png_err)?;
    writer.finish().map_err(png_err)
}
