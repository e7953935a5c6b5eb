//! `doorslam service team` on a robot: the team link with the real pieces, fed by the
//! robot's iceoryx2 topics.
//!
//! In: `keyframes` (the front-end's, for verification packets), `descriptors` (place
//! recognition's), `team-out` (the back-end's messages for peers, and its start
//! announcements). Out: `closures` (verified inter-robot loop closures) and `team-in`
//! (peers present/absent and the back-end messages they sent) to the back-end.

use std::sync::atomic::AtomicBool;

use doorslam_ipc::wire::Message;
use doorslam_ipc::{
    create_node, EnvelopeEvent, Keyframe, LoopClosure, PlaceDescriptor, Receiver, Sender, Topic,
    WireEnvelope,
};
use doorslam_team::runner::{run_robot, BackendStatus, RobotSide, RunError, Status, TeamSection};
use doorslam_team::{Node, Pieces};

use crate::pieces::{MatchSettings, Shared};

fn side_error(e: impl std::fmt::Display) -> RunError {
    RunError::Side(e.to_string())
}

/// The robot's side of the team link over its iceoryx2 topics.
pub struct IpcSide {
    shared: Shared,
    robot_index: u8,
    keyframes: Receiver<Keyframe>,
    descriptors: Receiver<PlaceDescriptor>,
    team_out: Receiver<WireEnvelope>,
    team_in: Sender<WireEnvelope>,
    closures: Sender<LoopClosure>,
    /// The back-end's epoch, from its last start announcement, and the link's.
    backend_epoch: Option<u64>,
    link_epoch: u64,
    // Declared last: dropped after the ports.
    _node: doorslam_ipc::iceoryx2::prelude::Node<doorslam_ipc::iceoryx2::prelude::ipc::Service>,
}

impl IpcSide {
    /// Opens the topics of robot `robot` (its id: the iceoryx2 service prefix).
    pub fn open(robot: &str, robot_index: u8, shared: Shared) -> Result<Self, RunError> {
        let (node, cleaned) = create_node("doorslam-team").map_err(side_error)?;
        if cleaned > 0 {
            tracing::warn!(cleaned, "team: removed shared memory of dead processes");
        }
        Ok(Self {
            keyframes: Receiver::new(&node, robot, Topic::Keyframes).map_err(side_error)?,
            descriptors: Receiver::new(&node, robot, Topic::Descriptors).map_err(side_error)?,
            team_out: Receiver::new(&node, robot, Topic::TeamOut).map_err(side_error)?,
            team_in: Sender::new(&node, robot, Topic::TeamIn).map_err(side_error)?,
            closures: Sender::new(&node, robot, Topic::Closures).map_err(side_error)?,
            shared,
            robot_index,
            backend_epoch: None,
            link_epoch: 0,
            _node: node,
        })
    }

    fn publish(&self) -> Result<(), RunError> {
        let (envelopes, closures) = self.shared.take_for_backend();
        for c in &closures {
            self.closures.send_copy(c).map_err(side_error)?;
        }
        for e in envelopes {
            self.team_in
                .send_with(|slot| {
                    WireEnvelope::write(slot, e.event, e.peer_robot, e.epoch, &e.bytes)
                })
                .map_err(side_error)?;
        }
        Ok(())
    }
}

impl RobotSide for IpcSide {
    fn pieces(&mut self) -> Pieces {
        self.shared.pieces()
    }

    fn epoch_started(&mut self, epoch: u64) -> Result<(), RunError> {
        self.link_epoch = epoch;
        self.shared.new_epoch(epoch);
        self.publish()
    }

    fn before_turn(&mut self, _now_ms: u64, _node: &mut Node) -> Result<bool, RunError> {
        while let Some(s) = self.keyframes.try_recv().map_err(side_error)? {
            if let Err(e) = self.shared.add_keyframe(s.payload()) {
                tracing::error!("team: keyframe refused: {e}");
            }
        }
        while let Some(s) = self.descriptors.try_recv().map_err(side_error)? {
            if let Err(e) = self.shared.add_descriptor(s.payload()) {
                tracing::error!("team: place descriptor refused: {e}");
            }
        }
        let mut restart = false;
        while let Some(s) = self.team_out.try_recv().map_err(side_error)? {
            let e = s.payload();
            match e.event() {
                Ok(EnvelopeEvent::BackendStarted) => {
                    if e.peer_robot != u32::from(self.robot_index) {
                        tracing::error!(robot = e.peer_robot, "team: back-end of another robot announced itself on this robot's topic");
                        continue;
                    }
                    match self.backend_epoch.replace(e.epoch) {
                        // The back-end restarted: peers hold state it lost.
                        Some(old) if old != e.epoch => restart = true,
                        // First heard (or again): tell it this link's epoch and who is here.
                        _ => {
                            self.shared.announce_team(self.link_epoch);
                            self.shared.announce_presence();
                        }
                    }
                }
                Ok(EnvelopeEvent::Message) => match Message::decode(e.bytes()) {
                    Ok(m) => match u8::try_from(e.peer_robot) {
                        Ok(r) => self.shared.queue_for_peer(r, m),
                        Err(_) => tracing::error!(
                            robot = e.peer_robot,
                            "team: back-end message for a robot number out of range"
                        ),
                    },
                    Err(err) => tracing::error!("team: back-end message does not decode: {err}"),
                },
                Ok(other) => {
                    tracing::error!(event = ?other, "team: team-out envelope of an event the back-end does not send")
                }
                Err(v) => tracing::error!(event = v, "team: team-out envelope of an unknown event"),
            }
        }
        Ok(restart)
    }

    fn after_turn(&mut self, _node: &mut Node) -> Result<(), RunError> {
        self.publish()
    }

    fn keyframes(&self) -> u64 {
        self.shared.keyframes()
    }

    fn backend_status(&self) -> BackendStatus {
        let s = self.shared.stats();
        BackendStatus {
            closures: s.closures_by_peer.clone(),
            estimates_received: s.backend_messages_by_peer.clone(),
            rounds_sent: s.peer_messages_by_peer.clone(),
        }
    }

    fn extra_status(&self) -> serde_json::Value {
        serde_json::to_value(self.shared.stats()).unwrap_or_default()
    }
}

/// How the robot's pieces are set up.
#[derive(Debug, Clone)]
pub struct RobotPieces {
    pub calibration: doorslam_dataset::StereoCalibration,
    pub matching: MatchSettings,
}

/// Runs the team link of robot `robot` (index `robot_index`) with its real pieces until
/// `stop` is set.
pub fn run(
    section: &TeamSection,
    robot: &str,
    robot_index: u8,
    pieces: &RobotPieces,
    stop: &AtomicBool,
) -> Result<Status, RunError> {
    let shared = Shared::new(robot_index, pieces.calibration, pieces.matching.clone());
    // Own keyframes of earlier runs (a restart): offered to the peers again.
    shared
        .open_store(&section.run_dir.join(robot).join("team.own"))
        .map_err(side_error)?;
    let mut side = IpcSide::open(robot, robot_index, shared)?;
    tracing::info!(
        robot,
        chain = ?pieces.matching.chain,
        own_loops = pieces.matching.own_loops.is_some(),
        "team: place matching (candidate chain), PnP verification and the back-end relay over iceoryx2"
    );
    run_robot(section, robot, robot_index, &mut side, stop)
}

/// `[rendezvous]` of robot.toml: how putative pairs are verified. (The camera model is
/// the front-end's, `[frontend]`; the descriptor threshold place recognition's, `[place]`.)
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RendezvousSection {
    /// Features in a verification packet (see [`MatchSettings`]).
    #[serde(default = "default_packet")]
    pub max_packet_features: usize,
    #[serde(default)]
    pub verify: doorslam_frontend::VerifyConfig,
    /// The back-end's messages waiting for one absent peer at most (see [`MatchSettings`]).
    #[serde(default = "default_for_peer_limit")]
    pub for_peer_limit: usize,
    /// Own keyframes' features held in memory at most (see [`MatchSettings`]).
    #[serde(default = "default_features_in_memory")]
    pub features_in_memory: usize,
}

fn default_features_in_memory() -> usize {
    MatchSettings::default().features_in_memory
}

fn default_for_peer_limit() -> usize {
    MatchSettings::default().for_peer_limit
}

fn default_packet() -> usize {
    MatchSettings::default().max_packet_features
}

impl Default for RendezvousSection {
    fn default() -> Self {
        Self {
            max_packet_features: default_packet(),
            verify: doorslam_frontend::VerifyConfig::default(),
            for_peer_limit: default_for_peer_limit(),
            features_in_memory: default_features_in_memory(),
        }
    }
}

impl RendezvousSection {
    /// Checks the values; the error names the key.
    pub fn validate(&self) -> Result<(), String> {
        let max = doorslam_frontend::packet::MAX_PACKET_FEATURES;
        if self.max_packet_features < self.verify.min_inliers.max(4)
            || self.max_packet_features > max
        {
            return Err(format!(
                "rendezvous.max_packet_features = {}: from verify.min_inliers ({}) to {max} (≤ 20 kB per packet)",
                self.max_packet_features, self.verify.min_inliers
            ));
        }
        if !(1..=1 << 20).contains(&self.for_peer_limit) {
            return Err(format!(
                "rendezvous.for_peer_limit = {}: from 1 to 1048576",
                self.for_peer_limit
            ));
        }
        if !(1..=1 << 20).contains(&self.features_in_memory) {
            return Err(format!(
                "rendezvous.features_in_memory = {}: from 1 to 1048576",
                self.features_in_memory
            ));
        }
        Ok(())
    }

    /// The matching settings, with place recognition's candidate chain (`[place]`), own
    /// loops on or off, and how recent an own keyframe is not a loop candidate.
    pub fn matching(
        &self,
        chain: doorslam_place_recognition::ChainConfig,
        own_loops: bool,
        temporal_exclusion: u64,
    ) -> MatchSettings {
        MatchSettings {
            own_loops: own_loops.then(|| chain.clone()),
            chain,
            temporal_exclusion,
            max_packet_features: self.max_packet_features,
            verify: self.verify.clone(),
            for_peer_limit: self.for_peer_limit,
            features_in_memory: self.features_in_memory,
        }
    }
}
