//! Reliable delivery over a lossy link, per neighbour and message kind: what arrived (for
//! acknowledgements) and what was sent and not yet acknowledged (for resends). The
//! transport may lose, delay or reorder messages; order is by the sender's epoch and
//! sequence, never by clocks.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use doorslam_ipc::wire::{Ack, Body, Header, Kind, Message, RobotId, MAX_ACK_RANGES};

/// What arrived of one kind from a neighbour, by its epoch and sequence.
#[derive(Debug, Default)]
pub(crate) struct Received {
    pub epoch: Option<u64>,
    /// Every sequence below this was received; `above` holds those received beyond it.
    pub next: u64,
    pub above: BTreeSet<u64>,
    pub ack_due: bool,
}

/// How a message's epoch relates to the neighbour's we know.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Arrival {
    /// The current epoch (or the first one heard).
    Current,
    /// A higher epoch: the neighbour restarted and lost what we sent it.
    Restarted,
    /// An older epoch: stale, not recorded.
    Stale,
}

impl Received {
    /// Records a message (epoch, sequence); an acknowledgement becomes due unless stale.
    pub fn arrive(&mut self, epoch: u64, sequence: u64) -> Arrival {
        let arrival = self.epoch_of(epoch);
        if arrival == Arrival::Stale {
            return arrival;
        }
        if self.epoch != Some(epoch) {
            *self = Self {
                epoch: Some(epoch),
                ..Self::default()
            };
        }
        if sequence >= self.next {
            self.above.insert(sequence);
            while self.above.remove(&self.next) {
                self.next += 1;
            }
        }
        self.ack_due = true;
        arrival
    }

    /// How `epoch` relates to the one we know, without recording anything.
    pub fn epoch_of(&self, epoch: u64) -> Arrival {
        match self.epoch {
            Some(e) if epoch < e => Arrival::Stale,
            Some(e) if epoch > e => Arrival::Restarted,
            _ => Arrival::Current,
        }
    }

    /// The acknowledgement due, of `kind`, once: our epoch and ack sequence in the header.
    pub fn take_ack(
        &mut self,
        id: &RobotId,
        own_epoch: u64,
        sequence: u64,
        kind: Kind,
    ) -> Option<Message> {
        let epoch = self.epoch.filter(|_| self.ack_due)?;
        self.ack_due = false;
        Some(ack_message(
            id,
            own_epoch,
            sequence,
            kind,
            epoch,
            self.next,
            &self.above,
        ))
    }
}

/// Messages of one kind sent to one neighbour and not yet acknowledged: sequence → (time
/// sent, on the agent's monotonic clock, what it carried).
#[derive(Debug)]
pub(crate) struct Outbox<T> {
    next: u64,
    in_flight: BTreeMap<u64, (Duration, T)>,
}

impl<T> Default for Outbox<T> {
    fn default() -> Self {
        Self {
            next: 0,
            in_flight: BTreeMap::new(),
        }
    }
}

/// What an acknowledgement or a timeout decided about messages in flight.
#[derive(Debug)]
pub(crate) struct Settled<T> {
    /// Acknowledged, in sequence order: the neighbour holds what they carried.
    pub delivered: Vec<T>,
    /// Taken as lost: what they carried is due again.
    pub lost: Vec<T>,
}

impl<T> Outbox<T> {
    /// Records a message about to be sent; its sequence number.
    pub fn send(&mut self, now: Duration, item: T) -> u64 {
        let s = self.next;
        self.next += 1;
        self.in_flight.insert(s, (now, item));
        s
    }

    pub fn is_empty(&self) -> bool {
        self.in_flight.is_empty()
    }

    /// What is in flight, oldest first.
    pub fn items(&self) -> impl Iterator<Item = &T> {
        self.in_flight.values().map(|(_, t)| t)
    }

    /// Drops what is in flight (the neighbour restarted: it holds nothing of it).
    pub fn clear(&mut self) {
        self.in_flight.clear();
    }

    /// Removes in-flight messages matching `f` (their content became moot).
    pub fn forget(&mut self, mut f: impl FnMut(&T) -> bool) -> Vec<T> {
        let gone: Vec<u64> = self
            .in_flight
            .iter()
            .filter(|(_, (_, t))| f(t))
            .map(|(s, _)| *s)
            .collect();
        gone.into_iter()
            .filter_map(|s| self.in_flight.remove(&s).map(|(_, t)| t))
            .collect()
    }

    /// An acknowledgement: acknowledged messages are delivered; one not acknowledged while a
    /// later one was is lost.
    pub fn acknowledge(&mut self, ack: &Ack) -> Settled<T> {
        let acked = |s: u64| s < ack.next || ack.received.iter().any(|r| r.contains(&s));
        let highest = self.in_flight.keys().copied().filter(|&s| acked(s)).max();
        let mut settled = Settled {
            delivered: Vec::new(),
            lost: Vec::new(),
        };
        let seqs: Vec<u64> = self.in_flight.keys().copied().collect();
        for s in seqs {
            if acked(s) {
                if let Some((_, t)) = self.in_flight.remove(&s) {
                    settled.delivered.push(t);
                }
            } else if highest.is_some_and(|h| s < h) {
                if let Some((_, t)) = self.in_flight.remove(&s) {
                    settled.lost.push(t);
                }
            }
        }
        settled
    }

    /// Messages unacknowledged for `after` (time, not steps: a step's length varies):
    /// taken as lost.
    pub fn expire(&mut self, now: Duration, after: Duration) -> Vec<T> {
        let old: Vec<u64> = self
            .in_flight
            .iter()
            .filter(|(_, (sent, _))| now.saturating_sub(*sent) >= after)
            .map(|(&s, _)| s)
            .collect();
        old.into_iter()
            .filter_map(|s| self.in_flight.remove(&s).map(|(_, t)| t))
            .collect()
    }
}

/// An acknowledgement of the sequences of `kind` received in the peer's `epoch`.
pub(crate) fn ack_message(
    id: &RobotId,
    own_epoch: u64,
    sequence: u64,
    kind: Kind,
    epoch: u64,
    next: u64,
    received: &BTreeSet<u64>,
) -> Message {
    // All below `next` received; then the ranges above it.
    let mut ranges: Vec<std::ops::Range<u64>> = Vec::new();
    for &s in received.range(next + 1..) {
        match ranges.last_mut() {
            Some(r) if r.end == s => r.end += 1,
            _ => ranges.push(s..s + 1),
        }
    }
    // The newest ranges matter most for loss detection; the wire bounds their number.
    let skip = ranges.len().saturating_sub(MAX_ACK_RANGES);
    Message::new(
        Header {
            sender: id.clone(),
            epoch: own_epoch,
            sequence,
        },
        Body::Ack(Ack {
            epoch,
            kind,
            next,
            received: ranges.split_off(skip),
        }),
    )
}

#[cfg(test)]
// Acknowledgements list received ranges; a list of one range is the case under test.
#[allow(clippy::single_range_in_vec_init)]
mod tests {
    use super::*;

    fn ack(next: u64, received: Vec<std::ops::Range<u64>>) -> Ack {
        Ack {
            epoch: 1,
            kind: Kind::Route,
            next,
            received,
        }
    }

    #[test]
    fn outbox_settles_acknowledged_and_overtaken_messages() {
        let mut o = Outbox::default();
        for i in 0..4 {
            assert_eq!(o.send(Duration::ZERO, i), i);
        }
        // 0 and 2 arrived, 1 did not (overtaken: lost), 3 is still in flight.
        let s = o.acknowledge(&ack(1, vec![2..3]));
        assert_eq!((s.delivered, s.lost), (vec![0, 2], vec![1]));
        assert_eq!(o.items().copied().collect::<Vec<_>>(), vec![3]);
        let ms = Duration::from_millis;
        assert_eq!(o.expire(ms(399), ms(400)), Vec::<u64>::new());
        assert_eq!(o.expire(ms(400), ms(400)), vec![3]);
        assert!(o.is_empty());
        assert_eq!(o.send(ms(500), 9), 4);
    }

    #[test]
    fn received_acknowledges_gaps_and_forgets_an_old_epoch() {
        let id = RobotId::new("a").unwrap();
        let mut r = Received::default();
        assert_eq!(r.arrive(2, 0), Arrival::Current);
        assert_eq!(r.arrive(2, 2), Arrival::Current);
        let Some(Message {
            body: Body::Ack(a), ..
        }) = r.take_ack(&id, 1, 0, Kind::Route)
        else {
            panic!("an ack is due")
        };
        assert_eq!((a.epoch, a.next, a.received), (2, 1, vec![2..3]));
        assert!(r.take_ack(&id, 1, 1, Kind::Route).is_none());
        assert_eq!(r.arrive(1, 5), Arrival::Stale);
        assert_eq!(r.arrive(3, 0), Arrival::Restarted);
        assert_eq!((r.next, r.above.len()), (1, 0));
    }
}
