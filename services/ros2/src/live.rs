//! `doorslam service ros2`: a running robot's *current* state as ROS 2 publishers, over a
//! Zenoh session of its own as rmw_zenoh publishes ([`crate::session`]): one node
//! `/<namespace>/doorslam` and, every `1 / rate_hz` seconds,
//!
//! - `/<ns>/team_path` (`nav_msgs/msg/Path`, frame `team`): `team_estimate.tum`, whole;
//! - `/<ns>/odometry_path` (`nav_msgs/msg/Path`, frame `<ns>/odom`): `odometry.tum`, whole;
//! - `/<ns>/pose` (`geometry_msgs/msg/PoseStamped`, frame `team`): the latest team pose;
//! - `/tf` (`tf2_msgs/msg/TFMessage`): `team` → `<ns>/odom` at the latest keyframe with
//!   both poses (team pose × inverse odometry pose);
//! - `/<ns>/loop_closures` (`visualization_msgs/msg/MarkerArray`): the robot's inter-robot
//!   closures (`graph.g2o`) as segments from its keyframe's team position to where the
//!   closure's measurement puts the other robot's keyframe, kept green, PCM's rejections
//!   (`backend.json`) red.
//!
//! The state comes from the files the back-end rewrites (atomically, file by file) in its
//! state folder every `write_every_s`; they are read again only when one changed (size or
//! modification time), and the last good state is published again every tick (volatile
//! subscribers that join late, RViz, see it within one period). Stamps are the keyframes'
//! (the robot's clock); the attachment's source time is the clock now. A separate process
//! with its own session, reading files: nothing here is on the team link's path, and a
//! slow or absent subscriber drops samples rather than holding the publisher up.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime};

use doorslam_geometry::key;
use doorslam_ros2_wire::msgs::{MarkerArray, Path as RosPath, PoseStamped, TfMessage};
use doorslam_ros2_wire::{RosMessage, TypeDef};
use serde::Deserialize;

use crate::messages::{
    closures_msg, odometry_frame, path_msg, point, pose_msg, team_to_odometry_msg, TEAM_FRAME,
};
use crate::session::{qos_of, LiveError, LivePublisher, RosSession, SessionOptions};
use crate::state::{RecordError, RobotFiles};

/// The largest `ROS_DOMAIN_ID` ROS 2 allows (its DDS port arithmetic; rmw_zenoh keeps the
/// same range).
pub const MAX_DOMAIN_ID: u32 = 232;
/// The highest publishing rate: a path message holds every keyframe, so a high rate costs
/// the laptop link bandwidth for no new information (the back-end writes at most every
/// `write_every_s`).
pub const MAX_RATE_HZ: f64 = 50.0;

/// `[ros2]` of `robot.toml`. Unknown keys are errors: a typo must not be ignored.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Section {
    /// Publish the robot's state as ROS 2 topics (`doorslam up` then starts the `ros2`
    /// service). Off by default.
    #[serde(default)]
    pub enabled: bool,
    /// `ROS_DOMAIN_ID`: the first part of every key expression and token.
    #[serde(default)]
    pub domain_id: u32,
    /// The node's namespace, `/<namespace>/doorslam`, and the topics' (default: the robot
    /// id). A ROS name: letters, digits and `_`, not starting with a digit.
    #[serde(default)]
    pub namespace: Option<String>,
    /// Samples per second on every topic.
    #[serde(default = "default_rate_hz")]
    pub rate_hz: f64,
    /// Zenoh endpoints this session listens on (a laptop's router connects to them) ...
    #[serde(default)]
    pub listen: Vec<String>,
    /// ... and connects to (default: a ROS 2 router on the robot itself, where rmw_zenoh's
    /// nodes look for it).
    #[serde(default = "default_connect")]
    pub connect: Vec<String>,
    /// Find peers by multicast (rmw_zenoh leaves it off and routes through `rmw_zenohd`).
    #[serde(default)]
    pub multicast_scouting: bool,
}

fn default_rate_hz() -> f64 {
    2.0
}

fn default_connect() -> Vec<String> {
    vec!["tcp/localhost:7447".into()]
}

impl Default for Ros2Section {
    fn default() -> Self {
        Self {
            enabled: false,
            domain_id: 0,
            namespace: None,
            rate_hz: default_rate_hz(),
            listen: Vec::new(),
            connect: default_connect(),
            multicast_scouting: false,
        }
    }
}

fn section(key: &'static str, reason: String) -> LiveError {
    LiveError::Section { key, reason }
}

/// A ROS name token: letters, digits and `_`, not starting with a digit (rcl's rule for
/// namespace and topic tokens).
fn is_ros_token(s: &str) -> bool {
    s.chars().next().is_some_and(|c| !c.is_ascii_digit())
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

impl Ros2Section {
    /// The namespace of robot `robot_id`: the configured one, or the id.
    pub fn namespace<'a>(&'a self, robot_id: &'a str) -> &'a str {
        self.namespace.as_deref().unwrap_or(robot_id)
    }

    /// Checks every key; errors name it (`ros2.rate_hz`, ...). The namespace defaulted
    /// from the robot id is checked only when enabled (an id with `-` is a fine robot id).
    pub fn validate(&self, robot_id: &str) -> Result<(), LiveError> {
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= MAX_RATE_HZ) {
            return Err(section(
                "rate_hz",
                format!(
                    "{}: samples per second above 0, at most {MAX_RATE_HZ}",
                    self.rate_hz
                ),
            ));
        }
        if self.domain_id > MAX_DOMAIN_ID {
            return Err(section(
                "domain_id",
                format!(
                    "{}: ROS 2 domain ids are 0 to {MAX_DOMAIN_ID}",
                    self.domain_id
                ),
            ));
        }
        let ns = self.namespace(robot_id);
        if (self.namespace.is_some() || self.enabled) && !is_ros_token(ns) {
            let whose = if self.namespace.is_some() {
                String::new()
            } else {
                " (the robot id, its default)".into()
            };
            return Err(section(
                "namespace",
                format!("{ns:?}{whose} is not a ROS name: letters, digits and _, not starting with a digit"),
            ));
        }
        for (key, list) in [("listen", &self.listen), ("connect", &self.connect)] {
            for e in list {
                if let Err(why) = e.parse::<zenoh::config::EndPoint>() {
                    return Err(section(key, format!("{e:?}: not a Zenoh endpoint: {why}")));
                }
            }
        }
        if self.enabled
            && self.listen.is_empty()
            && self.connect.is_empty()
            && !self.multicast_scouting
        {
            return Err(section(
                "connect",
                "empty, and neither listen nor multicast_scouting: no subscriber could reach the publishers".into(),
            ));
        }
        Ok(())
    }

    /// The live publishers of robot `robot_id` (index `robot_index` in the team) whose
    /// back-end keeps its state under `state_dir` (`[backend] state_dir`).
    pub fn for_robot(&self, robot_id: &str, robot_index: u8, state_dir: &Path) -> LiveConfig {
        LiveConfig {
            namespace: self.namespace(robot_id).to_string(),
            robot_index,
            dir: state_dir.join(robot_id),
            rate_hz: self.rate_hz,
            session: SessionOptions {
                domain_id: self.domain_id,
                listen: self.listen.clone(),
                connect: self.connect.clone(),
                multicast_scouting: self.multicast_scouting,
            },
        }
    }
}

/// Settings of one `ros2` service.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveConfig {
    pub namespace: String,
    /// The robot's index in multi-robot keys: which end of a closure is its own.
    pub robot_index: u8,
    /// The robot's state folder (`<state_dir>/<robot id>/`).
    pub dir: PathBuf,
    pub rate_hz: f64,
    pub session: SessionOptions,
}

/// What the service did, logged when it stops.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct LiveSummary {
    pub session_id: String,
    pub tokens: Vec<String>,
    pub ticks: u64,
    /// Times the state folder was read (a file had changed), and reads that failed.
    pub reads: u64,
    pub read_errors: u64,
    pub samples: u64,
    pub bytes: u64,
    pub seconds: f64,
}

/// The topics, in the order their publishers are declared.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Topic {
    TeamPath,
    OdometryPath,
    Pose,
    Tf,
    LoopClosures,
}

const TOPICS: [Topic; 5] = [
    Topic::TeamPath,
    Topic::OdometryPath,
    Topic::Pose,
    Topic::Tf,
    Topic::LoopClosures,
];

impl Topic {
    fn name(self, ns: &str) -> String {
        match self {
            Topic::TeamPath => format!("/{ns}/team_path"),
            Topic::OdometryPath => format!("/{ns}/odometry_path"),
            Topic::Pose => format!("/{ns}/pose"),
            Topic::Tf => "/tf".into(),
            Topic::LoopClosures => format!("/{ns}/loop_closures"),
        }
    }

    fn ty(self) -> &'static TypeDef {
        match self {
            Topic::TeamPath | Topic::OdometryPath => RosPath::TYPE,
            Topic::Pose => PoseStamped::TYPE,
            Topic::Tf => TfMessage::TYPE,
            Topic::LoopClosures => MarkerArray::TYPE,
        }
    }
}

/// The files whose change means a new state.
const STATE_FILES: [&str; 5] = [
    "keyframes.csv",
    "odometry.tum",
    "team_estimate.tum",
    "graph.g2o",
    "backend.json",
];

type Fingerprint = Vec<Option<(SystemTime, u64)>>;

fn fingerprint(dir: &Path) -> Fingerprint {
    STATE_FILES
        .iter()
        .map(|f| {
            let m = std::fs::metadata(dir.join(f)).ok()?;
            Some((m.modified().ok()?, m.len()))
        })
        .collect()
}

/// Encoded messages of one state, by topic.
type Snapshot = Vec<(Topic, Vec<u8>)>;

/// The current state of the folder as encoded messages, `None` before the back-end wrote
/// its first files.
fn snapshot(c: &LiveConfig) -> Result<Option<Snapshot>, RecordError> {
    if !c.dir.join("keyframes.csv").is_file() || !c.dir.join("odometry.tum").is_file() {
        return Ok(None);
    }
    let ns = &c.namespace;
    let r = RobotFiles::read(&c.dir, ns)?;
    let mut out = Vec::new();
    if !r.odometry.is_empty() {
        let odometry = path_msg(&odometry_frame(ns), &r.odometry);
        out.push((Topic::OdometryPath, odometry.to_cdr()?));
    }
    // Before the robot has a team estimate there is nothing in the team frame.
    let Some(latest) = r.team.last() else {
        return Ok(Some(out));
    };
    out.push((Topic::TeamPath, path_msg(TEAM_FRAME, &r.team).to_cdr()?));
    out.push((Topic::Pose, pose_msg(TEAM_FRAME, latest).to_cdr()?));
    if let Some((p, t)) = r
        .team
        .iter()
        .rev()
        .find_map(|p| Some((p, r.team_to_odometry(p)?)))
    {
        out.push((
            Topic::Tf,
            team_to_odometry_msg(ns, p.stamp_ns, &t).to_cdr()?,
        ));
    }
    let rejected = r.rejected()?;
    let (mut kept, mut dropped) = (Vec::new(), Vec::new());
    for cl in r.closures()? {
        // Own end: its team pose; other end: where the measurement Z = Xa⁻¹ Xb puts it.
        let (own, other_from_own) = if key::robot(cl.a) == Some(c.robot_index) {
            (cl.a, cl.measured)
        } else if key::robot(cl.b) == Some(c.robot_index) {
            (cl.b, cl.measured.inverse())
        } else {
            continue;
        };
        let Some(x_own) = r.team_at(key::index(own)).map(|p| p.isometry()) else {
            continue;
        };
        let x_other = x_own * other_from_own;
        let is_rejected = rejected.contains(&(key::label(cl.a), key::label(cl.b)));
        let list = if is_rejected { &mut dropped } else { &mut kept };
        list.extend([
            point(&x_own.translation.vector),
            point(&x_other.translation.vector),
        ]);
    }
    out.push((
        Topic::LoopClosures,
        closures_msg(latest.stamp_ns, kept, dropped).to_cdr()?,
    ));
    Ok(Some(out))
}

/// Waits until `t` or `stop`, whichever first.
pub(crate) fn sleep_until(t: Instant, stop: &AtomicBool) {
    while !stop.load(Ordering::Relaxed) {
        let now = Instant::now();
        if now >= t {
            return;
        }
        std::thread::sleep((t - now).min(Duration::from_millis(50)));
    }
}

/// Publishes the state folder of `c` every `1 / rate_hz` until `stop`.
pub fn run(c: &LiveConfig, stop: &AtomicBool) -> Result<LiveSummary, LiveError> {
    if !(c.rate_hz.is_finite() && c.rate_hz > 0.0 && c.rate_hz <= MAX_RATE_HZ) {
        return Err(section("rate_hz", format!("{}", c.rate_hz)));
    }
    let mut session = RosSession::open(&c.session)?;
    let node = session.node(&format!("/{}", c.namespace), "doorslam")?;
    let mut publishers: Vec<(Topic, LivePublisher)> = Vec::new();
    for t in TOPICS {
        let name = t.name(&c.namespace);
        let p = session.publisher(&node, &name, t.ty(), qos_of(&name))?;
        publishers.push((t, p));
    }
    let mut summary = LiveSummary {
        session_id: session.zid().to_string(),
        tokens: session.tokens().to_vec(),
        ..Default::default()
    };
    tracing::info!(
        dir = %c.dir.display(),
        namespace = %c.namespace,
        session = %summary.session_id,
        rate_hz = c.rate_hz,
        "ros2: publishing"
    );
    doorslam_ipc::lifecycle::sd_notify(&format!(
        "READY=1\nSTATUS=ros2: /{}/doorslam at {} Hz",
        c.namespace, c.rate_hz
    ));
    // Pinged while waiting too: a slow rate's period may exceed the unit's watchdog.
    let watchdog = doorslam_ipc::lifecycle::watchdog_interval();
    let mut pinged = Instant::now();
    let mut wait_until = |t: Instant| {
        while !stop.load(Ordering::Relaxed) && Instant::now() < t {
            if watchdog.is_some_and(|w| pinged.elapsed() >= w) {
                doorslam_ipc::lifecycle::sd_notify("WATCHDOG=1");
                pinged = Instant::now();
            }
            std::thread::sleep(
                t.saturating_duration_since(Instant::now())
                    .min(Duration::from_millis(50)),
            );
        }
    };

    let start = Instant::now();
    let period = Duration::from_secs_f64(1.0 / c.rate_hz);
    let mut next = start;
    let mut seen: Option<Fingerprint> = None;
    let mut current: Snapshot = Vec::new();
    let mut last_error: Option<String> = None;
    let result = loop {
        if stop.load(Ordering::Relaxed) {
            break Ok(());
        }
        let now_fp = fingerprint(&c.dir);
        if seen.as_ref() != Some(&now_fp) {
            match snapshot(c) {
                Ok(Some(s)) => {
                    current = s;
                    seen = Some(now_fp);
                    summary.reads += 1;
                    last_error = None;
                }
                Ok(None) => {}
                Err(e) => {
                    // Kept: the last good state; said once per distinct failure.
                    let e = e.to_string();
                    if last_error.as_ref() != Some(&e) {
                        tracing::warn!("ros2: {e} (publishing the last good state)");
                    }
                    last_error = Some(e);
                    seen = Some(now_fp);
                    summary.read_errors += 1;
                }
            }
        }
        let mut failed = None;
        for (topic, cdr) in &current {
            if let Some((_, p)) = publishers.iter_mut().find(|(t, _)| t == topic) {
                if let Err(e) = p.put(cdr.clone()) {
                    failed = Some(e);
                    break;
                }
            }
        }
        if let Some(e) = failed {
            break Err(e);
        }
        summary.ticks += 1;
        // A late tick (a loaded machine) is not caught up by a burst.
        next = (next + period).max(Instant::now());
        wait_until(next);
    };
    doorslam_ipc::lifecycle::sd_notify("STOPPING=1");
    summary.seconds = start.elapsed().as_secs_f64();
    summary.samples = publishers.iter().map(|(_, p)| p.samples()).sum();
    summary.bytes = publishers.iter().map(|(_, p)| p.bytes).sum();
    drop(publishers);
    session.close()?;
    result.map(|()| summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Ros2Section {
        toml::from_str(text).unwrap()
    }

    #[test]
    fn defaults_are_off_at_two_hertz_on_domain_zero() {
        let s = Ros2Section::default();
        assert!(!s.enabled);
        assert_eq!((s.domain_id, s.rate_hz), (0, 2.0));
        assert_eq!(s.namespace("a"), "a");
        assert_eq!(s.connect, ["tcp/localhost:7447"]);
        s.validate("a").unwrap();
        // A robot id that is no ROS name is fine while the publishers are off.
        s.validate("robot-1").unwrap();
    }

    #[test]
    fn bad_values_are_refused_naming_the_key() {
        let cases = [
            ("rate_hz = 0.0", "ros2.rate_hz"),
            ("rate_hz = 51.0", "ros2.rate_hz"),
            ("rate_hz = nan", "ros2.rate_hz"),
            ("domain_id = 233", "ros2.domain_id"),
            ("namespace = \"9a\"", "ros2.namespace"),
            ("namespace = \"a-b\"", "ros2.namespace"),
            ("namespace = \"\"", "ros2.namespace"),
            ("listen = [\"nope\"]", "ros2.listen"),
            ("enabled = true\nconnect = []", "ros2.connect"),
        ];
        for (text, key) in cases {
            let e = parse(text).validate("a").unwrap_err().to_string();
            assert!(e.starts_with(key), "{text}: {e}");
        }
        let e = parse("enabled = true")
            .validate("robot-1")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ros2.namespace") && e.contains("robot id"),
            "{e}"
        );
        parse("enabled = true\nnamespace = \"robot_1\"")
            .validate("robot-1")
            .unwrap();
        parse("domain_id = 232\nrate_hz = 50.0")
            .validate("a")
            .unwrap();
    }
}
