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
use std::io::{Read, Write};
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

/// The append-only file of own keyframes.
#[derive(Debug)]
pub struct OwnStore {
    path: PathBuf,
    file: File,
}

impl OwnStore {
    /// Opens (or creates) the store at `path` and returns what it holds, oldest first.
    pub fn open(path: &Path) -> Result<(Self, Vec<Body>), StoreError> {
        let io = |source| StoreError::Io {
            path: path.to_path_buf(),
            source,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let mut bytes = Vec::new();
        match File::open(path) {
            Ok(mut f) => {
                f.read_to_end(&mut bytes).map_err(io)?;
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io(e)),
        }
        let mut bodies = Vec::new();
        let mut at = 0usize;
        while at < bytes.len() {
            let corrupt = |reason: String| StoreError::Corrupt {
                path: path.to_path_buf(),
                offset: at as u64,
                reason,
            };
            let Some(len) = bytes.get(at..at + 4) else {
                break; // a torn length
            };
            let len = u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize;
            if len == 0 || len > MAX_MESSAGE_BYTES {
                return Err(corrupt(format!(
                    "length {len} (1..={MAX_MESSAGE_BYTES} expected)"
                )));
            }
            let Some(record) = bytes.get(at + 4..at + 4 + len) else {
                break; // a torn record
            };
            let message = Message::decode(record).map_err(|e| corrupt(e.to_string()))?;
            match message.body {
                b @ (Body::VerificationFeatures(_) | Body::Descriptors(_)) => bodies.push(b),
                other => {
                    return Err(corrupt(format!(
                        "a {} message: only verification packets and descriptors are kept here",
                        other.kind().name()
                    )))
                }
            }
            at += 4 + len;
        }
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(io)?;
        if at < bytes.len() {
            tracing::warn!(
                path = %path.display(),
                kept = at,
                cut = bytes.len() - at,
                "team: own keyframe store ends in a torn record (the process died mid-write): cut off"
            );
            file.set_len(at as u64).map_err(io)?;
        }
        Ok((
            Self {
                path: path.to_path_buf(),
                file,
            },
            bodies,
        ))
    }

    /// Appends one body (a verification packet or a one-keyframe descriptor batch).
    pub fn append(&mut self, body: Body) -> Result<(), StoreError> {
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
        // One write per record: a crash leaves at most this record torn.
        self.file
            .write_all(&record)
            .map_err(|source| StoreError::Io {
                path: self.path.clone(),
                source,
            })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}
