//! Trajectories (timestamped poses) and the readers of the KITTI, TUM and EuRoC formats.
//!
//! Every reader skips blank lines and lines starting with `#`, rejects NaN/inf, and names
//! the file and 1-based line of the first bad line. Formats: see
//! `shared/data/trajectories/README.md`.

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use nalgebra::{Isometry3, Matrix3, Point3, Quaternion, Rotation3, Translation3, UnitQuaternion};

use super::error::{EvalError, LineProblem};

/// A KITTI 3x3 block further than this from orthonormal (max |RᵀR - I|) is not a rotation
/// written with few digits but garbage. Real files deviate by ~1e-7 (7 printed digits).
const MAX_ROTATION_DEVIATION: f64 = 1e-2;

/// Below this norm a quaternion has no meaningful direction to normalize to.
const MIN_QUATERNION_NORM: f64 = 1e-6;

/// Poses with their timestamps (seconds). KITTI files have no stamps: the pose index is
/// used, unless a times file is given.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Trajectory {
    timestamps: Vec<f64>,
    poses: Vec<Isometry3<f64>>,
}

impl Trajectory {
    /// Fails when there are not as many timestamps as poses.
    pub fn new(timestamps: Vec<f64>, poses: Vec<Isometry3<f64>>) -> Result<Self, EvalError> {
        if timestamps.len() != poses.len() {
            return Err(EvalError::Inconsistent {
                timestamps: timestamps.len(),
                poses: poses.len(),
            });
        }
        Ok(Self { timestamps, poses })
    }

    /// Stamps the poses with their index 0, 1, 2, ... (KITTI convention: line k = image k).
    pub fn from_poses(poses: Vec<Isometry3<f64>>) -> Self {
        let timestamps = (0..poses.len()).map(|k| k as f64).collect();
        Self { timestamps, poses }
    }

    pub fn timestamps(&self) -> &[f64] {
        &self.timestamps
    }

    pub fn poses(&self) -> &[Isometry3<f64>] {
        &self.poses
    }

    pub fn positions(&self) -> Vec<Point3<f64>> {
        self.poses
            .iter()
            .map(|p| Point3::from(p.translation.vector))
            .collect()
    }

    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The same timestamps with other poses; callers map the poses one to one.
    pub(crate) fn with_poses(&self, poses: Vec<Isometry3<f64>>) -> Self {
        Self {
            timestamps: self.timestamps.clone(),
            poses,
        }
    }

    /// The sub-trajectory at `ids` (in that order). Callers pass indices they got from this
    /// trajectory, so they are in range.
    pub(crate) fn select(&self, ids: &[usize]) -> Self {
        Self {
            timestamps: ids.iter().map(|&i| self.timestamps[i]).collect(),
            poses: ids.iter().map(|&i| self.poses[i]).collect(),
        }
    }
}

/// The trajectory file formats [`read_trajectory`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TrajectoryFormat {
    /// 12 numbers per line: the first three rows of the 4x4 pose matrix, row-major.
    Kitti,
    /// `timestamp tx ty tz qx qy qz qw`.
    Tum,
    /// EuRoC/ASL csv: `timestamp_ns, p_x, p_y, p_z, q_w, q_x, q_y, q_z, ...`.
    Euroc,
}

impl TrajectoryFormat {
    /// Guesses the format: `.csv` is EuRoC; otherwise the first data line decides (commas:
    /// EuRoC, 12 fields: KITTI, 8 fields: TUM).
    pub fn from_path(path: impl AsRef<Path>) -> Result<Self, EvalError> {
        let path = path.as_ref();
        let is_csv = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
        if is_csv {
            return Ok(Self::Euroc);
        }
        let text = read_text(path)?;
        let first = data_lines(&text).next().map(|(_, l)| l);
        match first {
            Some(l) if l.contains(',') => Ok(Self::Euroc),
            Some(l) if l.split_whitespace().count() == 12 => Ok(Self::Kitti),
            Some(l) if l.split_whitespace().count() == 8 => Ok(Self::Tum),
            Some(_) => Err(EvalError::UnknownFormat { path: path.into() }),
            None => Err(EvalError::Empty { path: path.into() }),
        }
    }
}

impl fmt::Display for TrajectoryFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Kitti => "kitti",
            Self::Tum => "tum",
            Self::Euroc => "euroc",
        })
    }
}

impl FromStr for TrajectoryFormat {
    type Err = EvalError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "kitti" => Ok(Self::Kitti),
            "tum" => Ok(Self::Tum),
            "euroc" | "asl" => Ok(Self::Euroc),
            _ => Err(EvalError::InvalidParameter(format!(
                "unknown trajectory format {s:?} (expected kitti, tum or euroc)"
            ))),
        }
    }
}

/// Reads a trajectory file of the given format (KITTI without a times file).
pub fn read_trajectory(
    path: impl AsRef<Path>,
    format: TrajectoryFormat,
) -> Result<Trajectory, EvalError> {
    match format {
        TrajectoryFormat::Kitti => read_kitti(path),
        TrajectoryFormat::Tum => read_tum(path),
        TrajectoryFormat::Euroc => read_euroc(path),
    }
}

/// Reads a KITTI pose file; timestamps are the pose indices. The 3x3 blocks are projected
/// to the nearest rotation (files store them with 6-9 digits, so they are not orthonormal).
pub fn read_kitti(path: impl AsRef<Path>) -> Result<Trajectory, EvalError> {
    let path = path.as_ref();
    let text = read_text(path)?;
    let mut poses = Vec::new();
    for (line, content) in data_lines(&text) {
        let v: [f64; 12] = parse_numbers(content, &|p| line_error(path, line, p), "12")?;
        let m = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
        let rotation = nearest_rotation(&m).map_err(|p| line_error(path, line, p))?;
        poses.push(Isometry3::from_parts(
            Translation3::new(v[3], v[7], v[11]),
            rotation,
        ));
    }
    non_empty(path, Trajectory::from_poses(poses))
}

/// Reads a KITTI pose file and its times file (one time in seconds per line, as KITTI's
/// `times.txt`); both must hold as many entries.
pub fn read_kitti_with_times(
    path: impl AsRef<Path>,
    times_path: impl AsRef<Path>,
) -> Result<Trajectory, EvalError> {
    let trajectory = read_kitti(path)?;
    let times_path = times_path.as_ref();
    let text = read_text(times_path)?;
    let mut times = Vec::new();
    for (line, content) in data_lines(&text) {
        let [t]: [f64; 1] = parse_numbers(content, &|p| line_error(times_path, line, p), "1")?;
        times.push(t);
    }
    if times.len() != trajectory.len() {
        return Err(EvalError::TimesCount {
            path: times_path.into(),
            times: times.len(),
            poses: trajectory.len(),
        });
    }
    Trajectory::new(times, trajectory.poses)
}

/// Reads a TUM trajectory: `timestamp tx ty tz qx qy qz qw` (quaternion w last).
pub fn read_tum(path: impl AsRef<Path>) -> Result<Trajectory, EvalError> {
    let path = path.as_ref();
    let text = read_text(path)?;
    let (mut timestamps, mut poses) = (Vec::new(), Vec::new());
    for (line, content) in data_lines(&text) {
        let err = |p: LineProblem| line_error(path, line, p);
        let v: [f64; 8] = parse_numbers(content, &err, "8")?;
        let q = unit_quaternion(v[7], v[4], v[5], v[6]).map_err(err)?;
        timestamps.push(v[0]);
        poses.push(Isometry3::from_parts(
            Translation3::new(v[1], v[2], v[3]),
            q,
        ));
    }
    non_empty(path, Trajectory { timestamps, poses })
}

/// Reads a EuRoC/ASL csv: `timestamp_ns, p_x, p_y, p_z, q_w, q_x, q_y, q_z, ...` (w first,
/// columns after the 8th ignored); timestamps are converted from ns to s.
pub fn read_euroc(path: impl AsRef<Path>) -> Result<Trajectory, EvalError> {
    let path = path.as_ref();
    let text = read_text(path)?;
    let (mut timestamps, mut poses) = (Vec::new(), Vec::new());
    for (line, content) in data_lines(&text) {
        let err = |p: LineProblem| line_error(path, line, p);
        let fields: Vec<&str> = content.split(',').map(str::trim).collect();
        if fields.len() < 8 {
            return Err(err(LineProblem::FieldCount {
                expected: "at least 8".into(),
                found: fields.len(),
            }));
        }
        let stamp = nanoseconds_to_seconds(fields[0]).map_err(err)?;
        let mut v = [0.0; 7];
        for (k, slot) in v.iter_mut().enumerate() {
            *slot = parse_number(fields[k + 1], k + 2).map_err(err)?;
        }
        let q = unit_quaternion(v[3], v[4], v[5], v[6]).map_err(err)?;
        timestamps.push(stamp);
        poses.push(Isometry3::from_parts(
            Translation3::new(v[0], v[1], v[2]),
            q,
        ));
    }
    non_empty(path, Trajectory { timestamps, poses })
}

fn read_text(path: &Path) -> Result<String, EvalError> {
    std::fs::read_to_string(path).map_err(|source| EvalError::Io {
        path: path.into(),
        source,
    })
}

/// (1-based line number, trimmed content) of every line that is neither blank nor a comment.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    // Some tools write a UTF-8 byte-order mark; evo skips it too.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    text.lines()
        .enumerate()
        .map(|(k, l)| (k + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn line_error(path: &Path, line: usize, problem: LineProblem) -> EvalError {
    EvalError::Line {
        path: PathBuf::from(path),
        line,
        problem,
    }
}

fn non_empty(path: &Path, trajectory: Trajectory) -> Result<Trajectory, EvalError> {
    if trajectory.is_empty() {
        return Err(EvalError::Empty { path: path.into() });
    }
    Ok(trajectory)
}

/// Exactly `N` whitespace-separated finite numbers.
fn parse_numbers<const N: usize>(
    content: &str,
    err: &dyn Fn(LineProblem) -> EvalError,
    expected: &str,
) -> Result<[f64; N], EvalError> {
    let fields: Vec<&str> = content.split_whitespace().collect();
    if fields.len() != N {
        return Err(err(LineProblem::FieldCount {
            expected: expected.into(),
            found: fields.len(),
        }));
    }
    let mut out = [0.0; N];
    for (k, (slot, text)) in out.iter_mut().zip(&fields).enumerate() {
        *slot = parse_number(text, k + 1).map_err(err)?;
    }
    Ok(out)
}

/// `field` is 1-based, for the message.
fn parse_number(text: &str, field: usize) -> Result<f64, LineProblem> {
    let value: f64 = text.parse().map_err(|_| LineProblem::Unparsable {
        field,
        text: text.into(),
    })?;
    if !value.is_finite() {
        return Err(LineProblem::NotFinite {
            field,
            text: text.into(),
        });
    }
    Ok(value)
}

/// EuRoC stamps are integer nanoseconds around 1.4e18, beyond f64's 2^53: split them into
/// seconds and nanoseconds before converting so no digit is lost. Non-integer text is
/// accepted as a float number of nanoseconds.
fn nanoseconds_to_seconds(text: &str) -> Result<f64, LineProblem> {
    if let Ok(ns) = text.parse::<u64>() {
        const NS_PER_S: u64 = 1_000_000_000;
        return Ok((ns / NS_PER_S) as f64 + (ns % NS_PER_S) as f64 * 1e-9);
    }
    Ok(parse_number(text, 1)? * 1e-9)
}

fn unit_quaternion(w: f64, x: f64, y: f64, z: f64) -> Result<UnitQuaternion<f64>, LineProblem> {
    let q = Quaternion::new(w, x, y, z);
    let norm = q.norm();
    if norm < MIN_QUATERNION_NORM {
        return Err(LineProblem::Quaternion { norm });
    }
    Ok(UnitQuaternion::new_normalize(q))
}

/// The rotation closest to `m` in the Frobenius norm, `U diag(1, 1, det(UVᵀ)) Vᵀ` from the
/// SVD `m = U Σ Vᵀ`; rejects blocks that are far from any rotation.
fn nearest_rotation(m: &Matrix3<f64>) -> Result<UnitQuaternion<f64>, LineProblem> {
    let deviation = (m.transpose() * m - Matrix3::identity()).abs().max();
    let det = m.determinant();
    if deviation > MAX_ROTATION_DEVIATION || det <= 0.0 {
        return Err(LineProblem::NotRotation { deviation, det });
    }
    let not_rotation = LineProblem::NotRotation { deviation, det };
    let svd = nalgebra::SVD::try_new(*m, true, true, f64::EPSILON, 100)
        .ok_or_else(|| not_rotation.clone())?;
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(not_rotation);
    };
    let mut s = Matrix3::identity();
    s[(2, 2)] = (u * v_t).determinant().signum();
    let r = Rotation3::from_matrix_unchecked(u * s * v_t);
    Ok(UnitQuaternion::from_rotation_matrix(&r))
}
