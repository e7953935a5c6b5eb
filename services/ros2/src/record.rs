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
use doorslam_ros2_wire::msgs::{DiagnosticArray, DiagnosticStatus, Header, KeyValue, Point};
use doorslam_ros2_wire::{RosMessage, TypeDef};

pub use crate::messages::TEAM_FRAME;
use crate::messages::{
    closures_msg, odometry_frame, path_msg, pose_msg, stamp, team_to_odometry_msg,
};
use crate::state::{input, RobotFiles as Robot};
pub use crate::state::{read_tum, RecordError, TumPose};

/// At most this many growing-path messages per robot and path (plus the final one): a
/// path message holds every keyframe so far, so one per keyframe would grow the file with
/// the square of the keyframes.
pub const PATH_MESSAGES: usize = 50;

/// What was written.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RecordSummary {
    pub path: PathBuf,
    pub robots: Vec<String>,
    /// Messages per topic.
    pub messages: BTreeMap<String, u64>,
    pub bytes: u64,
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
                bag.push(
                    &r.name,
                    &format!("/{}/odometry_path", r.name),
                    *t,
                    &path_msg(&odometry_frame(&r.name), &r.odometry[..*end]),
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
                    &pose_msg(TEAM_FRAME, p),
                )?;
                if let Some(t_team_odom) = r.team_to_odometry(p) {
                    bag.push(
                        &r.name,
                        "/tf",
                        *t,
                        &team_to_odometry_msg(&r.name, p.stamp_ns, &t_team_odom),
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
        Some(r.team_at(key::index(k))?.point())
    };
    for r in &robots {
        let rejected = r.rejected()?;
        let (mut kept, mut dropped) = (Vec::new(), Vec::new());
        for c in r.closures()? {
            let (Some(pa), Some(pb)) = (position(c.a), position(c.b)) else {
                continue;
            };
            let is_rejected = rejected.contains(&(key::label(c.a), key::label(c.b)));
            let list = if is_rejected { &mut dropped } else { &mut kept };
            list.extend([pa, pb]);
        }
        bag.push(
            &r.name,
            &format!("/{}/loop_closures", r.name),
            end_ns,
            &closures_msg(end_ns, kept, dropped),
        )?;
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
    fn path_ends_are_bounded_and_end_with_the_whole() {
        assert!(path_ends(0).is_empty());
        assert_eq!(path_ends(3), vec![1, 2, 3]);
        let e = path_ends(1001);
        assert!(e.len() <= PATH_MESSAGES + 1, "{}", e.len());
        assert_eq!(e.last(), Some(&1001));
    }
}
