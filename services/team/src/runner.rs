//! `doorslam service team`: one robot's team link over Zenoh, with the stand-ins of
//! [`crate::standin`] until place recognition, verification and the distributed back-end
//! are plugged in (simulated keyframes appear one per `keyframe_interval_ms`).
//!
//! Writes to `<run_dir>/<robot id>/`: `team.epoch` (incremented at every start: the
//! epoch of every message header), `ledger.json` and `status.json` (peer sessions,
//! delivered descriptors, what the link published), every `write_every_ms` and at the end.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use doorslam_ipc::wire::RobotId;
use serde::{Deserialize, Serialize};

use crate::ledger::{Ledger, LedgerError, LedgerHandle};
use crate::link::{team_name, LinkConfig, LinkMode, TeamError};
use crate::node::{Node, Pieces};
use crate::protocol::{Identity, PeerStats, ProtocolConfig};
use crate::security::{Holder, Security, TlsSection};
use crate::standin::{BackendLog, EchoBackend, SimPlaces, SimWorld, TruthVerifier};
use crate::zenoh_link::{ZenohLink, ZenohLinkConfig};

/// `[team]` of robot.toml.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TeamSection {
    /// Team prefix of every key expression (`doorslam/<name>/...`).
    #[serde(default = "default_name")]
    pub name: String,
    /// `peer` (default): robots reach each other directly; `client`: through a
    /// `doorslam router` in `connect` (then `listen = []`).
    #[serde(default)]
    pub mode: LinkMode,
    #[serde(default = "default_listen")]
    pub listen: Vec<String>,
    #[serde(default)]
    pub connect: Vec<String>,
    #[serde(default = "default_true")]
    pub multicast_scouting: bool,
    /// A peer silent this long is gone (Zenoh link lease).
    #[serde(default = "default_lease_ms")]
    pub lease_ms: u64,
    /// Run folder: `<run_dir>/<robot id>/ledger.json`, `status.json`, `team.epoch`.
    #[serde(default = "default_run_dir")]
    pub run_dir: PathBuf,
    #[serde(default = "default_retransmit_ms")]
    pub retransmit_ms: u64,
    #[serde(default = "default_write_every_ms")]
    pub write_every_ms: u64,
    /// Size of one raw keyframe image (8-bit grayscale), the comparison of `doorslam bw`.
    #[serde(default = "default_width")]
    pub raw_image_width: u64,
    #[serde(default = "default_height")]
    pub raw_image_height: u64,
    #[serde(default)]
    pub standin: StandinSection,
    /// `[team.tls]`: TLS with mutual authentication and access control (see
    /// [`crate::security`]); absent = plain TCP, open to anyone on the network.
    #[serde(default)]
    pub tls: Option<TlsSection>,
}

/// `[team.standin]`: the simulated keyframes and descriptors (the same seed on every robot
/// of a test: one simulated world).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StandinSection {
    #[serde(default = "default_seed")]
    pub seed: u64,
    #[serde(default = "default_places")]
    pub places: u64,
    #[serde(default = "default_alias_every")]
    pub alias_every: u64,
    /// Keyframes this robot makes in all.
    #[serde(default = "default_keyframes")]
    pub keyframes: u64,
    #[serde(default = "default_keyframe_interval_ms")]
    pub keyframe_interval_ms: u64,
    #[serde(default = "default_features")]
    pub features_per_keyframe: usize,
}

fn default_name() -> String {
    "doorslam".into()
}
fn default_listen() -> Vec<String> {
    vec!["tcp/0.0.0.0:7447".into()]
}
fn default_true() -> bool {
    true
}
fn default_lease_ms() -> u64 {
    10_000
}
fn default_run_dir() -> PathBuf {
    PathBuf::from("/var/lib/doorslam/run")
}
fn default_retransmit_ms() -> u64 {
    1000
}
fn default_write_every_ms() -> u64 {
    1000
}
fn default_width() -> u64 {
    752
}
fn default_height() -> u64 {
    480
}
fn default_seed() -> u64 {
    1
}
fn default_places() -> u64 {
    100
}
fn default_alias_every() -> u64 {
    5
}
fn default_keyframes() -> u64 {
    200
}
fn default_keyframe_interval_ms() -> u64 {
    50
}
fn default_features() -> usize {
    200
}

impl Default for StandinSection {
    fn default() -> Self {
        Self {
            seed: default_seed(),
            places: default_places(),
            alias_every: default_alias_every(),
            keyframes: default_keyframes(),
            keyframe_interval_ms: default_keyframe_interval_ms(),
            features_per_keyframe: default_features(),
        }
    }
}

impl Default for TeamSection {
    fn default() -> Self {
        Self {
            name: default_name(),
            mode: LinkMode::Peer,
            listen: default_listen(),
            connect: Vec::new(),
            multicast_scouting: true,
            lease_ms: default_lease_ms(),
            run_dir: default_run_dir(),
            retransmit_ms: default_retransmit_ms(),
            write_every_ms: default_write_every_ms(),
            raw_image_width: default_width(),
            raw_image_height: default_height(),
            standin: StandinSection::default(),
            tls: None,
        }
    }
}

/// Failures of the team service.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error("team.{key}: {reason}")]
    Config { key: &'static str, reason: String },
    #[error(transparent)]
    Team(#[from] TeamError),
    #[error(transparent)]
    Ledger(#[from] LedgerError),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {reason}")]
    Epoch { path: PathBuf, reason: String },
}

impl TeamSection {
    pub fn validate(&self) -> Result<(), RunError> {
        let bad = |key, reason: &str| RunError::Config {
            key,
            reason: reason.into(),
        };
        team_name(&self.name).map_err(|e| bad("name", &e.to_string()))?;
        if self.lease_ms < 500 {
            return Err(bad("lease_ms", "must be at least 500"));
        }
        if self.retransmit_ms == 0 || self.write_every_ms == 0 {
            return Err(bad(
                "retransmit_ms",
                "retransmit_ms and write_every_ms must be >= 1",
            ));
        }
        if self.standin.places == 0 {
            return Err(bad("standin.places", "must be >= 1"));
        }
        if self.standin.features_per_keyframe == 0
            || self.standin.features_per_keyframe > doorslam_ipc::wire::MAX_FEATURES
        {
            return Err(bad(
                "standin.features_per_keyframe",
                "must be 1 to MAX_FEATURES",
            ));
        }
        if let Some(tls) = &self.tls {
            tls.roster().map_err(|e| bad("tls", &e))?;
        }
        if self.mode == LinkMode::Client {
            if !self.listen.is_empty() {
                return Err(bad(
                    "listen",
                    "a client (mode = \"client\") does not listen: set listen = []",
                ));
            }
            if self.connect.is_empty() && !self.multicast_scouting {
                return Err(bad("connect", "a client (mode = \"client\") needs the router's endpoint in connect (or multicast scouting)"));
            }
        }
        Ok(())
    }
}

/// `status.json`: what the robot's link did, for tests and operators.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Status {
    pub robot: String,
    pub epoch: u64,
    pub keyframes_created: u64,
    /// Bytes and messages handed to Zenoh, counted by the link apart from the ledger.
    pub published_bytes: u64,
    pub published_messages: u64,
    pub peers: BTreeMap<String, PeerStatus>,
    pub present: Vec<String>,
    pub backend: BackendStatus,
    pub finished: bool,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PeerStatus {
    pub stats: PeerStats,
    /// Indices of the peer's keyframes whose descriptors were delivered here.
    pub delivered_descriptors: Vec<u64>,
    pub unacknowledged_messages: usize,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct BackendStatus {
    pub closures: BTreeMap<String, u64>,
    pub estimates_received: BTreeMap<String, u64>,
    pub rounds_sent: BTreeMap<String, u64>,
}

impl From<BackendLog> for BackendStatus {
    fn from(l: BackendLog) -> Self {
        Self {
            closures: l.closures,
            estimates_received: l.estimates_received,
            rounds_sent: l.rounds_sent,
        }
    }
}

/// Reads `<dir>/team.epoch`, adds one and writes it back (atomically).
pub fn next_epoch(dir: &Path) -> Result<u64, RunError> {
    let path = dir.join("team.epoch");
    let previous = match std::fs::read_to_string(&path) {
        Ok(text) => text.trim().parse::<u64>().map_err(|e| RunError::Epoch {
            path: path.clone(),
            reason: format!("not an epoch number: {e}"),
        })?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => 0,
        Err(source) => return Err(RunError::Io { path, source }),
    };
    // An epoch at the top of the range is a corrupted file, not a restart count: refused
    // (never wrapped to 0, which every peer would take for a stale replay).
    let epoch = previous.checked_add(1).ok_or_else(|| RunError::Epoch {
        path: path.clone(),
        reason: format!("epoch {previous} cannot be incremented: remove the file to start at 1"),
    })?;
    write_atomic(&path, &format!("{epoch}\n"))?;
    Ok(epoch)
}

fn write_atomic(path: &Path, text: &str) -> Result<(), RunError> {
    let tmp = path.with_extension("tmp");
    let io = |source| RunError::Io {
        path: path.into(),
        source,
    };
    std::fs::write(&tmp, text).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// Runs one robot's team link until `stop` is set (SIGTERM/SIGINT in the CLI).
pub fn run(
    section: &TeamSection,
    robot: &str,
    robot_index: u8,
    stop: &AtomicBool,
) -> Result<Status, RunError> {
    section.validate()?;
    let id = RobotId::new(robot).map_err(|e| RunError::Config {
        key: "robot id",
        reason: e.to_string(),
    })?;
    let dir = section.run_dir.join(robot);
    std::fs::create_dir_all(&dir).map_err(|source| RunError::Io {
        path: dir.clone(),
        source,
    })?;
    // TLS files are checked before the epoch advances: a bad certificate fails the start
    // naming the file; the epoch file is written before the link opens.
    let security = match &section.tls {
        Some(tls) => Some(
            Security::check(tls, &section.name, &Holder::Robot(id.clone()))
                .map_err(TeamError::from)?,
        ),
        None => {
            tracing::warn!(team = %section.name, "team link is open: no [team.tls], anyone on the network can join the team and inject messages (see doorslam team certs)");
            None
        }
    };
    let epoch = next_epoch(&dir)?;
    let s = &section.standin;
    let world = SimWorld {
        seed: s.seed,
        places: s.places,
        alias_every: s.alias_every,
        ..SimWorld::default()
    };
    let place = SimPlaces::new(world, robot_index, s.features_per_keyframe);
    let created = place.created();
    let backend = EchoBackend::new(robot_index);
    let backend_log = backend.log.clone();
    let mut ledger = Ledger::new(
        robot,
        &section.name,
        epoch,
        section.raw_image_width * section.raw_image_height,
    );
    if security.is_some() {
        ledger = ledger.over_tls();
    }
    let ledger = LedgerHandle::new(ledger);
    let me = Identity {
        id: id.clone(),
        robot: robot_index,
        epoch,
    };
    let config = ProtocolConfig {
        retransmit_ms: section.retransmit_ms,
        ..ProtocolConfig::default()
    };
    let mut node = Node::new(
        me,
        config,
        ledger.clone(),
        Pieces {
            place: Box::new(place),
            verifier: Box::new(TruthVerifier::from_world(world)),
            backend: Box::new(backend),
        },
    );
    let link = ZenohLink::open_until(
        &ZenohLinkConfig {
            team: section.name.clone(),
            me: id,
            link: LinkConfig {
                listen: section.listen.clone(),
                connect: section.connect.clone(),
                multicast_scouting: section.multicast_scouting,
            },
            mode: section.mode,
            lease_ms: Some(section.lease_ms),
            security,
        },
        stop,
    )?;
    let Some(mut link) = link else {
        tracing::info!(robot, "team: stopped before the link opened");
        return Ok(Status {
            robot: robot.into(),
            epoch,
            keyframes_created: 0,
            published_bytes: 0,
            published_messages: 0,
            peers: BTreeMap::new(),
            present: Vec::new(),
            backend: BackendStatus::default(),
            finished: true,
        });
    };
    doorslam_ipc::lifecycle::sd_notify(&format!(
        "READY=1\nSTATUS=team {} epoch {epoch}",
        section.name
    ));
    let watchdog = doorslam_ipc::lifecycle::watchdog_interval();
    tracing::info!(robot, epoch, team = %section.name, "team: link open");

    let start = Instant::now();
    let mut last_write = 0u64;
    let mut last_ping = Instant::now();
    let status = |node: &Node, link: &ZenohLink, finished: bool| Status {
        robot: robot.into(),
        epoch,
        keyframes_created: created.load(Ordering::Acquire),
        published_bytes: link.published_bytes(),
        published_messages: link.published_messages(),
        peers: node
            .sessions()
            .map(|s| {
                let unacked = doorslam_ipc::wire::Kind::ALL
                    .iter()
                    .map(|&k| s.unacknowledged(k).len())
                    .sum();
                (
                    s.peer().to_string(),
                    PeerStatus {
                        stats: s.stats().clone(),
                        delivered_descriptors: s
                            .delivered_descriptors()
                            .iter()
                            .map(|&k| doorslam_geometry::key::index(k))
                            .collect(),
                        unacknowledged_messages: unacked,
                    },
                )
            })
            .collect(),
        present: node
            .sessions()
            .filter(|s| s.is_connected())
            .map(|s| s.peer().to_string())
            .collect(),
        backend: backend_log
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .into(),
        finished,
    };
    let write = |node: &Node, link: &ZenohLink, finished: bool| -> Result<(), RunError> {
        ledger.write_json(&dir.join("ledger.json"))?;
        let text = serde_json::to_string_pretty(&status(node, link, finished)).map_err(|e| {
            RunError::Io {
                path: dir.join("status.json"),
                source: std::io::Error::other(e),
            }
        })?;
        write_atomic(&dir.join("status.json"), &text)
    };
    while !stop.load(Ordering::Acquire) {
        let now_ms = start.elapsed().as_millis() as u64;
        let made = (now_ms / s.keyframe_interval_ms.max(1) + 1).min(s.keyframes);
        created.store(made, Ordering::Release);
        node.step(&mut link, now_ms, Duration::from_millis(20));
        if now_ms >= last_write + section.write_every_ms {
            write(&node, &link, false)?;
            last_write = now_ms;
        }
        if let Some(period) = watchdog {
            if last_ping.elapsed() >= period {
                doorslam_ipc::lifecycle::sd_notify("WATCHDOG=1");
                last_ping = Instant::now();
            }
        }
    }
    doorslam_ipc::lifecycle::sd_notify("STOPPING=1");
    write(&node, &link, true)?;
    let final_status = status(&node, &link, true);
    link.close()?;
    tracing::info!(robot, "team: stopped");
    Ok(final_status)
}
