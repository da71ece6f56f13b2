//! What the two views share: resolving a path of a view to a document of a snapshot, the
//! documents' bodies, and the errors a request for one can meet.
//!
//! A view is a projection of one [`Snapshot`], never a copy: its metadata is computed from the
//! layout and voxel scale, its chunks are bricks (the brick edge is the chunk edge), either as
//! the stored zstd frame itself or decoded. The same functions answer HTTP requests and write
//! exports, so an exported tree holds exactly the bytes the server sends.

use crate::store::lru::ByteLru;
use crate::store::{Snapshot, StoreError, StoredBrick};
use crate::volume::LiveVolume;
use bytes::Bytes;
use isovox_proto::BrickKey;
use std::sync::Arc;
use thiserror::Error;

/// The two views.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ViewKind {
    /// OME-Zarr 0.5 on Zarr v3 (`formats::zarr`).
    Zarr,
    /// Neuroglancer precomputed (`formats::precomputed`).
    Precomputed,
}

impl ViewKind {
    /// The path segment the view lives under (`/v1/volumes/{name}/{segment}/`).
    pub fn segment(self) -> &'static str {
        match self {
            ViewKind::Zarr => "zarr",
            ViewKind::Precomputed => "precomputed",
        }
    }
}

/// Why a path of a view names nothing.
#[derive(Debug, Error)]
pub enum ViewError {
    /// The path is not one the view has (wrong shape, a level or chunk outside the volume).
    #[error("{0}")]
    NotFound(String),
    /// The path has the view's shape but is malformed (a misaligned chunk range).
    #[error("{0}")]
    BadRequest(String),
    /// A pinned version that compaction removed from the file.
    #[error("{0}")]
    Gone(String),
    /// Reading the brick failed: the file is damaged.
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// What a path of a view resolves to.
#[derive(Debug)]
pub enum Document<'s> {
    /// A JSON metadata document.
    Metadata(Vec<u8>),
    /// A chunk, made from one brick.
    Chunk(Chunk<'s>),
    /// A chunk whose every voxel is the fill value: Zarr clients read a missing chunk as the
    /// fill value, so it is answered 404 (and left out of exports).
    Absent,
}

/// A chunk of a view: the brick it is made from and how.
#[derive(Debug)]
pub struct Chunk<'s> {
    pub key: BrickKey,
    pub stored: StoredBrick<'s>,
    pub encoding: ChunkEncoding,
}

/// How a chunk's bytes are made from its brick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChunkEncoding {
    /// A zstd frame of the whole brick (Zarr's `bytes` + `zstd` codecs): the stored frame as it
    /// is when it qualifies, else compressed on request.
    ZstdFrame,
    /// The decoded voxels, cropped to this extent (x, y, z) when it is smaller than the brick
    /// (precomputed's edge chunks).
    Raw { extent: [u32; 3] },
}

/// Representations made from a brick's content, which a server keeps between requests.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodyKind {
    /// The decoded voxels.
    Decoded = 0,
    /// A zstd frame of the decoded voxels, made here.
    Zstd = 1,
    /// A constant brick's voxels; keyed by [`constant_key`], not a content hash.
    ConstantDecoded = 2,
    /// A zstd frame of a constant brick; keyed by [`constant_key`].
    ConstantZstd = 3,
}

/// The key of a constant brick's bodies: its value and its size in bytes, which together
/// determine its voxels (brick edges are powers of two, so a u8 and a u16 brick never have the
/// same size). Most bricks of a sparse volume are constant: making their bodies once saves a
/// fill and a compression of a whole brick per request.
pub fn constant_key(value: u16, brick_bytes: usize) -> u64 {
    u64::from(value) | ((brick_bytes as u64) << 16)
}

/// Where bodies made from a brick's content (keyed by its content hash) are kept: the server's
/// body cache, or nothing ([`NoMemo`]) for exports, which make each body once.
pub trait BodyMemo {
    /// The body of `kind` for content `hash`, made by `make` when not kept.
    ///
    /// # Errors
    /// Whatever `make` fails with.
    fn get_or_make(
        &self,
        hash: u64,
        kind: BodyKind,
        make: &mut dyn FnMut() -> Result<Bytes, StoreError>,
    ) -> Result<Bytes, StoreError>;
}

/// Bodies kept in memory, bounded by bytes, least recently used out first (the server's).
#[derive(Debug)]
pub struct ChunkCache {
    lru: ByteLru<Bytes>,
}

impl ChunkCache {
    pub fn new(capacity: usize) -> Self {
        ChunkCache {
            lru: ByteLru::new(capacity),
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.lru.bytes()
    }
}

impl BodyMemo for ChunkCache {
    fn get_or_make(
        &self,
        hash: u64,
        kind: BodyKind,
        make: &mut dyn FnMut() -> Result<Bytes, StoreError>,
    ) -> Result<Bytes, StoreError> {
        // A content hash is uniform in its low bits (they pick the shard); a constant's key is
        // not, so it is hashed first. The kind goes on top.
        let spread = match kind {
            BodyKind::ConstantDecoded | BodyKind::ConstantZstd => {
                xxhash_rust::xxh3::xxh3_64(&hash.to_le_bytes())
            }
            BodyKind::Decoded | BodyKind::Zstd => hash,
        };
        let key = u128::from(spread) | ((kind as u128) << 64);
        if let Some(body) = self.lru.get(key) {
            return Ok((*body).clone());
        }
        let body = make()?;
        self.lru.put(key, Arc::new(body.clone()), body.len());
        Ok(body)
    }
}

/// Keeps nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoMemo;

impl BodyMemo for NoMemo {
    fn get_or_make(
        &self,
        _: u64,
        _: BodyKind,
        make: &mut dyn FnMut() -> Result<Bytes, StoreError>,
    ) -> Result<Bytes, StoreError> {
        make()
    }
}

/// The zstd level of frames made on request (stored frames keep the level they were written
/// with; decoders do not need to know it).
pub const ZSTD_LEVEL: i32 = 3;

impl Chunk<'_> {
    /// The chunk's bytes.
    ///
    /// # Errors
    /// The brick does not decode (the file is damaged).
    pub fn body(&self, snap: &Snapshot, memo: &dyn BodyMemo) -> Result<Bytes, StoreError> {
        let layout = snap.layout();
        match (self.encoding, self.stored) {
            (
                ChunkEncoding::ZstdFrame,
                StoredBrick::Record {
                    offset,
                    header,
                    payload,
                },
            ) if header.codec == isovox_proto::vod2::Codec::Zstd
                && frame_qualifies(payload, layout.brick_bytes()) =>
            {
                snap.payload_bytes(offset, &header)
            }
            (ChunkEncoding::ZstdFrame, StoredBrick::Record { header, .. }) => {
                memo.get_or_make(header.hash, BodyKind::Zstd, &mut || {
                    let voxels = self.decoded(snap, memo)?;
                    compress_frame(&voxels)
                })
            }
            (ChunkEncoding::ZstdFrame, StoredBrick::Constant(v)) => memo.get_or_make(
                constant_key(v, layout.brick_bytes()),
                BodyKind::ConstantZstd,
                &mut || compress_frame(&self.decoded(snap, memo)?),
            ),
            (ChunkEncoding::Raw { extent }, _) => {
                let voxels = self.decoded(snap, memo)?;
                let b = layout.brick();
                if extent == [b; 3] {
                    return Ok(voxels);
                }
                Ok(crop(&voxels, b, extent, layout.voxel_type().bytes()).into())
            }
        }
    }

    /// The brick's voxels (x fastest, u16 little endian).
    fn decoded(&self, snap: &Snapshot, memo: &dyn BodyMemo) -> Result<Bytes, StoreError> {
        let layout = snap.layout();
        match self.stored {
            StoredBrick::Constant(v) => memo.get_or_make(
                constant_key(v, layout.brick_bytes()),
                BodyKind::ConstantDecoded,
                &mut || {
                    let mut out = vec![0u8; layout.brick_bytes()];
                    crate::store::codec::fill_constant(&mut out, v, layout.voxel_type());
                    Ok(out.into())
                },
            ),
            StoredBrick::Record { header, .. } => {
                memo.get_or_make(header.hash, BodyKind::Decoded, &mut || {
                    let mut out = vec![0u8; layout.brick_bytes()];
                    crate::store::vod2::decode_stored(&self.stored, layout, &mut out)?;
                    Ok(out.into())
                })
            }
        }
    }
}

/// Whether a stored zstd frame can go out as a Zarr chunk as it is: exactly one frame, whose
/// header records its content size, equal to one brick. (Zarr's zstd codec hands the frame to
/// one-shot decoders, several of which size their output from that header field.)
pub fn frame_qualifies(frame: &[u8], brick_bytes: usize) -> bool {
    use zstd::zstd_safe;
    matches!(
        zstd_safe::get_frame_content_size(frame),
        Ok(Some(n)) if n == brick_bytes as u64
    ) && zstd_safe::find_frame_compressed_size(frame).is_ok_and(|n| n == frame.len())
}

/// One zstd frame of `voxels`, with its content size in the header.
fn compress_frame(voxels: &[u8]) -> Result<Bytes, StoreError> {
    zstd::bulk::compress(voxels, ZSTD_LEVEL)
        .map(Bytes::from)
        .map_err(|source| StoreError::Io {
            context: "cannot compress a chunk".into(),
            source,
        })
}

/// The first `extent` voxels per axis of a brick of edge `b` (x fastest), packed.
pub fn crop(voxels: &[u8], b: u32, extent: [u32; 3], voxel_bytes: usize) -> Vec<u8> {
    let [ex, ey, ez] = extent.map(|e| e as usize);
    let b = b as usize;
    let row = ex * voxel_bytes;
    let mut out = Vec::with_capacity(row * ey * ez);
    for z in 0..ez {
        for y in 0..ey {
            let at = (z * b + y) * b * voxel_bytes;
            out.extend_from_slice(&voxels[at..at + row]);
        }
    }
    out
}

/// What a request for a path of a view gets.
#[derive(Debug)]
pub struct ViewRead {
    /// The version read.
    pub version: u64,
    pub body: ViewBody,
}

/// The body of a view's document.
#[derive(Debug)]
pub enum ViewBody {
    /// A JSON metadata document.
    Json(Bytes),
    /// A chunk.
    Chunk(Bytes),
    /// A chunk of fill values only, left out (Zarr).
    Absent,
}

/// The snapshot a view of `volume` reads: `version`, or the head when `None`.
///
/// # Errors
/// A version after the head ([`ViewError::NotFound`]) or compacted away ([`ViewError::Gone`]).
pub fn snapshot(volume: &LiveVolume, version: Option<u64>) -> Result<Arc<Snapshot>, ViewError> {
    let head = volume.head();
    let Some(v) = version else {
        return Ok(head);
    };
    if v > head.version || v == 0 {
        return Err(ViewError::NotFound(format!(
            "version {v} does not exist: {:?} is at version {}",
            volume.name(),
            head.version
        )));
    }
    if v < volume.oldest() {
        return Err(ViewError::Gone(format!(
            "version {v} of {:?} was compacted away; the oldest kept is {}",
            volume.name(),
            volume.oldest()
        )));
    }
    Ok(volume.version(v)?)
}

/// Reads `path` of view `kind` of `volume` at `version` (the head when `None`).
///
/// # Errors
/// See [`snapshot`] and [`resolve`]; a chunk whose brick does not decode.
pub fn read(
    volume: &LiveVolume,
    kind: ViewKind,
    version: Option<u64>,
    path: &str,
    memo: &dyn BodyMemo,
) -> Result<ViewRead, ViewError> {
    match version {
        // The head is borrowed from the volume's current file: no reference count touched (one
        // shared by every core serving chunks is a cache line they would fight over).
        None => read_snapshot(volume.load().head_ref(), volume.name(), kind, path, memo),
        Some(_) => read_snapshot(
            &*snapshot(volume, version)?,
            volume.name(),
            kind,
            path,
            memo,
        ),
    }
}

fn read_snapshot(
    snap: &Snapshot,
    name: &str,
    kind: ViewKind,
    path: &str,
    memo: &dyn BodyMemo,
) -> Result<ViewRead, ViewError> {
    let body = match resolve(kind, snap, name, path)? {
        Document::Metadata(json) => ViewBody::Json(json.into()),
        Document::Chunk(chunk) => ViewBody::Chunk(chunk.body(snap, memo)?),
        Document::Absent => ViewBody::Absent,
    };
    Ok(ViewRead {
        version: snap.version,
        body,
    })
}

/// Resolves `path` (relative to the view's root, no leading slash) of view `kind` of `snap`.
///
/// # Errors
/// The path names nothing in the view ([`ViewError::NotFound`]), is malformed
/// ([`ViewError::BadRequest`]), or the brick's record is damaged.
pub fn resolve<'s>(
    kind: ViewKind,
    snap: &'s Snapshot,
    name: &str,
    path: &str,
) -> Result<Document<'s>, ViewError> {
    match kind {
        ViewKind::Zarr => super::zarr::document(snap, name, path),
        ViewKind::Precomputed => super::precomputed::document(snap, path),
    }
}

/// The level a path segment names, if the volume has it.
pub(crate) fn level_segment(snap: &Snapshot, segment: &str) -> Result<u8, ViewError> {
    let levels = snap.layout().levels();
    segment
        .parse::<u8>()
        .ok()
        .filter(|l| *l < levels && (segment == "0" || !segment.starts_with('0')))
        .ok_or_else(|| {
            ViewError::NotFound(format!(
                "no level {segment:?}: the volume has levels 0..{}",
                levels - 1
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crop_keeps_the_leading_corner() {
        // A 2^3 brick holding 0..8 (x fastest); the extent 1 x 2 x 1 keeps voxels 0 and 2.
        let voxels: Vec<u8> = (0..8).collect();
        assert_eq!(crop(&voxels, 2, [1, 2, 1], 1), vec![0, 2]);
        assert_eq!(crop(&voxels, 2, [2, 1, 2], 1), vec![0, 1, 4, 5]);
        // u16: two bytes per voxel.
        let wide: Vec<u8> = (0..16).collect();
        assert_eq!(crop(&wide, 2, [1, 1, 2], 2), vec![0, 1, 8, 9]);
    }

    #[test]
    fn frames_qualify_only_with_their_content_size() {
        let voxels = vec![7u8; 4096];
        let with_size = zstd::bulk::compress(&voxels, 3).unwrap();
        assert!(frame_qualifies(&with_size, 4096));
        assert!(!frame_qualifies(&with_size, 4095));
        // The same content written by a streaming encoder that does not know the size in
        // advance: its header has no content size.
        let mut streamed = Vec::new();
        {
            let mut enc = zstd::stream::write::Encoder::new(&mut streamed, 3).unwrap();
            std::io::Write::write_all(&mut enc, &voxels).unwrap();
            enc.finish().unwrap();
        }
        assert_eq!(
            zstd::zstd_safe::get_frame_content_size(&streamed).unwrap(),
            None
        );
        assert!(!frame_qualifies(&streamed, 4096));
        // Two frames back to back are not one chunk.
        let mut two = with_size.clone();
        two.extend_from_slice(&with_size);
        assert!(!frame_qualifies(&two, 4096));
        assert!(!frame_qualifies(b"not zstd", 4096));
    }
}
