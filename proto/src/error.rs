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
    #[error(
        "{what} has a bad signature: expected {}, found {}",
        signature(expected),
        signature(found)
    )]
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

/// A signature as text, the way it is written in the format's documentation: `".VOD"`, with
/// bytes that are not printable ASCII escaped (`"PK\x03\x04"`).
fn signature(bytes: &[u8]) -> String {
    let text: String = bytes
        .iter()
        .flat_map(|&b| std::ascii::escape_default(b))
        .map(char::from)
        .collect();
    format!("\"{text}\"")
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

#[cfg(test)]
mod tests {
    use super::FormatError;

    #[test]
    fn signatures_print_as_text() {
        let e = FormatError::BadMagic {
            what: "file header",
            expected: *b".VOD",
            found: [b'P', b'K', 3, 4],
        };
        assert_eq!(
            e.to_string(),
            r#"file header has a bad signature: expected ".VOD", found "PK\x03\x04""#
        );
        // Quotes, backslashes and high bytes are escaped too, so the text is unambiguous.
        let e = FormatError::BadMagic {
            what: "commit",
            expected: *b"ICMT",
            found: [b'"', b'\\', 0xff, b'a'],
        };
        assert_eq!(
            e.to_string(),
            r#"commit has a bad signature: expected "ICMT", found "\"\\\xffa""#
        );
    }
}
