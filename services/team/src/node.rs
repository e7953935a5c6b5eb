//! One robot's end of the team link, independent of the transport: discovery events and
//! raw messages come in through a [`Link`] (Zenoh: [`crate::zenoh_link::ZenohLink`];
//! in-process emulation with loss and cuts: [`crate::emulate::EmulatedLink`]), go through
//! the checks every message from another robot gets (known peer, decodes, the key's sender
//! is the header's), the [`Ledger`], and one [`PeerSession`] per peer.

use std::collections::BTreeMap;

use doorslam_ipc::wire::{Kind, Message, RobotId};

use crate::ledger::{items, Direction, LedgerHandle};
use crate::protocol::{
    BackendExchange, DescriptorSource, Identity, PeerSession, ProtocolConfig, Services, Verifier,
};

/// What a link reports.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LinkEvent {
    /// The peer's liveliness token appeared: a rendezvous starts.
    PeerAppeared(RobotId),
    /// The peer's token disappeared (it left radio range or stopped).
    PeerLeft(RobotId),
    /// Bytes published to this robot; `from` and `kind` as the key expression names them.
    Message {
        from: RobotId,
        kind: String,
        bytes: Vec<u8>,
    },
    /// A sample under this robot's inbox whose key is not a message key.
    Malformed { key: String, bytes: usize },
}

/// Failures of a link.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("publish {kind} to {to}: {reason}")]
    Publish {
        to: String,
        kind: &'static str,
        reason: String,
    },
}

/// A transport between robots: Zenoh, or an in-process emulation with the same behaviour.
pub trait Link {
    /// Publishes one encoded message to `to` under `doorslam/<team>/<to>/<kind>/<me>`.
    fn publish(&mut self, to: &RobotId, kind: Kind, bytes: &[u8]) -> Result<(), LinkError>;
    /// Events since the last call, waiting at most `timeout` for the first.
    fn poll_events(&mut self, timeout: std::time::Duration) -> Vec<LinkEvent>;
}

/// This robot's pieces the protocol calls into.
pub struct Pieces {
    pub place: Box<dyn DescriptorSource + Send>,
    pub verifier: Box<dyn Verifier + Send>,
    pub backend: Box<dyn BackendExchange + Send>,
}

/// One robot's team link state: every peer ever met, the present ones, the ledger.
pub struct Node {
    me: Identity,
    config: ProtocolConfig,
    sessions: BTreeMap<RobotId, PeerSession>,
    ledger: LedgerHandle,
    pieces: Pieces,
    /// Messages whose encoding failed when sent (our own bug, not the peer's): counted,
    /// never sent. Every body is checked when queued (refused there, see
    /// [`crate::delivery::QueueError`]), so this stays 0 unless a Hello or an
    /// acknowledgement, which the link makes itself, fails.
    pub encode_failures: u64,
    /// Publishes the link refused.
    pub publish_failures: u64,
    /// Peers that appeared while `max_peers` sessions were held and none could make room
    /// (their messages are dropped as `unknown_peer`), and sessions evicted to make room.
    pub peers_refused: u64,
    pub peers_evicted: u64,
}

impl Node {
    pub fn new(me: Identity, config: ProtocolConfig, ledger: LedgerHandle, pieces: Pieces) -> Self {
        Self {
            me,
            config,
            sessions: BTreeMap::new(),
            ledger,
            pieces,
            encode_failures: 0,
            publish_failures: 0,
            peers_refused: 0,
            peers_evicted: 0,
        }
    }

    pub fn identity(&self) -> &Identity {
        &self.me
    }

    /// The protocol's tunables (and bounds) of every session.
    pub fn config(&self) -> &ProtocolConfig {
        &self.config
    }

    pub fn ledger(&self) -> &LedgerHandle {
        &self.ledger
    }

    pub fn session(&self, peer: &RobotId) -> Option<&PeerSession> {
        self.sessions.get(peer)
    }

    pub fn sessions(&self) -> impl Iterator<Item = &PeerSession> {
        self.sessions.values()
    }

    pub fn pieces(&mut self) -> &mut Pieces {
        &mut self.pieces
    }

    fn rendezvous(&self, peer: &RobotId) -> Option<u64> {
        self.sessions
            .get(peer)
            .filter(|s| s.is_connected())
            .map(|s| s.stats().meetings - 1)
    }

    /// Room for a session with a new peer within `max_peers`: when full, the session of a
    /// peer that is absent and never said Hello (a token that came and went, nothing of a
    /// robot's state in it) is evicted; with none such the new peer is refused, so a flood
    /// of made-up ids cannot push out the team's real robots.
    fn make_room(&mut self, peer: &RobotId) -> bool {
        if self.sessions.len() < self.config.max_peers {
            return true;
        }
        let idle = self
            .sessions
            .iter()
            .find(|(_, s)| !s.is_connected() && s.peer_robot().is_none())
            .map(|(id, _)| id.clone());
        match idle {
            Some(id) => {
                self.sessions.remove(&id);
                self.peers_evicted += 1;
                true
            }
            None => {
                tracing::warn!(peer = %peer, max_peers = self.config.max_peers, "peer refused: max_peers sessions held");
                self.peers_refused += 1;
                self.ledger.lock().dropped(peer.as_str(), "max_peers", 0);
                false
            }
        }
    }

    /// Applies one link event at local time `now_ms`.
    pub fn handle(&mut self, event: LinkEvent, now_ms: u64) {
        match event {
            LinkEvent::PeerAppeared(peer) => {
                if peer == self.me.id {
                    return;
                }
                if !self.sessions.contains_key(&peer) && !self.make_room(&peer) {
                    return;
                }
                let session = self.sessions.entry(peer.clone()).or_insert_with(|| {
                    PeerSession::new(self.me.clone(), peer.clone(), self.config)
                });
                if session.is_connected() {
                    return;
                }
                session.meeting_started();
                let index = session.stats().meetings - 1;
                tracing::info!(peer = %peer, rendezvous = index, "peer appeared");
                // A peer met before does not say Hello again (unless it restarted).
                if let (Some(robot), Some(epoch)) = (session.peer_robot(), session.peer_epoch()) {
                    self.pieces.backend.presence(&peer, robot, epoch, true);
                }
                self.ledger
                    .lock()
                    .rendezvous_started(peer.as_str(), index, now_ms);
            }
            LinkEvent::PeerLeft(peer) => {
                if let Some(s) = self.sessions.get_mut(&peer) {
                    if s.is_connected() {
                        s.meeting_ended();
                        tracing::info!(peer = %peer, "peer left");
                        self.ledger.lock().rendezvous_ended(peer.as_str(), now_ms);
                        if let (Some(robot), Some(epoch)) = (s.peer_robot(), s.peer_epoch()) {
                            self.pieces.backend.presence(&peer, robot, epoch, false);
                        }
                    }
                }
            }
            LinkEvent::Malformed { key, bytes } => {
                tracing::debug!(key, "sample with a malformed key dropped");
                self.ledger.lock().dropped("?", "bad_key", bytes);
            }
            LinkEvent::Message { from, kind, bytes } => self.message(from, &kind, &bytes),
        }
    }

    fn message(&mut self, from: RobotId, kind: &str, bytes: &[u8]) {
        let drop = |node: &Self, reason: &str| {
            node.ledger
                .lock()
                .dropped(from.as_str(), reason, bytes.len());
        };
        // Only peers whose token is present: a robot that never joined the team's
        // liveliness (or left it) cannot inject.
        let Some(rendezvous) = self.rendezvous(&from) else {
            drop(self, "unknown_peer");
            return;
        };
        let msg = match Message::decode(bytes) {
            Ok(m) => m,
            Err(e) => {
                tracing::debug!(peer = %from, error = %e, "undecodable message dropped");
                drop(self, "decode_error");
                return;
            }
        };
        if msg.header.sender != from {
            drop(self, "wrong_sender");
            return;
        }
        if msg.kind().name() != kind {
            drop(self, "wrong_kind");
            return;
        }
        self.ledger.lock().record(
            Direction::Received,
            from.as_str(),
            Some(rendezvous),
            kind,
            bytes.len(),
            items(&msg.body),
            false,
        );
        let Some(session) = self.sessions.get_mut(&from) else {
            return;
        };
        let mut svc = Services {
            place: self.pieces.place.as_mut(),
            verifier: self.pieces.verifier.as_mut(),
            backend: self.pieces.backend.as_mut(),
        };
        let refusals = match session.receive(msg, &mut svc) {
            Ok(refusals) => refusals,
            Err(refusal) => vec![refusal],
        };
        for refusal in refusals {
            tracing::debug!(peer = %from, %refusal, "message not processed");
            self.ledger
                .lock()
                .dropped(from.as_str(), refusal.reason(), bytes.len());
        }
    }

    /// Sends what every present peer's session has to send at local time `now_ms`.
    pub fn flush(&mut self, link: &mut dyn Link, now_ms: u64) {
        let mut svc = Services {
            place: self.pieces.place.as_mut(),
            verifier: self.pieces.verifier.as_mut(),
            backend: self.pieces.backend.as_mut(),
        };
        for (peer, session) in self.sessions.iter_mut() {
            if !session.is_connected() {
                continue;
            }
            let rendezvous = session.stats().meetings - 1;
            for out in session.poll(now_ms, &mut svc) {
                let msg = out.message;
                let bytes = match msg.encode() {
                    Ok(b) => b,
                    Err(e) => {
                        tracing::error!(peer = %peer, kind = msg.kind().name(), error = %e, "own message does not encode");
                        self.encode_failures += 1;
                        continue;
                    }
                };
                // Counted when handed to the link: what the ledger says was published is
                // what was published (a failed publish is counted apart).
                if let Err(e) = link.publish(peer, msg.kind(), &bytes) {
                    tracing::warn!(error = %e, "publish failed");
                    self.publish_failures += 1;
                    continue;
                }
                self.ledger.lock().record(
                    Direction::Sent,
                    peer.as_str(),
                    Some(rendezvous),
                    msg.kind().name(),
                    bytes.len(),
                    items(&msg.body),
                    out.resend,
                );
            }
        }
    }

    /// One turn: take the link's events (waiting at most `timeout`), then send.
    pub fn step(&mut self, link: &mut dyn Link, now_ms: u64, timeout: std::time::Duration) {
        for event in link.poll_events(timeout) {
            self.handle(event, now_ms);
        }
        self.flush(link, now_ms);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ledger::Ledger;
    use crate::standin::{NoBackend, SimPlaces, SimWorld, TruthVerifier};
    use doorslam_ipc::wire::{Body, Header, Hello};

    fn id(s: &str) -> RobotId {
        RobotId::new(s).unwrap()
    }

    /// `max_peers` holds against a flood of made-up ids: new peers are refused (counted,
    /// in the ledger) once full, an absent peer that never said Hello makes room, one that
    /// did (a robot of the team, its state kept for the next meeting) never does.
    #[test]
    fn sessions_stay_within_max_peers_and_keep_the_robots_that_said_hello() {
        let world = SimWorld::default();
        let config = ProtocolConfig {
            max_peers: 3,
            ..ProtocolConfig::default()
        };
        let mut node = Node::new(
            Identity {
                id: id("a"),
                robot: 0,
                epoch: 1,
            },
            config,
            LedgerHandle::new(Ledger::new("a", "test", 1, 752 * 480)),
            Pieces {
                place: Box::new(SimPlaces::new(world, 0, 8)),
                verifier: Box::new(TruthVerifier::from_world(world)),
                backend: Box::new(NoBackend::default()),
            },
        );
        node.handle(LinkEvent::PeerAppeared(id("p1")), 0);
        let hello = Message::new(
            Header {
                sender: id("p1"),
                epoch: 1,
                sequence: 0,
            },
            Body::Hello(Hello {
                robot: 1,
                heard: None,
                base: 0,
            }),
        );
        node.handle(
            LinkEvent::Message {
                from: id("p1"),
                kind: Kind::Hello.name().into(),
                bytes: hello.encode().unwrap(),
            },
            0,
        );
        assert_eq!(
            node.session(&id("p1")).and_then(|s| s.peer_robot()),
            Some(1)
        );
        node.handle(LinkEvent::PeerLeft(id("p1")), 0);
        node.handle(LinkEvent::PeerAppeared(id("p2")), 0);
        node.handle(LinkEvent::PeerAppeared(id("p3")), 0);
        node.handle(LinkEvent::PeerAppeared(id("p4")), 0);
        assert!(node.session(&id("p4")).is_none());
        assert_eq!((node.peers_refused, node.peers_evicted), (1, 0));
        node.handle(LinkEvent::PeerLeft(id("p2")), 0);
        node.handle(LinkEvent::PeerAppeared(id("p5")), 0);
        assert_eq!(node.peers_evicted, 1);
        for i in 0..30 {
            node.handle(LinkEvent::PeerAppeared(id(&format!("x{i}"))), 0);
            assert!(node.sessions().count() <= 3);
        }
        let held: Vec<String> = node.sessions().map(|s| s.peer().to_string()).collect();
        assert_eq!(held, ["p1", "p3", "p5"]);
        assert_eq!(node.peers_refused, 31);
        assert_eq!(node.ledger().lock().dropped_count("max_peers"), 31);
    }
}
