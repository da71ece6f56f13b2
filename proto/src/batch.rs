//! The batch brick encoding (`application/x-isovox-bricks`): many bricks in one response, so a
//! viewer does not need thousands of tiny requests.
//!
//! Request (`POST /v1/volumes/{name}/batch`, JSON): [`BatchRequest`].
//!
//! Response, little endian:
//!
//! ```text
//! 0     magic "IVBB", u32 count n
//! 8     n x 28-byte entries: u8 level, u8 codec (0 raw voxels, 1 lz4 block, 2 zstd frame,
//!       3 constant: the payload is the value, a u16, or a u64 in a u32 or u64 stream),
//!       u16 zero, u32 x, u32 y, u32 z,
//!       u64 content hash, u32 payload length
//! 8+28n payloads, in entry order
//! ```

use crate::error::FormatError;
use crate::layout::BrickKey;
use crate::vod2::Fields;
use serde::{Deserialize, Serialize};

/// Most bricks one batch may ask for.
pub const MAX_BATCH: usize = 4096;

/// `{"keys": [[level, x, y, z], ...], "version": N, "encoding": "raw" | "stored"}`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BatchRequest {
    /// The bricks, as (level, x, y, z).
    pub keys: Vec<(u8, u32, u32, u32)>,
    /// The version to read; the newest when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<u64>,
    /// `raw` (default): decoded voxels; `stored`: the payload as stored (lz4, zstd, raw, or a
    /// constant's value), for clients that decode themselves.
    #[serde(default)]
    pub encoding: BatchEncoding,
}

/// How the bricks of a batch are sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BatchEncoding {
    /// Decoded voxels.
    #[default]
    Raw,
    /// As stored, for clients that decode themselves.
    Stored,
}

/// How one brick's payload is encoded in a batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchCodec {
    /// Decoded voxels.
    Raw = 0,
    /// An lz4 block of the voxels.
    Lz4 = 1,
    /// A zstd frame of the voxels.
    Zstd = 2,
    /// A constant brick: the payload is its one value, little endian: a u16 for u8 and u16
    /// bricks, a u64 for u32 and u64 bricks ([`constant_payload`]).
    Constant = 3,
}

/// The payload of a [`BatchCodec::Constant`] entry of value `v` in a stream of `voxel_type`.
pub fn constant_payload(v: u64, voxel_type: crate::VoxelType) -> Vec<u8> {
    if voxel_type.is_wide() {
        v.to_le_bytes().to_vec()
    } else {
        (v as u16).to_le_bytes().to_vec()
    }
}

/// One brick of a batch.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BatchEntry {
    /// The brick.
    pub key: BrickKey,
    /// How the payload is encoded.
    pub codec: BatchCodec,
    /// The brick's content hash (of its decoded voxels).
    pub hash: u64,
    /// The payload bytes.
    pub payload: Vec<u8>,
}

const MAGIC: [u8; 4] = *b"IVBB";
const ENTRY: usize = 28;

/// Encodes a batch response.
pub fn encode_batch(entries: &[BatchEntry]) -> Vec<u8> {
    let total = 8 + entries.len() * ENTRY + entries.iter().map(|e| e.payload.len()).sum::<usize>();
    let mut b = Vec::with_capacity(total);
    b.extend_from_slice(&MAGIC);
    b.extend_from_slice(&(entries.len() as u32).to_le_bytes());
    for e in entries {
        b.push(e.key.level);
        b.push(e.codec as u8);
        b.extend_from_slice(&[0, 0]);
        for c in [e.key.x, e.key.y, e.key.z] {
            b.extend_from_slice(&c.to_le_bytes());
        }
        b.extend_from_slice(&e.hash.to_le_bytes());
        b.extend_from_slice(&(e.payload.len() as u32).to_le_bytes());
    }
    for e in entries {
        b.extend_from_slice(&e.payload);
    }
    b
}

/// Decodes a batch response.
///
/// # Errors
/// Bad magic, a count or lengths the bytes cannot hold, an unknown codec.
pub fn decode_batch(bytes: &[u8]) -> Result<Vec<BatchEntry>, FormatError> {
    let f = Fields::new("brick batch", bytes, 0);
    f.magic(0, MAGIC)?;
    let n = f.u32(4)? as usize;
    if n > MAX_BATCH || 8 + n * ENTRY > bytes.len() {
        return Err(FormatError::invalid(
            "brick batch",
            format!("{n} entries do not fit {} bytes", bytes.len()),
        ));
    }
    let mut at = 8 + n * ENTRY;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let e = 8 + i * ENTRY;
        let codec = match f.slice(e + 1, 1)?[0] {
            0 => BatchCodec::Raw,
            1 => BatchCodec::Lz4,
            2 => BatchCodec::Zstd,
            3 => BatchCodec::Constant,
            other => {
                return Err(FormatError::Unsupported {
                    what: "batch codec",
                    detail: other.to_string(),
                })
            }
        };
        let len = f.u32(e + 24)? as usize;
        out.push(BatchEntry {
            key: BrickKey {
                level: f.slice(e, 1)?[0],
                x: f.u32(e + 4)?,
                y: f.u32(e + 8)?,
                z: f.u32(e + 12)?,
            },
            codec,
            hash: f.u64(e + 16)?,
            payload: f.slice(at, len)?.to_vec(),
        });
        at += len;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_golden_layout() {
        let entries = vec![
            BatchEntry {
                key: BrickKey {
                    level: 1,
                    x: 2,
                    y: 3,
                    z: 4,
                },
                codec: BatchCodec::Constant,
                hash: 7,
                payload: vec![255, 0],
            },
            BatchEntry {
                key: BrickKey {
                    level: 0,
                    x: 0,
                    y: 0,
                    z: 1,
                },
                codec: BatchCodec::Raw,
                hash: 9,
                payload: vec![1, 2, 3],
            },
        ];
        let b = encode_batch(&entries);
        assert_eq!(b.len(), 8 + 2 * 28 + 5);
        assert_eq!(&b[..8], &[b'I', b'V', b'B', b'B', 2, 0, 0, 0]);
        assert_eq!(&b[8..12], &[1, 3, 0, 0]);
        assert_eq!(decode_batch(&b).unwrap(), entries);
        for cut in 0..b.len() {
            assert!(decode_batch(&b[..cut]).is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn request_json() {
        let r: BatchRequest =
            serde_json::from_str(r#"{"keys": [[0, 1, 2, 3]], "encoding": "stored"}"#).unwrap();
        assert_eq!(r.keys, vec![(0, 1, 2, 3)]);
        assert_eq!(r.encoding, BatchEncoding::Stored);
        assert!(serde_json::from_str::<BatchRequest>(r#"{"keys": [[0, 1, 2]]}"#).is_err());
    }
}
