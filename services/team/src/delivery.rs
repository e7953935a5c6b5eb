//! The team link's delivery contract with one peer, for every kind: each message is
//! delivered to the peer **exactly once and in order per kind**, whatever the radio loses,
//! duplicates or reorders, across meetings cut off mid-way; **state** messages (a slot's
//! newest value: separator estimates, a graph version, a route — see
//! [`doorslam_ipc::wire::Slot`]) **supersede** the ones still waiting to be sent. No
//! clock is compared between robots: order is by the sender's epoch and sequence.
//!
//! Sending: per kind a window of messages in flight (sent, not yet acknowledged), at most
//! one per slot for state kinds; the rest waits in the outbox, where a state message
//! absorbs the newer one of its slot ([`Body::supersede`]), so what waits is bounded by the
//! slots. A message in flight is resent after `retransmit_ms` of local time, doubling up
//! to 16 times that, and at once at the start of a meeting; it gets its sequence when it
//! is first sent, so the sequences of a kind are consecutive on the wire.
//!
//! What waits is bounded too: at most `outbox_limit` messages per kind (a state message
//! merges into the newest waiting one of its slot first, which takes no room). A message
//! that would go beyond it is refused at queueing with [`QueueError::Full`] and counted,
//! never dropped later: what is queued is delivered in order or not at all. So is a
//! message that does not encode or is larger than the wire's limit ([`QueueError`]): it
//! would never be sent, and kept in flight it would block its kind for good.
//!
//! Receiving: per kind the next sequence expected and a hold-back buffer of at most
//! `hold_back` messages that came early; a message is delivered when every earlier one
//! of its kind has been, then the ones it held back behind it. What is below the next
//! expected is a duplicate (acknowledged again, not delivered); what is beyond the buffer
//! is dropped unacknowledged and comes again.
//!
//! Sessions: sequences are those of a session the sender starts for each epoch of the
//! peer it hears (a restart of the peer loses what it had received). The session opens
//! with a `Hello` naming the peer's epoch and the session's first sequence (`base`, above
//! every sequence the sender used before, so nothing of an older session is mistaken for
//! this one's); the receiver takes nothing but Hellos until a Hello names its current
//! epoch. When the peer restarts, messages of stream kinds still unacknowledged are sent
//! again in the new session; state messages are dropped (the back-end, told of the
//! restart, sends its whole state again).

use std::collections::{BTreeMap, BTreeSet};

use doorslam_ipc::wire::{
    Ack, Body, Header, Hello, Kind, Message, RobotId, Slot, MAX_ACK_RANGES, MAX_MESSAGE_BYTES,
};

/// Tunables of delivery.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeliveryConfig {
    /// Resend an unacknowledged message after this much local time (ms; doubling per
    /// resend up to 16 times).
    pub retransmit_ms: u64,
    /// Messages of one kind in flight at most.
    pub window: usize,
    /// Messages of one kind the receiver holds back for order at most.
    pub hold_back: u64,
    /// Messages of one kind waiting to be sent at most (beyond: refused at queueing).
    pub outbox_limit: usize,
}

/// Why a message was not queued (nothing of it is sent; counted in [`DeliveryStats`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum QueueError {
    /// The encoder refuses it (a count beyond the wire's limits, a bad key or value): a
    /// bug of the piece that made it, never the peer's.
    #[error("{kind:?} message does not encode ({bytes} bytes up to the error): {reason}")]
    Unencodable {
        kind: Kind,
        bytes: usize,
        reason: String,
    },
    /// Larger than any peer decodes.
    #[error("{kind:?} message of {bytes} bytes is larger than the wire limit of {max} bytes")]
    TooLarge {
        kind: Kind,
        bytes: usize,
        max: usize,
    },
    /// Its kind's outbox holds `outbox_limit` messages already (the peer is slower than
    /// what is made for it, or away).
    #[error("{kind:?} message of {bytes} bytes refused: {waiting} messages of its kind wait to be sent (outbox_limit {limit})")]
    Full {
        kind: Kind,
        bytes: usize,
        waiting: usize,
        limit: usize,
    },
}

impl QueueError {
    /// Short name for counters and logs.
    pub fn reason(&self) -> &'static str {
        match self {
            QueueError::Unencodable { .. } => "unencodable",
            QueueError::TooLarge { .. } => "too_large",
            QueueError::Full { .. } => "outbox_full",
        }
    }

    pub fn kind(&self) -> Kind {
        match self {
            QueueError::Unencodable { kind, .. }
            | QueueError::TooLarge { kind, .. }
            | QueueError::Full { kind, .. } => *kind,
        }
    }
}

/// Counters of delivery with one peer (in `status.json` through the session's stats).
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct DeliveryStats {
    /// Messages that arrived before an earlier one of their kind and waited for it.
    pub held_back: u64,
    /// Messages dropped because they came further ahead than the hold-back buffer.
    pub beyond_hold_back: u64,
    /// State messages that absorbed a newer one while waiting (one send saved each).
    pub superseded: u64,
    /// Most messages waiting to be sent at once (all kinds).
    pub most_waiting: u64,
    /// Sessions started (the peer's epochs heard).
    pub sessions: u64,
    /// State messages dropped at a restart of the peer (its back-end is sent anew).
    pub dropped_at_restart: u64,
    /// Messages refused at queueing because their kind's outbox was full.
    #[serde(default)]
    pub refused_full: u64,
    /// Messages refused at queueing because they do not encode or exceed the wire limit.
    #[serde(default)]
    pub refused_unencodable: u64,
}

#[derive(Debug, Clone)]
struct InFlight {
    body: Body,
    slot: Option<Slot>,
    last_sent_ms: Option<u64>,
    sends: u32,
}

/// Messages of one kind to the peer.
#[derive(Debug, Clone, Default)]
struct Outbox {
    next_seq: u64,
    in_flight: BTreeMap<u64, InFlight>,
    /// Not sent yet, in the order queued; a state message stands for its slot.
    waiting: Vec<(Option<Slot>, Body)>,
}

impl Outbox {
    fn slot_in_flight(&self, slot: Slot) -> bool {
        self.in_flight.values().any(|m| m.slot == Some(slot))
    }
}

/// Received messages of one kind in the current session.
#[derive(Debug, Clone, Default)]
struct Inbox {
    /// Every sequence below this was delivered.
    next: u64,
    held: BTreeMap<u64, (Header, Body)>,
}

impl Inbox {
    /// The ranges held beyond `next`, at most [`MAX_ACK_RANGES`] (the first ones: the
    /// sender resends the rest, which are then acknowledged again).
    fn ranges(&self) -> Vec<std::ops::Range<u64>> {
        let mut out: Vec<std::ops::Range<u64>> = Vec::new();
        for &s in self.held.keys() {
            match out.last_mut() {
                Some(r) if r.end == s => r.end = s + 1,
                _ => {
                    if out.len() == MAX_ACK_RANGES {
                        break;
                    }
                    out.push(s..s + 1);
                }
            }
        }
        out
    }
}

/// What became of a message that arrived.
#[derive(Debug)]
pub enum Arrived {
    /// Delivered now, with the ones it held back behind it, in order.
    Deliver(Vec<(Header, Body)>),
    /// Held back until the earlier ones of its kind arrive.
    Held,
    /// Already delivered (acknowledged again).
    Duplicate { sequence: u64 },
    /// Further ahead than the hold-back buffer: dropped, it comes again.
    BeyondHoldBack { sequence: u64 },
    /// Before the Hello that opens this robot's session with the peer: dropped, it comes
    /// again.
    BeforeSession,
}

/// One message to send.
#[derive(Debug, Clone, PartialEq)]
pub struct Outgoing {
    pub message: Message,
    /// A resend (counted apart by the ledger).
    pub resend: bool,
}

/// Delivery to and from one peer.
#[derive(Debug)]
pub struct Delivery {
    me: RobotId,
    robot: u8,
    epoch: u64,
    config: DeliveryConfig,
    outboxes: BTreeMap<Kind, Outbox>,
    /// The Hello of the current session (resent until acknowledged), its sequence.
    hello: Option<(u64, InFlight)>,
    hello_next: u64,
    /// The first sequence of this robot's current session towards the peer.
    base: u64,
    inboxes: BTreeMap<Kind, Inbox>,
    /// The peer's session towards us is open (its Hello named our epoch).
    accepting: bool,
    /// Highest Hello sequence of the peer processed (in its current epoch).
    hello_seen: Option<u64>,
    ack_due: BTreeSet<Kind>,
    ack_sequence: u64,
    pub stats: DeliveryStats,
    pub retransmissions: u64,
}

impl Delivery {
    pub fn new(me: RobotId, robot: u8, epoch: u64, config: DeliveryConfig) -> Self {
        Self {
            me,
            robot,
            epoch,
            config,
            outboxes: BTreeMap::new(),
            hello: None,
            hello_next: 0,
            base: 0,
            inboxes: BTreeMap::new(),
            accepting: false,
            hello_seen: None,
            ack_due: BTreeSet::new(),
            ack_sequence: 0,
            stats: DeliveryStats::default(),
            retransmissions: 0,
        }
    }

    fn header(&self, sequence: u64) -> Header {
        Header {
            sender: self.me.clone(),
            epoch: self.epoch,
            sequence,
        }
    }

    /// Starts a session towards the peer's epoch `heard` (None: none heard yet): a Hello
    /// naming it, and sequences from above every one used before. Stream messages still
    /// unacknowledged go again in the new session; state messages are dropped when the
    /// peer restarted (`drop_state`).
    pub fn start_session(&mut self, heard: Option<u64>, drop_state: bool) {
        self.stats.sessions += 1;
        self.base = self
            .outboxes
            .values()
            .map(|o| o.next_seq)
            .max()
            .unwrap_or(0)
            .max(self.base);
        for outbox in self.outboxes.values_mut() {
            let flying = std::mem::take(&mut outbox.in_flight);
            let mut again: Vec<(Option<Slot>, Body)> =
                flying.into_values().map(|m| (m.slot, m.body)).collect();
            again.append(&mut outbox.waiting);
            if drop_state {
                let before = again.len();
                again.retain(|(slot, _)| slot.is_none());
                self.stats.dropped_at_restart += (before - again.len()) as u64;
            }
            outbox.waiting = again;
            outbox.next_seq = self.base;
        }
        let seq = self.hello_next;
        self.hello_next += 1;
        self.hello = Some((
            seq,
            InFlight {
                body: Body::Hello(Hello {
                    robot: self.robot,
                    heard,
                    base: self.base,
                }),
                slot: None,
                last_sent_ms: None,
                sends: 0,
            },
        ));
    }

    /// The peer's messages of its new epoch will come in a new session: what arrived of
    /// the old one is forgotten.
    pub fn peer_epoch_changed(&mut self) {
        self.inboxes.clear();
        self.ack_due.clear();
        self.accepting = false;
        self.hello_seen = None;
    }

    /// `body` as it will go on the wire, checked: it encodes and fits the wire's limit.
    /// The header is the largest this session can give it (sequence `u64::MAX`), so the
    /// real one is never longer.
    fn check(&self, body: Body) -> Result<Body, (QueueError, Body)> {
        let msg = Message::new(self.header(u64::MAX), body);
        let kind = msg.kind();
        match msg.encode() {
            Err(e) => {
                let bytes = msg.encoded_len();
                Err((
                    QueueError::Unencodable {
                        kind,
                        bytes,
                        reason: e.to_string(),
                    },
                    msg.body,
                ))
            }
            Ok(b) if b.len() > MAX_MESSAGE_BYTES => Err((
                QueueError::TooLarge {
                    kind,
                    bytes: b.len(),
                    max: MAX_MESSAGE_BYTES,
                },
                msg.body,
            )),
            Ok(_) => Ok(msg.body),
        }
    }

    /// Queues `body` behind what waits of its kind; a state message absorbs into the
    /// newest one of its slot still waiting (if the two still encode as one). Refused,
    /// with nothing queued, when it does not encode or its kind's outbox is full.
    pub fn queue(&mut self, body: Body) -> Result<(), QueueError> {
        let body = match self.check(body) {
            Ok(b) => b,
            Err((e, _)) => {
                self.stats.refused_unencodable += 1;
                return Err(e);
            }
        };
        let slot = body.slot();
        // A kind first sent in this session numbers from the session's base, as the peer's
        // inbox expects (its Hello said so): from 0 it would take them for duplicates of an
        // older session and never deliver them (a restarted peer's first back-end message
        // lost for good).
        let base = self.base;
        let kind = body.kind();
        let outbox = self.outboxes.entry(kind).or_insert_with(|| Outbox {
            next_seq: base,
            ..Outbox::default()
        });
        if let Some(s) = slot {
            // The newest of its slot: an update composes with the version just before it
            // (a graph delta names its base), not with an older one.
            if let Some(at) = outbox.waiting.iter().rposition(|(x, _)| *x == Some(s)) {
                let mut merged = outbox.waiting[at].1.clone();
                // Merged, the two may not go on the wire as one (each was checked alone):
                // then both wait, one after the other.
                if merged.supersede(body.clone()).is_ok() {
                    if let Ok(m) = self.check(merged) {
                        if let Some(o) = self.outboxes.get_mut(&kind) {
                            o.waiting[at].1 = m;
                        }
                        self.stats.superseded += 1;
                        return Ok(());
                    }
                }
            }
        }
        let Some(outbox) = self.outboxes.get_mut(&kind) else {
            return Ok(());
        };
        let limit = self.config.outbox_limit;
        if outbox.waiting.len() >= limit {
            let waiting = outbox.waiting.len();
            self.stats.refused_full += 1;
            let bytes = Message::new(self.header(u64::MAX), body).encoded_len();
            return Err(QueueError::Full {
                kind,
                bytes,
                waiting,
                limit,
            });
        }
        outbox.waiting.push((slot, body));
        let waiting: usize = self.outboxes.values().map(|o| o.waiting.len()).sum();
        self.stats.most_waiting = self.stats.most_waiting.max(waiting as u64);
        Ok(())
    }

    /// Messages of `kind` in flight or waiting.
    pub fn unsettled(&self, kind: Kind) -> usize {
        self.outboxes
            .get(&kind)
            .map_or(0, |o| o.in_flight.len() + o.waiting.len())
    }

    /// Sequences of `kind` sent and not yet acknowledged.
    pub fn unacknowledged(&self, kind: Kind) -> Vec<u64> {
        if kind == Kind::Hello {
            return self.hello.iter().map(|(s, _)| *s).collect();
        }
        self.outboxes
            .get(&kind)
            .map(|o| o.in_flight.keys().copied().collect())
            .unwrap_or_default()
    }

    /// Nothing in flight, waiting, or to acknowledge.
    pub fn idle(&self) -> bool {
        self.hello.is_none()
            && self.ack_due.is_empty()
            && self
                .outboxes
                .values()
                .all(|o| o.in_flight.is_empty() && o.waiting.is_empty())
    }

    /// Everything in flight is due at the next poll (a meeting starts).
    pub fn resend_all(&mut self) {
        for outbox in self.outboxes.values_mut() {
            for m in outbox.in_flight.values_mut() {
                m.last_sent_ms = None;
            }
        }
        if let Some((_, h)) = &mut self.hello {
            h.last_sent_ms = None;
        }
    }

    /// Acknowledgements due (of the peer's `peer_epoch`), then what waits and fits in the
    /// windows, then resends of what is in flight past its time.
    pub fn poll(&mut self, now_ms: u64, peer_epoch: Option<u64>) -> Vec<Outgoing> {
        let mut out = Vec::new();
        if let Some(epoch) = peer_epoch {
            for kind in std::mem::take(&mut self.ack_due) {
                let ack = match kind {
                    Kind::Hello => Ack {
                        epoch,
                        kind,
                        next: self.hello_seen.map_or(0, |s| s + 1),
                        received: Vec::new(),
                    },
                    _ => {
                        let r = self.inboxes.get(&kind).cloned().unwrap_or_default();
                        Ack {
                            epoch,
                            kind,
                            next: r.next,
                            received: r.ranges(),
                        }
                    }
                };
                out.push(Outgoing {
                    message: Message::new(self.header(self.ack_sequence), ack),
                    resend: false,
                });
                self.ack_sequence += 1;
            }
        }
        let retransmit = self.config.retransmit_ms;
        let due = |m: &InFlight| match m.last_sent_ms {
            None => true,
            // Exponential back-off (×2 per resend, up to ×16): on a slow radio an
            // acknowledgment can take longer than `retransmit_ms`, and resending at a fixed
            // rate would fill the link with copies.
            Some(t) => now_ms.saturating_sub(t) >= retransmit << m.sends.saturating_sub(1).min(4),
        };
        let mut emitted: Vec<(u64, Body, bool)> = Vec::new();
        if let Some((seq, h)) = &mut self.hello {
            if due(h) {
                emitted.push((*seq, h.body.clone(), h.sends > 0));
                h.sends = h.sends.saturating_add(1);
                h.last_sent_ms = Some(now_ms);
            }
        }
        let window = self.config.window;
        for outbox in self.outboxes.values_mut() {
            // Move what fits into flight: the kind's window, one per slot.
            let mut k = 0;
            while k < outbox.waiting.len() && outbox.in_flight.len() < window {
                let blocked = outbox.waiting[k]
                    .0
                    .is_some_and(|s| outbox.slot_in_flight(s));
                if blocked {
                    k += 1;
                    continue;
                }
                let (slot, body) = outbox.waiting.remove(k);
                let seq = outbox.next_seq;
                outbox.next_seq += 1;
                outbox.in_flight.insert(
                    seq,
                    InFlight {
                        body,
                        slot,
                        last_sent_ms: None,
                        sends: 0,
                    },
                );
            }
            for (&seq, m) in outbox.in_flight.iter_mut() {
                if due(m) {
                    emitted.push((seq, m.body.clone(), m.sends > 0));
                    m.sends = m.sends.saturating_add(1);
                    m.last_sent_ms = Some(now_ms);
                }
            }
        }
        for (seq, body, resend) in emitted {
            self.retransmissions += u64::from(resend);
            out.push(Outgoing {
                message: Message::new(self.header(seq), body),
                resend,
            });
        }
        out
    }

    /// An acknowledgement from the peer (checked for our epoch by the caller): what it
    /// covers leaves the outbox; the bodies that left, for the caller's counters.
    pub fn acknowledged(&mut self, ack: &Ack) -> Result<Vec<Body>, &'static str> {
        if ack.kind == Kind::Hello {
            if let Some((seq, _)) = &self.hello {
                if *seq < ack.next {
                    self.hello = None;
                }
            }
            return Ok(Vec::new());
        }
        let Some(outbox) = self.outboxes.get_mut(&ack.kind) else {
            return Ok(Vec::new());
        };
        if ack.next > outbox.next_seq || ack.received.iter().any(|r| r.end > outbox.next_seq) {
            return Err("acknowledges sequences never sent");
        }
        let done: Vec<u64> = outbox
            .in_flight
            .keys()
            .copied()
            .filter(|&s| s < ack.next || ack.received.iter().any(|r| r.contains(&s)))
            .collect();
        Ok(done
            .into_iter()
            .filter_map(|s| outbox.in_flight.remove(&s).map(|m| m.body))
            .collect())
    }

    /// A Hello of the peer's current epoch with sequence `seq`: whether it is new (an older
    /// or repeated one is only acknowledged again). One naming our epoch opens the peer's
    /// session: its sequences start at `base` for every kind.
    pub fn hello(&mut self, seq: u64, hello: &Hello) -> bool {
        self.ack_due.insert(Kind::Hello);
        if self.hello_seen.is_some_and(|s| seq <= s) {
            return false;
        }
        self.hello_seen = Some(seq);
        if hello.heard == Some(self.epoch) {
            self.accepting = true;
            self.inboxes.clear();
            for kind in Kind::ALL {
                if kind != Kind::Hello && kind != Kind::Ack {
                    self.inboxes.insert(
                        kind,
                        Inbox {
                            next: hello.base,
                            held: BTreeMap::new(),
                        },
                    );
                }
            }
        }
        true
    }

    /// A message of a kind other than Hello and Ack, of the peer's current epoch.
    pub fn arrive(&mut self, header: Header, body: Body) -> Arrived {
        if !self.accepting {
            return Arrived::BeforeSession;
        }
        let kind = body.kind();
        let sequence = header.sequence;
        let inbox = self.inboxes.entry(kind).or_default();
        if sequence < inbox.next || inbox.held.contains_key(&sequence) {
            self.ack_due.insert(kind);
            return Arrived::Duplicate { sequence };
        }
        if sequence >= inbox.next.saturating_add(self.config.hold_back) {
            self.stats.beyond_hold_back += 1;
            return Arrived::BeyondHoldBack { sequence };
        }
        self.ack_due.insert(kind);
        if sequence > inbox.next {
            inbox.held.insert(sequence, (header, body));
            self.stats.held_back += 1;
            return Arrived::Held;
        }
        let mut run = vec![(header, body)];
        inbox.next += 1;
        while let Some(m) = inbox.held.remove(&inbox.next) {
            run.push(m);
            inbox.next += 1;
        }
        Arrived::Deliver(run)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use doorslam_ipc::wire::{Descriptors, LoopClosures, Match, Matches, Route};

    fn config() -> DeliveryConfig {
        DeliveryConfig {
            retransmit_ms: 100,
            window: 8,
            hold_back: 64,
            outbox_limit: 16,
        }
    }

    fn closures() -> Body {
        Body::LoopClosures(LoopClosures {
            closures: Vec::new(),
        })
    }

    /// The demo's rejoin fault: a peer restarts while this robot has only sent one kind
    /// (its first session's sequences make the new session's base > 0); the first message
    /// of a kind this robot never sent before (the back-end's route) must reach the
    /// restarted peer, numbered from the base its Hello announced.
    #[test]
    fn a_kind_first_sent_after_a_restart_of_the_peer_is_delivered() {
        let me = RobotId::new("a").unwrap();
        let mut a = Delivery::new(me, 0, 1, config());
        a.start_session(Some(1), false);
        for _ in 0..3 {
            a.queue(closures()).unwrap();
        }
        assert_eq!(a.poll(0, Some(1)).len(), 4, "a Hello and three messages");
        // The peer restarts (epoch 2): a new session, and then the first route.
        a.peer_epoch_changed();
        a.start_session(Some(2), true);
        a.queue(Body::Route(Route {
            path: vec![0],
            subtree: 0,
            session: 0,
        }))
        .unwrap();
        let out = a.poll(1, Some(2));
        let mut b = Delivery::new(RobotId::new("b").unwrap(), 1, 2, config());
        let mut delivered = Vec::new();
        for o in out {
            let m = o.message;
            match m.body {
                Body::Hello(h) => assert!(b.hello(m.header.sequence, &h)),
                body => {
                    if let Arrived::Deliver(run) = b.arrive(m.header, body) {
                        delivered.extend(run.into_iter().map(|(_, b)| b.kind()));
                    }
                }
            }
        }
        assert_eq!(
            delivered.iter().filter(|k| **k == Kind::Route).count(),
            1,
            "the route reaches the restarted peer: {delivered:?}"
        );
        assert_eq!(
            delivered
                .iter()
                .filter(|k| **k == Kind::LoopClosures)
                .count(),
            3
        );
    }

    fn batch(i: u64) -> Body {
        Body::Descriptors(Descriptors {
            robot: 0,
            keyframes: i..i + 1,
            descriptors: Vec::new(),
        })
    }

    fn route(session: u64) -> Body {
        Body::Route(Route {
            path: vec![0],
            subtree: 0,
            session,
        })
    }

    /// Every message of `a`'s outbox handed to a fresh peer, polling until idle: the
    /// bodies delivered, in order.
    fn drain(a: &mut Delivery) -> Vec<Body> {
        let mut b = Delivery::new(RobotId::new("b").unwrap(), 1, 1, config());
        let mut delivered = Vec::new();
        for now in 0..1000 {
            let out = a.poll(now * 1000, Some(1));
            if out.is_empty() && a.idle() {
                break;
            }
            for o in out {
                let m = o.message;
                match m.body {
                    Body::Hello(h) => {
                        b.hello(m.header.sequence, &h);
                    }
                    Body::Ack(_) => {}
                    body => {
                        if let Arrived::Deliver(run) = b.arrive(m.header, body) {
                            delivered.extend(run.into_iter().map(|(_, b)| b));
                        }
                    }
                }
            }
            for o in b.poll(now * 1000, Some(1)) {
                if let Body::Ack(ack) = &o.message.body {
                    a.acknowledged(ack).unwrap();
                }
            }
        }
        delivered
    }

    /// A stream kind flooded with ten times its outbox bound while the peer is away: what
    /// waits stays at the bound, the rest is refused at queueing (counted, typed), and what
    /// was queued is delivered whole and in order — nothing queued is dropped.
    #[test]
    fn a_full_stream_outbox_refuses_new_messages_and_keeps_the_queued_ones() {
        let mut a = Delivery::new(RobotId::new("a").unwrap(), 0, 1, config());
        a.start_session(Some(1), false);
        let limit = config().outbox_limit;
        let mut refused = 0;
        for i in 0..10 * limit as u64 {
            match a.queue(batch(i)) {
                Ok(()) => {}
                Err(QueueError::Full {
                    kind,
                    waiting,
                    limit: l,
                    bytes,
                }) => {
                    assert_eq!(kind, Kind::Descriptors);
                    assert_eq!((waiting, l), (limit, limit));
                    assert!(bytes > 0);
                    refused += 1;
                }
                Err(e) => panic!("unexpected refusal {e}"),
            }
            assert!(a.unsettled(Kind::Descriptors) <= limit);
        }
        assert_eq!(refused, 9 * limit);
        assert_eq!(a.stats.refused_full, 9 * limit as u64);
        let delivered = drain(&mut a);
        let ranges: Vec<u64> = delivered
            .iter()
            .filter_map(|b| match b {
                Body::Descriptors(d) => Some(d.keyframes.start),
                _ => None,
            })
            .collect();
        assert_eq!(ranges, (0..limit as u64).collect::<Vec<_>>());
        // Room again once delivered.
        assert!(a.queue(batch(999)).is_ok());
    }

    /// A state kind flooded with ten times the bound: each newer message supersedes the
    /// one waiting, so one waits, nothing is refused, and the peer gets the newest.
    #[test]
    fn a_flooded_state_slot_keeps_only_the_newest() {
        let mut a = Delivery::new(RobotId::new("a").unwrap(), 0, 1, config());
        a.start_session(Some(1), false);
        let n = 10 * config().outbox_limit as u64;
        for i in 0..n {
            a.queue(route(i)).unwrap();
            assert_eq!(a.unsettled(Kind::Route), 1);
        }
        assert_eq!(a.stats.superseded, n - 1);
        assert_eq!(a.stats.refused_full, 0);
        let delivered = drain(&mut a);
        assert_eq!(delivered, vec![route(n - 1)]);
    }

    /// A message the encoder refuses is refused at queueing, naming its kind, and nothing
    /// of it stays to be retried: the outbox is idle and the next message goes.
    #[test]
    fn an_unencodable_message_is_refused_at_queueing() {
        let mut a = Delivery::new(RobotId::new("a").unwrap(), 0, 1, config());
        a.start_session(Some(1), false);
        let pair = Match {
            query: doorslam_geometry::key::symbol(0, 1).unwrap(),
            candidate: doorslam_geometry::key::symbol(1, 1).unwrap(),
            distance: 0.5,
        };
        let big = Body::Matches(Matches {
            matches: vec![pair; doorslam_ipc::wire::MAX_MATCHES + 1],
        });
        match a.queue(big) {
            Err(QueueError::Unencodable {
                kind,
                bytes,
                reason,
            }) => {
                assert_eq!(kind, Kind::Matches);
                assert!(bytes > 0);
                assert!(reason.contains("match count"), "{reason}");
            }
            other => panic!("expected Unencodable, got {other:?}"),
        }
        assert_eq!(a.stats.refused_unencodable, 1);
        assert_eq!(a.unsettled(Kind::Matches), 0);
        a.queue(closures()).unwrap();
        let delivered = drain(&mut a);
        assert_eq!(delivered.len(), 1);
        assert!(a.idle());
    }
}
