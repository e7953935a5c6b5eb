//! The bandwidth ledger: every message that crosses the team link, counted once, by peer,
//! rendezvous, direction and kind; payload bytes (the encoded wire message, exactly) and an
//! on-the-wire estimate that adds Zenoh's framing per message ([`ZENOH_FRAMING_BYTES`],
//! measured); and every message dropped on the way in, by reason.
//!
//! A [`LedgerHandle`] is shared between the link and whoever reads it at run time
//! ([`LedgerHandle::snapshot`]); [`LedgerHandle::write_json`] writes `ledger.json` to the
//! run folder (atomically: a reader never sees half a file).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use doorslam_ipc::wire::Body;
use serde::{Deserialize, Serialize};

/// Zenoh's bytes per message on a TCP link beyond the wire payload, for a `put` through a
/// declared publisher with the message alone in its batch (the worst case: messages sent
/// in a burst share a batch header). Measured by `tests/framing.rs` (a counting TCP relay
/// between two Zenoh 1.10 peers; the test fails if this constant drifts from the
/// measurement by more than 2 bytes). TCP/IP headers (40-52 bytes per segment) come on top
/// and depend on segmentation, so they are not included.
pub const ZENOH_FRAMING_BYTES: u64 = 12;

/// How [`ZENOH_FRAMING_BYTES`] was obtained, recorded in every ledger file.
pub const FRAMING_METHOD: &str = "zenoh 1.10 peer-to-peer over TCP, declared publisher, one message per batch: bytes counted by a TCP relay between two sessions minus the payload (services/team/tests/framing.rs); TCP/IP headers excluded";

/// What TLS adds per message on top of [`ZENOH_FRAMING_BYTES`] when the team link runs
/// over TLS (`[team.tls]`): one TLS 1.3 record per Zenoh batch (5-byte record header,
/// 1-byte inner content type, 16-byte AEAD tag), independent of the payload size below a
/// record (16 KiB). Measured by `tests/framing.rs` the same way as the TCP figure: 34 B
/// per message over TLS (33 B in one run) against 12 B over TCP; the test fails if the
/// measurement drifts by more than 2 bytes.
pub const TLS_RECORD_BYTES: u64 = 22;

/// How the TLS framing was obtained, recorded in ledger files of TLS links.
pub const TLS_FRAMING_METHOD: &str = "zenoh 1.10 peer-to-peer over TLS 1.3 (mutual authentication), declared publisher, one message per batch: bytes counted by a TCP relay between two sessions minus the payload (services/team/tests/framing.rs); TCP/IP headers excluded";

/// Format name and version of `ledger.json`.
pub const LEDGER_FORMAT: &str = "doorslam-ledger";
pub const LEDGER_VERSION: u32 = 1;

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    Sent,
    Received,
}

/// Counts of one (peer, rendezvous, direction, kind).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counts {
    pub messages: u64,
    /// Encoded wire messages (header included), exactly.
    pub payload_bytes: u64,
    /// `payload_bytes` + Zenoh framing per message.
    pub wire_bytes: u64,
    /// What the messages carry: descriptors, pairs, features, closures, pose estimates
    /// (1 per message for the other kinds).
    pub items: u64,
    /// Of the above, resends of unacknowledged messages (sent direction only).
    #[serde(default)]
    pub resent_messages: u64,
    #[serde(default)]
    pub resent_payload_bytes: u64,
    #[serde(default)]
    pub resent_items: u64,
}

/// One row of `ledger.json`'s `traffic`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TrafficEntry {
    pub peer: String,
    /// The meeting with that peer, from 0 in this robot's count (None: outside a meeting).
    pub rendezvous: Option<u64>,
    pub direction: Direction,
    pub kind: String,
    #[serde(flatten)]
    pub counts: Counts,
}

/// One row of `ledger.json`'s `dropped`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DropEntry {
    /// The claimed sender (from the key expression; `?` if even that was unreadable).
    pub peer: String,
    pub reason: String,
    pub messages: u64,
    pub bytes: u64,
}

/// One meeting with a peer, in this robot's local time since the link started.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RendezvousEntry {
    pub peer: String,
    pub index: u64,
    pub local_start_ms: u64,
    pub local_end_ms: Option<u64>,
}

/// The framing model used for `wire_bytes`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Framing {
    pub overhead_bytes_per_message: u64,
    pub method: String,
}

/// `ledger.json`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LedgerFile {
    pub format: String,
    pub version: u32,
    pub robot: String,
    pub team: String,
    pub epoch: u64,
    pub framing: Framing,
    /// Bytes of one raw keyframe image (width × height, 8-bit grayscale, left eye): what
    /// `doorslam bw` compares against.
    pub raw_image_bytes: u64,
    pub traffic: Vec<TrafficEntry>,
    pub dropped: Vec<DropEntry>,
    pub rendezvous: Vec<RendezvousEntry>,
    /// The link's own count of what it handed to Zenoh, over every start of the link in
    /// this run folder (absent in ledgers of older builds).
    #[serde(default)]
    pub link: LinkCount,
}

/// What the team link itself counted, apart from `traffic` (which the node records per
/// message): the two must agree. Kept in the ledger's file, not beside it, so that a
/// restarted link continues both counts from one snapshot: a link killed between writing
/// two files would leave them a write interval apart.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LinkCount {
    /// Times the link was started in this run folder (1 for a link that never restarted).
    pub starts: u64,
    pub published_bytes: u64,
    pub published_messages: u64,
}

type TrafficKey = (String, Option<u64>, Direction, String);

/// The ledger's state.
#[derive(Debug, Clone)]
pub struct Ledger {
    robot: String,
    team: String,
    epoch: u64,
    raw_image_bytes: u64,
    framing_bytes: u64,
    framing_method: &'static str,
    traffic: BTreeMap<TrafficKey, Counts>,
    dropped: BTreeMap<(String, String), (u64, u64)>,
    rendezvous: Vec<RendezvousEntry>,
    /// The link's count up to the previous start, and this start's (`link_published`).
    link_before: LinkCount,
    link_now: (u64, u64),
}

/// What a message carries, for `items`.
pub fn items(body: &Body) -> u64 {
    let n = if let Body::Descriptors(d) = body {
        d.descriptors.len()
    } else if let Body::Matches(m) = body {
        m.matches.len()
    } else if let Body::VerificationFeatures(v) = body {
        v.features.len()
    } else if let Body::LoopClosures(l) = body {
        l.closures.len()
    } else if let Body::PoseEstimates(p) = body {
        p.estimates.len()
    } else {
        1
    };
    n as u64
}

impl Ledger {
    pub fn new(robot: &str, team: &str, epoch: u64, raw_image_bytes: u64) -> Self {
        Self {
            robot: robot.into(),
            team: team.into(),
            epoch,
            raw_image_bytes,
            framing_bytes: ZENOH_FRAMING_BYTES,
            framing_method: FRAMING_METHOD,
            traffic: BTreeMap::new(),
            dropped: BTreeMap::new(),
            rendezvous: Vec::new(),
            link_before: LinkCount::default(),
            link_now: (0, 0),
        }
    }

    /// A ledger that continues `file` (this robot's, written before a restart) in a new
    /// epoch: every byte counted before the restart stays counted. Rendezvous indices
    /// restart at 0 with the new link's sessions, so a meeting after the restart adds to
    /// the first meeting's rows (totals per kind and peer stay exact).
    pub fn resume(file: LedgerFile, epoch: u64) -> Self {
        let mut ledger = Self::new(&file.robot, &file.team, epoch, file.raw_image_bytes);
        if file.framing.method == TLS_FRAMING_METHOD {
            ledger = ledger.over_tls();
        }
        ledger.framing_bytes = file.framing.overhead_bytes_per_message;
        for t in file.traffic {
            ledger
                .traffic
                .insert((t.peer, t.rendezvous, t.direction, t.kind), t.counts);
        }
        for d in file.dropped {
            ledger
                .dropped
                .insert((d.peer, d.reason), (d.messages, d.bytes));
        }
        ledger.rendezvous = file.rendezvous;
        ledger.link_before = file.link;
        // A meeting open when the robot died ended then.
        for r in &mut ledger.rendezvous {
            if r.local_end_ms.is_none() {
                r.local_end_ms = Some(r.local_start_ms);
            }
        }
        ledger
    }

    /// The on-the-wire estimate of a TLS link: Zenoh's framing plus one TLS record per
    /// message ([`TLS_RECORD_BYTES`]).
    pub fn over_tls(mut self) -> Self {
        self.framing_bytes = ZENOH_FRAMING_BYTES + TLS_RECORD_BYTES;
        self.framing_method = TLS_FRAMING_METHOD;
        self
    }

    /// Counts one message sent or received (`resend`: a resend of an unacknowledged one).
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &mut self,
        direction: Direction,
        peer: &str,
        rendezvous: Option<u64>,
        kind: &str,
        payload_bytes: usize,
        items: u64,
        resend: bool,
    ) {
        let c = self
            .traffic
            .entry((peer.into(), rendezvous, direction, kind.into()))
            .or_default();
        c.messages += 1;
        c.payload_bytes += payload_bytes as u64;
        c.wire_bytes += payload_bytes as u64 + self.framing_bytes;
        c.items += items;
        if resend {
            c.resent_messages += 1;
            c.resent_payload_bytes += payload_bytes as u64;
            c.resent_items += items;
        }
    }

    /// Counts one incoming message that was dropped.
    pub fn dropped(&mut self, peer: &str, reason: &str, bytes: usize) {
        let d = self
            .dropped
            .entry((peer.into(), reason.into()))
            .or_default();
        d.0 += 1;
        d.1 += bytes as u64;
    }

    pub fn rendezvous_started(&mut self, peer: &str, index: u64, local_ms: u64) {
        self.rendezvous.push(RendezvousEntry {
            peer: peer.into(),
            index,
            local_start_ms: local_ms,
            local_end_ms: None,
        });
    }

    pub fn rendezvous_ended(&mut self, peer: &str, local_ms: u64) {
        if let Some(r) = self
            .rendezvous
            .iter_mut()
            .rev()
            .find(|r| r.peer == peer && r.local_end_ms.is_none())
        {
            r.local_end_ms = Some(local_ms);
        }
    }

    /// Sum over every entry of one direction.
    pub fn total(&self, direction: Direction) -> Counts {
        let mut t = Counts::default();
        for ((_, _, d, _), c) in &self.traffic {
            if *d == direction {
                t.messages += c.messages;
                t.payload_bytes += c.payload_bytes;
                t.wire_bytes += c.wire_bytes;
                t.items += c.items;
                t.resent_messages += c.resent_messages;
                t.resent_payload_bytes += c.resent_payload_bytes;
                t.resent_items += c.resent_items;
            }
        }
        t
    }

    /// Messages dropped for `reason` (all peers).
    pub fn dropped_count(&self, reason: &str) -> u64 {
        self.dropped
            .iter()
            .filter(|((_, r), _)| r == reason)
            .map(|(_, (n, _))| n)
            .sum()
    }

    /// What this start of the link has handed to Zenoh so far (its own count).
    pub fn link_published(&mut self, bytes: u64, messages: u64) {
        self.link_now = (bytes, messages);
    }

    /// The link's count over every start: the previous starts' and this one's.
    pub fn link_count(&self) -> LinkCount {
        LinkCount {
            starts: self.link_before.starts + 1,
            published_bytes: self.link_before.published_bytes + self.link_now.0,
            published_messages: self.link_before.published_messages + self.link_now.1,
        }
    }

    pub fn to_file(&self) -> LedgerFile {
        LedgerFile {
            format: LEDGER_FORMAT.into(),
            version: LEDGER_VERSION,
            robot: self.robot.clone(),
            team: self.team.clone(),
            epoch: self.epoch,
            framing: Framing {
                overhead_bytes_per_message: self.framing_bytes,
                method: self.framing_method.into(),
            },
            raw_image_bytes: self.raw_image_bytes,
            traffic: self
                .traffic
                .iter()
                .map(
                    |((peer, rendezvous, direction, kind), counts)| TrafficEntry {
                        peer: peer.clone(),
                        rendezvous: *rendezvous,
                        direction: *direction,
                        kind: kind.clone(),
                        counts: *counts,
                    },
                )
                .collect(),
            dropped: self
                .dropped
                .iter()
                .map(|((peer, reason), (messages, bytes))| DropEntry {
                    peer: peer.clone(),
                    reason: reason.clone(),
                    messages: *messages,
                    bytes: *bytes,
                })
                .collect(),
            rendezvous: self.rendezvous.clone(),
            link: self.link_count(),
        }
    }
}

/// Failures writing or reading a ledger file.
#[derive(Debug, thiserror::Error)]
pub enum LedgerError {
    #[error("cannot write ledger {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot read ledger {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("ledger {path} is not a doorslam ledger: {reason}")]
    Parse { path: PathBuf, reason: String },
}

impl LedgerFile {
    /// Reads and checks one `ledger.json`; errors name the file.
    pub fn read(path: &Path) -> Result<LedgerFile, LedgerError> {
        let text = std::fs::read_to_string(path).map_err(|source| LedgerError::Read {
            path: path.into(),
            source,
        })?;
        let file: LedgerFile = serde_json::from_str(&text).map_err(|e| LedgerError::Parse {
            path: path.into(),
            reason: e.to_string(),
        })?;
        if file.format != LEDGER_FORMAT || file.version != LEDGER_VERSION {
            return Err(LedgerError::Parse {
                path: path.into(),
                reason: format!(
                    "format {:?} version {} (expected {LEDGER_FORMAT:?} version {LEDGER_VERSION})",
                    file.format, file.version
                ),
            });
        }
        Ok(file)
    }
}

/// The ledger, shared between the link and its readers.
#[derive(Debug, Clone)]
pub struct LedgerHandle(Arc<Mutex<Ledger>>);

impl LedgerHandle {
    pub fn new(ledger: Ledger) -> Self {
        Self(Arc::new(Mutex::new(ledger)))
    }

    /// The ledger itself, locked (a panic elsewhere while holding it leaves counts that
    /// are still the best there are, so a poisoned lock is used as is).
    pub fn lock(&self) -> MutexGuard<'_, Ledger> {
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub fn snapshot(&self) -> LedgerFile {
        self.lock().to_file()
    }

    /// Writes `ledger.json` atomically (temporary file, then rename).
    pub fn write_json(&self, path: &Path) -> Result<(), LedgerError> {
        let file = self.snapshot();
        let text = serde_json::to_string_pretty(&file).map_err(|e| LedgerError::Write {
            path: path.into(),
            source: std::io::Error::other(e),
        })?;
        let tmp = path.with_extension("json.tmp");
        let err = |source| LedgerError::Write {
            path: path.into(),
            source,
        };
        std::fs::write(&tmp, text).map_err(err)?;
        std::fs::rename(&tmp, path).map_err(err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A restarted link continues the link's own count with the rows, from one file: the
    /// two still agree after the restart, and the starts are counted.
    #[test]
    fn a_resumed_ledger_continues_the_links_count() {
        let mut first = Ledger::new("a", "t", 1, 100);
        first.record(Direction::Sent, "b", Some(0), "descriptors", 300, 3, false);
        first.link_published(300, 1);
        let file: LedgerFile =
            serde_json::from_str(&serde_json::to_string(&first.to_file()).unwrap()).unwrap();
        assert_eq!(
            file.link,
            LinkCount {
                starts: 1,
                published_bytes: 300,
                published_messages: 1
            }
        );
        let mut again = Ledger::resume(file, 2);
        again.record(Direction::Sent, "b", Some(0), "descriptors", 50, 1, true);
        again.link_published(50, 1);
        let file = again.to_file();
        let rows: u64 = file
            .traffic
            .iter()
            .filter(|t| t.direction == Direction::Sent)
            .map(|t| t.counts.payload_bytes)
            .sum();
        assert_eq!(file.link.published_bytes, rows);
        assert_eq!(file.link.published_bytes, 350);
        assert_eq!(file.link.published_messages, 2);
        assert_eq!(file.link.starts, 2);
    }

    /// A ledger written before the link's count was kept reads as no earlier start.
    #[test]
    fn an_older_ledger_without_the_links_count_still_reads() {
        let mut text: serde_json::Value =
            serde_json::to_value(Ledger::new("a", "t", 1, 100).to_file()).unwrap();
        text.as_object_mut().unwrap().remove("link");
        let file: LedgerFile = serde_json::from_value(text).unwrap();
        assert_eq!(file.link, LinkCount::default());
        assert_eq!(Ledger::resume(file, 2).link_count().starts, 1);
    }
}
