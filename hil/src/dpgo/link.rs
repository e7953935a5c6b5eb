//! `doorslam dpgo` over the team link robots run: one [`PeerSession`] per pair of
//! neighbours (the delivery contract: in order, exactly once per kind, state superseding,
//! acknowledgements and resends), over an emulated radio that drops, reorders and
//! duplicates messages. The agents run with `AgentOptions::link_delivers` (no transport
//! logic of their own), as the back-end service does behind the team link.
//!
//! Time: each round of the runner is `round_ms` of every robot's local clock (the link's
//! retransmission time is in milliseconds of it).

use std::collections::{BTreeMap, BTreeSet};

use doorslam_backend::distributed::runner::{robot_id, Transport, TransportCounts};
use doorslam_backend::distributed::DpgoError;
use doorslam_ipc::wire::{Body, Header, LoopClosure, Message, RobotId};
use doorslam_team::protocol::{
    BackendExchange, BackendRefusal, Identity, PeerSession, ProtocolConfig, Refusal, Services,
};
use doorslam_team::standin::{SimPlaces, SimWorld, TruthVerifier};

/// The radio's faults, per message put on it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Faults {
    /// Lost.
    pub drop: f64,
    /// Held back 1-3 rounds (later messages overtake it).
    pub reorder: f64,
    /// Arrives twice (the copy delayed like any message).
    pub duplicate: f64,
    pub seed: u64,
}

/// The link's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkOptions {
    pub faults: Faults,
    /// Local time of one round.
    pub round_ms: u64,
    pub protocol: ProtocolConfig,
}

impl Default for LinkOptions {
    fn default() -> Self {
        Self {
            faults: Faults {
                drop: 0.0,
                reorder: 0.0,
                duplicate: 0.0,
                seed: 1,
            },
            round_ms: 100,
            protocol: ProtocolConfig {
                retransmit_ms: 300,
                ..ProtocolConfig::default()
            },
        }
    }
}

/// The agent's side of one session: bodies to send, messages received.
#[derive(Debug, Default)]
struct Mailbox {
    out: Vec<Body>,
    inbox: Vec<(Header, Body)>,
}

impl BackendExchange for Mailbox {
    fn loop_closures(&mut self, _peer: &RobotId, _closures: &[LoopClosure]) {}

    fn messages_for(&mut self, _peer: &RobotId) -> Vec<Body> {
        std::mem::take(&mut self.out)
    }

    fn receive(
        &mut self,
        _peer: &RobotId,
        header: &Header,
        body: Body,
    ) -> Result<(), BackendRefusal> {
        self.inbox.push((header.clone(), body));
        Ok(())
    }
}

/// One robot's end of the link with one neighbour.
struct End {
    session: PeerSession,
    mailbox: Mailbox,
    /// The rendezvous' own pieces: no keyframes, so no descriptors (closures come from the
    /// graph in this runner).
    place: SimPlaces,
    verifier: TruthVerifier,
}

impl End {
    fn services(&mut self) -> (&mut PeerSession, Services<'_>) {
        (
            &mut self.session,
            Services {
                place: &mut self.place,
                verifier: &mut self.verifier,
                backend: &mut self.mailbox,
            },
        )
    }
}

/// A message on the air: rounds still to wait, to, from, bytes.
type OnAir = (u32, u8, u8, Vec<u8>);

/// The team link of a simulated team: [`Transport`] for the `dpgo` runner.
pub struct SessionLink {
    options: LinkOptions,
    ends: BTreeMap<(u8, u8), End>,
    in_range: BTreeSet<(u8, u8)>,
    air: Vec<OnAir>,
    now_ms: u64,
    rng: u64,
    counts: TransportCounts,
    /// Messages the receiving session did not take, by reason (duplicates, beyond the
    /// hold-back buffer, ...): the link's own bookkeeping, not errors.
    pub not_taken: BTreeMap<&'static str, u64>,
    pub reordered: u64,
    pub duplicated: u64,
}

impl SessionLink {
    pub fn new(options: LinkOptions) -> Self {
        Self {
            options,
            ends: BTreeMap::new(),
            in_range: BTreeSet::new(),
            air: Vec::new(),
            now_ms: 0,
            rng: options.faults.seed | 1,
            counts: TransportCounts::default(),
            not_taken: BTreeMap::new(),
            reordered: 0,
            duplicated: 0,
        }
    }

    fn random(&mut self) -> f64 {
        // xorshift64*: deterministic for a seed.
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        (self.rng.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn end(&mut self, me: u8, peer: u8) -> Result<&mut End, DpgoError> {
        if !self.ends.contains_key(&(me, peer)) {
            let identity = Identity {
                id: robot_id(me)?,
                robot: me,
                epoch: 1,
            };
            let session = PeerSession::new(identity, robot_id(peer)?, self.options.protocol);
            let world = SimWorld::default();
            self.ends.insert(
                (me, peer),
                End {
                    session,
                    mailbox: Mailbox::default(),
                    place: SimPlaces::new(world, me, 0),
                    verifier: TruthVerifier::from_world(world),
                },
            );
        }
        Ok(self.ends.get_mut(&(me, peer)).expect("inserted above"))
    }

    /// Every session's delivery counters, summed.
    pub fn delivery(&self) -> doorslam_team::delivery::DeliveryStats {
        let mut d = doorslam_team::delivery::DeliveryStats::default();
        for e in self.ends.values() {
            let s = &e.session.stats().delivery;
            d.held_back += s.held_back;
            d.beyond_hold_back += s.beyond_hold_back;
            d.superseded += s.superseded;
            d.most_waiting = d.most_waiting.max(s.most_waiting);
            d.sessions += s.sessions;
            d.dropped_at_restart += s.dropped_at_restart;
        }
        d
    }
}

fn pair(a: u8, b: u8) -> (u8, u8) {
    (a.min(b), a.max(b))
}

fn bad(from: u8, reason: String) -> DpgoError {
    DpgoError::BadMessage { from, reason }
}

impl Transport for SessionLink {
    fn presence(&mut self, a: u8, b: u8, present: bool) {
        let Ok(end) = self.end(a, b) else {
            return;
        };
        match (present, end.session.is_connected()) {
            (true, false) => end.session.meeting_started(),
            (false, true) => end.session.meeting_ended(),
            _ => {}
        }
        if present {
            self.in_range.insert(pair(a, b));
        } else if self.in_range.remove(&pair(a, b)) {
            // Out of range: what is on the air between them is lost.
            let lost = self
                .air
                .iter()
                .filter(|(_, to, from, _)| pair(*to, *from) == pair(a, b))
                .count();
            self.counts.dropped += lost as u64;
            self.air
                .retain(|(_, to, from, _)| pair(*to, *from) != pair(a, b));
        }
    }

    fn send(&mut self, from: u8, to: u8, message: Message) -> Result<(), DpgoError> {
        self.end(from, to)?.mailbox.out.push(message.body);
        Ok(())
    }

    fn deliver(&mut self) -> Result<Vec<(u8, u8, Message)>, DpgoError> {
        self.now_ms += self.options.round_ms;
        let now = self.now_ms;
        // What arrives this round (held back earlier), then what is sent now.
        let mut arriving = Vec::new();
        for m in std::mem::take(&mut self.air) {
            if m.0 == 0 {
                arriving.push(m);
            } else {
                self.air.push((m.0 - 1, m.1, m.2, m.3));
            }
        }
        let keys: Vec<(u8, u8)> = self.ends.keys().copied().collect();
        for (me, peer) in keys {
            let Some(end) = self.ends.get_mut(&(me, peer)) else {
                continue;
            };
            let (session, mut services) = end.services();
            let out = session.poll(now, &mut services);
            for o in out {
                let bytes = o.message.encode().map_err(|e| bad(me, e.to_string()))?;
                let kind = o.message.kind().name().to_string();
                self.counts.messages += 1;
                self.counts.bytes += bytes.len() as u64;
                self.counts.resent += u64::from(o.resend);
                *self.counts.bytes_by_kind.entry(kind.clone()).or_default() += bytes.len() as u64;
                *self.counts.messages_by_kind.entry(kind).or_default() += 1;
                let f = self.options.faults;
                if f.drop > 0.0 && self.random() < f.drop {
                    self.counts.dropped += 1;
                    continue;
                }
                let copies = if f.duplicate > 0.0 && self.random() < f.duplicate {
                    self.duplicated += 1;
                    2
                } else {
                    1
                };
                for _ in 0..copies {
                    if f.reorder > 0.0 && self.random() < f.reorder {
                        self.reordered += 1;
                        let rounds = 1 + (self.random() * 3.0) as u32;
                        self.air.push((rounds - 1, peer, me, bytes.clone()));
                    } else {
                        arriving.push((0, peer, me, bytes.clone()));
                    }
                }
            }
        }
        for (_, to, from, bytes) in arriving {
            if !self.in_range.contains(&pair(to, from)) {
                self.counts.dropped += 1;
                continue;
            }
            let message = Message::decode(&bytes).map_err(|e| bad(from, e.to_string()))?;
            let end = self.end(to, from)?;
            let (session, mut services) = end.services();
            let refusals = match session.receive(message, &mut services) {
                Ok(r) => r,
                Err(r) => vec![r],
            };
            for r in refusals {
                if matches!(r, Refusal::Backend(_) | Refusal::Invalid { .. }) {
                    self.counts.refused += 1;
                }
                *self.not_taken.entry(r.reason()).or_default() += 1;
            }
        }
        let mut delivered = Vec::new();
        for (&(me, peer), end) in &mut self.ends {
            for (header, body) in end.mailbox.inbox.drain(..) {
                delivered.push((me, peer, Message::new(header, body)));
            }
        }
        Ok(delivered)
    }

    fn idle(&self) -> bool {
        self.air.is_empty()
            && self
                .ends
                .values()
                .all(|e| e.mailbox.out.is_empty() && e.session.idle())
    }

    fn sent(&self) -> TransportCounts {
        self.counts.clone()
    }
}
