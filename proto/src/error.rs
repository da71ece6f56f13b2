//! Errors of decoding on-disk and wire records.

use thiserror::Error;

/// A record read from bytes is malformed. Each variant names what is wrong, so that a corrupted
/// or hostile file is reported precisely instead of panicking or reading out of bounds.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum FormatError {
    /// The bytes end before the record does.
    #[error(
        "{what} is truncated: needs {needed} bytes at offset {offset}, only {available} available"
    )]
    Truncated {
        what: &'static str,
        offset: u64,
        needed: u64,
        available: u64,
    },
    /// A magic number or signature does not match.
    #[error("{what} has a bad signature: expected {expected:?}, found {found:?}")]
    BadMagic {
        what: &'static str,
        expected: [u8; 4],
        found: [u8; 4],
    },
    /// A stored checksum does not match the bytes it covers.
    #[error("{what} checksum mismatch at offset {offset}: stored {stored:#018x}, computed {computed:#018x}")]
    Checksum {
        what: &'static str,
        offset: u64,
        stored: u64,
        computed: u64,
    },
    /// A field holds a value outside its allowed range.
    #[error("{what}: {detail}")]
    Invalid { what: &'static str, detail: String },
    /// The file is a version or variant this build does not read.
    #[error("unsupported {what}: {detail}")]
    Unsupported { what: &'static str, detail: String },
}

impl FormatError {
    /// An `Invalid` error.
    pub fn invalid(what: &'static str, detail: impl Into<String>) -> Self {
        FormatError::Invalid {
            what,
            detail: detail.into(),
        }
    }
}
