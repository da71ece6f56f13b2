//! The head object: which version is current and which segments hold the volume's bytes.
//!
//! It is small JSON, rewritten by every commit with a conditional PUT. Its segment list is
//! bounded: past [`TAIL_MAX`] segments a writer folds them into a manifest object (immutable,
//! named once) and the head keeps only the segments after it.
//!
//! A small commit's segment rides in the head itself ([`Segment::inline`], up to
//! [`DEFAULT_INLINE_MAX`] bytes of them in one head by default): the commit is then one PUT,
//! and a replica catching up reads it with the head, one GET. When the next segment would not fit, the
//! writer spills every inlined segment and its own into one object (each then names it in
//! [`Segment::within`]) before its head PUT, so a manifest never carries bytes.

use super::super::StoreError;
use base64::engine::general_purpose::STANDARD as BASE64;
use base64::Engine as _;
use bytes::Bytes;
use isovox_proto::vod2::HeaderSlot;
use serde::{Deserialize, Serialize};

/// The value of the head's `format` field. (Revision 1 had no inline segments; a head of
/// revision 1 still reads, a binary that knows only revision 1 refuses this one.)
pub const HEAD_FORMAT: &str = "isovox-head/2";

/// The `format` of heads and manifests of the first revision, whose every segment is an object
/// of its own.
pub const HEAD_FORMAT_1: &str = "isovox-head/1";

/// Bytes of segments one head may carry inline (their base64 is a third larger): a head
/// carrying more is refused, whatever its writer was set to.
pub const INLINE_LIMIT: u64 = 512 << 10;

/// Bytes of segments a writer lets one head carry unless told otherwise. A commit's segment is
/// a few KiB to a few tens of KiB when its group is a few small edits; larger ones go up as
/// objects.
pub const DEFAULT_INLINE_MAX: u64 = 192 << 10;

/// Segments a head lists itself before they are folded into a manifest.
pub const TAIL_MAX: usize = 64;

/// A head or manifest larger than this is refused (a hostile or damaged object).
pub const MAX_HEAD_BYTES: usize = 1 << 20;
/// See [`MAX_HEAD_BYTES`].
pub const MAX_MANIFEST_BYTES: usize = 64 << 20;

/// One segment: bytes `[start, start + len)` of the volume's logical VOD 2 file, in one
/// immutable object, in part of one ([`Segment::within`]), or in the head ([`Segment::inline`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Segment {
    /// Its first byte's offset.
    pub start: u64,
    /// Its length.
    pub len: u64,
    /// Its name, unique, below the volume's prefix: the key of the object holding it unless
    /// `within` or `inline` says otherwise. It stays the segment's name when an inlined
    /// segment is spilled, so replicas that knew it inline know it spilled.
    pub key: String,
    /// The object holding it among other segments, and where in that object it starts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub within: Option<Within>,
    /// Its bytes, when the head carries them (no object holds them yet).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inline: Option<Inline>,
}

/// Where a segment spilled with others lies: object `key` from byte `at`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Within {
    /// The object's key, below the volume's prefix.
    pub key: String,
    /// The segment's first byte in it.
    pub at: u64,
}

/// A segment's bytes carried in the head, as base64 in its JSON.
#[derive(Clone, PartialEq, Eq)]
pub struct Inline(pub Bytes);

impl std::fmt::Debug for Inline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Inline({} bytes)", self.0.len())
    }
}

impl Serialize for Inline {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(&BASE64.encode(&self.0))
    }
}

impl<'de> Deserialize<'de> for Inline {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Inline, D::Error> {
        let text = <std::borrow::Cow<'de, str>>::deserialize(deserializer)?;
        BASE64
            .decode(text.as_bytes())
            .map(|b| Inline(Bytes::from(b)))
            .map_err(serde::de::Error::custom)
    }
}

impl Segment {
    /// A segment in an object of its own.
    pub fn object(start: u64, len: u64, key: String) -> Segment {
        Segment {
            start,
            len,
            key,
            within: None,
            inline: None,
        }
    }

    /// One past its last byte.
    pub fn end(&self) -> u64 {
        self.start + self.len
    }

    /// Whether `other` names the same bytes: the same place and name, wherever each says they
    /// are kept (inline, spilled, or as this process last saw them).
    pub fn same_as(&self, other: &Segment) -> bool {
        (self.start, self.len, &self.key) == (other.start, other.len, &other.key)
    }

    /// The object its bytes are fetched from and their first byte's offset in it.
    pub fn location(&self) -> (&str, u64) {
        match &self.within {
            Some(w) => (&w.key, w.at),
            None => (&self.key, 0),
        }
    }

    /// The segment without its inline bytes (what a replica keeps once they are in its
    /// mirror).
    pub fn without_bytes(&self) -> Segment {
        Segment {
            inline: None,
            ..self.clone()
        }
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

/// Checks that `segments` are contiguous from `start`, that each key is a plain relative key
/// and that inline bytes (where `inline_allowed`: in a head) are the segment's length; returns
/// where they end.
fn check_run(
    what: &'static str,
    segments: &[Segment],
    start: u64,
    inline_allowed: bool,
) -> Result<u64, StoreError> {
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
        if !valid_key(&s.key) || s.within.as_ref().is_some_and(|w| !valid_key(&w.key)) {
            return Err(invalid(
                what,
                format!("segment key {:?} is not a plain key", s.key),
            ));
        }
        match (&s.inline, &s.within) {
            (Some(bytes), None) if inline_allowed && bytes.0.len() as u64 == s.len => {}
            (None, _) => {}
            _ => {
                return Err(invalid(
                    what,
                    format!(
                        "segment {}: inline bytes where none may be, or not {} of them",
                        s.key, s.len
                    ),
                ))
            }
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
        if head.format != HEAD_FORMAT && head.format != HEAD_FORMAT_1 {
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
        let end = check_run("head object", &head.segments, start, true)?;
        let carried = head.carried();
        if carried > INLINE_LIMIT {
            return Err(invalid(
                "head object",
                format!("{carried} bytes of segments inline; at most {INLINE_LIMIT}"),
            ));
        }
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

    /// Bytes of the segments it carries inline.
    pub fn carried(&self) -> u64 {
        self.segments
            .iter()
            .filter(|s| s.inline.is_some())
            .map(|s| s.len)
            .sum()
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
        let end = check_run("manifest", &m.segments, 0, false)?;
        if (m.format != HEAD_FORMAT && m.format != HEAD_FORMAT_1)
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
        Segment::object(start, len, format!("seg/{start}"))
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
            head(vec![Segment::object(0, 200, "../x".into())], 200),
        ] {
            assert!(Head::decode(&bad.encode()).is_err(), "{bad:?}");
        }
        assert!(Head::decode(b"{").is_err());
        assert!(Head::decode(&vec![b' '; MAX_HEAD_BYTES + 1]).is_err());
    }

    fn inline(start: u64, bytes: &[u8]) -> Segment {
        Segment {
            inline: Some(Inline(Bytes::copy_from_slice(bytes))),
            ..seg(start, bytes.len() as u64)
        }
    }

    #[test]
    fn inline_bytes_ride_as_base64_and_come_back() {
        let h = head(vec![seg(0, 150), inline(150, b"\x00\xffhello")], 157);
        let json = String::from_utf8(h.encode()).unwrap();
        // "\0\xffhello" in base64, by hand: 00 ff 68 | 65 6c 6c | 6f -> AP9o ZWxs bw==
        assert!(json.contains(r#""inline":"AP9oZWxsbw==""#), "{json}");
        assert!(!json.contains("within"), "{json}");
        let back = Head::decode(json.as_bytes()).unwrap();
        assert_eq!(back, h);
        assert_eq!(
            back.segments[1].inline.as_ref().unwrap().0.as_ref(),
            b"\x00\xffhello"
        );
    }

    #[test]
    fn a_spilled_segment_is_fetched_from_its_object_and_is_still_the_same_segment() {
        let carried = inline(150, b"abc");
        let spilled = Segment {
            within: Some(Within {
                key: "seg/spill".into(),
                at: 40,
            }),
            ..carried.without_bytes()
        };
        assert!(carried.same_as(&spilled) && spilled.same_as(&carried));
        assert_eq!(spilled.location(), ("seg/spill", 40));
        assert_eq!(carried.location(), ("seg/150", 0));
        assert!(!spilled.same_as(&seg(150, 4)));
    }

    #[test]
    fn inline_bytes_that_do_not_belong_are_refused() {
        let mut wrong_length = inline(150, b"abc");
        wrong_length.len = 4;
        let mut both = inline(150, b"abc");
        both.within = Some(Within {
            key: "seg/x".into(),
            at: 0,
        });
        let mut bad_object = seg(150, 3);
        bad_object.within = Some(Within {
            key: "../x".into(),
            at: 0,
        });
        for (bad, len) in [(wrong_length, 154), (both, 153), (bad_object, 153)] {
            let h = head(vec![seg(0, 150), bad], len);
            assert!(Head::decode(&h.encode()).is_err(), "{h:?}");
        }
        // More than INLINE_LIMIT carried in all.
        let big = vec![7u8; (INLINE_LIMIT / 2 + 1) as usize];
        let n = big.len() as u64;
        let h = head(
            vec![seg(0, 150), inline(150, &big), inline(150 + n, &big)],
            150 + 2 * n,
        );
        assert!(Head::decode(&h.encode()).is_err());
        let h = head(vec![seg(0, 150), inline(150, &big)], 150 + n);
        assert!(Head::decode(&h.encode()).is_ok());
        // Not in a manifest: it is immutable and read whole by every replica that opens.
        let m = Manifest {
            format: HEAD_FORMAT.into(),
            segments: vec![seg(0, 150), inline(150, b"abc")],
        };
        let reference = ManifestRef {
            key: "manifests/m".into(),
            segments: 2,
            end: 153,
        };
        assert!(Manifest::decode(&serde_json::to_vec(&m).unwrap(), &reference).is_err());
    }

    #[test]
    fn a_head_of_the_first_revision_still_reads() {
        let json = r#"{"format":"isovox-head/1","version":3,"commit":100,"committed_len":200,
            "manifest":null,"segments":[{"start":0,"len":200,"key":"seg/0"}]}"#;
        let h = Head::decode(json.as_bytes()).unwrap();
        assert_eq!(h.segments, vec![seg(0, 200)]);
        assert_eq!(h.segments[0].location(), ("seg/0", 0));
    }
}
