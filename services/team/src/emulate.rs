//! In-process link emulation behind [`Link`], for fast deterministic tests of the protocol:
//! robots on one [`Bus`], each pair in range or not ([`Bus::join`], [`Bus::cut`]: what the
//! liveliness tokens would say), random loss, reordering and duplication with a seed, and
//! counters of what was published and delivered.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use doorslam_ipc::wire::{Kind, RobotId};

use crate::node::{Link, LinkError, LinkEvent};

#[derive(Debug, Default)]
struct BusState {
    queues: BTreeMap<RobotId, VecDeque<LinkEvent>>,
    in_range: BTreeSet<(RobotId, RobotId)>,
    loss: f64,
    /// Probability that a message is held back 1-4 polls of its receiver (arriving after
    /// messages sent later), and that it arrives twice (the copy delayed the same way).
    reorder: f64,
    duplicate: f64,
    /// Messages held back per receiver: polls still to wait, the message.
    delayed: BTreeMap<RobotId, Vec<(u32, LinkEvent)>>,
    reordered: u64,
    duplicated: u64,
    rng: u64,
    published_bytes: BTreeMap<RobotId, u64>,
    published: BTreeMap<RobotId, Vec<(RobotId, Vec<u8>)>>,
}

impl BusState {
    fn random(&mut self) -> f64 {
        // xorshift64*: deterministic for a seed.
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        (self.rng.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn pair(a: &RobotId, b: &RobotId) -> (RobotId, RobotId) {
    if a < b {
        (a.clone(), b.clone())
    } else {
        (b.clone(), a.clone())
    }
}

/// The shared medium of an emulated team.
#[derive(Debug, Clone)]
pub struct Bus(Arc<Mutex<BusState>>);

impl Bus {
    /// A bus dropping each message with probability `loss` (random, from `seed`).
    pub fn new(loss: f64, seed: u64) -> Self {
        Self(Arc::new(Mutex::new(BusState {
            loss,
            rng: seed | 1,
            ..BusState::default()
        })))
    }

    fn state(&self) -> MutexGuard<'_, BusState> {
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A robot's end of the bus.
    pub fn link(&self, me: &RobotId) -> EmulatedLink {
        self.state().queues.entry(me.clone()).or_default();
        EmulatedLink {
            me: me.clone(),
            bus: self.clone(),
        }
    }

    /// `a` and `b` come into range: each sees the other's token appear.
    pub fn join(&self, a: &RobotId, b: &RobotId) {
        let mut s = self.state();
        if s.in_range.insert(pair(a, b)) {
            s.queues
                .entry(a.clone())
                .or_default()
                .push_back(LinkEvent::PeerAppeared(b.clone()));
            s.queues
                .entry(b.clone())
                .or_default()
                .push_back(LinkEvent::PeerAppeared(a.clone()));
        }
    }

    /// `a` and `b` go out of range: messages in flight between them are lost, and each
    /// sees the other's token disappear.
    pub fn cut(&self, a: &RobotId, b: &RobotId) {
        let mut s = self.state();
        if s.in_range.remove(&pair(a, b)) {
            for (me, other) in [(a, b), (b, a)] {
                if let Some(d) = s.delayed.get_mut(me) {
                    d.retain(
                        |(_, e)| !matches!(e, LinkEvent::Message { from, .. } if from == other),
                    );
                }
                let q = s.queues.entry(me.clone()).or_default();
                q.retain(|e| !matches!(e, LinkEvent::Message { from, .. } if from == other));
                q.push_back(LinkEvent::PeerLeft(other.clone()));
            }
        }
    }

    pub fn set_loss(&self, loss: f64) {
        self.state().loss = loss;
    }

    /// Each message is held back with probability `reorder` (1-4 polls of its receiver,
    /// so later ones overtake it) and arrives twice with probability `duplicate`.
    pub fn set_reorder_duplicate(&self, reorder: f64, duplicate: f64) {
        let mut s = self.state();
        s.reorder = reorder;
        s.duplicate = duplicate;
    }

    /// Messages held back so far, and messages that arrived twice.
    pub fn reordered_duplicated(&self) -> (u64, u64) {
        let s = self.state();
        (s.reordered, s.duplicated)
    }

    /// Bytes `robot` published (lost ones included: they left the robot).
    pub fn published_bytes(&self, robot: &RobotId) -> u64 {
        self.state()
            .published_bytes
            .get(robot)
            .copied()
            .unwrap_or(0)
    }

    /// Every message `robot` published, with its destination, in order.
    pub fn published(&self, robot: &RobotId) -> Vec<(RobotId, Vec<u8>)> {
        self.state()
            .published
            .get(robot)
            .cloned()
            .unwrap_or_default()
    }

    /// Injects raw bytes as if published by `from` (tests of misbehaving peers).
    pub fn inject(&self, to: &RobotId, from: &RobotId, kind: &str, bytes: Vec<u8>) {
        self.state()
            .queues
            .entry(to.clone())
            .or_default()
            .push_back(LinkEvent::Message {
                from: from.clone(),
                kind: kind.into(),
                bytes,
            });
    }
}

/// One robot's end of a [`Bus`].
#[derive(Debug, Clone)]
pub struct EmulatedLink {
    me: RobotId,
    bus: Bus,
}

impl Link for EmulatedLink {
    fn publish(&mut self, to: &RobotId, kind: Kind, bytes: &[u8]) -> Result<(), LinkError> {
        let mut s = self.bus.state();
        *s.published_bytes.entry(self.me.clone()).or_default() += bytes.len() as u64;
        s.published
            .entry(self.me.clone())
            .or_default()
            .push((to.clone(), bytes.to_vec()));
        if !s.in_range.contains(&pair(&self.me, to)) {
            return Ok(());
        }
        let loss = s.loss;
        if loss > 0.0 && s.random() < loss {
            return Ok(());
        }
        let copies = if s.duplicate > 0.0 && s.random() < s.duplicate {
            s.duplicated += 1;
            2
        } else {
            1
        };
        for _ in 0..copies {
            let event = LinkEvent::Message {
                from: self.me.clone(),
                kind: kind.name().into(),
                bytes: bytes.to_vec(),
            };
            if s.reorder > 0.0 && s.random() < s.reorder {
                s.reordered += 1;
                let polls = 1 + (s.random() * 4.0) as u32;
                s.delayed
                    .entry(to.clone())
                    .or_default()
                    .push((polls, event));
            } else {
                s.queues.entry(to.clone()).or_default().push_back(event);
            }
        }
        Ok(())
    }

    fn poll_events(&mut self, _timeout: Duration) -> Vec<LinkEvent> {
        let mut s = self.bus.state();
        // Held-back messages whose time came go after what arrived meanwhile.
        let mut due = Vec::new();
        if let Some(d) = s.delayed.get_mut(&self.me) {
            for (polls, _) in d.iter_mut() {
                *polls = polls.saturating_sub(1);
            }
            let (now, later): (Vec<_>, Vec<_>) = d.drain(..).partition(|(p, _)| *p == 0);
            *d = later;
            due = now.into_iter().map(|(_, e)| e).collect();
        }
        let q = s.queues.entry(self.me.clone()).or_default();
        q.extend(due);
        q.drain(..).collect()
    }
}
