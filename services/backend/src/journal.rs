//! The back-end's persisted log: every accepted keyframe and odometry edge, appended and
//! fsync'd before it is applied, so a restarted back-end rebuilds exactly the graph it had.
//! Recovery never destroys data: it cuts off only what a crash can leave behind, and moves
//! anything else it cannot read into a side file before it shortens the journal.
//!
//! # Format (version [`FORMAT_VERSION`])
//!
//! Header, written once when the journal is created:
//! `[magic "DSJOURNL"][version: u32 LE][robot id length n: u8][robot id: n bytes, UTF-8]`
//! `[crc32 of the preceding header bytes: u32 LE]`.
//!
//! Then records: `[len: u32 LE][crc32 of payload: u32 LE][payload]`. The payload starts
//! with a kind byte (1 keyframe, 2 odometry, 3 inter-robot loop closure) followed by little-endian fields; `len` is at
//! most [`MAX_RECORD_LEN`], so a damaged length never makes the reader allocate or skip
//! gigabytes.
//!
//! # Recovery ([`Journal::open`])
//!
//! - Missing or empty file: a fresh journal (header written and fsync'd, directory too).
//! - A strict prefix of the header this back-end would write (crash while creating the
//!   journal, so no record was ever appended): rewritten, reported in
//!   [`Recovery::torn_header_bytes`].
//! - Not a journal (bad magic), a headerless journal from before version 1, a newer format
//!   version, a damaged header, or the journal of another robot: a typed error naming the
//!   file, which is left untouched.
//! - Torn last record: each append is one write followed by fsync, so a crash tears at
//!   most the record being written, leaving a prefix of it (its length field intact) or,
//!   on some file systems, zeros. A last record that runs past the end of the file, or
//!   fails its CRC and ends exactly at the end of the file, and whose length is the one
//!   its kind byte calls for, is such a tear: cut off and reported in
//!   [`Recovery::truncated_bytes`]. So is a tail of only zero bytes.
//! - Anything else (a CRC error with bytes after the record, an unknown kind from a newer
//!   version, an implausible length, a length that does not match the kind) is
//!   corruption: the bytes from the bad record to the end of the file are copied to
//!   `<journal>.corrupt-<unix seconds>[-<n>]` (a new file, never an existing one), which
//!   is fsync'd with its directory before the journal is cut back to its last good record
//!   so appending can continue. The records before it are recovered; the side file and the
//!   reason are reported in [`Recovery::corruption`].

use std::fs::{File, OpenOptions};
use std::io::{ErrorKind, Read, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

/// First bytes of every journal.
pub const MAGIC: [u8; 8] = *b"DSJOURNL";
/// The format version this build writes and the newest it reads.
pub const FORMAT_VERSION: u32 = 1;
/// Longest robot id a header holds (the config allows 32 bytes).
pub const MAX_ROBOT_LEN: usize = 64;
/// Largest record payload accepted; far above any record written (249 bytes), so a record
/// from a newer version still fits, while a damaged length is recognized as such.
pub const MAX_RECORD_LEN: u32 = 64 * 1024;

/// `[len][crc]` in front of every payload.
const RECORD_HEADER: usize = 8;
/// Magic and version: the part of the header every version shares.
const FIXED_HEADER: usize = 12;

/// Failures of the journal; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("journal {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} is not a doorslam journal (bad magic bytes); left untouched")]
    NotAJournal { path: PathBuf },
    #[error(
        "journal {path} has no header (written before format version {FORMAT_VERSION}); \
         left untouched: move it aside to start a new journal"
    )]
    Unversioned { path: PathBuf },
    #[error(
        "journal {path} has format version {found}, this build reads up to version \
         {supported}; left untouched"
    )]
    NewerVersion {
        path: PathBuf,
        found: u32,
        supported: u32,
    },
    #[error("journal {path}: damaged header ({reason}); left untouched")]
    BadHeader { path: PathBuf, reason: String },
    #[error("journal {path} belongs to robot {found:?}, not to {expected:?}; left untouched")]
    OtherRobot {
        path: PathBuf,
        found: String,
        expected: String,
    },
    #[error("journal {path}: robot id {robot:?} must be 1-{MAX_ROBOT_LEN} bytes long")]
    RobotId { path: PathBuf, robot: String },
    #[error(
        "journal {path}: cannot preserve its {bytes} corrupt bytes in {side}: {source}; \
         journal left untouched"
    )]
    Preserve {
        path: PathBuf,
        side: PathBuf,
        bytes: u64,
        #[source]
        source: std::io::Error,
    },
}

/// Why a record in the middle of a journal could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BadRecord {
    #[error("record length {len} outside 1..={MAX_RECORD_LEN}")]
    Length { len: u32 },
    #[error("checksum mismatch (stored {stored:#010x}, computed {computed:#010x})")]
    Checksum { stored: u32, computed: u32 },
    #[error("unknown record kind {kind} (written by a newer version?)")]
    UnknownKind { kind: u8 },
    #[error("record of kind {kind} with {len} payload bytes, expected {expected}")]
    Size {
        kind: u8,
        len: usize,
        expected: usize,
    },
    #[error("record of {len} bytes runs past the end of the file, and no record this version writes has that length")]
    PastEnd { len: u32 },
}

/// One journaled fact.
#[derive(Debug, Clone, PartialEq)]
pub enum Entry {
    /// Keyframe `id` with its pose estimate (x y z qx qy qz qw).
    Keyframe {
        id: u64,
        stamp_ns: u64,
        pose: [f64; 7],
    },
    /// Odometry between keyframes, information rotation-first (upper triangle).
    Odometry {
        from: u64,
        to: u64,
        relative: [f64; 7],
        information: [f64; 21],
    },
    /// A verified loop closure between this robot's keyframe and another robot's, handed
    /// over by the team link (multi-robot keys; `relative ≈ X_a⁻¹ X_b`, information
    /// rotation-first). Kind 3: a journal holding one is not readable by builds before it
    /// (they refuse the unknown kind and keep it in a side file).
    Closure {
        key_a: u64,
        key_b: u64,
        relative: [f64; 7],
        information: [f64; 21],
        inliers: u64,
    },
}

const KEYFRAME: u8 = 1;
const ODOMETRY: u8 = 2;
const CLOSURE: u8 = 3;
const KEYFRAME_LEN: usize = 1 + 16 + 56;
const ODOMETRY_LEN: usize = 1 + 16 + 56 + 168;
const CLOSURE_LEN: usize = 1 + 24 + 56 + 168;

/// The payload length of a record kind this version writes.
fn payload_len(kind: u8) -> Option<usize> {
    match kind {
        KEYFRAME => Some(KEYFRAME_LEN),
        ODOMETRY => Some(ODOMETRY_LEN),
        CLOSURE => Some(CLOSURE_LEN),
        _ => None,
    }
}

/// Checks a payload's kind byte against its length.
fn check_kind(kind: u8, len: usize) -> Result<(), BadRecord> {
    match payload_len(kind) {
        None => Err(BadRecord::UnknownKind { kind }),
        Some(expected) if expected != len => Err(BadRecord::Size {
            kind,
            len,
            expected,
        }),
        Some(_) => Ok(()),
    }
}

fn floats<const N: usize>(w: &[u64]) -> [f64; N] {
    std::array::from_fn(|k| f64::from_bits(w[k]))
}

impl Entry {
    fn encode(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(CLOSURE_LEN);
        let f64s = |b: &mut Vec<u8>, v: &[f64]| {
            v.iter().for_each(|x| b.extend_from_slice(&x.to_le_bytes()))
        };
        match self {
            Entry::Keyframe { id, stamp_ns, pose } => {
                b.push(KEYFRAME);
                b.extend_from_slice(&id.to_le_bytes());
                b.extend_from_slice(&stamp_ns.to_le_bytes());
                f64s(&mut b, pose);
            }
            Entry::Odometry {
                from,
                to,
                relative,
                information,
            } => {
                b.push(ODOMETRY);
                b.extend_from_slice(&from.to_le_bytes());
                b.extend_from_slice(&to.to_le_bytes());
                f64s(&mut b, relative);
                f64s(&mut b, information);
            }
            Entry::Closure {
                key_a,
                key_b,
                relative,
                information,
                inliers,
            } => {
                b.push(CLOSURE);
                b.extend_from_slice(&key_a.to_le_bytes());
                b.extend_from_slice(&key_b.to_le_bytes());
                b.extend_from_slice(&inliers.to_le_bytes());
                f64s(&mut b, relative);
                f64s(&mut b, information);
            }
        }
        b
    }

    fn decode(b: &[u8]) -> Result<Entry, BadRecord> {
        let Some((&kind, fields)) = b.split_first() else {
            return Err(BadRecord::Length { len: 0 });
        };
        check_kind(kind, b.len())?;
        // The length is checked above, so every index below is in bounds.
        let w: Vec<u64> = fields
            .chunks_exact(8)
            .map(|c| c.iter().rev().fold(0, |a, &x| (a << 8) | u64::from(x)))
            .collect();
        match kind {
            KEYFRAME => Ok(Entry::Keyframe {
                id: w[0],
                stamp_ns: w[1],
                pose: floats(&w[2..9]),
            }),
            ODOMETRY => Ok(Entry::Odometry {
                from: w[0],
                to: w[1],
                relative: floats(&w[2..9]),
                information: floats(&w[9..30]),
            }),
            CLOSURE => Ok(Entry::Closure {
                key_a: w[0],
                key_b: w[1],
                inliers: w[2],
                relative: floats(&w[3..10]),
                information: floats(&w[10..31]),
            }),
            kind => Err(BadRecord::UnknownKind { kind }),
        }
    }
}

/// A bad record that is not a torn tail, and where its bytes and all after them went.
#[derive(Debug, Clone, PartialEq)]
pub struct Corruption {
    /// Offset of the bad record in the file; the journal now ends there.
    pub offset: u64,
    /// Bytes from `offset` to the former end of the file.
    pub bytes: u64,
    pub reason: BadRecord,
    /// The side file holding exactly those bytes (`open`); `None` from `read`, which
    /// changes nothing.
    pub preserved: Option<PathBuf>,
}

/// What recovery found.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Recovery {
    /// The robot named in the header; `None` from `read` when there is no complete header.
    pub robot: Option<String>,
    pub entries: Vec<Entry>,
    /// There was no complete header: `open` wrote one (the file was missing or empty, or
    /// its header torn while it was created); `read` found none yet.
    pub fresh: bool,
    /// Bytes of a header torn at creation, which `open` replaced (0 for a missing or empty
    /// file).
    pub torn_header_bytes: u64,
    /// Bytes of a torn last record that `open` cut off (`read` does not return them).
    pub truncated_bytes: u64,
    /// A bad record that is not a torn tail (usually in the middle; also a complete record
    /// of an unknown kind at the end).
    pub corruption: Option<Corruption>,
}

/// An append-only, fsync'd journal file.
pub struct Journal {
    path: PathBuf,
    file: File,
}

/// The header of a journal of `robot` (1..=MAX_ROBOT_LEN bytes, checked by the caller).
fn header_bytes(robot: &str) -> Vec<u8> {
    let mut h = Vec::with_capacity(FIXED_HEADER + 1 + robot.len() + 4);
    h.extend_from_slice(&MAGIC);
    h.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    h.push(robot.len() as u8);
    h.extend_from_slice(robot.as_bytes());
    let crc = crc32fast::hash(&h);
    h.extend_from_slice(&crc.to_le_bytes());
    h
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    let s = b.get(at..at + 4)?;
    Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

enum Header {
    /// No complete header: the file is empty or holds a prefix of a header.
    Missing,
    Valid {
        robot: String,
        len: usize,
    },
}

/// Reads the header of `bytes`. `ours` is the header `open` would write: a torn header is
/// only taken as such when it is a prefix of it, so another robot's journal or one of
/// another version is never claimed.
fn check_header(path: &Path, bytes: &[u8], ours: Option<&[u8]>) -> Result<Header, JournalError> {
    let path = || path.to_path_buf();
    let bad = |reason: &str| JournalError::BadHeader {
        path: path(),
        reason: reason.into(),
    };
    if bytes.is_empty() {
        return Ok(Header::Missing);
    }
    let k = bytes.len().min(MAGIC.len());
    if bytes[..k] != MAGIC[..k] {
        return Err(if first_record_valid(bytes) {
            JournalError::Unversioned { path: path() }
        } else {
            JournalError::NotAJournal { path: path() }
        });
    }
    let Some(version) = u32_at(bytes, MAGIC.len()) else {
        let mut fixed = MAGIC.to_vec();
        fixed.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        return if fixed.starts_with(bytes) {
            Ok(Header::Missing)
        } else {
            Err(bad("torn header of another format version"))
        };
    };
    if version > FORMAT_VERSION {
        return Err(JournalError::NewerVersion {
            path: path(),
            found: version,
            supported: FORMAT_VERSION,
        });
    }
    if version == 0 {
        return Err(bad("format version 0"));
    }
    let Some(&n) = bytes.get(FIXED_HEADER) else {
        return Ok(Header::Missing);
    };
    let n = usize::from(n);
    if n == 0 || n > MAX_ROBOT_LEN {
        return Err(bad(&format!(
            "robot id length {n} outside 1..={MAX_ROBOT_LEN}"
        )));
    }
    let body = FIXED_HEADER + 1 + n;
    let Some(stored) = u32_at(bytes, body) else {
        return match ours {
            Some(h) if !h.starts_with(bytes) => Err(bad("torn header of another robot")),
            _ => Ok(Header::Missing),
        };
    };
    if crc32fast::hash(&bytes[..body]) != stored {
        return Err(bad("header checksum mismatch"));
    }
    let robot = std::str::from_utf8(&bytes[FIXED_HEADER + 1..body])
        .map_err(|_| bad("robot id is not UTF-8"))?;
    Ok(Header::Valid {
        robot: robot.to_owned(),
        len: body + 4,
    })
}

/// Whether `bytes` starts with a record of the headerless format (before version 1).
fn first_record_valid(bytes: &[u8]) -> bool {
    matches!(record(bytes), Ok(Some(_)))
}

/// How the records of a journal end.
enum End {
    Clean,
    Torn,
    Corrupt(BadRecord),
}

/// The record at the start of `rest` and its size in bytes; `Ok(None)` at end of file.
fn record(rest: &[u8]) -> Result<Option<(Entry, usize)>, End> {
    if rest.is_empty() {
        return Ok(None);
    }
    let result = record_inner(rest);
    // Zeros to the end of the file: space the file system allocated but the crash kept
    // from being written; there is nothing in it to keep.
    if result.is_err() && rest.iter().all(|&b| b == 0) {
        return Err(End::Torn);
    }
    result.map(Some)
}

fn record_inner(rest: &[u8]) -> Result<(Entry, usize), End> {
    let (Some(len), Some(stored)) = (u32_at(rest, 0), u32_at(rest, 4)) else {
        return Err(End::Torn);
    };
    if len == 0 || len > MAX_RECORD_LEN {
        return Err(End::Corrupt(BadRecord::Length { len }));
    }
    let total = RECORD_HEADER + len as usize;
    // A tear leaves the length field intact, so its length is the one its kind calls for;
    // any other record is a damaged one, and the bytes behind it may be good records.
    let torn_unless_kind_mismatch = || match rest.get(RECORD_HEADER) {
        Some(&kind) => match check_kind(kind, len as usize) {
            Ok(()) => End::Torn,
            Err(e) => End::Corrupt(e),
        },
        None if [KEYFRAME_LEN, ODOMETRY_LEN].contains(&(len as usize)) => End::Torn,
        None => End::Corrupt(BadRecord::PastEnd { len }),
    };
    let Some(payload) = rest.get(RECORD_HEADER..total) else {
        return Err(torn_unless_kind_mismatch());
    };
    let computed = crc32fast::hash(payload);
    if computed != stored {
        return Err(if rest.len() == total {
            torn_unless_kind_mismatch()
        } else {
            End::Corrupt(BadRecord::Checksum { stored, computed })
        });
    }
    Entry::decode(payload)
        .map(|e| (e, total))
        .map_err(End::Corrupt)
}

/// The records of `bytes` from offset `start`, the end of the last good one, and how
/// they end.
fn parse(bytes: &[u8], start: usize) -> (Vec<Entry>, usize, End) {
    let mut entries = Vec::new();
    let mut at = start;
    loop {
        match record(bytes.get(at..).unwrap_or_default()) {
            Ok(Some((entry, n))) => {
                entries.push(entry);
                at += n;
            }
            Ok(None) => return (entries, at, End::Clean),
            Err(end) => return (entries, at, end),
        }
    }
}

/// Makes the directory entry of `path` durable (a new file, or a new side file that must
/// exist before the journal is shortened).
fn sync_dir(path: &Path) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    File::open(dir)?.sync_all()
}

/// Copies `tail` into a new side file next to the journal and makes it durable; returns
/// its path. An existing file is never opened: the name gets a counter instead.
fn preserve(path: &Path, tail: &[u8]) -> Result<PathBuf, JournalError> {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let side_name = |n: u32| {
        let mut s = path.as_os_str().to_owned();
        s.push(format!(".corrupt-{secs}"));
        if n > 0 {
            s.push(format!("-{n}"));
        }
        PathBuf::from(s)
    };
    let failed = |side: PathBuf, source| JournalError::Preserve {
        path: path.to_path_buf(),
        side,
        bytes: tail.len() as u64,
        source,
    };
    for n in 0..10_000 {
        let side = side_name(n);
        let mut file = match OpenOptions::new().write(true).create_new(true).open(&side) {
            Ok(f) => f,
            Err(e) if e.kind() == ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(failed(side, e)),
        };
        let written = file
            .write_all(tail)
            .and_then(|()| file.sync_all())
            .and_then(|()| sync_dir(&side));
        return match written {
            Ok(()) => Ok(side),
            Err(e) => {
                // An incomplete copy must not pass for the preserved bytes; the journal
                // still holds them all.
                let _ = std::fs::remove_file(&side);
                Err(failed(side, e))
            }
        };
    }
    Err(failed(
        side_name(10_000),
        std::io::Error::new(
            ErrorKind::AlreadyExists,
            "too many side files of this second",
        ),
    ))
}

impl Journal {
    /// Reads a journal without modifying it (for tools and tests; a live back-end may be
    /// appending, so a partial last record is simply not returned). It accepts a journal of
    /// any robot: the robot is in [`Recovery::robot`].
    pub fn read(path: &Path) -> Result<Recovery, JournalError> {
        let bytes = std::fs::read(path).map_err(|source| JournalError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let (robot, start) = match check_header(path, &bytes, None)? {
            Header::Missing => {
                return Ok(Recovery {
                    fresh: true,
                    torn_header_bytes: bytes.len() as u64,
                    ..Default::default()
                })
            }
            Header::Valid { robot, len } => (robot, len),
        };
        let (entries, good, end) = parse(&bytes, start);
        let rest = (bytes.len() - good) as u64;
        Ok(Recovery {
            robot: Some(robot),
            entries,
            truncated_bytes: if matches!(end, End::Torn) { rest } else { 0 },
            corruption: match end {
                End::Corrupt(reason) => Some(Corruption {
                    offset: good as u64,
                    bytes: rest,
                    reason,
                    preserved: None,
                }),
                _ => None,
            },
            ..Default::default()
        })
    }

    /// Opens the journal of `robot` (creating it if needed), recovers its entries, cuts a
    /// torn tail and moves corrupt bytes into a side file (see the module docs). A file that
    /// is not a journal of `robot` in a readable version is an error and left untouched.
    pub fn open(path: &Path, robot: &str) -> Result<(Self, Recovery), JournalError> {
        let io = |source| JournalError::Io {
            path: path.to_path_buf(),
            source,
        };
        if robot.is_empty() || robot.len() > MAX_ROBOT_LEN {
            return Err(JournalError::RobotId {
                path: path.to_path_buf(),
                robot: robot.into(),
            });
        }
        let ours = header_bytes(robot);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        // Not `create(true)` on every open: only a file that did not exist is new, and its
        // directory entry then has to be made durable too.
        let options = || {
            let mut o = OpenOptions::new();
            o.read(true).append(true);
            o
        };
        let mut file = match options().open(path) {
            Ok(f) => f,
            Err(e) if e.kind() == ErrorKind::NotFound => {
                options().create_new(true).open(path).map_err(io)?
            }
            Err(e) => return Err(io(e)),
        };
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes).map_err(io)?;
        let mut recovery = Recovery {
            robot: Some(robot.into()),
            ..Default::default()
        };
        match check_header(path, &bytes, Some(&ours))? {
            Header::Missing => {
                // Empty, or a header torn while it was written: no record was ever appended.
                recovery.fresh = true;
                recovery.torn_header_bytes = bytes.len() as u64;
                file.set_len(0).map_err(io)?;
                file.write_all(&ours).map_err(io)?;
                file.sync_all().map_err(io)?;
                sync_dir(path).map_err(io)?;
            }
            Header::Valid { robot: found, len } => {
                if found != robot {
                    return Err(JournalError::OtherRobot {
                        path: path.to_path_buf(),
                        found,
                        expected: robot.into(),
                    });
                }
                let (entries, good, end) = parse(&bytes, len);
                recovery.entries = entries;
                let rest = (bytes.len() - good) as u64;
                match end {
                    End::Clean => {}
                    End::Torn => {
                        recovery.truncated_bytes = rest;
                        file.set_len(good as u64).map_err(io)?;
                        file.sync_all().map_err(io)?;
                    }
                    End::Corrupt(reason) => {
                        // Durable copy first: only then may the journal lose these bytes.
                        let side = preserve(path, &bytes[good..])?;
                        file.set_len(good as u64).map_err(io)?;
                        file.sync_all().map_err(io)?;
                        recovery.corruption = Some(Corruption {
                            offset: good as u64,
                            bytes: rest,
                            reason,
                            preserved: Some(side),
                        });
                    }
                }
            }
        }
        Ok((
            Self {
                path: path.to_path_buf(),
                file,
            },
            recovery,
        ))
    }

    /// Appends an entry and waits until it is on disk.
    pub fn append(&mut self, entry: &Entry) -> Result<(), JournalError> {
        let payload = entry.encode();
        let mut record = Vec::with_capacity(RECORD_HEADER + payload.len());
        record.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        record.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
        record.extend_from_slice(&payload);
        let io = |source| JournalError::Io {
            path: self.path.clone(),
            source,
        };
        self.file.write_all(&record).map_err(io)?;
        self.file.sync_data().map_err(io)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}
