//! Writing a simulated team to disk: g2o graph, ground truth (KITTI and TUM), labels.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use doorslam_backend::{write_g2o, Graph};
use doorslam_geometry::key;
use nalgebra::Isometry3;

use super::{SimError, SimulatedTeam};

/// The ground-truth file name of a robot: `gt_a.txt` / `gt_a.tum` for robot 0.
pub fn truth_file_name(robot: usize, extension: &str) -> String {
    let c = u8::try_from(robot)
        .ok()
        .and_then(|r| doorslam_geometry::key::robot_char(r).ok())
        .unwrap_or('?');
    format!("gt_{c}.{extension}")
}

fn io_error(path: &Path) -> impl Fn(std::io::Error) -> SimError + '_ {
    move |source| SimError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Creates `path` and writes it with `body`, mapping every I/O failure to the path.
fn write_file(
    path: PathBuf,
    body: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<(), SimError> {
    let err = io_error(&path);
    let mut w = BufWriter::new(File::create(&path).map_err(&err)?);
    body(&mut w).and_then(|()| w.flush()).map_err(err)
}

/// KITTI: the row-major 3×4 [R | t], 12 numbers a line. `{:e}` is the shortest text that
/// parses back to the same f64, so the files are exact and byte-stable.
fn kitti_line(p: &Isometry3<f64>) -> String {
    let (r, t) = (p.rotation.to_rotation_matrix(), p.translation.vector);
    let m = r.matrix();
    let mut v = Vec::with_capacity(12);
    for row in 0..3 {
        for col in 0..3 {
            v.push(m[(row, col)]);
        }
        v.push(t[row]);
    }
    v.iter()
        .map(|x| format!("{x:e}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// TUM: `t x y z qx qy qz qw`.
fn tum_line(time: f64, p: &Isometry3<f64>) -> String {
    let (t, q) = (p.translation.vector, p.rotation.quaternion());
    [time, t.x, t.y, t.z, q.i, q.j, q.k, q.w]
        .iter()
        .map(|x| format!("{x:e}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Writes the team into `dir` (created if missing):
/// - `graph.g2o`: the noisy graph with its initial estimate (multi-robot keys);
/// - `gt_<robot>.txt` (KITTI) and `gt_<robot>.tum` (TUM, time = pose index in seconds);
/// - `labels.txt`: one line per closure, in graph edge order,
///   `key_a key_b robot_a index_a robot_b index_b label group`, robots as 0-based indices
///   (0 = 'a'), label 1 inlier / 0 outlier, group -1 unless a correlated outlier.
pub fn write_dataset(team: &SimulatedTeam, dir: &Path) -> Result<(), SimError> {
    std::fs::create_dir_all(dir).map_err(io_error(dir))?;
    let g2o = dir.join("graph.g2o");
    write_g2o(&Graph::Se3(team.graph.clone()), &g2o)
        .map_err(|source| SimError::Graph { path: g2o, source })?;
    for (robot, poses) in team.truth.iter().enumerate() {
        write_file(dir.join(truth_file_name(robot, "txt")), |w| {
            poses
                .iter()
                .try_for_each(|p| writeln!(w, "{}", kitti_line(p)))
        })?;
        write_file(dir.join(truth_file_name(robot, "tum")), |w| {
            writeln!(w, "# t x y z qx qy qz qw")?;
            poses
                .iter()
                .enumerate()
                .try_for_each(|(k, p)| writeln!(w, "{}", tum_line(k as f64, p)))
        })?;
    }
    write_file(dir.join("labels.txt"), |w| {
        writeln!(
            w,
            "# key_a key_b robot_a index_a robot_b index_b label group"
        )?;
        writeln!(w, "# {}", team.config_line())?;
        for c in &team.closures {
            let robot = |k: u64| key::robot(k).map_or(-1, i64::from);
            writeln!(
                w,
                "{} {} {} {} {} {} {} {}",
                c.key_a,
                c.key_b,
                robot(c.key_a),
                key::index(c.key_a),
                robot(c.key_b),
                key::index(c.key_b),
                u8::from(c.inlier),
                c.group.map_or(-1, |g| g as i64),
            )?;
        }
        Ok(())
    })
}
