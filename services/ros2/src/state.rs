//! A robot's state folder as the back-end leaves it (`<state_dir>/<robot>/`, rewritten
//! atomically file by file every `write_every_s`), read: `keyframes.csv` (keyframe index →
//! stamp), `odometry.tum`, `team_estimate.tum`, the inter-robot closures of `graph.g2o` and
//! those PCM rejected (`backend.json`). Every error names the file (and the line).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use doorslam_geometry::key;
use doorslam_ros2_wire::msgs::{Point, Pose, Quaternion};
use doorslam_ros2_wire::WireError;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// Failures of reading a state folder or writing a record; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {reason}")]
    Input { path: PathBuf, reason: String },
    #[error("{path}: {reason}")]
    Output { path: PathBuf, reason: String },
    #[error("{0}: no robot folders (sub-folders with a keyframes.csv)")]
    NoRobots(PathBuf),
    #[error("ROS message: {0}")]
    Wire(#[from] WireError),
}

pub(crate) fn input(path: &Path, reason: impl std::fmt::Display) -> RecordError {
    RecordError::Input {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

/// One keyframe pose of a TUM file: exact stamp in ns, position, quaternion (x y z w) as
/// written.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TumPose {
    pub stamp_ns: i64,
    pub p: [f64; 3],
    pub q: [f64; 4],
}

impl TumPose {
    pub fn pose(&self) -> Pose {
        Pose {
            position: self.point(),
            orientation: Quaternion {
                x: self.q[0],
                y: self.q[1],
                z: self.q[2],
                w: self.q[3],
            },
        }
    }

    pub fn point(&self) -> Point {
        Point {
            x: self.p[0],
            y: self.p[1],
            z: self.p[2],
        }
    }

    pub fn isometry(&self) -> Isometry3<f64> {
        let q = nalgebra::Quaternion::new(self.q[3], self.q[0], self.q[1], self.q[2]);
        Isometry3::from_parts(
            Translation3::new(self.p[0], self.p[1], self.p[2]),
            UnitQuaternion::from_quaternion(q),
        )
    }
}

/// `sec.fraction` → ns, exactly (no float on the way).
pub(crate) fn parse_stamp(s: &str) -> Option<i64> {
    let (sec, frac) = s.split_once('.').unwrap_or((s, ""));
    if frac.len() > 9 || !frac.chars().all(|c| c.is_ascii_digit()) {
        return None;
    }
    let sec: i64 = sec.parse().ok()?;
    let frac: i64 = if frac.is_empty() {
        0
    } else {
        format!("{frac:0<9}").parse().ok()?
    };
    sec.checked_mul(1_000_000_000)?.checked_add(frac)
}

/// Reads a TUM trajectory (`stamp x y z qx qy qz qw`, `#` comments).
pub fn read_tum(path: &Path) -> Result<Vec<TumPose>, RecordError> {
    let text = std::fs::read_to_string(path).map_err(|e| input(path, e))?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = || {
            input(
                path,
                format!("line {}: not `stamp x y z qx qy qz qw`", i + 1),
            )
        };
        let mut it = line.split_whitespace();
        let stamp_ns = it.next().and_then(parse_stamp).ok_or_else(bad)?;
        let v: Vec<f64> = it
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|_| bad())?;
        if v.len() != 7 || v.iter().any(|x| !x.is_finite()) {
            return Err(bad());
        }
        out.push(TumPose {
            stamp_ns,
            p: [v[0], v[1], v[2]],
            q: [v[3], v[4], v[5], v[6]],
        });
    }
    Ok(out)
}

/// `keyframes.csv`: keyframe index → stamp in ns.
fn read_keyframes(path: &Path) -> Result<BTreeMap<u64, i64>, RecordError> {
    let text = std::fs::read_to_string(path).map_err(|e| input(path, e))?;
    let mut out = BTreeMap::new();
    for (i, line) in text.lines().enumerate().skip(1) {
        if line.trim().is_empty() {
            continue;
        }
        let bad = || input(path, format!("line {}: not `id,stamp_ns`", i + 1));
        let (id, stamp) = line.split_once(',').ok_or_else(bad)?;
        out.insert(
            id.trim().parse().map_err(|_| bad())?,
            stamp.trim().parse().map_err(|_| bad())?,
        );
    }
    Ok(out)
}

/// An inter-robot closure of `graph.g2o`: keys `a`, `b` and the measured pose of `b` in
/// `a`'s frame (`Z = Xa⁻¹ Xb`).
#[derive(Debug, Clone, PartialEq)]
pub struct Closure {
    pub a: u64,
    pub b: u64,
    pub measured: Isometry3<f64>,
}

/// One robot's files, read.
#[derive(Debug, Clone)]
pub struct RobotFiles {
    pub name: String,
    pub dir: PathBuf,
    pub keyframes: BTreeMap<u64, i64>,
    pub odometry: Vec<TumPose>,
    /// Empty while the robot has not joined a team (no `team_estimate.tum` yet).
    pub team: Vec<TumPose>,
}

impl RobotFiles {
    /// Reads `dir/keyframes.csv`, `odometry.tum` and, when there, `team_estimate.tum`.
    pub fn read(dir: &Path, name: &str) -> Result<Self, RecordError> {
        let keyframes = read_keyframes(&dir.join("keyframes.csv"))?;
        let odometry = read_tum(&dir.join("odometry.tum"))?;
        // A robot that never joined a team has no team estimate.
        let team_path = dir.join("team_estimate.tum");
        let team = if team_path.is_file() {
            read_tum(&team_path)?
        } else {
            Vec::new()
        };
        Ok(Self {
            name: name.to_string(),
            dir: dir.to_path_buf(),
            keyframes,
            odometry,
            team,
        })
    }

    /// The team pose of keyframe `index`.
    pub fn team_at(&self, index: u64) -> Option<&TumPose> {
        let stamp = self.keyframes.get(&index)?;
        self.team.iter().find(|p| p.stamp_ns == *stamp)
    }

    /// The odometry pose of the keyframe stamped `stamp_ns`.
    pub fn odometry_at(&self, stamp_ns: i64) -> Option<&TumPose> {
        self.odometry.iter().find(|o| o.stamp_ns == stamp_ns)
    }

    /// `team` → `<robot>/odom` at the team pose `p`: `T_team_kf · T_odom_kf⁻¹` of the same
    /// keyframe, when its odometry pose is known.
    pub fn team_to_odometry(&self, p: &TumPose) -> Option<Isometry3<f64>> {
        let o = self.odometry_at(p.stamp_ns)?;
        Some(p.isometry() * o.isometry().inverse())
    }

    /// Closures PCM rejected ([`rejected`]) of this folder.
    pub fn rejected(&self) -> Result<Vec<(String, String)>, RecordError> {
        rejected(&self.dir)
    }

    /// Inter-robot closures ([`closures`]) of this folder.
    pub fn closures(&self) -> Result<Vec<Closure>, RecordError> {
        closures(&self.dir)
    }
}

/// Rejected closures of a robot's `backend.json` (`team.rejected_closures`) as key labels,
/// both orders.
pub fn rejected(dir: &Path) -> Result<Vec<(String, String)>, RecordError> {
    let path = dir.join("backend.json");
    if !path.is_file() {
        return Ok(Vec::new());
    }
    let text = std::fs::read_to_string(&path).map_err(|e| input(&path, e))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| input(&path, e))?;
    let mut out = Vec::new();
    for pair in v
        .pointer("/team/rejected_closures")
        .and_then(|x| x.as_array())
        .into_iter()
        .flatten()
    {
        if let (Some(a), Some(b)) = (
            pair.get(0).and_then(|x| x.as_str()),
            pair.get(1).and_then(|x| x.as_str()),
        ) {
            out.push((a.to_string(), b.to_string()));
            out.push((b.to_string(), a.to_string()));
        }
    }
    Ok(out)
}

/// A robot's inter-robot closures from its `graph.g2o` (none without the file).
pub fn closures(dir: &Path) -> Result<Vec<Closure>, RecordError> {
    let path = dir.join("graph.g2o");
    if !path.is_file() {
        return Ok(Vec::new());
    }
    let (graph, _) =
        doorslam_backend::g2o::merge_g2o_files(std::slice::from_ref(&path), Default::default())
            .map_err(|e| input(&path, e))?;
    let keys = graph.keys();
    Ok(graph
        .edges()
        .iter()
        .map(|e| Closure {
            a: keys[e.i],
            b: keys[e.j],
            measured: e.measured,
        })
        .filter(|c| {
            key::robot(c.a).is_some()
                && key::robot(c.b).is_some()
                && key::robot(c.a) != key::robot(c.b)
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_are_parsed_exactly() {
        assert_eq!(parse_stamp("12.000000345"), Some(12_000_000_345));
        assert_eq!(parse_stamp("12.5"), Some(12_500_000_000));
        assert_eq!(parse_stamp("3"), Some(3_000_000_000));
        assert_eq!(parse_stamp("1.0000000001"), None);
        assert_eq!(parse_stamp("x.1"), None);
    }

    #[test]
    fn a_bad_tum_line_is_an_error_naming_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.tum");
        std::fs::write(&p, "# c\n1.0 0 0 0 0 0 0 1\n2.0 0 0\n").unwrap();
        let e = read_tum(&p).unwrap_err().to_string();
        assert!(e.contains("x.tum") && e.contains("line 3"), "{e}");
    }
}
