//! Which peers are present, as this robot's link reports them to its [`crate::Node`], kept
//! consistent with Zenoh's routing tables.
//!
//! The liveliness subscriber alone is not enough on a lossy radio. Two demo runs (a chaos
//! run and a killed robot's rejoin, 30 % loss) ended with one robot never again told that
//! its peer was there, although the peer's messages kept arriving: the robot dropped them
//! (`unknown_peer`) for the whole 90 s at base and stayed in its own frame. So the link
//! also asks Zenoh which tokens it holds (a liveliness query, answered from the local
//! routing tables for peers already met: no bytes on the radio) every
//! [`PresenceRules::check_every_ms`], and at once when a peer it does not count as present
//! talks to it. The query's answer is the truth:
//!
//! - a token the query finds but the subscriber never reported: the peer appeared;
//! - a present peer whose token two queries in a row do not find: the peer left (its
//!   delete was missed);
//! - a peer that keeps talking to this robot for [`PresenceRules::reopen_after_ms`] while
//!   no query finds its token: this session's tables are broken; the link reopens its
//!   Zenoh session (new tables, new declarations) — the only mend from this side. Each
//!   reopen doubles the time the next one needs (up to [`MAX_REOPEN_AFTER_MS`]), so a
//!   teammate that talks without ever declaring its token cannot make this robot leave
//!   and rejoin the team every few seconds.
//!
//! Pure state, driven by the link with times in milliseconds, so every rule is tested
//! without a network.

use std::collections::{BTreeMap, BTreeSet};

use doorslam_ipc::wire::RobotId;

use crate::node::LinkEvent;

/// The longest a peer must be heard without a token before a reopen, after backoff.
pub const MAX_REOPEN_AFTER_MS: u64 = 600_000;

/// When the link checks presence against Zenoh, and when it gives up on its session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PresenceRules {
    /// Period of the liveliness query (local: costs no radio bytes for peers met).
    pub check_every_ms: u64,
    /// Least time between two queries started by messages from absent peers.
    pub min_gap_ms: u64,
    /// A peer heard from for this long, its token found by no query in between: reopen.
    pub reopen_after_ms: u64,
    /// Queries in a row that must miss such a peer's token before a reopen.
    pub reopen_misses: u32,
    /// A peer not heard from for this long is forgotten (its messages were in flight
    /// when it left). Longer than the protocol's longest resend period (16 s), so a peer
    /// whose only traffic is backed-off resends still counts as talking.
    pub forget_unheard_ms: u64,
}

impl Default for PresenceRules {
    fn default() -> Self {
        Self {
            check_every_ms: 3_000,
            min_gap_ms: 1_000,
            reopen_after_ms: 10_000,
            reopen_misses: 3,
            forget_unheard_ms: 60_000,
        }
    }
}

/// What the presence checks mended, for `status.json` (`presence`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PresenceMends {
    /// Peers found by a liveliness query after the subscriber missed their arrival.
    pub found_by_check: u64,
    /// Peers removed by queries after the subscriber missed their departure.
    pub lost_by_check: u64,
    /// Times the Zenoh session was reopened because its tables lost a talking peer.
    pub reopens: u64,
}

/// A peer heard from while not counted present.
#[derive(Debug, Clone, Copy)]
struct Unheard {
    first_ms: u64,
    last_ms: u64,
    misses: u32,
}

/// What a finished query asks of the link.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Checked {
    /// Events for the node (peers appeared or left by the query's word).
    pub events: Vec<LinkEvent>,
    /// Reopen the Zenoh session: a peer talks to us that our tables do not hold.
    pub reopen: bool,
}

/// The present peers and the reconciliation of them with Zenoh's tables.
#[derive(Debug)]
pub struct Presence {
    me: RobotId,
    rules: PresenceRules,
    present: BTreeSet<RobotId>,
    /// Present peers a query missed once (a second miss: they left).
    missed_once: BTreeSet<RobotId>,
    unheard: BTreeMap<RobotId, Unheard>,
    /// `rules.reopen_after_ms`, doubled by each reopen.
    reopen_after_ms: u64,
    next_check_ms: u64,
    last_start_ms: Option<u64>,
    in_flight: bool,
    /// Peers found by a query after the subscriber missed their put.
    pub found_by_check: u64,
    /// Peers removed by a query after the subscriber missed their delete.
    pub lost_by_check: u64,
}

impl Presence {
    pub fn new(me: RobotId, rules: PresenceRules, now_ms: u64) -> Self {
        Self {
            me,
            rules,
            present: BTreeSet::new(),
            missed_once: BTreeSet::new(),
            unheard: BTreeMap::new(),
            reopen_after_ms: rules.reopen_after_ms,
            next_check_ms: now_ms + rules.check_every_ms,
            last_start_ms: None,
            in_flight: false,
            found_by_check: 0,
            lost_by_check: 0,
        }
    }

    pub fn is_present(&self, peer: &RobotId) -> bool {
        self.present.contains(peer)
    }

    /// A token put (`alive`) or delete from the liveliness subscriber.
    pub fn token(&mut self, peer: RobotId, alive: bool) -> Option<LinkEvent> {
        if peer == self.me {
            return None;
        }
        self.missed_once.remove(&peer);
        if alive {
            self.unheard.remove(&peer);
            self.present
                .insert(peer.clone())
                .then_some(LinkEvent::PeerAppeared(peer))
        } else {
            self.present
                .remove(&peer)
                .then_some(LinkEvent::PeerLeft(peer))
        }
    }

    /// A message from `peer` arrived at `now_ms`. From a peer not counted present it asks
    /// for a query soon (at most one per `min_gap_ms`).
    pub fn heard_from(&mut self, peer: &RobotId, now_ms: u64) {
        if *peer == self.me || self.present.contains(peer) {
            return;
        }
        let u = self.unheard.entry(peer.clone()).or_insert(Unheard {
            first_ms: now_ms,
            last_ms: now_ms,
            misses: 0,
        });
        u.last_ms = now_ms;
        let soonest = self
            .last_start_ms
            .map_or(now_ms, |t| t + self.rules.min_gap_ms);
        self.next_check_ms = self.next_check_ms.min(soonest.max(now_ms));
    }

    /// Whether to start a query now; if so it is counted as started.
    pub fn start_check(&mut self, now_ms: u64) -> bool {
        if self.in_flight || now_ms < self.next_check_ms {
            return false;
        }
        self.in_flight = true;
        self.last_start_ms = Some(now_ms);
        self.next_check_ms = now_ms + self.rules.check_every_ms;
        true
    }

    /// The query started last found exactly the tokens of `alive` (its reply channel
    /// closed). `complete`: false when it timed out, so absence proves nothing.
    pub fn checked(&mut self, alive: &BTreeSet<RobotId>, complete: bool, now_ms: u64) -> Checked {
        self.in_flight = false;
        let mut out = Checked::default();
        for peer in alive {
            if *peer != self.me && self.present.insert(peer.clone()) {
                tracing::warn!(peer = %peer, "presence check: the peer's token is held but its arrival was never reported; peer present");
                self.found_by_check += 1;
                self.unheard.remove(peer);
                out.events.push(LinkEvent::PeerAppeared(peer.clone()));
            }
        }
        if !complete {
            return out;
        }
        let missing: Vec<RobotId> = self
            .present
            .iter()
            .filter(|p| !alive.contains(*p))
            .cloned()
            .collect();
        self.missed_once.retain(|p| missing.contains(p));
        for peer in missing {
            if self.missed_once.insert(peer.clone()) {
                continue;
            }
            tracing::warn!(peer = %peer, "presence check: the peer's token is gone but its departure was never reported; peer left");
            self.missed_once.remove(&peer);
            self.present.remove(&peer);
            self.lost_by_check += 1;
            out.events.push(LinkEvent::PeerLeft(peer));
        }
        // A peer that went quiet: its messages were in flight when it left.
        let stale = self.rules.forget_unheard_ms;
        self.unheard
            .retain(|_, u| now_ms.saturating_sub(u.last_ms) <= stale);
        for (peer, u) in &mut self.unheard {
            u.misses += 1;
            if u.misses >= self.rules.reopen_misses
                && u.last_ms.saturating_sub(u.first_ms) >= self.reopen_after_ms
            {
                tracing::warn!(peer = %peer, heard_for_ms = u.last_ms - u.first_ms, "presence check: the peer keeps talking to us but no query finds its token; reopening the Zenoh session");
                out.reopen = true;
            }
        }
        if out.reopen {
            self.unheard.clear();
            self.reopen_after_ms = (2 * self.reopen_after_ms).min(MAX_REOPEN_AFTER_MS);
        }
        out
    }

    /// The session was reopened: what the old one reported stays (the new subscriber's
    /// history repeats the tokens still there; queries remove the others).
    pub fn reopened(&mut self, now_ms: u64) {
        self.in_flight = false;
        self.next_check_ms = now_ms + self.rules.check_every_ms;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id(s: &str) -> RobotId {
        RobotId::new(s).unwrap()
    }

    fn set(ids: &[&str]) -> BTreeSet<RobotId> {
        ids.iter().map(|s| id(s)).collect()
    }

    fn presence() -> Presence {
        Presence::new(id("a"), PresenceRules::default(), 0)
    }

    #[test]
    fn tokens_are_reported_once_and_never_our_own() {
        let mut p = presence();
        assert_eq!(
            p.token(id("b"), true),
            Some(LinkEvent::PeerAppeared(id("b")))
        );
        assert_eq!(p.token(id("b"), true), None);
        assert_eq!(p.token(id("a"), true), None);
        assert_eq!(p.token(id("b"), false), Some(LinkEvent::PeerLeft(id("b"))));
        assert_eq!(p.token(id("b"), false), None);
    }

    #[test]
    fn a_missed_put_is_found_by_the_next_check() {
        let mut p = presence();
        assert!(!p.start_check(2_999));
        assert!(p.start_check(3_000));
        assert!(!p.start_check(3_001), "one query at a time");
        let c = p.checked(&set(&["a", "b"]), true, 3_010);
        assert_eq!(c.events, vec![LinkEvent::PeerAppeared(id("b"))]);
        assert!(!c.reopen);
        assert_eq!(p.found_by_check, 1);
        assert!(!p.start_check(5_999));
        assert!(p.start_check(6_000));
    }

    #[test]
    fn a_missed_delete_takes_two_complete_checks() {
        let mut p = presence();
        p.token(id("b"), true);
        assert!(p.start_check(3_000));
        assert!(p.checked(&set(&[]), true, 3_000).events.is_empty());
        // A timed-out query proves no absence.
        assert!(p.start_check(6_000));
        assert!(p.checked(&set(&[]), false, 6_000).events.is_empty());
        assert!(p.start_check(9_000));
        assert_eq!(
            p.checked(&set(&[]), true, 9_000).events,
            vec![LinkEvent::PeerLeft(id("b"))]
        );
        assert!(!p.is_present(&id("b")));
        assert_eq!(p.lost_by_check, 1);
    }

    #[test]
    fn a_miss_then_a_find_keeps_the_peer() {
        let mut p = presence();
        p.token(id("b"), true);
        p.start_check(3_000);
        p.checked(&set(&[]), true, 3_000);
        p.start_check(6_000);
        assert!(p.checked(&set(&["b"]), true, 6_000).events.is_empty());
        p.start_check(9_000);
        assert!(p.checked(&set(&[]), true, 9_000).events.is_empty());
        assert!(p.is_present(&id("b")));
    }

    #[test]
    fn a_message_from_an_absent_peer_asks_for_a_check_soon_but_not_too_often() {
        let mut p = presence();
        p.heard_from(&id("b"), 100);
        assert!(p.start_check(100));
        p.checked(&set(&[]), true, 120);
        p.heard_from(&id("b"), 500);
        assert!(!p.start_check(500), "at most one query per min_gap_ms");
        assert!(p.start_check(1_100));
        // Messages from present peers ask for nothing.
        p.checked(&set(&["b"]), true, 1_110);
        p.heard_from(&id("b"), 2_200);
        assert!(!p.start_check(2_200));
    }

    #[test]
    fn a_peer_heard_for_long_without_a_token_reopens_the_session() {
        let mut p = presence();
        let mut reopened_at = None;
        for t in (0..20_000).step_by(500) {
            p.heard_from(&id("b"), t);
            if p.start_check(t) && p.checked(&set(&[]), true, t).reopen {
                reopened_at = Some(t);
                break;
            }
        }
        let t = reopened_at.expect("reopen asked");
        assert!((10_000..12_000).contains(&t), "reopen at {t} ms");
        // The evidence starts over, and the next reopen needs twice as long.
        p.reopened(t);
        let mut again = None;
        for t2 in (t + 500..t + 60_000).step_by(500) {
            p.heard_from(&id("b"), t2);
            if p.start_check(t2) && p.checked(&set(&[]), true, t2).reopen {
                again = Some(t2 - t);
                break;
            }
        }
        let after = again.expect("second reopen asked");
        assert!(
            (20_000..23_000).contains(&after),
            "second reopen {after} ms later"
        );
    }

    #[test]
    fn a_peer_whose_only_traffic_is_backed_off_resends_still_reopens_the_session() {
        let mut p = presence();
        let mut reopened_at = None;
        for t in (0..60_000).step_by(250) {
            if t % 16_000 == 0 {
                p.heard_from(&id("b"), t);
            }
            if p.start_check(t) && p.checked(&set(&[]), true, t).reopen {
                reopened_at = Some(t);
                break;
            }
        }
        let t = reopened_at.expect("reopen asked");
        assert!((16_000..20_000).contains(&t), "reopen at {t} ms");
    }

    #[test]
    fn stale_messages_of_a_departed_peer_reopen_nothing() {
        let mut p = presence();
        p.token(id("b"), true);
        p.token(id("b"), false);
        // In flight when b left: a burst over two seconds, then silence.
        for t in [10, 500, 1_200, 2_000] {
            p.heard_from(&id("b"), t);
        }
        for t in (0..120_000).step_by(250) {
            if p.start_check(t) {
                let c = p.checked(&set(&[]), true, t);
                assert!(!c.reopen && c.events.is_empty(), "at {t} ms: {c:?}");
            }
        }
    }
}
