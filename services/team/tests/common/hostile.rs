//! The hostile teammate's forgeries and what the hostile tests measure, shared by the
//! attack over the link emulation (`hostile.rs`) and over real Zenoh sessions with mutual
//! TLS (`hostile_zenoh.rs`), so both send the same kinds of forgery in the same mix.

use std::collections::BTreeMap;

use doorslam_ipc::wire::{Body, Header, Kind, Message, RobotId};
use doorslam_team::ledger::{Direction, LedgerFile};
use doorslam_team::Node;

/// xorshift64*: the attack is the same on every run.
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    pub fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

/// `m` encoded with its header (or kind) changed; `None` when the encoder refuses it.
fn reencoded(m: &Message, header: Header) -> Option<Vec<u8>> {
    Message::new(header, m.body.clone()).encode().ok()
}

/// A loop-closure message of z whose first pose value is replaced by `value`, in the
/// encoded bytes (the encoder would refuse a NaN itself, a hostile peer need not).
pub fn closures_with_pose_value(template: &Message, value: f32) -> Option<Vec<u8>> {
    let Body::LoopClosures(c) = &template.body else {
        return None;
    };
    let first = c.closures.first()?;
    let marker = first.relative.raw()[0];
    let mut bytes = template.encode().ok()?;
    let at = bytes
        .windows(4)
        .position(|w| w == marker.to_le_bytes() || w == marker.to_be_bytes())?;
    bytes[at..at + 4].copy_from_slice(&value.to_le_bytes());
    Some(bytes)
}

/// One forged message: what it is (for the counts), the kind its key names, its bytes.
pub struct Forgery {
    pub what: &'static str,
    pub kind: &'static str,
    pub bytes: Vec<u8>,
}

/// Forges messages from a hostile robot's real traffic: garbage, truncated and bit-flipped
/// messages, replays, stale epochs, sequence jumps, another sender in the header, another
/// kind in the key, loop closures with NaN or 3e38 pose values, descriptor floods.
pub struct Forger {
    pub rng: Rng,
    /// What the hostile robot sent honestly (the templates).
    honest: Vec<Message>,
    /// Well-formed descriptor and closure messages under the hostile robot's name.
    descriptors: Vec<Message>,
    closures: Vec<Message>,
    /// The robot the "wrong sender" forgeries claim to be.
    impersonated: RobotId,
    kinds: Vec<&'static str>,
    pub by_what: BTreeMap<&'static str, u64>,
    /// Bit flips that still decode and claim a newer epoch of the hostile robot.
    pub epoch_claims: u64,
}

impl Forger {
    pub fn new(
        seed: u64,
        honest: Vec<Message>,
        descriptors: Vec<Message>,
        closures: Vec<Message>,
        impersonated: RobotId,
    ) -> Self {
        assert!(!honest.is_empty(), "no honest traffic to forge from");
        assert!(!closures.is_empty(), "no closures to forge from");
        assert!(!descriptors.is_empty(), "no descriptors to forge from");
        Self {
            rng: Rng(seed),
            honest,
            descriptors,
            closures,
            impersonated,
            kinds: Kind::ALL.iter().map(|k| k.name()).collect(),
            by_what: BTreeMap::new(),
            epoch_claims: 0,
        }
    }

    /// The next forgery (the mix: one in eleven of each, closures twice).
    pub fn next(&mut self) -> Forgery {
        let rng = &mut self.rng;
        let kinds = &self.kinds;
        let m = &self.honest[rng.below(self.honest.len() as u64) as usize];
        let original = m.encode().unwrap();
        let mut h = m.header.clone();
        let (what, kind, bytes): (&'static str, &'static str, Vec<u8>) = match rng.below(11) {
            0 => {
                let n = rng.below(3000) as usize;
                let kind = kinds[rng.below(kinds.len() as u64) as usize];
                ("garbage", kind, (0..n).map(|_| rng.next() as u8).collect())
            }
            1 => {
                let cut = rng.below(original.len() as u64) as usize;
                ("truncated", m.kind().name(), original[..cut].to_vec())
            }
            2 => {
                let mut bytes = original.clone();
                for _ in 0..1 + rng.below(8) {
                    let i = rng.below(bytes.len() as u64) as usize;
                    bytes[i] = rng.next() as u8;
                }
                // A flip in the header's epoch that still decodes claims a new epoch of
                // z: z's session restarts (only z can claim z's epoch), and its
                // older-epoch messages that follow are refused as stale.
                if Message::decode(&bytes).is_ok_and(|f| f.header.epoch > m.header.epoch) {
                    self.epoch_claims += 1;
                }
                ("bit_flipped", m.kind().name(), bytes)
            }
            3 => ("replayed", m.kind().name(), original),
            4 => {
                h.epoch = 0;
                ("stale_epoch", m.kind().name(), reencoded(m, h).unwrap())
            }
            5 => {
                h.sequence = h.sequence.wrapping_add(1 + rng.below(u64::MAX / 2));
                ("sequence_jump", m.kind().name(), reencoded(m, h).unwrap())
            }
            6 => {
                h.sender = self.impersonated.clone();
                ("wrong_sender", m.kind().name(), reencoded(m, h).unwrap())
            }
            7 => {
                let other = kinds[rng.below(kinds.len() as u64) as usize];
                ("wrong_kind", other, original)
            }
            8 | 9 => {
                let c = &self.closures[rng.below(self.closures.len() as u64) as usize];
                let value = if rng.below(2) == 0 { f32::NAN } else { 3.0e38 };
                match closures_with_pose_value(c, value) {
                    Some(bytes) => ("absurd_closure", "loop_closures", bytes),
                    None => ("replayed", c.kind().name(), c.encode().unwrap()),
                }
            }
            _ => {
                // A descriptor flood: well-formed descriptors under fresh sequences.
                let d = &self.descriptors[rng.below(self.descriptors.len() as u64) as usize];
                let mut h = d.header.clone();
                h.sequence = h.sequence.wrapping_add(1 + rng.below(1 << 20));
                ("descriptor_flood", "descriptors", reencoded(d, h).unwrap())
            }
        };
        *self.by_what.entry(what).or_default() += 1;
        Forgery { what, kind, bytes }
    }
}

/// Messages from `peer` the ledger saw: received (any kind) and dropped (any reason).
pub fn accounted(ledger: &LedgerFile, peer: &str) -> (u64, u64) {
    let received = ledger
        .traffic
        .iter()
        .filter(|t| t.peer == peer && t.direction == Direction::Received)
        .map(|t| t.counts.messages)
        .sum();
    let dropped = ledger
        .dropped
        .iter()
        .filter(|d| d.peer == peer)
        .map(|d| d.messages)
        .sum();
    (received, dropped)
}

/// What robot `me`'s ledger says of the attacker z after the attack, asserted: every message
/// z sent (`honest` + `injected`) is in it, delivered or dropped with a reason (a message
/// received and then found a duplicate is in both), and the hostile bulk is refused, not
/// taken in: at most one in eleven forgeries (the floods' new sequences and the replays'
/// first copies) can be new to the delivery layer. Prints z's refusals by reason.
pub fn assert_attacker_accounted(me: &str, ledger: &LedgerFile, honest: u64, injected: u64) {
    let (received, dropped) = accounted(ledger, "z");
    println!(
        "{me}: z sent {honest} honest + {injected} hostile; ledger: {received} received, \
         {dropped} dropped {:?}",
        ledger
            .dropped
            .iter()
            .filter(|d| d.peer == "z")
            .map(|d| (d.reason.as_str(), d.messages))
            .collect::<Vec<_>>()
    );
    assert!(
        received + dropped >= honest + injected,
        "{me}: {} of z's messages are not in the ledger",
        honest + injected - received - dropped
    );
    assert!(
        dropped >= injected / 2,
        "{me}: only {dropped} of {injected} hostile messages refused"
    );
}

/// `x` and `y` have met: nothing of either is unacknowledged by the other, and one of
/// them has `n` of the other's descriptors (the protocol gives one of the pair the
/// descriptor sender's role, α).
pub fn met(x: &Node, y: &Node, n: u64) -> bool {
    let settled = |p: &Node, q: &Node| {
        p.session(&q.identity().id)
            .is_some_and(|s| Kind::ALL.iter().all(|&k| s.unacknowledged(k).is_empty()))
    };
    let has = |p: &Node, q: &Node| {
        p.session(&q.identity().id)
            .is_some_and(|s| s.delivered_descriptors().len() as u64 == n)
    };
    settled(x, y) && settled(y, x) && (has(x, y) || has(y, x))
}

/// Resident memory of this process, kB.
pub fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmRSS:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}
