//! `run.mcap`: a finished run folder as ROS 2 messages in an MCAP file (`ros2msg` schemas,
//! `cdr` payloads: what `ros2 bag record` writes), readable by `ros2 bag play`, Foxglove,
//! Lichtblick and Rerun.
//!
//! What a run folder holds and what becomes of it (per robot folder `<out>/<robot>/`,
//! every sub-folder with a `keyframes.csv`):
//! - `odometry.tum` → `/<robot>/odometry_path` (`nav_msgs/msg/Path`, frame `<robot>/odom`),
//!   growing keyframe by keyframe;
//! - `team_estimate.tum` → `/<robot>/team_path` (frame `team`), growing the same way and
//!   ending with the whole file, `/<robot>/pose` (`geometry_msgs/msg/PoseStamped`) at every
//!   keyframe and `/tf` (`team` → `<robot>/odom`, the team pose times the inverse odometry
//!   pose of the same keyframe). The files hold the back-end's final estimate, so the
//!   growing team path is the final estimate's prefix, not what the robot believed then;
//! - `graph.g2o` (its inter-robot closures) and `backend.json` (those PCM rejected) →
//!   `/<robot>/loop_closures` (`visualization_msgs/msg/MarkerArray`, two `LINE_LIST`s
//!   between the keyframes' team positions: kept green, rejected red), once at the end;
//! - `ledger.json` → `/team/bandwidth` (`diagnostic_msgs/msg/DiagnosticArray`, one status
//!   per robot, its link's bytes and messages per peer, direction and kind), once at the
//!   end.
//!
//! Times are the keyframes' stamps (the robots' replay clock), log and publish time alike.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use doorslam_geometry::key;
use doorslam_ros2_wire::msgs::{
    ColorRgba, DiagnosticArray, DiagnosticStatus, Header, KeyValue, Marker, MarkerArray,
    Path as RosPath, Point, Pose, PoseStamped, Quaternion, TfMessage, Time, Transform,
    TransformStamped, Vector3,
};
use doorslam_ros2_wire::{RosMessage, TypeDef, WireError};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// The frame every robot's team estimate is in.
pub const TEAM_FRAME: &str = "team";
/// At most this many growing-path messages per robot and path (plus the final one): a
/// path message holds every keyframe so far, so one per keyframe would grow the file with
/// the square of the keyframes.
pub const PATH_MESSAGES: usize = 50;

/// Failures of the record; each names the file.
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

fn input(path: &Path, reason: impl std::fmt::Display) -> RecordError {
    RecordError::Input {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

/// What was written.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RecordSummary {
    pub path: PathBuf,
    pub robots: Vec<String>,
    /// Messages per topic.
    pub messages: BTreeMap<String, u64>,
    pub bytes: u64,
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
    fn pose(&self) -> Pose {
        Pose {
            position: Point {
                x: self.p[0],
                y: self.p[1],
                z: self.p[2],
            },
            orientation: Quaternion {
                x: self.q[0],
                y: self.q[1],
                z: self.q[2],
                w: self.q[3],
            },
        }
    }

    fn isometry(&self) -> Isometry3<f64> {
        let q = nalgebra::Quaternion::new(self.q[3], self.q[0], self.q[1], self.q[2]);
        Isometry3::from_parts(
            Translation3::new(self.p[0], self.p[1], self.p[2]),
            UnitQuaternion::from_quaternion(q),
        )
    }
}

/// `sec.fraction` → ns, exactly (no float on the way).
fn parse_stamp(s: &str) -> Option<i64> {
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

/// One robot's files, read.
struct Robot {
    name: String,
    dir: PathBuf,
    keyframes: BTreeMap<u64, i64>,
    odometry: Vec<TumPose>,
    team: Vec<TumPose>,
}

impl Robot {
    fn read(dir: &Path, name: &str) -> Result<Self, RecordError> {
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

    fn team_at(&self, index: u64) -> Option<&TumPose> {
        let stamp = self.keyframes.get(&index)?;
        self.team.iter().find(|p| p.stamp_ns == *stamp)
    }
}

fn stamp(ns: i64) -> Time {
    Time::from_nanos(ns)
}

fn path_msg(frame: &str, poses: &[TumPose]) -> RosPath {
    RosPath {
        header: Header {
            stamp: stamp(poses.last().map_or(0, |p| p.stamp_ns)),
            frame_id: frame.to_string(),
        },
        poses: poses
            .iter()
            .map(|p| PoseStamped {
                header: Header {
                    stamp: stamp(p.stamp_ns),
                    frame_id: frame.to_string(),
                },
                pose: p.pose(),
            })
            .collect(),
    }
}

/// Path prefixes to publish: about `PATH_MESSAGES` evenly spaced ends, and the whole.
fn path_ends(n: usize) -> Vec<usize> {
    if n == 0 {
        return Vec::new();
    }
    let step = n.div_ceil(PATH_MESSAGES).max(1);
    let mut ends: Vec<usize> = (1..=n).filter(|e| e % step == 0).collect();
    if ends.last() != Some(&n) {
        ends.push(n);
    }
    ends
}

/// One encoded message of a run: when, on which topic, of which robot (whose node
/// publishes it live), its type and its CDR payload.
#[derive(Debug, Clone)]
pub struct RosSample {
    pub time_ns: i64,
    pub topic: String,
    pub robot: String,
    pub ty: &'static TypeDef,
    pub cdr: Vec<u8>,
}

/// The messages of a run, in time order.
#[derive(Debug, Clone, Default)]
pub struct RunMessages {
    pub robots: Vec<String>,
    pub samples: Vec<RosSample>,
}

impl RunMessages {
    fn push<M: RosMessage>(
        &mut self,
        robot: &str,
        topic: &str,
        time_ns: i64,
        msg: &M,
    ) -> Result<(), RecordError> {
        self.samples.push(RosSample {
            time_ns,
            topic: topic.to_string(),
            robot: robot.to_string(),
            ty: M::TYPE,
            cdr: msg.to_cdr()?,
        });
        Ok(())
    }
}

fn write_mcap(messages: &RunMessages, out: &Path) -> Result<RecordSummary, RecordError> {
    let out_err = |e: &dyn std::fmt::Display| RecordError::Output {
        path: out.to_path_buf(),
        reason: e.to_string(),
    };
    let file = File::create(out).map_err(|e| out_err(&e))?;
    let mut writer = mcap::WriteOptions::new()
        .compression(None)
        .profile("ros2")
        .create(BufWriter::new(file))
        .map_err(|e| out_err(&e))?;
    let mut schemas: BTreeMap<&'static str, u16> = BTreeMap::new();
    let mut channels: BTreeMap<&str, (u16, u32)> = BTreeMap::new();
    let mut summary = RecordSummary {
        path: out.to_path_buf(),
        robots: messages.robots.clone(),
        ..Default::default()
    };
    for m in &messages.samples {
        let schema = match schemas.get(m.ty.name) {
            Some(&id) => id,
            None => {
                let id = writer
                    .add_schema(m.ty.name, "ros2msg", m.ty.schema_text().as_bytes())
                    .map_err(|e| out_err(&e))?;
                schemas.insert(m.ty.name, id);
                id
            }
        };
        let (channel, sequence) = match channels.get(m.topic.as_str()) {
            Some(&c) => c,
            None => {
                let id = writer
                    .add_channel(schema, &m.topic, "cdr", &BTreeMap::new())
                    .map_err(|e| out_err(&e))?;
                (id, 0)
            }
        };
        let t = u64::try_from(m.time_ns).unwrap_or(0);
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence,
                    log_time: t,
                    publish_time: t,
                },
                &m.cdr,
            )
            .map_err(|e| out_err(&e))?;
        channels.insert(&m.topic, (channel, sequence + 1));
        *summary.messages.entry(m.topic.clone()).or_default() += 1;
    }
    writer.finish().map_err(|e| out_err(&e))?;
    drop(writer);
    summary.bytes = std::fs::metadata(out).map(|m| m.len()).unwrap_or(0);
    Ok(summary)
}

/// The robot folders of a run: sub-folders with a `keyframes.csv`, by name.
fn robot_dirs(run: &Path) -> Result<Vec<(String, PathBuf)>, RecordError> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(run).map_err(|e| input(run, e))? {
        let e = e.map_err(|e| input(run, e))?;
        let p = e.path();
        if p.join("keyframes.csv").is_file() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(input(
                    &p,
                    "a robot folder's name must be a ROS name (letters, digits, _)",
                ));
            }
            out.push((name, p));
        }
    }
    out.sort();
    if out.is_empty() {
        return Err(RecordError::NoRobots(run.to_path_buf()));
    }
    Ok(out)
}

/// Rejected closures of a robot's `backend.json` (`team.rejected_closures`), both orders.
fn rejected(dir: &Path) -> Result<Vec<(String, String)>, RecordError> {
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

/// A robot's inter-robot closures from its `graph.g2o`: (key a, key b).
fn closures(dir: &Path) -> Result<Vec<(u64, u64)>, RecordError> {
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
        .map(|e| (keys[e.i], keys[e.j]))
        .filter(|(a, b)| {
            key::robot(*a).is_some() && key::robot(*b).is_some() && key::robot(*a) != key::robot(*b)
        })
        .collect())
}

fn line_list(id: i32, ns: &str, time_ns: i64, color: ColorRgba, points: Vec<Point>) -> Marker {
    Marker {
        header: Header {
            stamp: stamp(time_ns),
            frame_id: TEAM_FRAME.into(),
        },
        ns: ns.into(),
        id,
        kind: Marker::LINE_LIST,
        action: Marker::ADD,
        scale: Vector3 {
            x: 0.1,
            y: 0.0,
            z: 0.0,
        },
        color,
        points,
        ..Marker::default()
    }
}

fn bandwidth(robots: &[Robot], time_ns: i64) -> Result<Option<DiagnosticArray>, RecordError> {
    let mut status = Vec::new();
    for r in robots {
        let path = r.dir.join("ledger.json");
        if !path.is_file() {
            continue;
        }
        let ledger = doorslam_team::ledger::LedgerFile::read(&path).map_err(|e| input(&path, e))?;
        let mut values = Vec::new();
        let mut sent = 0u64;
        for t in &ledger.traffic {
            let dir = match t.direction {
                doorslam_team::ledger::Direction::Sent => {
                    sent += t.counts.wire_bytes;
                    "sent"
                }
                doorslam_team::ledger::Direction::Received => "received",
            };
            let at = |what: &str| format!("{dir}/{}/{}/{what}", t.peer, t.kind);
            values.push(KeyValue {
                key: at("messages"),
                value: t.counts.messages.to_string(),
            });
            values.push(KeyValue {
                key: at("wire_bytes"),
                value: t.counts.wire_bytes.to_string(),
            });
        }
        values.insert(
            0,
            KeyValue {
                key: "sent_wire_bytes".into(),
                value: sent.to_string(),
            },
        );
        status.push(DiagnosticStatus {
            level: DiagnosticStatus::OK,
            name: format!("{}/team_link", r.name),
            message: format!("{sent} bytes sent"),
            hardware_id: r.name.clone(),
            values,
        });
    }
    Ok((!status.is_empty()).then(|| DiagnosticArray {
        header: Header {
            stamp: stamp(time_ns),
            frame_id: String::new(),
        },
        status,
    }))
}

/// The set-up's Python (`$DOORSLAM_HOME/venv/bin/python`, default under
/// `~/.cache/doorslam`) when it imports every one of `modules`: what the ROS 2 checks of
/// `tests/ros2/` decode with (decoders that are not ours). `Err` says what is missing.
pub fn reference_python(modules: &[&str]) -> Result<PathBuf, String> {
    let home = std::env::var_os("DOORSLAM_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/doorslam")));
    let python = home
        .map(|h| h.join("venv/bin/python"))
        .filter(|p| p.is_file())
        .ok_or("no set-up venv (run deploy/setup)")?;
    let imports = format!("import {}", modules.join(", "));
    let has = std::process::Command::new(&python)
        .args(["-c", &imports])
        .status()
        .is_ok_and(|s| s.success());
    if has {
        Ok(python)
    } else {
        Err(format!(
            "{} cannot {imports} (run deploy/setup)",
            python.display()
        ))
    }
}

/// Writes `out` (default `<run>/run.mcap`) from the run folder `run`.
pub fn record(run: &Path, out: Option<&Path>) -> Result<RecordSummary, RecordError> {
    let out = out.map_or_else(|| run.join("run.mcap"), Path::to_path_buf);
    write_mcap(&run_messages(run)?, &out)
}

/// Every message of the run folder `run` (what `run.mcap` holds), in time order.
pub fn run_messages(run: &Path) -> Result<RunMessages, RecordError> {
    let robots: Vec<Robot> = robot_dirs(run)?
        .iter()
        .map(|(name, dir)| Robot::read(dir, name))
        .collect::<Result<_, _>>()?;
    let mut bag = RunMessages {
        robots: robots.iter().map(|r| r.name.clone()).collect(),
        samples: Vec::new(),
    };

    // Every robot's timeline, merged in time order (an MCAP reader wants no order, but a
    // player streams in file order).
    enum Event<'a> {
        Odometry(&'a Robot, usize),
        Team(&'a Robot, usize),
        Pose(&'a Robot, usize),
    }
    let mut events: Vec<(i64, usize, Event)> = Vec::new();
    for r in &robots {
        for end in path_ends(r.odometry.len()) {
            events.push((r.odometry[end - 1].stamp_ns, 0, Event::Odometry(r, end)));
        }
        for end in path_ends(r.team.len()) {
            events.push((r.team[end - 1].stamp_ns, 1, Event::Team(r, end)));
        }
        for i in 0..r.team.len() {
            events.push((r.team[i].stamp_ns, 2, Event::Pose(r, i)));
        }
    }
    events.sort_by_key(|(t, order, _)| (*t, *order));
    let end_ns = events.last().map_or(0, |e| e.0);
    for (t, _, ev) in &events {
        match ev {
            Event::Odometry(r, end) => {
                let frame = format!("{}/odom", r.name);
                bag.push(
                    &r.name,
                    &format!("/{}/odometry_path", r.name),
                    *t,
                    &path_msg(&frame, &r.odometry[..*end]),
                )?;
            }
            Event::Team(r, end) => {
                bag.push(
                    &r.name,
                    &format!("/{}/team_path", r.name),
                    *t,
                    &path_msg(TEAM_FRAME, &r.team[..*end]),
                )?;
            }
            Event::Pose(r, i) => {
                let p = &r.team[*i];
                bag.push(
                    &r.name,
                    &format!("/{}/pose", r.name),
                    *t,
                    &PoseStamped {
                        header: Header {
                            stamp: stamp(p.stamp_ns),
                            frame_id: TEAM_FRAME.into(),
                        },
                        pose: p.pose(),
                    },
                )?;
                // team → odom: T_team_kf * T_odom_kf⁻¹ at the keyframe of that stamp.
                if let Some(o) = r.odometry.iter().find(|o| o.stamp_ns == p.stamp_ns) {
                    let t_team_odom = p.isometry() * o.isometry().inverse();
                    let (v, q) = (t_team_odom.translation.vector, t_team_odom.rotation);
                    bag.push(
                        &r.name,
                        "/tf",
                        *t,
                        &TfMessage {
                            transforms: vec![TransformStamped {
                                header: Header {
                                    stamp: stamp(p.stamp_ns),
                                    frame_id: TEAM_FRAME.into(),
                                },
                                child_frame_id: format!("{}/odom", r.name),
                                transform: Transform {
                                    translation: Vector3 {
                                        x: v.x,
                                        y: v.y,
                                        z: v.z,
                                    },
                                    rotation: Quaternion {
                                        x: q.i,
                                        y: q.j,
                                        z: q.k,
                                        w: q.w,
                                    },
                                },
                            }],
                        },
                    )?;
                }
            }
        }
    }

    // Loop closures and bandwidth: the run's end state.
    let by_name: BTreeMap<&str, &Robot> = robots.iter().map(|r| (r.name.as_str(), r)).collect();
    let position = |k: u64| -> Option<Point> {
        let c = key::robot_char(key::robot(k)?).ok()?;
        let r = by_name.get(c.to_string().as_str())?;
        let p = r.team_at(key::index(k))?;
        Some(Point {
            x: p.p[0],
            y: p.p[1],
            z: p.p[2],
        })
    };
    for r in &robots {
        let rejected = rejected(&r.dir)?;
        let (mut kept, mut dropped) = (Vec::new(), Vec::new());
        for (a, b) in closures(&r.dir)? {
            let (Some(pa), Some(pb)) = (position(a), position(b)) else {
                continue;
            };
            let is_rejected = rejected.contains(&(key::label(a), key::label(b)));
            let list = if is_rejected { &mut dropped } else { &mut kept };
            list.extend([pa, pb]);
        }
        let msg = MarkerArray {
            markers: vec![
                line_list(
                    0,
                    "kept",
                    end_ns,
                    ColorRgba {
                        r: 0.1,
                        g: 0.8,
                        b: 0.1,
                        a: 1.0,
                    },
                    kept,
                ),
                line_list(
                    1,
                    "rejected",
                    end_ns,
                    ColorRgba {
                        r: 0.9,
                        g: 0.1,
                        b: 0.1,
                        a: 1.0,
                    },
                    dropped,
                ),
            ],
        };
        bag.push(&r.name, &format!("/{}/loop_closures", r.name), end_ns, &msg)?;
    }
    // The team's topic, published live by the first robot's node.
    if let Some(bw) = bandwidth(&robots, end_ns)? {
        bag.push(&robots[0].name, "/team/bandwidth", end_ns, &bw)?;
    }
    Ok(bag)
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
    fn path_ends_are_bounded_and_end_with_the_whole() {
        assert!(path_ends(0).is_empty());
        assert_eq!(path_ends(3), vec![1, 2, 3]);
        let e = path_ends(1001);
        assert!(e.len() <= PATH_MESSAGES + 1, "{}", e.len());
        assert_eq!(e.last(), Some(&1001));
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
