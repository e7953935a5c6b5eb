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

use crate::ledger::{Ledger, LedgerError, LedgerHandle, LinkCount};
use crate::link::{team_name, LinkConfig, LinkMode, TeamError};
use crate::node::{LinkEvent, Node, Pieces};
use crate::presence::PresenceMends;
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
    /// The bounds of the link's state per peer (README, "Bounds"): messages of one kind
    /// in flight, held back for order by the receiver, and waiting to be sent.
    #[serde(default = "default_window")]
    pub window: usize,
    #[serde(default = "default_receive_window")]
    pub receive_window: u64,
    #[serde(default = "default_outbox_limit")]
    pub outbox_limit: usize,
    /// α: the peer's verification packets kept; putative pairs waiting for one.
    #[serde(default = "default_features_cache")]
    pub features_cache: usize,
    #[serde(default = "default_pending_matches")]
    pub pending_matches: usize,
    /// Ids kept by each set that prevents processing twice (older ones count as seen).
    #[serde(default = "default_seen_ids")]
    pub seen_ids: usize,
    /// Peer sessions held at most (one per robot id heard).
    #[serde(default = "default_max_peers")]
    pub max_peers: usize,
    /// Size of one raw keyframe image (8-bit grayscale), the comparison of `doorslam bw`.
    #[serde(default = "default_width")]
    pub raw_image_width: u64,
    #[serde(default = "default_height")]
    pub raw_image_height: u64,
    /// What the protocol calls into: `robot` (place matching, PnP verification and the
    /// back-end over the robot's iceoryx2 topics: `doorslam-rendezvous`) or `standin`
    /// (simulated keyframes and descriptors of `[team.standin]`, for tests of the link).
    #[serde(default)]
    pub pieces: PiecesKind,
    #[serde(default)]
    pub standin: StandinSection,
    /// `[team.tls]`: TLS with mutual authentication and access control (see
    /// [`crate::security`]); absent = plain TCP, open to anyone on the network.
    #[serde(default)]
    pub tls: Option<TlsSection>,
}

/// `[team] pieces`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PiecesKind {
    #[default]
    Robot,
    Standin,
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
fn default_window() -> usize {
    ProtocolConfig::default().window
}
fn default_receive_window() -> u64 {
    ProtocolConfig::default().receive_window
}
fn default_outbox_limit() -> usize {
    ProtocolConfig::default().outbox_limit
}
fn default_features_cache() -> usize {
    ProtocolConfig::default().features_cache
}
fn default_pending_matches() -> usize {
    ProtocolConfig::default().pending_matches
}
fn default_seen_ids() -> usize {
    ProtocolConfig::default().seen_ids
}
fn default_max_peers() -> usize {
    ProtocolConfig::default().max_peers
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
            window: default_window(),
            receive_window: default_receive_window(),
            outbox_limit: default_outbox_limit(),
            features_cache: default_features_cache(),
            pending_matches: default_pending_matches(),
            seen_ids: default_seen_ids(),
            max_peers: default_max_peers(),
            raw_image_width: default_width(),
            raw_image_height: default_height(),
            pieces: PiecesKind::default(),
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
    /// A failure of the robot's side (its shared memory, its data).
    #[error("{0}")]
    Side(String),
}

impl TeamSection {
    /// The protocol's tunables from this section (the rest at their defaults).
    pub fn protocol(&self) -> ProtocolConfig {
        ProtocolConfig {
            retransmit_ms: self.retransmit_ms,
            window: self.window,
            receive_window: self.receive_window,
            outbox_limit: self.outbox_limit,
            features_cache: self.features_cache,
            pending_matches: self.pending_matches,
            seen_ids: self.seen_ids,
            max_peers: self.max_peers,
            ..ProtocolConfig::default()
        }
    }

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
        // Each bound at least 1 (0 would stall its kind or forget at once), and at most
        // 2^20: a bound is there to cap memory, one larger is a typo.
        let bounds: [(&'static str, u64); 7] = [
            ("window", self.window as u64),
            ("receive_window", self.receive_window),
            ("outbox_limit", self.outbox_limit as u64),
            ("features_cache", self.features_cache as u64),
            ("pending_matches", self.pending_matches as u64),
            ("seen_ids", self.seen_ids as u64),
            ("max_peers", self.max_peers as u64),
        ];
        for (key, value) in bounds {
            if !(1..=1 << 20).contains(&value) {
                return Err(RunError::Config {
                    key,
                    reason: format!("{value}: must be 1 to 1048576"),
                });
            }
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
    /// Bytes and messages handed to Zenoh, counted by the link apart from the ledger's
    /// rows, over every start of the link in this run folder (a restarted link continues
    /// the count, as it continues the ledger).
    pub published_bytes: u64,
    pub published_messages: u64,
    /// Times the link was started in this run folder: more than 1 after a kill, or after
    /// the service failed and its supervisor restarted it.
    #[serde(default)]
    pub link_starts: u64,
    pub peers: BTreeMap<String, PeerStatus>,
    pub present: Vec<String>,
    pub backend: BackendStatus,
    /// The robot side's own counters (place matching, verification, the relay).
    #[serde(default)]
    pub pieces: serde_json::Value,
    pub finished: bool,
    /// The bounds this link runs with (`[team]`), beside the counters of what reached
    /// them (each peer's `stats`).
    #[serde(default)]
    pub bounds: Option<Bounds>,
    /// Messages that failed to encode when sent, and publishes the link refused.
    #[serde(default)]
    pub encode_failures: u64,
    #[serde(default)]
    pub publish_failures: u64,
    /// Peers refused (or sessions evicted) to stay within `max_peers`.
    #[serde(default)]
    pub peers_refused: u64,
    #[serde(default)]
    pub peers_evicted: u64,
    /// What the link's presence checks mended (missed token puts and deletes, sessions
    /// reopened); all 0 on a healthy radio.
    #[serde(default)]
    pub presence: PresenceMends,
}

/// `status.json`'s `bounds`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Bounds {
    pub window: usize,
    pub receive_window: u64,
    pub outbox_limit: usize,
    pub features_cache: usize,
    pub pending_matches: usize,
    pub seen_ids: usize,
    pub max_peers: usize,
}

impl From<&ProtocolConfig> for Bounds {
    fn from(c: &ProtocolConfig) -> Self {
        Self {
            window: c.window,
            receive_window: c.receive_window,
            outbox_limit: c.outbox_limit,
            features_cache: c.features_cache,
            pending_matches: c.pending_matches,
            seen_ids: c.seen_ids,
            max_peers: c.max_peers,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PeerStatus {
    pub stats: PeerStats,
    /// Indices of the peer's keyframes whose descriptors were delivered here.
    pub delivered_descriptors: Vec<u64>,
    /// Every index of the peer at or below this was delivered too (the set above is the
    /// newest `seen_ids`); absent while none was forgotten.
    #[serde(default)]
    pub delivered_floor: Option<u64>,
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
    doorslam_ipc::lifecycle::next_epoch(dir, "team.epoch").map_err(|e| RunError::Epoch {
        path: e.path,
        reason: e.reason,
    })
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

/// What a robot plugs into its team link: the pieces the protocol calls into, and the
/// hooks of every turn that move data in and out of them (the robot's iceoryx2 topics in
/// `doorslam-rendezvous`; a clock for the stand-ins, [`StandinSide`]).
pub trait RobotSide {
    /// Pieces for a node; called at start and whenever the link starts a new epoch (the
    /// pieces share their state, so new ones continue where the old ones were).
    fn pieces(&mut self) -> Pieces;
    /// The link started epoch `epoch` (at start, and after [`Self::before_turn`] asked).
    fn epoch_started(&mut self, epoch: u64) -> Result<(), RunError>;
    /// Before each turn (local time `now_ms`): take new data in. `Ok(true)`: start a new
    /// epoch (what peers were told of this robot's back-end is gone; they resend).
    fn before_turn(&mut self, now_ms: u64, node: &mut Node) -> Result<bool, RunError>;
    /// After each turn: hand out what the pieces produced.
    fn after_turn(&mut self, node: &mut Node) -> Result<(), RunError>;
    /// Keyframes this robot has made so far (for `status.json`).
    fn keyframes(&self) -> u64;
    /// The back-end side's counters (for `status.json`).
    fn backend_status(&self) -> BackendStatus;
    /// Anything else the side reports in `status.json` (`pieces`).
    fn extra_status(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
}

/// The stand-ins of [`crate::standin`] on a clock: simulated keyframes appear one per
/// `keyframe_interval_ms`, verified by a truth table, answered by the echo back-end.
pub struct StandinSide {
    world: SimWorld,
    robot: u8,
    features: usize,
    keyframes: u64,
    interval_ms: u64,
    created: Option<std::sync::Arc<std::sync::atomic::AtomicU64>>,
    log: std::sync::Arc<std::sync::Mutex<BackendLog>>,
}

impl StandinSide {
    pub fn new(s: &StandinSection, robot: u8) -> Self {
        Self {
            world: SimWorld {
                seed: s.seed,
                places: s.places,
                alias_every: s.alias_every,
                ..SimWorld::default()
            },
            robot,
            features: s.features_per_keyframe,
            keyframes: s.keyframes,
            interval_ms: s.keyframe_interval_ms.max(1),
            created: None,
            log: Default::default(),
        }
    }
}

impl RobotSide for StandinSide {
    fn pieces(&mut self) -> Pieces {
        let place = SimPlaces::new(self.world, self.robot, self.features);
        if let Some(old) = &self.created {
            place
                .created()
                .store(old.load(Ordering::Acquire), Ordering::Release);
        }
        self.created = Some(place.created());
        let mut backend = EchoBackend::new(self.robot);
        backend.log = self.log.clone();
        Pieces {
            place: Box::new(place),
            verifier: Box::new(TruthVerifier::from_world(self.world)),
            backend: Box::new(backend),
        }
    }
    fn epoch_started(&mut self, _epoch: u64) -> Result<(), RunError> {
        Ok(())
    }
    fn before_turn(&mut self, now_ms: u64, _node: &mut Node) -> Result<bool, RunError> {
        let made = (now_ms / self.interval_ms + 1).min(self.keyframes);
        if let Some(c) = &self.created {
            c.store(made, Ordering::Release);
        }
        Ok(false)
    }
    fn after_turn(&mut self, _node: &mut Node) -> Result<(), RunError> {
        Ok(())
    }
    fn keyframes(&self) -> u64 {
        self.created
            .as_ref()
            .map_or(0, |c| c.load(Ordering::Acquire))
    }
    fn backend_status(&self) -> BackendStatus {
        self.log
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .into()
    }
}

/// Runs one robot's team link with the stand-ins until `stop` is set (SIGTERM/SIGINT in
/// the CLI).
pub fn run(
    section: &TeamSection,
    robot: &str,
    robot_index: u8,
    stop: &AtomicBool,
) -> Result<Status, RunError> {
    let mut side = StandinSide::new(&section.standin, robot_index);
    run_robot(section, robot, robot_index, &mut side, stop)
}

/// `status.json` of a node.
fn status_of(
    robot: &str,
    epoch: u64,
    node: &Node,
    published: LinkCount,
    presence: PresenceMends,
    side: &dyn RobotSide,
    finished: bool,
) -> Status {
    Status {
        robot: robot.into(),
        epoch,
        keyframes_created: side.keyframes(),
        published_bytes: published.published_bytes,
        published_messages: published.published_messages,
        link_starts: published.starts,
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
                        delivered_floor: s.delivered_floor().map(doorslam_geometry::key::index),
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
        backend: side.backend_status(),
        pieces: side.extra_status(),
        finished,
        bounds: Some(Bounds::from(node.config())),
        encode_failures: node.encode_failures,
        publish_failures: node.publish_failures,
        peers_refused: node.peers_refused,
        peers_evicted: node.peers_evicted,
        presence,
    }
}

/// Runs one robot's team link with `side`'s pieces until `stop` is set. Writes
/// `<run_dir>/<robot>/ledger.json` and `status.json` every `write_every_ms` and at the end.
pub fn run_robot(
    section: &TeamSection,
    robot: &str,
    robot_index: u8,
    side: &mut dyn RobotSide,
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
    let mut epoch = next_epoch(&dir)?;
    // A restarted link continues its ledger: every byte of the run stays counted.
    let previous = dir.join("ledger.json");
    let ledger = match previous
        .is_file()
        .then(|| crate::ledger::LedgerFile::read(&previous))
    {
        Some(Ok(file)) if file.robot == robot && file.team == section.name => {
            tracing::info!(ledger = %previous.display(), "team: continuing the ledger of the previous start");
            Ledger::resume(file, epoch)
        }
        Some(Ok(_)) | None => Ledger::new(
            robot,
            &section.name,
            epoch,
            section.raw_image_width * section.raw_image_height,
        ),
        Some(Err(e)) => {
            let aside = dir.join(format!("ledger.json.unreadable-{epoch}"));
            tracing::error!(
                "team: {e}; kept as {} and starting a new ledger",
                aside.display()
            );
            std::fs::rename(&previous, &aside).map_err(|source| RunError::Io {
                path: previous.clone(),
                source,
            })?;
            Ledger::new(
                robot,
                &section.name,
                epoch,
                section.raw_image_width * section.raw_image_height,
            )
        }
    };
    let ledger = LedgerHandle::new(if security.is_some() {
        ledger.over_tls()
    } else {
        ledger
    });
    let config = section.protocol();
    let new_node = |epoch: u64, side: &mut dyn RobotSide| {
        let me = Identity {
            id: id.clone(),
            robot: robot_index,
            epoch,
        };
        Node::new(me, config, ledger.clone(), side.pieces())
    };
    let mut node = new_node(epoch, side);
    let link = ZenohLink::open_until(
        &ZenohLinkConfig {
            team: section.name.clone(),
            me: id.clone(),
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
        let published = ledger.lock().link_count();
        return Ok(Status {
            robot: robot.into(),
            epoch,
            keyframes_created: side.keyframes(),
            published_bytes: published.published_bytes,
            published_messages: published.published_messages,
            link_starts: published.starts,
            peers: BTreeMap::new(),
            present: Vec::new(),
            backend: side.backend_status(),
            pieces: side.extra_status(),
            finished: true,
            bounds: Some(Bounds::from(&config)),
            encode_failures: 0,
            publish_failures: 0,
            peers_refused: 0,
            peers_evicted: 0,
            presence: PresenceMends::default(),
        });
    };
    side.epoch_started(epoch)?;
    doorslam_ipc::lifecycle::sd_notify(&format!(
        "READY=1\nSTATUS=team {} epoch {epoch}",
        section.name
    ));
    let watchdog = doorslam_ipc::lifecycle::watchdog_interval();
    tracing::info!(robot, epoch, team = %section.name, "team: link open");

    let start = Instant::now();
    let mut last_write = 0u64;
    let mut last_ping = Instant::now();
    let write = |node: &Node,
                 link: &ZenohLink,
                 side: &dyn RobotSide,
                 epoch: u64,
                 finished: bool|
     -> Result<(), RunError> {
        // The link's count goes into the ledger's file with the rows it must agree with.
        let published = {
            let mut l = ledger.lock();
            l.link_published(link.published_bytes(), link.published_messages());
            l.link_count()
        };
        ledger.write_json(&dir.join("ledger.json"))?;
        let status = status_of(
            robot,
            epoch,
            node,
            published,
            link.presence_mends(),
            side,
            finished,
        );
        let text = serde_json::to_string_pretty(&status).map_err(|e| RunError::Io {
            path: dir.join("status.json"),
            source: std::io::Error::other(e),
        })?;
        write_atomic(&dir.join("status.json"), &text)
    };
    while !stop.load(Ordering::Acquire) {
        let now_ms = start.elapsed().as_millis() as u64;
        if side.before_turn(now_ms, &mut node)? {
            // The back-end behind this link restarted: a new epoch makes every peer forget
            // what it sent us and send it again; peers present now stay present.
            epoch = next_epoch(&dir)?;
            let present: Vec<RobotId> = node
                .sessions()
                .filter(|s| s.is_connected())
                .map(|s| s.peer().clone())
                .collect();
            node = new_node(epoch, side);
            for p in present {
                node.handle(LinkEvent::PeerAppeared(p), now_ms);
            }
            side.epoch_started(epoch)?;
            tracing::info!(robot, epoch, "team: new epoch (the back-end restarted)");
        }
        node.step(&mut link, now_ms, Duration::from_millis(20));
        side.after_turn(&mut node)?;
        if now_ms >= last_write + section.write_every_ms {
            write(&node, &link, side, epoch, false)?;
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
    side.after_turn(&mut node)?;
    write(&node, &link, side, epoch, true)?;
    let final_status = status_of(
        robot,
        epoch,
        &node,
        ledger.lock().link_count(),
        link.presence_mends(),
        side,
        true,
    );
    link.close()?;
    tracing::info!(robot, "team: stopped");
    Ok(final_status)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bounds are read from `[team]`, absent keys keep the protocol's defaults, and a
    /// bound of 0 is refused naming its key.
    #[test]
    fn bounds_come_from_the_team_section() {
        let section: TeamSection =
            toml::from_str("features_cache = 64\nreceive_window = 8\nseen_ids = 100\n").unwrap();
        let c = section.protocol();
        assert_eq!(c.features_cache, 64);
        assert_eq!(c.receive_window, 8);
        assert_eq!(c.seen_ids, 100);
        let d = ProtocolConfig::default();
        assert_eq!(c.outbox_limit, d.outbox_limit);
        assert_eq!(c.pending_matches, d.pending_matches);
        assert_eq!(c.window, d.window);
        assert_eq!(
            TeamSection::default().protocol(),
            ProtocolConfig {
                retransmit_ms: 1000,
                ..d
            }
        );
        let zero: TeamSection = toml::from_str("outbox_limit = 0\n").unwrap();
        match zero.validate() {
            Err(RunError::Config { key, .. }) => assert_eq!(key, "outbox_limit"),
            other => panic!("expected a config error, got {other:?}"),
        }
    }
}
