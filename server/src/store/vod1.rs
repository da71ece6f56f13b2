//! VOD 1: the thesis's file layout (its Figure 24), as resolved in `docs/vod1.md`.
//!
//! ```text
//! u32 signature '.VOD' (bytes in file order), u32 fileVersion 1,
//! u32[3] volumeSize, u32[3] brickSize, f32[3] voxelScale, u32 treeHeight, u32 voxelSize (bits),
//! u32 hashAlgorithm ('XH64'; 'XH32' read too), u32 compAlgorithm ('LZ4B' or 'NONE'), u32 flags
//! u32[(8^treeHeight - 1) / 7] brickID of each octree node, preorder
//! u32 numberOfBricks; numberOfBricks x { u32 brickID, u32 brickFileOffset, hash }
//! numberOfBricks x { u32 dataSize, data[dataSize] }
//! ```
//!
//! Fixed here where the thesis is silent: children are visited x fastest, then y, then z; brick
//! IDs start at 1 and an ID of 0 (the thesis's "empty node") reads as all L; `brickFileOffset`
//! points at the brick's `dataSize` field; with compression (flag bit 0) every payload is an lz4
//! block. The octree is complete over a cube of 2^(treeHeight-1) bricks per side; nodes outside
//! the volume reference the all-L brick. All offsets are u32, so a VOD 1 file is at most 4 GiB.

use super::codec;
use super::pyramid::{BrickSource, FirstError};
use super::vod2::Snapshot;
use super::StoreError;
use isovox_proto::vod2::{content_hash, Fields, SIGNATURE};
use isovox_proto::{BrickKey, FormatError, VolumeLayout, VoxelType};
use std::collections::HashMap;
use std::io::Write;

/// Bytes of the fixed header.
pub const HEADER_LEN: usize = 64;
const FLAG_COMPRESSED: u32 = 1 << 0;
const FLAG_PADDING: u32 = 1 << 1;
const FLAG_FLOAT: u32 = 1 << 2;

/// Nodes of a complete octree with `height` levels: (8^height - 1) / 7.
/// Saturates at `u64::MAX` for heights no file can hold.
pub fn node_count(height: u32) -> u64 {
    if height >= 21 {
        return u64::MAX;
    }
    ((1u64 << (3 * height)) - 1) / 7
}

/// Preorder index of the node at `key` in a complete octree of `height` levels (level 0 = the
/// deepest, at depth height - 1).
pub fn preorder_index(height: u32, key: BrickKey) -> u64 {
    let depth = height - 1 - key.level as u32;
    let mut index = 0u64;
    for d in 1..=depth {
        let shift = depth - d;
        let octant =
            ((key.x >> shift) & 1) | (((key.y >> shift) & 1) << 1) | (((key.z >> shift) & 1) << 2);
        index += 1 + octant as u64 * node_count(height - d);
    }
    index
}

/// Every node of the complete octree, in preorder, as the key it would have at its level.
fn preorder_keys(height: u32) -> Vec<BrickKey> {
    let mut out = Vec::with_capacity(node_count(height) as usize);
    fn visit(out: &mut Vec<BrickKey>, height: u32, key: BrickKey) {
        out.push(key);
        if key.level == 0 {
            return;
        }
        let _ = height;
        for octant in 0..8u32 {
            visit(
                out,
                height,
                BrickKey {
                    level: key.level - 1,
                    x: key.x * 2 + (octant & 1),
                    y: key.y * 2 + (octant >> 1 & 1),
                    z: key.z * 2 + (octant >> 2),
                },
            );
        }
    }
    visit(
        &mut out,
        height,
        BrickKey {
            level: (height - 1) as u8,
            x: 0,
            y: 0,
            z: 0,
        },
    );
    out
}

/// Writes `snap` (every level) as a VOD 1 file; returns the bytes written.
///
/// # Errors
/// A brick is corrupt, the result would exceed VOD 1's 4 GiB offsets, or writing fails.
pub fn write_vod1(snap: &Snapshot, compress: bool, out: &mut dyn Write) -> Result<u64, StoreError> {
    let layout = snap.layout();
    let height = layout.levels() as u32;
    let keys = preorder_keys(height);
    let mut ids: HashMap<u64, Vec<u32>> = HashMap::new();
    let mut bricks: Vec<(u64, Vec<u8>)> = Vec::new(); // (hash, payload), id = index + 1
    let mut nodes = Vec::with_capacity(keys.len());
    let mut decoded = vec![0u8; layout.brick_bytes()];
    let mut other = vec![0u8; layout.brick_bytes()];
    for key in keys {
        if layout.contains(key) {
            snap.read_into(key, &mut decoded)?;
        } else {
            decoded.fill(0);
        }
        let hash = content_hash(&decoded);
        let mut found = None;
        for &id in ids.get(&hash).into_iter().flatten() {
            decode_payload(&bricks[id as usize - 1].1, compress, &mut other, 0)?;
            if other == decoded {
                found = Some(id);
                break;
            }
        }
        let id = match found {
            Some(id) => id,
            None => {
                let payload = if compress {
                    lz4_flex::block::compress(&decoded)
                } else {
                    decoded.clone()
                };
                bricks.push((hash, payload));
                let id = bricks.len() as u32;
                ids.entry(hash).or_default().push(id);
                id
            }
        };
        nodes.push(id);
    }
    let table_at = HEADER_LEN as u64 + 4 * nodes.len() as u64 + 4;
    let mut offset = table_at + 16 * bricks.len() as u64;
    let total = offset + bricks.iter().map(|(_, p)| 4 + p.len() as u64).sum::<u64>();
    if total > u32::MAX as u64 {
        return Err(StoreError::BadInput(format!(
            "a VOD 1 file of this volume would take {total} bytes; VOD 1's u32 offsets stop at 4 GiB (use VOD 2)"
        )));
    }
    let mut buf = Vec::with_capacity(total as usize);
    buf.extend_from_slice(&SIGNATURE);
    buf.extend_from_slice(&1u32.to_le_bytes());
    for d in layout.dims() {
        buf.extend_from_slice(&d.to_le_bytes());
    }
    for _ in 0..3 {
        buf.extend_from_slice(&layout.brick().to_le_bytes());
    }
    for s in snap.header().voxel_scale {
        buf.extend_from_slice(&s.to_le_bytes());
    }
    buf.extend_from_slice(&height.to_le_bytes());
    buf.extend_from_slice(&layout.voxel_type().bits().to_le_bytes());
    buf.extend_from_slice(b"XH64");
    buf.extend_from_slice(if compress { b"LZ4B" } else { b"NONE" });
    let flags = FLAG_PADDING | if compress { FLAG_COMPRESSED } else { 0 };
    buf.extend_from_slice(&flags.to_le_bytes());
    for id in &nodes {
        buf.extend_from_slice(&id.to_le_bytes());
    }
    buf.extend_from_slice(&(bricks.len() as u32).to_le_bytes());
    for (i, (hash, payload)) in bricks.iter().enumerate() {
        buf.extend_from_slice(&(i as u32 + 1).to_le_bytes());
        buf.extend_from_slice(&(offset as u32).to_le_bytes());
        buf.extend_from_slice(&hash.to_le_bytes());
        offset += 4 + payload.len() as u64;
    }
    for (_, payload) in &bricks {
        buf.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        buf.extend_from_slice(payload);
    }
    out.write_all(&buf)
        .map_err(StoreError::io("cannot write the VOD 1 file"))?;
    Ok(buf.len() as u64)
}

fn decode_payload(
    payload: &[u8],
    compressed: bool,
    out: &mut [u8],
    offset: u64,
) -> Result<(), StoreError> {
    let codec = if compressed {
        isovox_proto::vod2::Codec::Lz4
    } else {
        isovox_proto::vod2::Codec::Raw
    };
    codec::decode(codec, payload, out, offset)
}

/// A VOD 1 file on disk, mapped: [`Vod1File::parse`] reads it (the parsed view borrows the
/// mapping).
#[derive(Debug)]
pub struct Vod1File {
    map: super::mapping::Mapping,
}

impl Vod1File {
    /// Maps the file at `path`.
    ///
    /// # Errors
    /// The file cannot be opened or mapped.
    pub fn open(path: &std::path::Path) -> Result<Vod1File, StoreError> {
        let file = std::fs::File::open(path).map_err(StoreError::io_path("cannot open", path))?;
        let len = file
            .metadata()
            .map_err(StoreError::io_path("cannot stat", path))?
            .len();
        let map = super::mapping::Mapping::new(&file, len)
            .map_err(StoreError::io_path("cannot map", path))?;
        Ok(Vod1File { map })
    }

    /// The file's length in bytes.
    pub fn len(&self) -> u64 {
        self.map.bytes().len() as u64
    }

    /// Whether the file is empty.
    pub fn is_empty(&self) -> bool {
        self.map.bytes().is_empty()
    }

    /// Parses the header and node table.
    ///
    /// # Errors
    /// The file is not a valid VOD 1 file.
    pub fn parse(&self) -> Result<Vod1<'_>, StoreError> {
        Vod1::parse(self.map.bytes())
    }
}

/// A parsed VOD 1 file (over its bytes, which it borrows).
#[derive(Debug)]
pub struct Vod1<'a> {
    bytes: &'a [u8],
    /// Dimensions, brick edge and voxel type.
    pub layout: VolumeLayout,
    /// World size of one voxel.
    pub voxel_scale: [f32; 3],
    /// Levels of the complete octree.
    pub height: u32,
    compressed: bool,
    hash_width: usize,
    nodes_at: usize,
    /// brickID -> (offset of its dataSize field, stored hash)
    bricks: HashMap<u32, (u64, u64)>,
}

impl<'a> Vod1<'a> {
    /// Parses and validates the header, node array and brick table.
    ///
    /// # Errors
    /// Anything malformed: signature, version, unsupported algorithms, a tree height that does
    /// not match the volume, counts the file cannot hold, offsets outside the file.
    pub fn parse(bytes: &'a [u8]) -> Result<Self, StoreError> {
        let f = Fields::new("VOD 1 header", bytes, 0);
        f.magic(0, SIGNATURE)?;
        let version = f.u32(4)?;
        if version != 1 {
            return Err(FormatError::Unsupported {
                what: "VOD 1 file version",
                detail: version.to_string(),
            }
            .into());
        }
        let dims = [f.u32(8)?, f.u32(12)?, f.u32(16)?];
        let brick = [f.u32(20)?, f.u32(24)?, f.u32(28)?];
        if brick[0] != brick[1] || brick[1] != brick[2] {
            return Err(FormatError::Unsupported {
                what: "brick size",
                detail: format!("{brick:?} (Isovox bricks are cubes)"),
            }
            .into());
        }
        let voxel_scale = [f.f32(32)?, f.f32(36)?, f.f32(40)?];
        let height = f.u32(44)?;
        let bits = f.u32(48)?;
        let flags = f.u32(60)?;
        if flags & FLAG_FLOAT != 0 {
            return Err(FormatError::Unsupported {
                what: "voxel data",
                detail: "float voxels".into(),
            }
            .into());
        }
        let voxel_type = VoxelType::from_bits(bits).ok_or_else(|| FormatError::Unsupported {
            what: "voxel size",
            detail: format!("{bits} bits"),
        })?;
        let layout = VolumeLayout::new(dims, brick[0], voxel_type)?;
        if height != layout.levels() as u32 {
            return Err(FormatError::invalid(
                "VOD 1 header",
                format!(
                    "tree height {height}, but the volume's octree has {} levels",
                    layout.levels()
                ),
            )
            .into());
        }
        let hash_width = match &f.fourcc(52)? {
            b"XH64" => 8,
            b"XH32" => 4,
            other => {
                return Err(FormatError::Unsupported {
                    what: "hash algorithm",
                    detail: String::from_utf8_lossy(other).into(),
                }
                .into())
            }
        };
        let compressed = match (&f.fourcc(56)?, flags & FLAG_COMPRESSED != 0) {
            (b"LZ4B", true) => true,
            (_, false) => false,
            (other, true) => {
                return Err(FormatError::Unsupported {
                    what: "compression",
                    detail: String::from_utf8_lossy(other).into(),
                }
                .into())
            }
        };
        let n_nodes = node_count(height);
        let nodes_at = HEADER_LEN;
        // Bounds before any allocation: the node array and the table must fit in the file.
        f.slice(
            nodes_at,
            n_nodes.saturating_mul(4).min(bytes.len() as u64 + 1) as usize,
        )?;
        let count_at = nodes_at + n_nodes as usize * 4; // fits: the slice above exists
        let n_bricks = f.u32(count_at)? as usize;
        let entry_len = 8 + hash_width;
        let table = f.slice(
            count_at + 4,
            n_bricks.saturating_mul(entry_len).min(bytes.len() + 1),
        )?;
        let mut bricks = HashMap::with_capacity(n_bricks);
        for e in table.chunks_exact(entry_len) {
            let t = Fields::new("VOD 1 brick table", e, 0);
            let id = t.u32(0)?;
            let offset = t.u32(4)? as u64;
            let hash = if hash_width == 8 {
                t.u64(8)?
            } else {
                t.u32(8)? as u64
            };
            let size = f.u32(offset as usize)?;
            f.slice(offset as usize + 4, size as usize)?;
            if id == 0 || bricks.insert(id, (offset, hash)).is_some() {
                return Err(FormatError::invalid(
                    "VOD 1 brick table",
                    format!("brick ID {id} is zero or listed twice"),
                )
                .into());
            }
        }
        Ok(Vod1 {
            bytes,
            layout,
            voxel_scale,
            height,
            compressed,
            hash_width,
            nodes_at,
            bricks,
        })
    }

    /// Number of distinct bricks stored.
    pub fn unique_bricks(&self) -> usize {
        self.bricks.len()
    }

    /// Decodes the brick of a node of the volume into `out`, checking its hash.
    ///
    /// # Errors
    /// The node names an unknown brick, or its payload is corrupt.
    pub fn read_into(&self, key: BrickKey, out: &mut [u8]) -> Result<(), StoreError> {
        let node = preorder_index(self.height, key) as usize;
        let f = Fields::new("VOD 1 node array", self.bytes, 0);
        let id = f.u32(self.nodes_at + node * 4)?;
        if id == 0 {
            out.fill(0);
            return Ok(());
        }
        let &(offset, hash) = self.bricks.get(&id).ok_or_else(|| {
            FormatError::invalid(
                "VOD 1 node array",
                format!("node {node} names unknown brick {id}"),
            )
        })?;
        let size = f.u32(offset as usize)? as usize;
        let payload = f.slice(offset as usize + 4, size)?;
        decode_payload(payload, self.compressed, out, offset)?;
        let computed = content_hash(out);
        let computed = if self.hash_width == 8 {
            computed
        } else {
            computed & 0xffff_ffff
        };
        if computed != hash {
            return Err(StoreError::corrupt(
                offset,
                format!("VOD 1 brick {id} with hash {hash:#x}"),
                format!("hash {computed:#x}"),
            ));
        }
        Ok(())
    }
}

/// A VOD 1 file's level 0 as the source of a VOD 2 build. Decoding errors are remembered and
/// reported by [`Vod1Source::finish`] (a source cannot fail mid-build).
#[derive(Debug)]
pub struct Vod1Source<'a> {
    /// The file read.
    pub vod1: &'a Vod1<'a>,
    errors: FirstError,
}

impl<'a> Vod1Source<'a> {
    /// A source reading `vod1`'s level 0.
    pub fn new(vod1: &'a Vod1<'a>) -> Self {
        Vod1Source {
            vod1,
            errors: FirstError::default(),
        }
    }

    /// # Errors
    /// The first brick that failed to decode during the build.
    pub fn finish(self) -> Result<(), StoreError> {
        self.errors.finish()
    }
}

impl BrickSource for Vod1Source<'_> {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        if let Err(e) = self.vod1.read_into(key, out) {
            self.errors.record(e);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_counts_match_the_thesis_formula() {
        assert_eq!(node_count(1), 1);
        assert_eq!(node_count(2), 9);
        assert_eq!(node_count(6), 37449);
    }

    #[test]
    fn preorder_index_agrees_with_traversal() {
        for height in 1..5 {
            for (i, key) in preorder_keys(height).into_iter().enumerate() {
                assert_eq!(
                    preorder_index(height, key),
                    i as u64,
                    "height {height} key {key}"
                );
            }
        }
        // Hand-computed, height 3: root 0; its child octant 1 (x=1) at 1 + 1*9 = 10; that node's
        // child octant 2 (y=1): 10 + 1 + 2*1 = 13, which is level-0 brick (2, 1, 0).
        assert_eq!(
            preorder_index(
                3,
                BrickKey {
                    level: 1,
                    x: 1,
                    y: 0,
                    z: 0
                }
            ),
            10
        );
        assert_eq!(
            preorder_index(
                3,
                BrickKey {
                    level: 0,
                    x: 2,
                    y: 1,
                    z: 0
                }
            ),
            13
        );
    }
}
