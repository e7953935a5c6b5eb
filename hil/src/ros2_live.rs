//! `doorslam ros2 replay`: a finished run's messages (the very payloads `run.mcap` holds,
//! [`crate::ros2_record::run_messages`]) published over Zenoh the way rmw_zenoh publishes,
//! so RViz or Foxglove with `RMW_IMPLEMENTATION=rmw_zenoh_cpp` on the same Zenoh network
//! sees one node per robot (`/<robot>/doorslam`) and its topics, without a bridge.
//!
//! Per robot: the node's `NN` liveliness token, per topic an `MP` token and a Zenoh
//! publisher on the topic's data key expression; every sample carries rmw_zenoh's
//! attachment (sequence number from 1 per publisher, source time now, the publisher's
//! GID). Node and entity ids come from one counter, as in an rmw_zenoh context.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use doorslam_ros2_wire::rmw::{Node, Publisher, Qos};
use doorslam_ros2_wire::WireError;
use zenoh::Wait;

use crate::ros2_record::{run_messages, RecordError};

/// Failures of the replay; each names its input.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("zenoh config {key}: {reason}")]
    Config { key: &'static str, reason: String },
    #[error("zenoh {what}: {reason}")]
    Zenoh { what: String, reason: String },
    #[error("--rate {0}: must be a finite number above 0")]
    Rate(f64),
}

fn zerr(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> LiveError {
    let what = what.into();
    move |e| LiveError::Zenoh {
        what,
        reason: e.to_string(),
    }
}

/// How to replay.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// `ROS_DOMAIN_ID` of the key expressions and tokens.
    pub domain_id: u32,
    /// Zenoh endpoints to listen on (`tcp/0.0.0.0:7447`) and to connect to (a laptop's
    /// `rmw_zenohd`, `tcp/<laptop>:7447`).
    pub listen: Vec<String>,
    pub connect: Vec<String>,
    pub multicast_scouting: bool,
    /// Run time per wall-clock time (2: twice as fast).
    pub rate: f64,
    /// Wait after declaring, before the first sample (subscribers' declarations travel
    /// to this session first; rmw_zenoh has no matching wait either).
    pub warmup: Duration,
    /// Keep the tokens this long after the last sample (late graph queries still see
    /// the nodes).
    pub linger: Duration,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            domain_id: 0,
            listen: Vec::new(),
            connect: Vec::new(),
            multicast_scouting: true,
            rate: 1.0,
            warmup: Duration::from_secs(1),
            linger: Duration::from_secs(1),
        }
    }
}

/// What was published.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ReplaySummary {
    pub session_id: String,
    /// Liveliness tokens: nodes, then publishers.
    pub tokens: Vec<String>,
    /// Data key expression → samples put.
    pub samples: BTreeMap<String, u64>,
    pub seconds: f64,
    /// Stopped before the end.
    pub stopped: bool,
}

fn json_list(items: &[String]) -> String {
    serde_json::to_string(items).unwrap_or_else(|_| "[]".into())
}

fn open_session(o: &ReplayOptions) -> Result<zenoh::Session, LiveError> {
    let mut config = zenoh::Config::default();
    let mut set = |key: &'static str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| LiveError::Config {
                key,
                reason: e.to_string(),
            })
    };
    set("mode", "\"peer\"".into())?;
    set("listen/endpoints", json_list(&o.listen))?;
    set("connect/endpoints", json_list(&o.connect))?;
    set(
        "scouting/multicast/enabled",
        o.multicast_scouting.to_string(),
    )?;
    zenoh::open(config).wait().map_err(zerr("open session"))
}

fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// Publishes the run folder `run`'s messages until the end or `stop`.
pub fn replay(
    run: &Path,
    o: &ReplayOptions,
    stop: &AtomicBool,
) -> Result<ReplaySummary, LiveError> {
    if !(o.rate.is_finite() && o.rate > 0.0) {
        return Err(LiveError::Rate(o.rate));
    }
    let messages = run_messages(run)?;
    let session = open_session(o)?;
    let zid = session.zid().to_string();
    let mut summary = ReplaySummary {
        session_id: zid.clone(),
        ..Default::default()
    };

    // Nodes, publishers and their tokens (dropped, hence undeclared, at the end).
    let mut next_id = 0u64;
    let mut tokens = Vec::new();
    let mut nodes = BTreeMap::new();
    for robot in &messages.robots {
        let node = Node::new(o.domain_id, &zid, next_id, &format!("/{robot}"), "doorslam")?;
        next_id += 1;
        tokens.push(
            session
                .liveliness()
                .declare_token(node.token())
                .wait()
                .map_err(zerr(format!("token {}", node.token())))?,
        );
        summary.tokens.push(node.token());
        nodes.insert(robot.clone(), node);
    }
    type Pub = (Publisher, zenoh::pubsub::Publisher<'static>, i64);
    let mut publishers: BTreeMap<(String, String), Pub> = BTreeMap::new();
    for s in &messages.samples {
        let k = (s.robot.clone(), s.topic.clone());
        if publishers.contains_key(&k) {
            continue;
        }
        let Some(node) = nodes.get(&s.robot) else {
            continue;
        };
        // tf2's listeners keep 100 transforms; the rest keep 10 (rclcpp's usual depth).
        let qos = Qos::keep_last(if s.topic == "/tf" { 100 } else { 10 });
        let p = node.publisher(next_id, &s.topic, s.ty, qos)?;
        next_id += 1;
        tokens.push(
            session
                .liveliness()
                .declare_token(p.token.clone())
                .wait()
                .map_err(zerr(format!("token {}", p.token)))?,
        );
        let zp = session
            .declare_publisher(p.key.clone())
            .wait()
            .map_err(zerr(format!("publisher {}", p.key)))?;
        summary.tokens.push(p.token.clone());
        publishers.insert(k, (p, zp, 0));
    }

    let sleep_until = |t: Instant| {
        while !stop.load(Ordering::Relaxed) {
            let now = Instant::now();
            if now >= t {
                return;
            }
            std::thread::sleep((t - now).min(Duration::from_millis(50)));
        }
    };
    sleep_until(Instant::now() + o.warmup);
    let start = Instant::now();
    let t0 = messages.samples.first().map_or(0, |s| s.time_ns);
    for s in &messages.samples {
        let offset = (s.time_ns - t0).max(0) as f64 / 1e9 / o.rate;
        sleep_until(start + Duration::from_secs_f64(offset));
        if stop.load(Ordering::Relaxed) {
            summary.stopped = true;
            break;
        }
        let Some((p, zp, seq)) = publishers.get_mut(&(s.robot.clone(), s.topic.clone())) else {
            continue;
        };
        *seq += 1;
        let attachment = p.attachment(*seq, now_ns()).encode();
        zp.put(s.cdr.clone())
            .attachment(attachment.to_vec())
            .wait()
            .map_err(zerr(format!("put {}", p.key)))?;
        *summary.samples.entry(p.key.clone()).or_default() += 1;
    }
    summary.seconds = start.elapsed().as_secs_f64();
    sleep_until(Instant::now() + o.linger);
    drop(publishers);
    drop(tokens);
    session.close().wait().map_err(zerr("close"))?;
    Ok(summary)
}
