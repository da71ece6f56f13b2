//! The head object: which version is current and which segments hold the volume's bytes.
//!
//! It is small JSON, rewritten by every commit with a conditional PUT. Its segment list is
//! bounded: past [`TAIL_MAX`] segments a writer folds them into a manifest object (immutable,
//! named once) and the head keeps only the segments after it.

use super::super::StoreError;
use isovox_proto::vod2::HeaderSlot;
use serde::{Deserialize, Serialize};

/// The value of the head's `format` field.
pub const HEAD_FORMAT: &str = "isovox-head/1";

/// Segments a head lists itself before they are folded into a manifest.
pub const TAIL_MAX: usize = 64;

/// A head or manifest larger than this is refused (a hostile or damaged object).
pub const MAX_HEAD_BYTES: usize = 1 << 20;
/// See [`MAX_HEAD_BYTES`].
pub const MAX_MANIFEST_BYTES: usize = 64 << 20;

/// One segment: bytes `[start, start + len)` of the volume's logical VOD 2 file, in one
/// immutable object.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Segment {
    /// Its first byte's offset.
    pub start: u64,
    /// Its length.
    pub len: u64,
    /// Its object key, below the volume's prefix.
    pub key: String,
}

impl Segment {
    /// One past its last byte.
    pub fn end(&self) -> u64 {
        self.start + self.len
    }
}

/// A manifest the head builds on: every segment from offset 0 up to `end`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestRef {
    /// Its object key, below the volume's prefix.
    pub key: String,
    /// How many segments it lists.
    pub segments: u64,
    /// The end of its last segment.
    pub end: u64,
}

/// The head object's content.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Head {
    /// [`HEAD_FORMAT`].
    pub format: String,
    /// The head version.
    pub version: u64,
    /// Offset of its commit record.
    pub commit: u64,
    /// Bytes of the logical file the head may reference.
    pub committed_len: u64,
    /// The manifest of the segments before [`Head::segments`], if any.
    pub manifest: Option<ManifestRef>,
    /// The segments after the manifest's (all of them without one), in order.
    pub segments: Vec<Segment>,
}

/// A manifest object's content.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`HEAD_FORMAT`].
    pub format: String,
    /// Every segment from offset 0, in order.
    pub segments: Vec<Segment>,
}

fn invalid(what: &'static str, detail: String) -> StoreError {
    StoreError::Format(isovox_proto::FormatError::invalid(what, detail))
}

/// Checks that `segments` are contiguous from `start` and that each key is a plain relative
/// key; returns where they end.
fn check_run(what: &'static str, segments: &[Segment], start: u64) -> Result<u64, StoreError> {
    let mut at = start;
    for s in segments {
        if s.start != at || s.len == 0 {
            return Err(invalid(
                what,
                format!(
                    "segment {} starts at {} where {at} was expected (or is empty)",
                    s.key, s.start
                ),
            ));
        }
        if !valid_key(&s.key) {
            return Err(invalid(
                what,
                format!("segment key {:?} is not a plain key", s.key),
            ));
        }
        at = s
            .start
            .checked_add(s.len)
            .ok_or_else(|| invalid(what, format!("segment {} ends past 2^64", s.key)))?;
    }
    Ok(at)
}

/// A key the volume's objects may have: relative, no empty or dot segments.
pub fn valid_key(key: &str) -> bool {
    !key.is_empty()
        && key.len() <= 256
        && key
            .split('/')
            .all(|p| !p.is_empty() && p != "." && p != "..")
        && key
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.' | b'/'))
}

impl Head {
    /// Decodes and checks a head object.
    ///
    /// # Errors
    /// Not a head, too large, or inconsistent (segments not contiguous, the commit outside the
    /// committed length).
    pub fn decode(bytes: &[u8]) -> Result<Head, StoreError> {
        if bytes.len() > MAX_HEAD_BYTES {
            return Err(invalid("head object", format!("{} bytes", bytes.len())));
        }
        let head: Head =
            serde_json::from_slice(bytes).map_err(|e| invalid("head object", e.to_string()))?;
        if head.format != HEAD_FORMAT {
            return Err(invalid("head object", format!("format {:?}", head.format)));
        }
        let start = match &head.manifest {
            Some(m) => {
                if !valid_key(&m.key) {
                    return Err(invalid("head object", format!("manifest key {:?}", m.key)));
                }
                m.end
            }
            None => 0,
        };
        let end = check_run("head object", &head.segments, start)?;
        if end != head.committed_len || head.commit >= head.committed_len || head.version == 0 {
            return Err(invalid(
                "head object",
                format!(
                    "version {} at {} with {} committed bytes, segments end at {end}",
                    head.version, head.commit, head.committed_len
                ),
            ));
        }
        Ok(head)
    }

    /// The object's bytes.
    pub fn encode(&self) -> Vec<u8> {
        serde_json::to_vec(self).unwrap_or_default()
    }

    /// The header slot it stands for (the sequence number is the version).
    pub fn slot(&self) -> HeaderSlot {
        HeaderSlot {
            seq: self.version,
            commit: self.commit,
            committed_len: self.committed_len,
            version: self.version,
            appended: None,
        }
    }
}

impl Manifest {
    /// Decodes and checks a manifest against the head's reference to it.
    ///
    /// # Errors
    /// Not a manifest, too large, or not what the reference says.
    pub fn decode(bytes: &[u8], reference: &ManifestRef) -> Result<Manifest, StoreError> {
        if bytes.len() > MAX_MANIFEST_BYTES {
            return Err(invalid("manifest", format!("{} bytes", bytes.len())));
        }
        let m: Manifest =
            serde_json::from_slice(bytes).map_err(|e| invalid("manifest", e.to_string()))?;
        let end = check_run("manifest", &m.segments, 0)?;
        if m.format != HEAD_FORMAT
            || end != reference.end
            || m.segments.len() as u64 != reference.segments
        {
            return Err(invalid(
                "manifest",
                format!(
                    "{} segments ending at {end}; the head names {} ending at {}",
                    m.segments.len(),
                    reference.segments,
                    reference.end
                ),
            ));
        }
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seg(start: u64, len: u64) -> Segment {
        Segment {
            start,
            len,
            key: format!("seg/{start}"),
        }
    }

    fn head(segments: Vec<Segment>, committed_len: u64) -> Head {
        Head {
            format: HEAD_FORMAT.into(),
            version: 3,
            commit: 100,
            committed_len,
            manifest: None,
            segments,
        }
    }

    #[test]
    fn a_consistent_head_round_trips() {
        let h = head(vec![seg(0, 150), seg(150, 50)], 200);
        assert_eq!(Head::decode(&h.encode()).unwrap(), h);
        assert_eq!(h.slot().version, 3);
        assert_eq!(h.slot().committed_len, 200);
    }

    #[test]
    fn gaps_overlaps_and_bad_keys_are_refused() {
        for bad in [
            head(vec![seg(0, 150), seg(151, 49)], 200),
            head(vec![seg(0, 150), seg(149, 51)], 200),
            head(vec![seg(0, 150)], 200),
            head(vec![seg(0, 90)], 90),
            head(
                vec![Segment {
                    start: 0,
                    len: 200,
                    key: "../x".into(),
                }],
                200,
            ),
        ] {
            assert!(Head::decode(&bad.encode()).is_err(), "{bad:?}");
        }
        assert!(Head::decode(b"{").is_err());
        assert!(Head::decode(&vec![b' '; MAX_HEAD_BYTES + 1]).is_err());
    }
}
