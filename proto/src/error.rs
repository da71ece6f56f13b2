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
        /// The record.
        what: &'static str,
        /// Where it starts in the file.
        offset: u64,
        /// The bytes it needs.
        needed: u64,
        /// The bytes there are.
        available: u64,
    },
    /// A magic number or signature does not match.
    #[error("{what} has a bad signature: expected {expected:?}, found {found:?}")]
    BadMagic {
        /// The record.
        what: &'static str,
        /// The signature it must have.
        expected: [u8; 4],
        /// The bytes found instead.
        found: [u8; 4],
    },
    /// A stored checksum does not match the bytes it covers.
    #[error("{what} checksum mismatch at offset {offset}: stored {stored:#018x}, computed {computed:#018x}")]
    Checksum {
        /// The record.
        what: &'static str,
        /// Where it starts in the file.
        offset: u64,
        /// The checksum stored with it.
        stored: u64,
        /// The checksum of its bytes.
        computed: u64,
    },
    /// A field holds a value outside its allowed range.
    #[error("{what}: {detail}")]
    Invalid {
        /// The record or field.
        what: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// The file is a version or variant this build does not read.
    #[error("unsupported {what}: {detail}")]
    Unsupported {
        /// The part.
        what: &'static str,
        /// What it is.
        detail: String,
    },
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
