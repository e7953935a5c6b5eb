//! The back-end's persisted log: every accepted keyframe and odometry edge, appended and
//! fsync'd before it is applied, so a restarted back-end rebuilds exactly the graph it had.
//!
//! Record: `[len: u32 LE][crc32 of payload: u32 LE][payload]`; payload starts with a kind
//! byte. A crash mid-write leaves at most one torn record at the end: it fails its length
//! or CRC check, recovery stops there and truncates it (reported, never silently).

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Failures of the journal; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("journal {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
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
}

const KEYFRAME: u8 = 1;
const ODOMETRY: u8 = 2;

impl Entry {
    fn encode(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(256);
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
        }
        b
    }

    fn decode(b: &[u8]) -> Option<Entry> {
        let u64_at = |o: usize| {
            b.get(o..o + 8)
                .map(|s| u64::from_le_bytes(s.try_into().unwrap_or([0; 8])))
        };
        let f64s = |o: usize, out: &mut [f64]| -> Option<()> {
            for (k, x) in out.iter_mut().enumerate() {
                *x = f64::from_bits(u64_at(o + 8 * k)?);
            }
            Some(())
        };
        match *b.first()? {
            KEYFRAME if b.len() == 1 + 16 + 56 => {
                let mut pose = [0.0; 7];
                f64s(17, &mut pose)?;
                Some(Entry::Keyframe {
                    id: u64_at(1)?,
                    stamp_ns: u64_at(9)?,
                    pose,
                })
            }
            ODOMETRY if b.len() == 1 + 16 + 56 + 168 => {
                let (mut relative, mut information) = ([0.0; 7], [0.0; 21]);
                f64s(17, &mut relative)?;
                f64s(73, &mut information)?;
                Some(Entry::Odometry {
                    from: u64_at(1)?,
                    to: u64_at(9)?,
                    relative,
                    information,
                })
            }
            _ => None,
        }
    }
}

/// What recovery found.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Recovery {
    pub entries: Vec<Entry>,
    /// Bytes of a torn or corrupt tail that were cut off.
    pub truncated_bytes: u64,
}

/// An append-only, fsync'd journal file.
pub struct Journal {
    path: PathBuf,
    file: File,
}

/// Parses journal bytes: the valid entries and the length of the valid prefix.
fn parse(bytes: &[u8]) -> (Vec<Entry>, usize) {
    let mut entries = Vec::new();
    let mut good = 0usize;
    while let Some(header) = bytes.get(good..good + 8) {
        let len = u32::from_le_bytes([header[0], header[1], header[2], header[3]]) as usize;
        let crc = u32::from_le_bytes([header[4], header[5], header[6], header[7]]);
        let Some(payload) = bytes.get(good + 8..good + 8 + len) else {
            break;
        };
        if crc32fast::hash(payload) != crc {
            break;
        }
        let Some(entry) = Entry::decode(payload) else {
            break;
        };
        entries.push(entry);
        good += 8 + len;
    }
    (entries, good)
}

impl Journal {
    /// Reads a journal without modifying it (for tools and tests; a live back-end may be
    /// appending, so a partial last record is simply not returned).
    pub fn read(path: &Path) -> Result<Recovery, JournalError> {
        let bytes = std::fs::read(path).map_err(|source| JournalError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let (entries, good) = parse(&bytes);
        Ok(Recovery {
            entries,
            truncated_bytes: (bytes.len() - good) as u64,
        })
    }

    /// Opens (creating if needed) the journal, recovers its entries, and cuts a torn tail.
    pub fn open(path: &Path) -> Result<(Self, Recovery), JournalError> {
        let io = |source| JournalError::Io {
            path: path.to_path_buf(),
            source,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let mut file = OpenOptions::new()
            .read(true)
            .append(true)
            .create(true)
            .open(path)
            .map_err(io)?;
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes).map_err(io)?;
        let (entries, good) = parse(&bytes);
        let truncated_bytes = (bytes.len() - good) as u64;
        if truncated_bytes > 0 {
            file.set_len(good as u64).map_err(io)?;
            file.sync_all().map_err(io)?;
        }
        file.seek(SeekFrom::End(0)).map_err(io)?;
        Ok((
            Self {
                path: path.to_path_buf(),
                file,
            },
            Recovery {
                entries,
                truncated_bytes,
            },
        ))
    }

    /// Appends an entry and waits until it is on disk.
    pub fn append(&mut self, entry: &Entry) -> Result<(), JournalError> {
        let payload = entry.encode();
        let mut record = Vec::with_capacity(8 + payload.len());
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
