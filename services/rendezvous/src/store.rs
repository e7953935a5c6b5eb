//! What the team link offers of this robot's own keyframes, kept on disk: each keyframe's
//! verification packet and place descriptor, appended as they arrive to
//! `<run_dir>/<robot>/team.own`, and read back when the team link starts.
//!
//! Without it a restarted robot (a crash, a kill, a reboot) would offer its peers nothing
//! of the keyframes from before: the front-end and place recognition never publish a
//! keyframe twice, and the back-end's journal holds poses, not features. With it the
//! peers match their descriptors against the old keyframes again and verify against them.
//!
//! Format: records of a little-endian `u32` length and one encoded wire
//! [`Message`] (header sender `own`, epoch and sequence 0), a `VerificationFeatures` or a
//! one-keyframe `Descriptors` body — the wire's own bounded, validated decoding. A torn
//! last record (the process died mid-write) is cut off when the file is opened; a record
//! that does not decode stops the reading with an error naming the file and offset, and
//! the file is left as it is.

use std::fs::{File, OpenOptions};
use std::io::{BufReader, Read, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use doorslam_ipc::wire::{Body, Header, Message, RobotId, MAX_MESSAGE_BYTES};

/// Failures of the store: every one names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: record at byte {offset}: {reason} (move the file away to start without the keyframes it holds)")]
    Corrupt {
        path: PathBuf,
        offset: u64,
        reason: String,
    },
}

/// The append-only file of own keyframes. Records are also read back one at a time by
/// their offset ([`OwnStore::read_at`]): the features of keyframes that left memory
/// (`[rendezvous] features_in_memory`) are read from here when they are needed again.
#[derive(Debug)]
pub struct OwnStore {
    path: PathBuf,
    file: File,
}

impl OwnStore {
    /// Opens (or creates) the store at `path`, handing `visit` what it holds, oldest
    /// first, with each record's offset (for [`Self::read_at`]). Records are read one at a
    /// time, so opening a long flight's store never holds the whole file in memory.
    pub fn open(path: &Path, mut visit: impl FnMut(Body, u64)) -> Result<Self, StoreError> {
        let io = |source| StoreError::Io {
            path: path.to_path_buf(),
            source,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .read(true)
            .open(path)
            .map_err(io)?;
        let total = file.metadata().map_err(io)?.len();
        let mut reader = BufReader::new(&file);
        let mut at = 0u64;
        let mut record = Vec::new();
        loop {
            let corrupt = |reason: String| StoreError::Corrupt {
                path: path.to_path_buf(),
                offset: at,
                reason,
            };
            if at + 4 > total {
                break; // the end, or a torn length
            }
            let mut len = [0u8; 4];
            reader.read_exact(&mut len).map_err(io)?;
            let len = u32::from_le_bytes(len) as usize;
            if len == 0 || len > MAX_MESSAGE_BYTES {
                return Err(corrupt(format!(
                    "length {len} (1..={MAX_MESSAGE_BYTES} expected)"
                )));
            }
            if at + 4 + len as u64 > total {
                break; // a torn record
            }
            record.resize(len, 0);
            reader.read_exact(&mut record).map_err(io)?;
            visit(Self::body(&record).map_err(corrupt)?, at);
            at += 4 + len as u64;
        }
        drop(reader);
        if at < total {
            tracing::warn!(
                path = %path.display(),
                kept = at,
                cut = total - at,
                "team: own keyframe store ends in a torn record (the process died mid-write): cut off"
            );
            file.set_len(at).map_err(io)?;
        }
        Ok(Self {
            path: path.to_path_buf(),
            file,
        })
    }

    /// A record's body: only verification packets and descriptors are kept here.
    fn body(record: &[u8]) -> Result<Body, String> {
        let message = Message::decode(record).map_err(|e| e.to_string())?;
        match message.body {
            b @ (Body::VerificationFeatures(_) | Body::Descriptors(_)) => Ok(b),
            other => Err(format!(
                "a {} message: only verification packets and descriptors are kept here",
                other.kind().name()
            )),
        }
    }

    /// Appends one body (a verification packet or a one-keyframe descriptor batch) and
    /// returns the offset of its record.
    pub fn append(&mut self, body: Body) -> Result<u64, StoreError> {
        let io = |source| StoreError::Io {
            path: self.path.clone(),
            source,
        };
        let header = Header {
            sender: RobotId::new("own").expect("a valid robot id"),
            epoch: 0,
            sequence: 0,
        };
        let bytes = Message::new(header, body)
            .encode()
            .map_err(|e| StoreError::Corrupt {
                path: self.path.clone(),
                offset: 0,
                reason: format!("own record does not encode: {e}"),
            })?;
        let mut record = Vec::with_capacity(4 + bytes.len());
        record.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        record.extend_from_slice(&bytes);
        // The file's length, not a count kept here: after a failed (partial) write the
        // next record still gets its true offset.
        let offset = self.file.metadata().map_err(io)?.len();
        // One write per record: a crash leaves at most this record torn.
        self.file.write_all(&record).map_err(io)?;
        Ok(offset)
    }

    /// The body of the record at `offset` (as [`Self::append`] returned it or
    /// [`Self::open`] handed it).
    pub fn read_at(&self, offset: u64) -> Result<Body, StoreError> {
        let io = |source| StoreError::Io {
            path: self.path.clone(),
            source,
        };
        let corrupt = |reason: String| StoreError::Corrupt {
            path: self.path.clone(),
            offset,
            reason,
        };
        let mut len = [0u8; 4];
        self.file.read_exact_at(&mut len, offset).map_err(io)?;
        let len = u32::from_le_bytes(len) as usize;
        if len == 0 || len > MAX_MESSAGE_BYTES {
            return Err(corrupt(format!(
                "length {len} (1..={MAX_MESSAGE_BYTES} expected)"
            )));
        }
        let mut record = vec![0; len];
        self.file
            .read_exact_at(&mut record, offset + 4)
            .map_err(io)?;
        Self::body(&record).map_err(corrupt)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}
