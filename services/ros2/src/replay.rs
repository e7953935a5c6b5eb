//! `doorslam ros2 replay`: a finished run's messages (the very payloads `run.mcap` holds,
//! [`crate::record::run_messages`]) published over Zenoh the way rmw_zenoh publishes,
//! so RViz or Foxglove with `RMW_IMPLEMENTATION=rmw_zenoh_cpp` on the same Zenoh network
//! sees one node per robot (`/<robot>/doorslam`) and its topics, without a bridge.
//!
//! Per robot: the node's `NN` liveliness token, per topic an `MP` token and a Zenoh
//! publisher on the topic's data key expression ([`crate::session`]); every sample carries
//! rmw_zenoh's attachment.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::record::run_messages;
pub use crate::session::LiveError;
use crate::session::{qos_of, LivePublisher, RosSession, SessionOptions};

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
    let mut session = RosSession::open(&SessionOptions {
        domain_id: o.domain_id,
        listen: o.listen.clone(),
        connect: o.connect.clone(),
        multicast_scouting: o.multicast_scouting,
    })?;
    let mut summary = ReplaySummary {
        session_id: session.zid().to_string(),
        ..Default::default()
    };

    // Nodes first, then one publisher per (robot, topic) in order of first use.
    let mut nodes = BTreeMap::new();
    for robot in &messages.robots {
        nodes.insert(
            robot.clone(),
            session.node(&format!("/{robot}"), "doorslam")?,
        );
    }
    let mut publishers: BTreeMap<(String, String), LivePublisher> = BTreeMap::new();
    for s in &messages.samples {
        let k = (s.robot.clone(), s.topic.clone());
        if publishers.contains_key(&k) {
            continue;
        }
        let Some(node) = nodes.get(&s.robot) else {
            continue;
        };
        let p = session.publisher(node, &s.topic, s.ty, qos_of(&s.topic))?;
        publishers.insert(k, p);
    }
    summary.tokens = session.tokens().to_vec();

    let sleep_until = |t: Instant| crate::live::sleep_until(t, stop);
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
        let Some(p) = publishers.get_mut(&(s.robot.clone(), s.topic.clone())) else {
            continue;
        };
        p.put(s.cdr.clone())?;
        *summary.samples.entry(p.wire.key.clone()).or_default() += 1;
    }
    summary.seconds = start.elapsed().as_secs_f64();
    sleep_until(Instant::now() + o.linger);
    drop(publishers);
    session.close()?;
    Ok(summary)
}
