//! Why a wire message was refused, on the way out or in. Every error names the field and
//! the byte offset (from the start of the message) where it was found.

use super::WIRE_VERSION;

/// A message that cannot be encoded or decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    #[error("wire version {found} is not supported (this build speaks version {supported})")]
    UnknownVersion { found: u8, supported: u8 },
    #[error("unknown message kind {found} at offset 1")]
    UnknownKind { found: u8 },
    #[error("{field} at offset {offset}: needs {needed} bytes, {available} available")]
    Truncated {
        field: &'static str,
        offset: usize,
        needed: usize,
        available: usize,
    },
    #[error("{field} at offset {offset}: {len} exceeds the maximum {max}")]
    TooLong {
        field: &'static str,
        offset: usize,
        len: u64,
        max: u64,
    },
    #[error("{count} trailing bytes after the end of the message")]
    TrailingBytes { count: usize },
    #[error("{field} at offset {offset}: {reason}")]
    Invalid {
        field: &'static str,
        offset: usize,
        reason: String,
    },
}

impl WireError {
    pub(crate) fn unknown_version(found: u8) -> Self {
        Self::UnknownVersion {
            found,
            supported: WIRE_VERSION,
        }
    }

    pub(crate) fn invalid(field: &'static str, offset: usize, reason: impl ToString) -> Self {
        Self::Invalid {
            field,
            offset,
            reason: reason.to_string(),
        }
    }
}
