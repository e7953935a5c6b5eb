//! The rendezvous protocol with one peer, as a pure state machine: no Zenoh, no clock of its
//! own (the caller passes its local monotonic time in milliseconds; no two robots' clocks
//! are ever compared), no threads. [`crate::node::Node`] drives one [`PeerSession`] per
//! discovered peer over any [`crate::node::Link`].
//!
//! For robots α < β (by robot id, [`Role`]), following the paper (§III-B, §III-C):
//! 1. α sends β its place descriptors of keyframes it has not sent yet (all on the first
//!    meeting), in batches that name the keyframe range they cover;
//! 2. β matches each new descriptor against its own ([`DescriptorSource::match_descriptors`])
//!    and replies with the putative [`Matches`] and, once per own keyframe, the
//!    [`VerificationFeatures`] of that keyframe;
//! 3. α verifies each pair ([`Verifier`]) and sends the accepted [`LoopClosures`]; both
//!    hand them to their back-end ([`BackendExchange::loop_closures`]);
//! 4. the back-end's rounds: whatever [`BackendExchange::messages_for`] returns is sent,
//!    and every other kind received goes to [`BackendExchange::receive`].
//!
//! Delivery is [`crate::delivery`]'s contract, the same for every kind: exactly once and
//! in order per kind, state messages superseding those still waiting, sessions per epoch of
//! the peer opened by a `Hello`. Back-end kinds travel under it like the rendezvous' own:
//! the back-end hands bodies over and gets the peer's bodies, never an acknowledgement.

use std::collections::{BTreeSet, HashMap, VecDeque};
use std::ops::Range;

use doorslam_geometry::key;
use doorslam_ipc::wire::{
    Ack, Body, Descriptor, Descriptors, Header, Hello, Kind, LoopClosure, LoopClosures, Match,
    Matches, Message, RobotId, VerificationFeatures, MAX_LOOP_CLOSURES, MAX_MATCHES,
};

pub use crate::delivery::Outgoing;
use crate::delivery::{Arrived, Delivery, DeliveryConfig, DeliveryStats, QueueError};
use crate::seen::SeenWindow;

/// This robot's own place descriptors, matching and verification packets: place
/// recognition and the front-end's keyframes, behind one trait so the protocol runs with a
/// simulation stand-in ([`crate::standin::SimPlaces`]) before the real ones land.
pub trait DescriptorSource {
    /// Own descriptors of keyframes with index `from..`, at most `limit` of them, in key
    /// order, and the keyframe range they cover (`from..end`, ending after the last
    /// keyframe that exists now; keyframes without a descriptor inside it are covered too).
    /// `end == from`: nothing new yet.
    fn descriptors_since(&mut self, from: u64, limit: usize) -> DescriptorBatch;
    /// Putative pairs between descriptors received from `peer` and own keyframes
    /// (`query` = the received key, `candidate` = the own key).
    fn match_descriptors(&mut self, peer: &RobotId, received: &[Descriptor]) -> Vec<Match>;
    /// The verification packet of own keyframe `key` (None: unknown keyframe).
    fn verification_features(&mut self, key: u64) -> Option<VerificationFeatures>;
}

/// What [`DescriptorSource::descriptors_since`] returns.
#[derive(Debug, Clone, PartialEq)]
pub struct DescriptorBatch {
    pub keyframes: Range<u64>,
    pub descriptors: Vec<Descriptor>,
}

/// Geometric verification of one putative pair against the peer's packet (the front-end's
/// PnP-RANSAC; stand-in: [`crate::standin::TruthVerifier`]). `m.query` is own, `m.candidate`
/// the peer's keyframe, `features.key == m.candidate`. An accepted pair is a closure with
/// `key_a = m.query`, `key_b = m.candidate`.
pub trait Verifier {
    fn verify(
        &mut self,
        peer: &RobotId,
        m: &Match,
        features: &VerificationFeatures,
    ) -> Option<LoopClosure>;
}

/// Why the back-end refused a message from a peer (counted in the ledger, then dropped).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("back-end refused the message: {0}")]
pub struct BackendRefusal(pub String);

/// The distributed back-end's side of the team link (stand-ins: [`crate::standin::NoBackend`],
/// [`crate::standin::EchoBackend`]).
pub trait BackendExchange {
    /// Inter-robot loop closures with `peer`, each given once: on α those it verified, on β
    /// those received from α. `key_a` is α's keyframe, `key_b` β's.
    fn loop_closures(&mut self, peer: &RobotId, closures: &[LoopClosure]);
    /// Messages to send to `peer` now (called repeatedly while the peer is present and the
    /// two have exchanged Hello); each is delivered once, in order per kind, even across
    /// meetings cut off mid-way, unless the peer restarts (a new epoch in
    /// [`Self::presence`]) — a state message ([`Body::slot`]) may instead reach the peer
    /// merged into the one before it that was still waiting ([`Body::supersede`]), which
    /// leaves the peer in the same state.
    fn messages_for(&mut self, peer: &RobotId) -> Vec<Body>;
    /// A message from `peer` of a kind the rendezvous itself does not handle (pose
    /// estimates, and any back-end kind added to the wire format), each delivered once and
    /// in order per kind, with the header it came with (the peer's epoch and sequence).
    fn receive(
        &mut self,
        peer: &RobotId,
        header: &Header,
        body: Body,
    ) -> Result<(), BackendRefusal>;
    /// The peer said Hello (`present`: its robot number and team-link epoch are known
    /// now; called again when it restarts with a new epoch), or left radio range.
    fn presence(&mut self, _peer: &RobotId, _robot: u8, _epoch: u64, _present: bool) {}
}

/// The three pieces a session calls into, borrowed for one call.
pub struct Services<'a> {
    pub place: &'a mut dyn DescriptorSource,
    pub verifier: &'a mut dyn Verifier,
    pub backend: &'a mut dyn BackendExchange,
}

/// Who does what in a pair: the robot with the smaller id initiates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// α: sends descriptors, verifies, sends closures.
    Initiator,
    /// β: matches, sends verification packets.
    Responder,
}

impl Role {
    pub fn of(me: &RobotId, peer: &RobotId) -> Role {
        if me < peer {
            Role::Initiator
        } else {
            Role::Responder
        }
    }
}

/// This robot, as the protocol sees it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Identity {
    pub id: RobotId,
    /// The robot number of its keys (0 = 'a').
    pub robot: u8,
    /// Incremented at every start of the team link (persisted by the caller).
    pub epoch: u64,
}

/// Tunables of the protocol.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProtocolConfig {
    /// Resend an unacknowledged message after this much local time.
    pub retransmit_ms: u64,
    /// Descriptors per batch.
    pub descriptor_batch: usize,
    /// A partial batch (fewer than `descriptor_batch` new keyframes) waits this long after
    /// the previous batch for more keyframes: a batch's header and range are shared by its
    /// descriptors, so keyframes trickling in during a meeting are not sent one by one.
    pub batch_linger_ms: u64,
    /// Messages of one kind in flight at most (the rest waits, state messages merged per
    /// slot); no new descriptor batch is queued while this many are unsettled.
    pub window: usize,
    /// Messages of one kind the receiver holds back for order at most (further ahead:
    /// dropped unacknowledged, they come again); bounds its memory against a peer.
    pub receive_window: u64,
    /// α: verification packets of the peer kept for pairs still to come (oldest evicted
    /// first); β re-sends a packet beyond half of it.
    pub features_cache: usize,
    /// Messages of one kind waiting to be sent at most; beyond, a new one is refused at
    /// queueing ([`QueueError::Full`], counted).
    pub outbox_limit: usize,
    /// Ids kept by each set that prevents processing twice (β: descriptors delivered,
    /// closures received; α: pairs verified): the newest this many, older ones count as
    /// seen ([`SeenWindow`]).
    pub seen_ids: usize,
    /// α: putative pairs waiting for their verification packet at most (oldest dropped
    /// first, counted in `matches_dropped`).
    pub pending_matches: usize,
    /// Peer sessions a node holds at most ([`crate::node::Node`]).
    pub max_peers: usize,
}

impl ProtocolConfig {
    /// The delivery layer's share of this configuration.
    pub fn delivery(&self) -> DeliveryConfig {
        DeliveryConfig {
            retransmit_ms: self.retransmit_ms,
            window: self.window,
            hold_back: self.receive_window,
            outbox_limit: self.outbox_limit,
        }
    }
}

impl Default for ProtocolConfig {
    fn default() -> Self {
        Self {
            retransmit_ms: 1000,
            descriptor_batch: 16,
            batch_linger_ms: 500,
            window: 32,
            receive_window: 64,
            features_cache: 512,
            outbox_limit: 1024,
            seen_ids: 16384,
            pending_matches: 4096,
            // Every robot has a key letter: a team has at most this many, so a real peer
            // always finds room.
            max_peers: usize::from(key::MAX_ROBOTS),
        }
    }
}

/// Why a message from a peer was not processed. [`Refusal::reason`] is the ledger's name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    #[error("epoch {got} is older than the peer's current epoch {current}")]
    StaleEpoch { got: u64, current: u64 },
    #[error("sequence {sequence} of kind {kind:?} already processed (acknowledged again)")]
    Duplicate { kind: Kind, sequence: u64 },
    #[error("sequence {sequence} of kind {kind:?} beyond the hold-back buffer (it comes again)")]
    OutOfWindow { kind: Kind, sequence: u64 },
    #[error("{0:?} before the peer's Hello opened its session (not acknowledged: it comes again)")]
    BeforeHello(Kind),
    #[error("{0:?} is not sent to a robot in this role")]
    UnexpectedKind(Kind),
    #[error("acknowledgment of epoch {got}, this robot's epoch is {current}")]
    AckEpoch { got: u64, current: u64 },
    #[error("invalid {kind:?}: {reason}")]
    Invalid { kind: Kind, reason: String },
    #[error(transparent)]
    Backend(#[from] BackendRefusal),
}

impl Refusal {
    /// Short name for the ledger's dropped counters.
    pub fn reason(&self) -> &'static str {
        match self {
            Refusal::StaleEpoch { .. } => "stale_epoch",
            Refusal::Duplicate { .. } => "duplicate",
            Refusal::OutOfWindow { .. } => "out_of_window",
            Refusal::BeforeHello(_) => "before_hello",
            Refusal::UnexpectedKind(_) => "unexpected_kind",
            Refusal::AckEpoch { .. } => "ack_epoch",
            Refusal::Invalid { .. } => "invalid",
            Refusal::Backend(_) => "backend_refused",
        }
    }
}

/// Counters of one peer session, readable at run time.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PeerStats {
    pub meetings: u64,
    /// Messages emitted (first sends and resends, acks included).
    pub messages_sent: u64,
    pub retransmissions: u64,
    /// β: descriptors received for the first time (given to matching).
    pub descriptors_delivered: u64,
    /// β: descriptors that arrived again in a message not seen before: the sender resent
    /// data already delivered (0 unless the sender lost its state).
    pub descriptors_redelivered: u64,
    /// α: descriptors acknowledged by the peer.
    pub descriptors_acknowledged: u64,
    pub matches_received: u64,
    pub closures_accepted: u64,
    pub closures_rejected: u64,
    pub closures_received: u64,
    pub backend_sent: u64,
    pub backend_received: u64,
    /// α: verification packets held, and dropped to stay within the cache
    /// ([`PEER_FEATURES_CACHE`]).
    pub features_held: u64,
    pub features_evicted: u64,
    /// α: putative pairs whose packet was evicted before it could verify them.
    pub matches_unverifiable: u64,
    /// α: putative pairs waiting for their packet now, and dropped, oldest first, to stay
    /// within `pending_matches`.
    #[serde(default)]
    pub matches_pending: u64,
    #[serde(default)]
    pub matches_dropped: u64,
    /// Ids that left a seen-window and raised its floor (β: descriptors, closures; α: pairs
    /// verified): below the floor an id counts as seen.
    #[serde(default)]
    pub seen_forgotten: u64,
    /// Arrivals taken for repeats because they were at or below a seen-window's floor.
    #[serde(default)]
    pub seen_below_floor: u64,
    /// Messages this robot made for the peer and did not queue, by reason
    /// (`outbox_full`, `unencodable`, `too_large`).
    #[serde(default)]
    pub queue_refused: std::collections::BTreeMap<String, u64>,
    pub delivery: DeliveryStats,
}

/// The protocol with one peer.
#[derive(Debug)]
pub struct PeerSession {
    me: Identity,
    peer: RobotId,
    role: Role,
    config: ProtocolConfig,
    connected: bool,
    delivery: Delivery,
    /// A session towards the peer was started (at the first meeting).
    session_started: bool,
    peer_epoch: Option<u64>,
    /// A message of the peer arrived in this meeting: its epoch is settled until the next.
    epoch_settled: bool,
    peer_robot: Option<u8>,
    // α
    descriptors_queued_below: u64,
    last_batch_ms: Option<u64>,
    pending_matches: Vec<Match>,
    /// Verification packets received, at most `features_cache` (oldest evicted first,
    /// unless a pair waiting for verification needs it), their arrival order, and the keys
    /// evicted last (a pair naming one is unverifiable: β sent it once).
    peer_features: HashMap<u64, VerificationFeatures>,
    features_order: VecDeque<u64>,
    evicted: VecDeque<u64>,
    verified: SeenWindow<(u64, u64)>,
    // β
    delivered: SeenWindow<u64>,
    /// The last `features_cache / 2` keyframes whose packet was sent: α still holds them
    /// (it evicts only beyond twice as many), so a pair naming one goes without it.
    features_sent: VecDeque<u64>,
    closures_received: SeenWindow<(u64, u64)>,
    stats: PeerStats,
}

fn invalid(kind: Kind, reason: impl Into<String>) -> Refusal {
    Refusal::Invalid {
        kind,
        reason: reason.into(),
    }
}

impl PeerSession {
    pub fn new(me: Identity, peer: RobotId, config: ProtocolConfig) -> Self {
        let role = Role::of(&me.id, &peer);
        Self {
            me: me.clone(),
            peer,
            role,
            config,
            connected: false,
            delivery: Delivery::new(me.id.clone(), me.robot, me.epoch, config.delivery()),
            session_started: false,
            peer_epoch: None,
            epoch_settled: false,
            peer_robot: None,
            descriptors_queued_below: 0,
            last_batch_ms: None,
            pending_matches: Vec::new(),
            peer_features: HashMap::new(),
            features_order: VecDeque::new(),
            evicted: VecDeque::new(),
            verified: SeenWindow::new(config.seen_ids),
            delivered: SeenWindow::new(config.seen_ids),
            features_sent: VecDeque::new(),
            closures_received: SeenWindow::new(config.seen_ids),
            stats: PeerStats::default(),
        }
    }

    pub fn peer(&self) -> &RobotId {
        &self.peer
    }

    pub fn role(&self) -> Role {
        self.role
    }

    pub fn stats(&self) -> &PeerStats {
        &self.stats
    }

    pub fn is_connected(&self) -> bool {
        self.connected
    }

    /// The peer's robot number, once its Hello arrived (in its current epoch).
    pub fn peer_robot(&self) -> Option<u8> {
        self.peer_robot
    }

    /// The peer's team-link epoch, once it sent anything.
    pub fn peer_epoch(&self) -> Option<u64> {
        self.peer_epoch
    }

    /// β: keys of every descriptor delivered from this peer.
    pub fn delivered_descriptors(&self) -> &BTreeSet<u64> {
        self.delivered.ids()
    }

    /// β: every descriptor key at or below this was delivered too (or counts as such):
    /// [`Self::delivered_descriptors`] holds the newest `seen_ids` above it.
    pub fn delivered_floor(&self) -> Option<u64> {
        self.delivered.floor()
    }

    /// Sequences of `kind` sent and not yet acknowledged.
    pub fn unacknowledged(&self, kind: Kind) -> Vec<u64> {
        self.delivery.unacknowledged(kind)
    }

    /// Nothing in flight, waiting, or to acknowledge with this peer.
    pub fn idle(&self) -> bool {
        self.delivery.idle()
    }

    /// α: every keyframe below this index has its descriptor queued (sent or to be resent).
    pub fn descriptors_queued_below(&self) -> u64 {
        self.descriptors_queued_below
    }

    /// The peer's token appeared: a meeting starts; everything unacknowledged goes out at
    /// the next [`PeerSession::poll`] (the cut-off meeting resumes here).
    pub fn meeting_started(&mut self) {
        self.connected = true;
        self.epoch_settled = false;
        self.stats.meetings += 1;
        if !self.session_started {
            self.session_started = true;
            self.delivery.start_session(self.peer_epoch, false);
        }
        self.delivery.resend_all();
    }

    /// The peer's token disappeared: nothing is sent until the next meeting; all state
    /// (outboxes, what was received) is kept for it.
    pub fn meeting_ended(&mut self) {
        self.connected = false;
    }

    /// Queues one message for the peer. A refusal is this robot's (its pieces made more,
    /// or larger, than the link carries): logged and counted by reason, never the peer's.
    fn queue(&mut self, body: Body) -> Result<(), QueueError> {
        let kind = body.kind();
        let r = self.delivery.queue(body);
        if let Err(e) = &r {
            tracing::warn!(peer = %self.peer, kind = kind.name(), error = %e, "message to the peer not queued");
            *self
                .stats
                .queue_refused
                .entry(e.reason().to_string())
                .or_default() += 1;
        }
        r
    }

    fn sync_stats(&mut self) {
        self.stats.retransmissions = self.delivery.retransmissions;
        self.stats.delivery = self.delivery.stats.clone();
        self.stats.features_held = self.peer_features.len() as u64;
        self.stats.matches_pending = self.pending_matches.len() as u64;
        let windows = [
            (self.delivered.forgotten(), self.delivered.below_floor()),
            (self.verified.forgotten(), self.verified.below_floor()),
            (
                self.closures_received.forgotten(),
                self.closures_received.below_floor(),
            ),
        ];
        self.stats.seen_forgotten = windows.iter().map(|w| w.0).sum();
        self.stats.seen_below_floor = windows.iter().map(|w| w.1).sum();
    }

    /// Messages to send now: new protocol steps, acknowledgments, and resends of what is
    /// unacknowledged after `retransmit_ms`. Nothing while the peer is away.
    pub fn poll(&mut self, now_ms: u64, svc: &mut Services<'_>) -> Vec<Outgoing> {
        if !self.connected {
            return Vec::new();
        }
        if self.peer_robot.is_some() {
            if self.role == Role::Initiator {
                self.queue_descriptors(now_ms, svc);
            }
            for body in svc.backend.messages_for(&self.peer) {
                // Counted as sent once queued: a refused one the back-end is not told
                // about (its trait has no way back); the counter by reason says it.
                if self.queue(body).is_ok() {
                    self.stats.backend_sent += 1;
                }
            }
        }
        let out = self.delivery.poll(now_ms, self.peer_epoch);
        self.stats.messages_sent += out.len() as u64;
        self.sync_stats();
        out
    }

    fn queue_descriptors(&mut self, now_ms: u64, svc: &mut Services<'_>) {
        loop {
            if self.delivery.unsettled(Kind::Descriptors) >= self.config.window {
                return;
            }
            let from = self.descriptors_queued_below;
            let batch = svc
                .place
                .descriptors_since(from, self.config.descriptor_batch);
            if batch.keyframes.end <= from || batch.keyframes.start != from {
                return;
            }
            let partial = batch.descriptors.len() < self.config.descriptor_batch;
            let lingering = self
                .last_batch_ms
                .is_some_and(|t| now_ms.saturating_sub(t) < self.config.batch_linger_ms);
            if partial && lingering {
                return;
            }
            self.last_batch_ms = Some(now_ms);
            let end = batch.keyframes.end;
            let body = Body::Descriptors(Descriptors {
                robot: self.me.robot,
                keyframes: batch.keyframes,
                descriptors: batch.descriptors,
            });
            // Refused (full, or the source made a batch the wire refuses): the range is
            // not marked as sent, so a full outbox asks for it again next turn rather than
            // skip it; a batch that never encodes is skipped, counted, or it would block
            // every later keyframe.
            match self.queue(body) {
                Ok(()) => self.descriptors_queued_below = end,
                Err(QueueError::Full { .. }) => return,
                Err(_) => self.descriptors_queued_below = end,
            }
        }
    }

    /// Processes one decoded message whose sender the caller checked (the key's `<from>`
    /// equals the header's sender, and the peer is present). `Err`: the message was not
    /// taken (a stale epoch, a duplicate, before the peer's session, ...). `Ok`: taken —
    /// held back for order, or delivered with the ones it held back; the refusals of those
    /// (invalid, refused by the back-end) are returned, each counted by the caller.
    pub fn receive(
        &mut self,
        msg: Message,
        svc: &mut Services<'_>,
    ) -> Result<Vec<Refusal>, Refusal> {
        let epoch = msg.header.epoch;
        match self.peer_epoch {
            Some(current) if epoch == current => {}
            // Older than what the peer said in this meeting: a replay from before a restart.
            // An epoch claim lasts until the peer's next appearance, no longer: the first
            // message of a meeting sets it again, lower or higher, so a claim that was
            // wrong (an epoch file lost, or a huge epoch from a bug) cannot refuse the
            // robot's real messages forever. Only the robot itself can claim its epoch
            // when the link runs with TLS and access control (`crate::security`).
            Some(current) if epoch < current && self.epoch_settled => {
                return Err(Refusal::StaleEpoch {
                    got: epoch,
                    current,
                })
            }
            previous => {
                // First message, or the peer restarted: its old sequences mean nothing
                // now, it has forgotten this robot's Hello and what this robot sent.
                self.peer_epoch = Some(epoch);
                self.peer_robot = None;
                self.delivery.peer_epoch_changed();
                self.session_started = true;
                self.delivery.start_session(Some(epoch), previous.is_some());
            }
        }
        self.epoch_settled = true;
        let kind = msg.kind();
        let header = msg.header;
        match msg.body {
            Body::Ack(ack) => self.acknowledged(&ack).map(|()| Vec::new()),
            Body::Hello(h) => {
                let sequence = header.sequence;
                if !self.delivery.hello(sequence, &h) {
                    return Err(Refusal::Duplicate { kind, sequence });
                }
                self.process_hello(&header, &h, svc).map(|()| Vec::new())
            }
            body => {
                let arrived = self.delivery.arrive(header, body);
                self.sync_stats();
                match arrived {
                    Arrived::Deliver(run) => {
                        let refusals = run
                            .into_iter()
                            .filter_map(|(h, b)| self.process(&h, b, svc).err())
                            .collect();
                        self.sync_stats();
                        Ok(refusals)
                    }
                    Arrived::Held => Ok(Vec::new()),
                    Arrived::Duplicate { sequence } => Err(Refusal::Duplicate { kind, sequence }),
                    Arrived::BeyondHoldBack { sequence } => {
                        Err(Refusal::OutOfWindow { kind, sequence })
                    }
                    Arrived::BeforeSession => Err(Refusal::BeforeHello(kind)),
                }
            }
        }
    }

    fn acknowledged(&mut self, ack: &Ack) -> Result<(), Refusal> {
        if ack.epoch != self.me.epoch {
            return Err(Refusal::AckEpoch {
                got: ack.epoch,
                current: self.me.epoch,
            });
        }
        let done = self
            .delivery
            .acknowledged(ack)
            .map_err(|reason| invalid(Kind::Ack, reason))?;
        for body in done {
            if let Body::Descriptors(d) = &body {
                self.stats.descriptors_acknowledged += d.descriptors.len() as u64;
            }
        }
        Ok(())
    }

    fn process_hello(
        &mut self,
        header: &Header,
        h: &Hello,
        svc: &mut Services<'_>,
    ) -> Result<(), Refusal> {
        if h.robot == self.me.robot {
            return Err(invalid(
                Kind::Hello,
                format!(
                    "peer {} claims this robot's key letter {}",
                    self.peer,
                    (b'a' + h.robot) as char
                ),
            ));
        }
        if self.peer_robot != Some(h.robot) {
            self.peer_robot = Some(h.robot);
            svc.backend
                .presence(&self.peer, h.robot, header.epoch, self.connected);
        }
        Ok(())
    }

    fn process(
        &mut self,
        header: &Header,
        body: Body,
        svc: &mut Services<'_>,
    ) -> Result<(), Refusal> {
        let kind = body.kind();
        let Some(peer_robot) = self.peer_robot else {
            return Err(Refusal::BeforeHello(kind));
        };
        let mine = |k: u64| key::robot(k) == Some(self.me.robot);
        let theirs = |k: u64| key::robot(k) == Some(peer_robot);
        // if-let rather than `match`: kinds added to the wire format later (the back-end's)
        // fall through to the back-end without touching this function.
        if let Body::Descriptors(d) = &body {
            if self.role != Role::Responder {
                return Err(Refusal::UnexpectedKind(kind));
            }
            if d.robot != peer_robot {
                return Err(invalid(kind, "batch of another robot than the peer's"));
            }
            let mut fresh = Vec::new();
            for desc in &d.descriptors {
                if self.delivered.insert(desc.key) {
                    fresh.push(desc.clone());
                } else {
                    self.stats.descriptors_redelivered += 1;
                }
            }
            self.stats.descriptors_delivered += fresh.len() as u64;
            if !fresh.is_empty() {
                let matches = svc.place.match_descriptors(&self.peer, &fresh);
                self.queue_matches(matches, svc);
            }
            Ok(())
        } else if let Body::Matches(m) = &body {
            if self.role != Role::Initiator {
                return Err(Refusal::UnexpectedKind(kind));
            }
            if let Some(bad) = m
                .matches
                .iter()
                .find(|p| !mine(p.query) || !theirs(p.candidate))
            {
                return Err(invalid(
                    kind,
                    format!(
                        "pair {:#x}/{:#x} is not (own, peer's)",
                        bad.query, bad.candidate
                    ),
                ));
            }
            self.stats.matches_received += m.matches.len() as u64;
            self.pending_matches.extend(
                m.matches
                    .iter()
                    .filter(|p| !self.verified.contains(&(p.query, p.candidate))),
            );
            self.try_verify(svc);
            // What still waits for its packet, oldest first: β sends a pair's packet
            // before the pair, so the pairs that waited longest are the ones least likely
            // to be verified still.
            let over = self
                .pending_matches
                .len()
                .saturating_sub(self.config.pending_matches);
            if over > 0 {
                self.pending_matches.drain(..over);
                self.stats.matches_dropped += over as u64;
            }
            Ok(())
        } else if let Body::VerificationFeatures(v) = body {
            if self.role != Role::Initiator {
                return Err(Refusal::UnexpectedKind(kind));
            }
            if !theirs(v.key) {
                return Err(invalid(kind, "packet of a keyframe not the peer's"));
            }
            self.keep_features(v);
            self.try_verify(svc);
            Ok(())
        } else if let Body::LoopClosures(l) = &body {
            if self.role != Role::Responder {
                return Err(Refusal::UnexpectedKind(kind));
            }
            if l.closures
                .iter()
                .any(|c| !theirs(c.key_a) || !mine(c.key_b))
            {
                return Err(invalid(kind, "closure keys are not (peer's, own)"));
            }
            let fresh: Vec<LoopClosure> = l
                .closures
                .iter()
                .filter(|c| self.closures_received.insert((c.key_a, c.key_b)))
                .cloned()
                .collect();
            self.stats.closures_received += fresh.len() as u64;
            if !fresh.is_empty() {
                svc.backend.loop_closures(&self.peer, &fresh);
            }
            Ok(())
        } else {
            self.stats.backend_received += 1;
            svc.backend.receive(&self.peer, header, body)?;
            Ok(())
        }
    }

    /// α: keeps a verification packet of the peer; beyond `features_cache`, the oldest
    /// that no pair waits for is evicted (β sends a packet again once it is beyond half of
    /// that in its own list, so a pair it sends later finds its packet).
    fn keep_features(&mut self, v: VerificationFeatures) {
        let k = v.key;
        if self.peer_features.insert(k, v).is_some() {
            self.features_order.retain(|x| *x != k);
        }
        self.features_order.push_back(k);
        while self.peer_features.len() > self.config.features_cache {
            let waited: BTreeSet<u64> = self.pending_matches.iter().map(|m| m.candidate).collect();
            // The oldest no pair waits for; if every packet held is waited for (a peer
            // sending pairs for packets it never sends), the oldest all the same: the
            // cache's bound is hard, its pairs become unverifiable (counted).
            let at = self
                .features_order
                .iter()
                .position(|x| !waited.contains(x))
                .unwrap_or(0);
            if let Some(old) = self.features_order.remove(at) {
                self.peer_features.remove(&old);
                self.stats.features_evicted += 1;
                self.evicted.push_back(old);
                if self.evicted.len() > 2 * self.config.features_cache {
                    self.evicted.pop_front();
                }
            } else {
                break;
            }
        }
    }

    /// β: queue the putative pairs and, once per own keyframe, its verification packet
    /// (before the pairs, so α usually verifies as the pairs arrive).
    fn queue_matches(&mut self, matches: Vec<Match>, svc: &mut Services<'_>) {
        let mut sendable = Vec::new();
        for m in matches {
            if key::robot(m.candidate) != Some(self.me.robot) {
                continue;
            }
            if !self.features_sent.contains(&m.candidate) {
                match svc.place.verification_features(m.candidate) {
                    Some(f) => {
                        // Not queued (counted by `queue`): neither is its pair, which α
                        // could never verify; the packet goes with the keyframe's next pair.
                        if self.queue(Body::VerificationFeatures(f)).is_err() {
                            continue;
                        }
                        self.features_sent.push_back(m.candidate);
                        if self.features_sent.len() > self.config.features_cache / 2 {
                            self.features_sent.pop_front();
                        }
                    }
                    None => continue,
                }
            }
            sendable.push(m);
        }
        for chunk in sendable.chunks(MAX_MATCHES) {
            // A refusal is counted by `queue`; the pairs are lost to this meeting's α.
            let _ = self.queue(Body::Matches(Matches {
                matches: chunk.to_vec(),
            }));
        }
    }

    /// α: verify every pair whose packet has arrived; send and hand over the accepted.
    fn try_verify(&mut self, svc: &mut Services<'_>) {
        let mut accepted = Vec::new();
        let mut waiting = Vec::new();
        for m in std::mem::take(&mut self.pending_matches) {
            let Some(features) = self.peer_features.get(&m.candidate) else {
                if self.evicted.contains(&m.candidate) {
                    // β sent it once and will not again for this pair.
                    self.stats.matches_unverifiable += 1;
                } else {
                    waiting.push(m);
                }
                continue;
            };
            if !self.verified.insert((m.query, m.candidate)) {
                continue;
            }
            match svc.verifier.verify(&self.peer, &m, features) {
                Some(c) => accepted.push(c),
                None => self.stats.closures_rejected += 1,
            }
        }
        self.pending_matches = waiting;
        if accepted.is_empty() {
            return;
        }
        self.stats.closures_accepted += accepted.len() as u64;
        svc.backend.loop_closures(&self.peer, &accepted);
        for chunk in accepted.chunks(MAX_LOOP_CLOSURES) {
            // A refusal is counted by `queue`: the closures stay in this robot's back-end
            // (given above) but do not reach β's.
            let _ = self.queue(Body::LoopClosures(LoopClosures {
                closures: chunk.to_vec(),
            }));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roles_follow_ids() {
        let a = RobotId::new("alpha").unwrap();
        let b = RobotId::new("beta").unwrap();
        assert_eq!(Role::of(&a, &b), Role::Initiator);
        assert_eq!(Role::of(&b, &a), Role::Responder);
    }

    use doorslam_ipc::wire::{Descriptor, DESCRIPTOR_DIM};

    /// Counts what it is asked; matches nothing, verifies nothing (no closure to send).
    #[derive(Default)]
    struct Counting {
        matched: usize,
        verified: Vec<(u64, u64)>,
    }

    impl DescriptorSource for Counting {
        fn descriptors_since(&mut self, from: u64, _limit: usize) -> DescriptorBatch {
            DescriptorBatch {
                keyframes: from..from,
                descriptors: Vec::new(),
            }
        }
        fn match_descriptors(&mut self, _peer: &RobotId, received: &[Descriptor]) -> Vec<Match> {
            self.matched += received.len();
            Vec::new()
        }
        fn verification_features(&mut self, _key: u64) -> Option<VerificationFeatures> {
            None
        }
    }

    impl Verifier for Counting {
        fn verify(
            &mut self,
            _peer: &RobotId,
            m: &Match,
            _features: &VerificationFeatures,
        ) -> Option<LoopClosure> {
            self.verified.push((m.query, m.candidate));
            None
        }
    }

    /// A session of `me` with `peer` whose Hello arrived (the peer's epoch 7), and the
    /// peer's next sequence.
    fn opened(me: (&str, u8), peer: (&str, u8), config: ProtocolConfig) -> (PeerSession, u64) {
        let mut s = PeerSession::new(
            Identity {
                id: RobotId::new(me.0).unwrap(),
                robot: me.1,
                epoch: 1,
            },
            RobotId::new(peer.0).unwrap(),
            config,
        );
        s.meeting_started();
        let hello = Message::new(
            header(peer.0, 0),
            Body::Hello(Hello {
                robot: peer.1,
                heard: Some(1),
                base: 0,
            }),
        );
        run(&mut s, &mut Counting::default(), hello);
        assert_eq!(s.peer_robot(), Some(peer.1));
        (s, 0)
    }

    fn header(peer: &str, sequence: u64) -> Header {
        Header {
            sender: RobotId::new(peer).unwrap(),
            epoch: 7,
            sequence,
        }
    }

    fn run(s: &mut PeerSession, c: &mut Counting, msg: Message) -> Vec<Refusal> {
        let mut backend = crate::standin::NoBackend::default();
        let mut place = Counting::default();
        let mut svc = Services {
            place: &mut place,
            verifier: c,
            backend: &mut backend,
        };
        let r = s.receive(msg, &mut svc).expect("taken");
        c.matched += place.matched;
        r
    }

    fn run_place(s: &mut PeerSession, c: &mut Counting, msg: Message) -> Vec<Refusal> {
        let mut backend = crate::standin::NoBackend::default();
        let mut verifier = Counting::default();
        let mut svc = Services {
            place: c,
            verifier: &mut verifier,
            backend: &mut backend,
        };
        s.receive(msg, &mut svc).expect("taken")
    }

    fn k(robot: u8, index: u64) -> u64 {
        key::symbol(robot, index).unwrap()
    }

    /// A valid packet of robot b's keyframe `index`.
    fn packet(index: u64) -> VerificationFeatures {
        let mut places = crate::standin::SimPlaces::new(crate::standin::SimWorld::default(), 1, 8);
        places
            .created()
            .store(index + 1, std::sync::atomic::Ordering::Release);
        places.verification_features(k(1, index)).expect("a packet")
    }

    fn small() -> ProtocolConfig {
        ProtocolConfig {
            features_cache: 8,
            seen_ids: 16,
            pending_matches: 16,
            ..ProtocolConfig::default()
        }
    }

    /// α flooded with ten times `pending_matches` pairs whose packets never come: what
    /// waits stays at the bound, the drops are counted, the newest pairs are the ones kept
    /// (their packet arriving verifies them; the oldest's does not).
    #[test]
    fn pending_pairs_stay_within_their_bound_keeping_the_newest() {
        let (mut s, _) = opened(("a", 0), ("b", 1), small());
        let mut c = Counting::default();
        for m in 0..10u64 {
            let matches = (0..16)
                .map(|i| Match {
                    query: k(0, 16 * m + i),
                    candidate: k(1, 16 * m + i),
                    distance: 0.1,
                })
                .collect();
            let refusals = run(
                &mut s,
                &mut c,
                Message::new(header("b", m), Body::Matches(Matches { matches })),
            );
            assert!(refusals.is_empty(), "{refusals:?}");
            assert!(s.stats().matches_pending <= 16);
        }
        assert_eq!(s.stats().matches_pending, 16);
        assert_eq!(s.stats().matches_dropped, 144);
        // Packets (sequences 0, 1 of their kind) for the newest and the oldest pair.
        run(
            &mut s,
            &mut c,
            Message::new(header("b", 0), Body::VerificationFeatures(packet(159))),
        );
        run(
            &mut s,
            &mut c,
            Message::new(header("b", 1), Body::VerificationFeatures(packet(0))),
        );
        assert_eq!(c.verified, vec![(k(0, 159), k(1, 159))]);
    }

    /// α flooded with ten times `features_cache` packets: at most the bound held, the
    /// evictions counted, the newest kept; a pair naming an evicted packet is counted as
    /// unverifiable (never waits for good), one naming a kept packet is verified.
    #[test]
    fn the_features_cache_keeps_the_newest_packets_within_its_bound() {
        let (mut s, _) = opened(("a", 0), ("b", 1), small());
        let mut c = Counting::default();
        for i in 0..80u64 {
            run(
                &mut s,
                &mut c,
                Message::new(header("b", i), Body::VerificationFeatures(packet(i))),
            );
            assert!(s.stats().features_held <= 8);
        }
        assert_eq!(s.stats().features_held, 8);
        assert_eq!(s.stats().features_evicted, 72);
        let pairs = [70u64, 79]
            .iter()
            .map(|&i| Match {
                query: k(0, i),
                candidate: k(1, i),
                distance: 0.1,
            })
            .collect();
        run(
            &mut s,
            &mut c,
            Message::new(header("b", 0), Body::Matches(Matches { matches: pairs })),
        );
        assert_eq!(c.verified, vec![(k(0, 79), k(1, 79))]);
        assert_eq!(s.stats().matches_unverifiable, 1);
        assert_eq!(s.stats().matches_pending, 0);
    }

    /// β given ten times `seen_ids` descriptors: the delivered set stays at the bound (the
    /// newest), every descriptor was matched once, and a resend of the oldest (below the
    /// floor) counts as a redelivery, not matched again.
    #[test]
    fn delivered_descriptors_are_a_window_above_a_floor() {
        let (mut s, _) = opened(("b", 1), ("a", 0), small());
        let mut c = Counting::default();
        let batch = |from: u64| {
            Body::Descriptors(Descriptors {
                robot: 0,
                keyframes: from..from + 16,
                descriptors: (from..from + 16)
                    .map(|i| Descriptor {
                        key: k(0, i),
                        scale: 0.01,
                        values: [1; DESCRIPTOR_DIM],
                    })
                    .collect(),
            })
        };
        for m in 0..10u64 {
            let refusals = run_place(&mut s, &mut c, Message::new(header("a", m), batch(16 * m)));
            assert!(refusals.is_empty(), "{refusals:?}");
            assert!(s.delivered_descriptors().len() <= 16);
        }
        assert_eq!(c.matched, 160);
        assert_eq!(s.stats().descriptors_delivered, 160);
        assert_eq!(
            s.delivered_descriptors()
                .iter()
                .copied()
                .collect::<Vec<_>>(),
            (144..160).map(|i| k(0, i)).collect::<Vec<_>>()
        );
        assert_eq!(s.delivered_floor(), Some(k(0, 143)));
        assert_eq!(s.stats().seen_forgotten, 144);
        run_place(&mut s, &mut c, Message::new(header("a", 10), batch(0)));
        assert_eq!(c.matched, 160, "nothing matched twice");
        assert_eq!(s.stats().descriptors_redelivered, 16);
        assert_eq!(s.stats().seen_below_floor, 16);
    }
}
