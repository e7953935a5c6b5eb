//! The back-end's side of the team: the distributed back-end's [`Agent`] behind the
//! relay with the team link (iceoryx2 topics `team-in` / `team-out`, one
//! [`doorslam_ipc::WireEnvelope`] per event or message).
//!
//! The team link is the transport, under its delivery contract (`doorslam-team`'s
//! `delivery`): every message it takes reaches the peer exactly once, in order per kind,
//! across meetings cut off mid-way. So the agent runs with
//! [`AgentOptions::link_delivers`]: it settles what it hands over as delivered and sends
//! no acknowledgements of its own; nothing is acknowledged in a peer's name. Two cases
//! break "delivered", and both are announced by the ends of the relay: the team link
//! restarted (messages it held are gone: [`EnvelopeEvent::TeamStarted`] makes the agent
//! send everything again) and a peer's team link restarted (a new epoch in its Hello,
//! reported in [`EnvelopeEvent::PeerPresent`]: the peer's link dropped the state messages
//! it held, so the agent sends everything again).
//! A restart of this back-end is announced to the team link
//! ([`EnvelopeEvent::BackendStarted`]), which starts a new epoch of its own so that peers
//! send their state again.
//!
//! This is a plain struct fed by values: no iceoryx2 here, tested in-process.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use doorslam_geometry::{key, TangentMatrix, SE3};
use doorslam_ipc::wire::{Message, RobotId};
use doorslam_ipc::EnvelopeEvent;

use crate::distributed::{Agent, AgentOptions, AgentStats, DpgoError};

/// What the bridge did, for the status file and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct BridgeStats {
    /// Messages received from peers and given to the agent.
    pub messages_in: u64,
    /// Messages handed to the team link.
    pub messages_out: u64,
    /// Bytes of those messages (encoded wire messages, headers included: what the team
    /// link publishes is a header of its own plus this body).
    pub bytes_out: u64,
    /// Messages from peers the agent refused (malformed, not a back-end kind, ...).
    pub refused: u64,
    /// Envelopes that were not understood (unknown event, undecodable message).
    pub bad_envelopes: u64,
    /// Times the team link restarted behind this back-end.
    pub team_restarts: u64,
}

/// One peer as the team link reported it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Peer {
    /// The peer's team-link epoch, from its Hello.
    epoch: u64,
    present: bool,
}

/// Why an envelope from the team link was not used.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error("team-in envelope with unknown event {0}")]
    UnknownEvent(u32),
    #[error("team-in envelope for robot {0}: not a robot number (0..26)")]
    Robot(u32),
    #[error("team-in message from robot {robot} does not decode: {reason}")]
    Decode { robot: u8, reason: String },
    #[error("team-in envelope of event {0:?} is not for the back-end")]
    Unexpected(EnvelopeEvent),
    #[error("message from robot {robot} refused: {source}")]
    Refused {
        robot: u8,
        #[source]
        source: DpgoError,
    },
}

/// The distributed back-end of one robot and its relay with the team link.
#[derive(Debug)]
pub struct TeamBridge {
    agent: Agent,
    robot: u8,
    /// The agent's epoch: this back-end's start count (acknowledgements carry it).
    epoch: u64,
    peers: BTreeMap<u8, Peer>,
    /// The team link's epoch last announced.
    team_epoch: Option<u64>,
    /// Something changed since the agent last stepped.
    dirty: bool,
    stats: BridgeStats,
    /// Messages the agent refused, per peer robot and message kind (`BridgeStats::refused`
    /// split: which teammate sent what that was refused).
    refused_from: BTreeMap<u8, BTreeMap<&'static str, u64>>,
    /// The origin of the agent's clock (its timeouts are in seconds of it).
    started: Instant,
}

impl TeamBridge {
    /// The bridge of robot `robot` (0 = 'a') with wire id `id`; `epoch` must grow at every
    /// start of the back-end (see `super::next_epoch`).
    pub fn new(robot: u8, id: RobotId, epoch: u64, options: AgentOptions) -> Self {
        let options = AgentOptions {
            link_delivers: true,
            ..options
        };
        Self {
            agent: Agent::new(robot, id, epoch, options),
            robot,
            epoch,
            peers: BTreeMap::new(),
            team_epoch: None,
            dirty: true,
            stats: BridgeStats::default(),
            refused_from: BTreeMap::new(),
            started: Instant::now(),
        }
    }

    pub fn epoch(&self) -> u64 {
        self.epoch
    }
    pub fn agent(&self) -> &Agent {
        &self.agent
    }
    pub fn stats(&self) -> BridgeStats {
        self.stats
    }
    pub fn agent_stats(&self) -> AgentStats {
        self.agent.stats()
    }
    /// Messages refused per peer robot and kind (`separator_graph`, `route`, ...).
    pub fn refused_from(&self) -> &BTreeMap<u8, BTreeMap<&'static str, u64>> {
        &self.refused_from
    }
    /// Peers the team link reports present.
    pub fn present(&self) -> impl Iterator<Item = u8> + '_ {
        self.peers
            .iter()
            .filter(|(_, p)| p.present)
            .map(|(r, _)| *r)
    }

    /// A keyframe of this robot (in index order).
    pub fn add_pose(&mut self, k: u64, pose: SE3) -> Result<(), DpgoError> {
        self.dirty = true;
        self.agent.add_pose(k, pose)
    }

    /// An odometry edge between two keyframes of this robot.
    pub fn add_odometry(
        &mut self,
        a: u64,
        b: u64,
        z: SE3,
        information: TangentMatrix,
    ) -> Result<(), DpgoError> {
        self.dirty = true;
        self.agent.add_odometry(a, b, z, information)
    }

    /// A verified inter-robot loop closure (outliers are PCM's job, inside the agent).
    pub fn add_closure(
        &mut self,
        a: u64,
        b: u64,
        z: SE3,
        information: TangentMatrix,
    ) -> Result<(), DpgoError> {
        self.dirty = true;
        let result = self.agent.add_closure(a, b, z, information);
        // A closure with a peer already present: the agent learns it is present now.
        for (&r, p) in &self.peers {
            self.agent.set_present(r, p.present);
        }
        result
    }

    /// One envelope from the team link. `Ok(true)` when the back-end must announce itself
    /// (a team link it had not heard of yet, which may not know this back-end's epoch).
    pub fn on_envelope(
        &mut self,
        event: u32,
        peer_robot: u32,
        epoch: u64,
        bytes: &[u8],
    ) -> Result<bool, BridgeError> {
        let event = EnvelopeEvent::try_from(event).map_err(|e| {
            self.stats.bad_envelopes += 1;
            BridgeError::UnknownEvent(e)
        })?;
        let robot = || key::robot_index(peer_robot).map_err(|_| BridgeError::Robot(peer_robot));
        match event {
            EnvelopeEvent::TeamStarted => {
                if self.team_epoch.is_some_and(|e| e != epoch) {
                    // Messages the old team link had not delivered are gone.
                    self.stats.team_restarts += 1;
                    let neighbours: Vec<u8> = self.agent.neighbors().collect();
                    for n in neighbours {
                        self.agent.link_restarted(n);
                    }
                    for p in self.peers.values_mut() {
                        p.present = false;
                    }
                    for r in self.peers.keys() {
                        self.agent.set_present(*r, false);
                    }
                }
                // Announce this back-end when the link is new to it (not for a repeat,
                // or the two ends would answer each other forever).
                let new = self.team_epoch != Some(epoch);
                self.team_epoch = Some(epoch);
                self.dirty = true;
                Ok(new)
            }
            EnvelopeEvent::PeerPresent | EnvelopeEvent::PeerAbsent => {
                let r = robot().inspect_err(|_| self.stats.bad_envelopes += 1)?;
                if r == self.robot {
                    self.stats.bad_envelopes += 1;
                    return Err(BridgeError::Robot(peer_robot));
                }
                let present = event == EnvelopeEvent::PeerPresent;
                let peer = self.peers.entry(r).or_insert(Peer { epoch, present });
                peer.present = present;
                if present && peer.epoch != epoch {
                    // The peer's team link restarted: what its old session held is gone.
                    peer.epoch = epoch;
                    self.agent.link_restarted(r);
                }
                self.agent.set_present(r, present);
                self.dirty = true;
                Ok(false)
            }
            EnvelopeEvent::Message => {
                let r = robot().inspect_err(|_| self.stats.bad_envelopes += 1)?;
                let message = Message::decode(bytes).map_err(|e| {
                    self.stats.bad_envelopes += 1;
                    BridgeError::Decode {
                        robot: r,
                        reason: e.to_string(),
                    }
                })?;
                self.stats.messages_in += 1;
                self.dirty = true;
                self.agent.receive(r, &message).map_err(|source| {
                    self.stats.refused += 1;
                    *self
                        .refused_from
                        .entry(r)
                        .or_default()
                        .entry(message.kind().name())
                        .or_default() += 1;
                    BridgeError::Refused { robot: r, source }
                })?;
                Ok(false)
            }
            EnvelopeEvent::BackendStarted => {
                self.stats.bad_envelopes += 1;
                Err(BridgeError::Unexpected(event))
            }
        }
    }

    /// Iterates the agent when something changed (new keyframes, closures, messages,
    /// peers); whether it solved anything.
    pub fn step(&mut self) -> Result<bool, DpgoError> {
        self.step_at(self.started.elapsed())
    }

    /// [`Self::step`] at `now` since the bridge started (tests drive a simulated clock).
    pub fn step_at(&mut self, now: Duration) -> Result<bool, DpgoError> {
        if !self.dirty {
            return Ok(false);
        }
        self.dirty = false;
        let solved = self.agent.step(now)?;
        // Messages still due (a neighbour newly present, forwarding delays) need more steps.
        if !self.agent.converged() {
            self.dirty = true;
        }
        Ok(solved)
    }

    /// The messages to hand to the team link now, encoded, per peer robot (the agent
    /// settles each as delivered: see the module documentation).
    pub fn outgoing(&mut self) -> Result<Vec<(u8, Vec<u8>)>, DpgoError> {
        let mut out = Vec::new();
        let present: Vec<u8> = self.present().collect();
        for r in present {
            for m in self.agent.messages_for(r)? {
                let bytes = match m.encode() {
                    Ok(b) => b,
                    Err(e) => {
                        // Our own message: a bug, logged and not sent.
                        tracing::error!(peer = r, error = %e, "backend: own message does not encode");
                        continue;
                    }
                };
                self.stats.messages_out += 1;
                self.stats.bytes_out += bytes.len() as u64;
                out.push((r, bytes));
            }
        }
        Ok(out)
    }

    /// This robot's poses: in the team's frame once the agent is anchored (see
    /// [`Agent::anchored`]), the odometry's frame before.
    pub fn estimate(&self) -> impl Iterator<Item = (u64, &SE3)> + '_ {
        self.agent.estimate()
    }
}
