//! The bandwidth report of a run (`doorslam bw`): the paper's Table II from ledger files.
//!
//! Every message is counted once, by its sender: the `sent` rows of each loaded ledger,
//! plus the `received` rows from peers whose own ledger is not loaded (what reached this
//! robot is all that is known of them). Figures:
//!
//! - place descriptor: bytes of `descriptors` messages per descriptor (= per keyframe);
//! - verification packet: bytes of `verification_features` messages per putative match
//!   (pairs in `matches` messages);
//! - pose estimate: bytes of `pose_estimates` messages per estimate;
//! - loop closure: bytes of `loop_closures` messages per closure;
//! - back-end: every kind the rendezvous does not define (pose estimates included);
//!
//! each with payload bytes (exact encoded messages) and wire bytes (plus Zenoh's framing,
//! measured). Raw images for comparison: one 8-bit grayscale keyframe image
//! (`raw_image_bytes` of the ledger) instead of each descriptor and each verification
//! packet.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::ledger::{Counts, Direction, LedgerError, LedgerFile};

/// Kinds the rendezvous itself defines; every other kind is the back-end's.
const RENDEZVOUS_KINDS: [&str; 6] = [
    "hello",
    "descriptors",
    "matches",
    "verification_features",
    "loop_closures",
    "ack",
];

/// Failures of `doorslam bw`.
#[derive(Debug, thiserror::Error)]
pub enum BwError {
    #[error("{0}: no such file or folder")]
    Missing(PathBuf),
    #[error("{0}: no ledger.json in this folder or its subfolders")]
    NoLedger(PathBuf),
    #[error("cannot list {path}: {source}")]
    List {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Ledger(#[from] LedgerError),
}

/// The ledgers of a run: `PATH` itself if it is a file, else `PATH/ledger.json` and
/// `PATH/*/ledger.json` (one folder per robot).
pub fn load(path: &Path) -> Result<Vec<(PathBuf, LedgerFile)>, BwError> {
    if !path.exists() {
        return Err(BwError::Missing(path.into()));
    }
    if path.is_file() {
        return Ok(vec![(path.into(), LedgerFile::read(path)?)]);
    }
    let mut files = Vec::new();
    let top = path.join("ledger.json");
    if top.is_file() {
        files.push(top);
    }
    let entries = std::fs::read_dir(path).map_err(|source| BwError::List {
        path: path.into(),
        source,
    })?;
    let mut subs: Vec<PathBuf> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.path().join("ledger.json"))
        .filter(|p| p.is_file())
        .collect();
    subs.sort();
    files.extend(subs);
    if files.is_empty() {
        return Err(BwError::NoLedger(path.into()));
    }
    files
        .into_iter()
        .map(|p| LedgerFile::read(&p).map(|l| (p, l)).map_err(BwError::from))
        .collect()
}

/// One line of Table II: first sends (what one message costs); resends of unacknowledged
/// messages (what the link's losses cost on top) apart.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct KindFigure {
    /// Units the average is per (see `unit`), first sends.
    pub count: u64,
    /// Payload bytes (encoded messages, headers included), first sends.
    pub bytes: u64,
    pub avg_bytes: f64,
    pub messages: u64,
    /// Payload plus Zenoh framing, first sends.
    pub wire_bytes: u64,
    pub avg_wire_bytes: f64,
    pub resent_messages: u64,
    pub resent_bytes: u64,
    pub unit: &'static str,
    /// The paper's figure (DOOR-SLAM Table II), bytes per unit, where it gives one.
    pub paper_avg_bytes: Option<f64>,
}

impl KindFigure {
    fn new(unit: &'static str, paper: Option<f64>) -> Self {
        Self {
            unit,
            paper_avg_bytes: paper,
            ..Self::default()
        }
    }

    /// Adds a ledger row; `count` of units, of which `resent_count` in resends.
    fn add(&mut self, c: &Counts, count: u64, resent_count: u64, framing: u64) {
        let first = c.messages - c.resent_messages.min(c.messages);
        self.messages += first;
        self.bytes += c.payload_bytes - c.resent_payload_bytes.min(c.payload_bytes);
        self.wire_bytes +=
            c.payload_bytes - c.resent_payload_bytes.min(c.payload_bytes) + first * framing;
        self.count += count - resent_count.min(count);
        self.resent_messages += c.resent_messages;
        self.resent_bytes += c.resent_payload_bytes;
    }

    fn finish(&mut self) {
        if self.count > 0 {
            self.avg_bytes = self.bytes as f64 / self.count as f64;
            self.avg_wire_bytes = self.wire_bytes as f64 / self.count as f64;
        }
    }
}

/// Table II's lines, and the other kinds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PerKind {
    pub descriptor: KindFigure,
    pub verification_features: KindFigure,
    pub loop_closure: KindFigure,
    pub pose_estimate: KindFigure,
    pub backend: KindFigure,
    pub matches: KindFigure,
    pub hello: KindFigure,
    pub ack: KindFigure,
}

/// Traffic of one robot with one peer (or in one rendezvous).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct TrafficFigure {
    pub messages_sent: u64,
    pub bytes_sent: u64,
    pub wire_bytes_sent: u64,
    pub messages_received: u64,
    pub bytes_received: u64,
    pub wire_bytes_received: u64,
}

impl TrafficFigure {
    fn add(&mut self, direction: Direction, c: &Counts) {
        match direction {
            Direction::Sent => {
                self.messages_sent += c.messages;
                self.bytes_sent += c.payload_bytes;
                self.wire_bytes_sent += c.wire_bytes;
            }
            Direction::Received => {
                self.messages_received += c.messages;
                self.bytes_received += c.payload_bytes;
                self.wire_bytes_received += c.wire_bytes;
            }
        }
    }
}

/// One meeting as one robot saw it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RendezvousFigure {
    pub robot: String,
    pub peer: String,
    pub index: u64,
    /// Local time of the robot, ms since its link started (robots' clocks are not compared).
    pub local_start_ms: Option<u64>,
    pub local_end_ms: Option<u64>,
    #[serde(flatten)]
    pub traffic: TrafficFigure,
    /// Payload bytes sent, by kind.
    pub bytes_sent_by_kind: BTreeMap<String, u64>,
}

/// `doorslam bw`'s report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BwReport {
    pub ledgers: Vec<String>,
    pub robots: Vec<String>,
    pub per_kind: PerKind,
    /// Robot → peer → traffic, as each robot's ledger counts it.
    pub per_peer: BTreeMap<String, BTreeMap<String, TrafficFigure>>,
    pub per_robot: BTreeMap<String, TrafficFigure>,
    pub per_rendezvous: Vec<RendezvousFigure>,
    /// One raw keyframe image per descriptor and per verification packet.
    pub raw_image_equivalent_bytes: u64,
    pub raw_image_bytes: u64,
    /// Payload bytes of every message, counted once (by its sender), resends included.
    pub total_bytes: u64,
    /// Of which resends of unacknowledged messages.
    pub resent_bytes: u64,
    pub total_wire_bytes: u64,
    pub framing_overhead_bytes_per_message: u64,
    pub framing_method: String,
    /// Incoming messages dropped, by reason (all robots).
    pub dropped: BTreeMap<String, u64>,
}

/// Builds the report from a run's ledgers.
pub fn report(ledgers: &[(PathBuf, LedgerFile)]) -> BwReport {
    let robots: BTreeSet<String> = ledgers.iter().map(|(_, l)| l.robot.clone()).collect();
    let mut per_kind = PerKind {
        descriptor: KindFigure::new("per keyframe (descriptor)", Some(1000.0)),
        verification_features: KindFigure::new("per putative match", Some(59_510.0)),
        loop_closure: KindFigure::new("per loop closure", Some(340.0)),
        pose_estimate: KindFigure::new("per pose estimate", Some(340.0)),
        backend: KindFigure::new("per message", None),
        matches: KindFigure::new("per putative pair", None),
        hello: KindFigure::new("per message", None),
        ack: KindFigure::new("per message", None),
    };
    let mut per_peer: BTreeMap<String, BTreeMap<String, TrafficFigure>> = BTreeMap::new();
    let mut per_robot: BTreeMap<String, TrafficFigure> = BTreeMap::new();
    let mut rendezvous: BTreeMap<(String, String, u64), RendezvousFigure> = BTreeMap::new();
    let mut dropped: BTreeMap<String, u64> = BTreeMap::new();
    let mut raw_image_bytes = 0;
    let mut framing = (0, String::new());
    let mut total = Counts::default();
    for (_, l) in ledgers {
        raw_image_bytes = raw_image_bytes.max(l.raw_image_bytes);
        framing = (
            l.framing.overhead_bytes_per_message,
            l.framing.method.clone(),
        );
        for d in &l.dropped {
            *dropped.entry(d.reason.clone()).or_default() += d.messages;
        }
        for t in &l.traffic {
            per_peer
                .entry(l.robot.clone())
                .or_default()
                .entry(t.peer.clone())
                .or_default()
                .add(t.direction, &t.counts);
            per_robot
                .entry(l.robot.clone())
                .or_default()
                .add(t.direction, &t.counts);
            if let Some(index) = t.rendezvous {
                let r = rendezvous
                    .entry((l.robot.clone(), t.peer.clone(), index))
                    .or_insert_with(|| {
                        let entry = l
                            .rendezvous
                            .iter()
                            .find(|r| r.peer == t.peer && r.index == index);
                        RendezvousFigure {
                            robot: l.robot.clone(),
                            peer: t.peer.clone(),
                            index,
                            local_start_ms: entry.map(|e| e.local_start_ms),
                            local_end_ms: entry.and_then(|e| e.local_end_ms),
                            traffic: TrafficFigure::default(),
                            bytes_sent_by_kind: BTreeMap::new(),
                        }
                    });
                r.traffic.add(t.direction, &t.counts);
                if t.direction == Direction::Sent {
                    *r.bytes_sent_by_kind.entry(t.kind.clone()).or_default() +=
                        t.counts.payload_bytes;
                }
            }
            // Once per message: by its sender.
            let by_sender = t.direction == Direction::Sent || !robots.contains(&t.peer);
            if !by_sender {
                continue;
            }
            total.messages += t.counts.messages;
            total.payload_bytes += t.counts.payload_bytes;
            total.wire_bytes += t.counts.wire_bytes;
            total.resent_payload_bytes += t.counts.resent_payload_bytes;
            let c = &t.counts;
            let f = l.framing.overhead_bytes_per_message;
            let (items, resent_items) = (c.items, c.resent_items);
            let (msgs, resent_msgs) = (c.messages, c.resent_messages);
            match t.kind.as_str() {
                "descriptors" => per_kind.descriptor.add(c, items, resent_items, f),
                "verification_features" => per_kind.verification_features.add(c, 0, 0, f),
                "matches" => {
                    per_kind.matches.add(c, items, resent_items, f);
                    // The verification packets are per putative match.
                    per_kind.verification_features.count += items - resent_items.min(items);
                }
                "loop_closures" => per_kind.loop_closure.add(c, items, resent_items, f),
                "hello" => per_kind.hello.add(c, msgs, resent_msgs, f),
                "ack" => per_kind.ack.add(c, msgs, resent_msgs, f),
                other => {
                    if other == "pose_estimates" {
                        per_kind.pose_estimate.add(c, items, resent_items, f);
                    }
                    debug_assert!(!RENDEZVOUS_KINDS.contains(&other));
                    per_kind.backend.add(c, msgs, resent_msgs, f);
                }
            }
        }
    }
    for f in [
        &mut per_kind.descriptor,
        &mut per_kind.verification_features,
        &mut per_kind.loop_closure,
        &mut per_kind.pose_estimate,
        &mut per_kind.backend,
        &mut per_kind.matches,
        &mut per_kind.hello,
        &mut per_kind.ack,
    ] {
        f.finish();
    }
    let raw_image_equivalent_bytes =
        raw_image_bytes * (per_kind.descriptor.count + per_kind.verification_features.count);
    BwReport {
        ledgers: ledgers
            .iter()
            .map(|(p, _)| p.display().to_string())
            .collect(),
        robots: robots.into_iter().collect(),
        per_kind,
        per_peer,
        per_robot,
        per_rendezvous: rendezvous.into_values().collect(),
        raw_image_equivalent_bytes,
        raw_image_bytes,
        total_bytes: total.payload_bytes,
        resent_bytes: total.resent_payload_bytes,
        total_wire_bytes: total.wire_bytes,
        framing_overhead_bytes_per_message: framing.0,
        framing_method: framing.1,
        dropped,
    }
}

fn kb(bytes: f64) -> String {
    format!("{:.3} kB", bytes / 1000.0)
}

impl BwReport {
    /// Table II as text.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let k = &self.per_kind;
        let _ = writeln!(
            s,
            "{:<22} {:>8} {:>12} {:>12} {:>12} {:>10}  unit",
            "message", "count", "avg payload", "avg on wire", "paper", "resent"
        );
        for (name, f) in [
            ("place descriptor", &k.descriptor),
            ("verification packet", &k.verification_features),
            ("pose estimate", &k.pose_estimate),
            ("loop closure", &k.loop_closure),
            ("back-end (all kinds)", &k.backend),
            ("putative pairs", &k.matches),
            ("hello", &k.hello),
            ("ack", &k.ack),
        ] {
            let _ = writeln!(
                s,
                "{:<22} {:>8} {:>12} {:>12} {:>12} {:>10}  {}",
                name,
                f.count,
                kb(f.avg_bytes),
                kb(f.avg_wire_bytes),
                f.paper_avg_bytes.map(kb).unwrap_or_else(|| "-".into()),
                kb(f.resent_bytes as f64),
                f.unit
            );
        }
        let _ = writeln!(
            s,
            "\ntotal {} payload ({} of it resends), {} on the wire (Zenoh framing {} B/message); raw images instead: {}",
            kb(self.total_bytes as f64),
            kb(self.resent_bytes as f64),
            kb(self.total_wire_bytes as f64),
            self.framing_overhead_bytes_per_message,
            kb(self.raw_image_equivalent_bytes as f64)
        );
        let _ = writeln!(s, "\nper robot:");
        for (robot, t) in &self.per_robot {
            let _ = writeln!(
                s,
                "  {robot}: sent {} in {} messages, received {} in {}",
                kb(t.bytes_sent as f64),
                t.messages_sent,
                kb(t.bytes_received as f64),
                t.messages_received
            );
        }
        let _ = writeln!(s, "\nper rendezvous:");
        for r in &self.per_rendezvous {
            let _ = writeln!(
                s,
                "  {} with {} #{}: sent {}, received {}",
                r.robot,
                r.peer,
                r.index,
                kb(r.traffic.bytes_sent as f64),
                kb(r.traffic.bytes_received as f64)
            );
        }
        if !self.dropped.is_empty() {
            let _ = writeln!(s, "\ndropped incoming messages: {:?}", self.dropped);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ledger::Ledger;

    #[test]
    fn each_message_counts_once_by_its_sender_and_resends_apart() {
        let mut a = Ledger::new("a", "t", 1, 1000);
        let mut b = Ledger::new("b", "t", 1, 1000);
        a.rendezvous_started("b", 0, 0);
        // a sends two batches of 10 descriptors, one of them twice.
        a.record(
            Direction::Sent,
            "b",
            Some(0),
            "descriptors",
            1350,
            10,
            false,
        );
        a.record(
            Direction::Sent,
            "b",
            Some(0),
            "descriptors",
            1350,
            10,
            false,
        );
        a.record(Direction::Sent, "b", Some(0), "descriptors", 1350, 10, true);
        b.record(
            Direction::Received,
            "a",
            Some(0),
            "descriptors",
            1350,
            10,
            false,
        );
        b.record(
            Direction::Received,
            "a",
            Some(0),
            "descriptors",
            1350,
            10,
            false,
        );
        // b answers 4 pairs with 2 packets.
        b.record(Direction::Sent, "a", Some(0), "matches", 40, 4, false);
        b.record(
            Direction::Sent,
            "a",
            Some(0),
            "verification_features",
            4200,
            100,
            false,
        );
        b.record(
            Direction::Sent,
            "a",
            Some(0),
            "verification_features",
            4200,
            100,
            false,
        );
        b.record(
            Direction::Sent,
            "a",
            Some(0),
            "pose_estimates",
            100,
            3,
            false,
        );
        let both = [
            (PathBuf::from("a/ledger.json"), a.to_file()),
            (PathBuf::from("b/ledger.json"), b.to_file()),
        ];
        let r = report(&both);
        assert_eq!(r.per_kind.descriptor.count, 20);
        assert_eq!(r.per_kind.descriptor.bytes, 2700);
        assert_eq!(r.per_kind.descriptor.avg_bytes, 135.0);
        assert_eq!(r.per_kind.descriptor.resent_bytes, 1350);
        assert_eq!(r.per_kind.verification_features.count, 4);
        assert_eq!(r.per_kind.verification_features.avg_bytes, 2100.0);
        assert_eq!(r.per_kind.pose_estimate.count, 3);
        assert_eq!(r.per_kind.backend.messages, 1);
        assert_eq!(r.total_bytes, 3 * 1350 + 40 + 8400 + 100);
        assert_eq!(r.resent_bytes, 1350);
        assert_eq!(r.raw_image_equivalent_bytes, 1000 * (20 + 4));
        assert_eq!(r.per_peer["a"]["b"].bytes_sent, 3 * 1350);
        // Alone, b's ledger still counts what it received from a (a's own is missing).
        let r = report(&both[1..]);
        assert_eq!(r.per_kind.descriptor.count, 20);
        assert_eq!(r.total_bytes, 2 * 1350 + 40 + 8400 + 100);
    }
}
