//! What the two views share: resolving a path of a view to a document of a snapshot, the
//! documents' bodies, and the errors a request for one can meet.
//!
//! A view is a projection of one [`Snapshot`], never a copy: its metadata is computed from the
//! layout and voxel scale, its chunks are bricks (the brick edge is the chunk edge), either as
//! the stored zstd frame itself or decoded. The same functions answer HTTP requests and write
//! exports, so an exported tree holds exactly the bytes the server sends.
//!
//! What a chunk is made from is kept in the process's one cache of decoded bricks
//! ([`DecodedBricks`], by content hash): the decoded voxels (shared with brick bodies and
//! meshing) and the zstd frames made from them. Most bricks of a sparse volume are constant and
//! share one content hash per value, so their chunks are compressed once.

use crate::store::decoded::{DecodedBricks, Form};
use crate::store::{Snapshot, StoreError, StoredBrick};
use crate::volume::{LiveVolume, VolumeError};
use bytes::Bytes;
use isovox_proto::vod2::Codec;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
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

/// Why a document of a view was not answered. The HTTP layer decides the status of each
/// variant (`http/error.rs`); this type says only what happened.
#[derive(Debug, Error)]
pub enum ViewError {
    /// The path names no document of the view (wrong shape, a level or chunk outside the
    /// volume).
    #[error("{0}")]
    NoSuchDocument(String),
    /// The path has the shape of a chunk, but its range is not a chunk's (misaligned, or
    /// ending elsewhere than the chunk does).
    #[error("{0}")]
    NotAChunk(String),
    /// A Zarr chunk whose every voxel is the fill value: Zarr clients read a missing chunk as
    /// the fill value, so it is answered as missing.
    #[error(
        "chunk {0} holds only the fill value 0 (Zarr reads a missing chunk as the fill value)"
    )]
    FillValue(String),
    /// A pinned version that compaction removed from the file.
    #[error("version {version} was compacted away; the oldest version kept is {oldest}")]
    Compacted {
        /// The version asked for.
        version: u64,
        /// The oldest version the file holds.
        oldest: u64,
    },
    /// The volume cannot answer (a version it never had, a damaged file).
    #[error(transparent)]
    Volume(#[from] VolumeError),
}

impl From<StoreError> for ViewError {
    fn from(e: StoreError) -> Self {
        ViewError::Volume(e.into())
    }
}

/// What a path of a view resolves to.
#[derive(Debug)]
pub enum Document<'s> {
    /// A JSON metadata document.
    Metadata(Vec<u8>),
    /// A chunk, made from one brick.
    Chunk(Chunk<'s>),
    /// A chunk whose every voxel is the fill value (see [`ViewError::FillValue`]); left out of
    /// exports.
    Absent,
}

/// A chunk of a view: the brick it is made from and how.
#[derive(Debug)]
pub struct Chunk<'s> {
    /// The brick.
    pub key: BrickKey,
    /// The brick as the file holds it.
    pub stored: StoredBrick<'s>,
    /// How the chunk's bytes are made from it.
    pub encoding: ChunkEncoding,
    /// The attribute channel's view the brick is read from, when it is a channel's (the
    /// snapshot resolved is then that view).
    pub view: Option<&'s Arc<Snapshot>>,
}

/// How a chunk's bytes are made from its brick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChunkEncoding {
    /// A zstd frame of the whole brick (Zarr's `bytes` + `zstd` codecs): the stored frame as it
    /// is when it qualifies, else compressed on request.
    ZstdFrame,
    /// The decoded voxels, cropped to this extent (x, y, z) when it is smaller than the brick
    /// (precomputed's edge chunks).
    Raw {
        /// Voxels kept per axis.
        extent: [u32; 3],
    },
    /// The decoded values cropped to this extent, as uint32 labels in Neuroglancer's
    /// `compressed_segmentation` (a channel's chunks in the precomputed view).
    CompressedSegmentation {
        /// Voxels kept per axis.
        extent: [u32; 3],
    },
}

/// The zstd level of frames made on request (stored frames keep the level they were written
/// with; decoders do not need to know it).
pub const ZSTD_LEVEL: i32 = 3;

impl Chunk<'_> {
    /// The chunk's bytes, made through `bricks` (the decoded voxels and the zstd frames made
    /// from them are kept there by content hash, beside every other reader's).
    ///
    /// # Errors
    /// The brick does not decode (the file is damaged).
    pub fn body(&self, snap: &Snapshot, bricks: &DecodedBricks) -> Result<Bytes, StoreError> {
        let layout = snap.layout();
        let hash = self.stored.content_hash(layout);
        match self.encoding {
            ChunkEncoding::ZstdFrame => {
                if let Some(frame) = self.stored_frame(snap, bricks)? {
                    return Ok(frame);
                }
                bricks.get_or_make(hash, layout.brick_bytes(), Form::Zstd, || {
                    compress_frame(&bricks.voxels(hash, &self.stored, layout)?)
                })
            }
            ChunkEncoding::Raw { extent } => {
                Ok(self.crop(layout, extent, bricks.voxels(hash, &self.stored, layout)?))
            }
            ChunkEncoding::CompressedSegmentation { extent } => {
                let voxels = self.crop(layout, extent, bricks.voxels(hash, &self.stored, layout)?);
                let t = layout.voxel_type();
                let labels: Vec<u64> = (0..voxels.len() / t.bytes())
                    .map(|i| isovox_proto::voxel::value_at(&voxels, t, i))
                    .collect();
                let wide = t == VoxelType::U64;
                Ok(super::compressed_segmentation::encode_chunk(&labels, extent, wide).into())
            }
        }
    }

    /// The chunk's bytes if they need no work: the stored frame (checked against its checksum),
    /// or a body `bricks` holds.
    ///
    /// # Errors
    /// The brick's record is damaged.
    pub fn ready_body(
        &self,
        snap: &Snapshot,
        bricks: &DecodedBricks,
    ) -> Result<Option<Bytes>, StoreError> {
        let layout = snap.layout();
        let hash = self.stored.content_hash(layout);
        Ok(match self.encoding {
            ChunkEncoding::ZstdFrame => match self.stored_frame(snap, bricks)? {
                Some(frame) => Some(frame),
                None => bricks.get(hash, layout.brick_bytes(), Form::Zstd),
            },
            ChunkEncoding::Raw { extent } => bricks
                .get(hash, layout.brick_bytes(), Form::Raw)
                .map(|voxels| self.crop(layout, extent, voxels)),
            // Encoded on the CPU queue, not here.
            ChunkEncoding::CompressedSegmentation { .. } => None,
        })
    }

    /// The stored zstd frame, when the brick is stored as one that can go out as it is,
    /// verified first (against its checksum, or for a record without one by decoding it once:
    /// see `Snapshot::verified_payload`).
    fn stored_frame(
        &self,
        snap: &Snapshot,
        bricks: &DecodedBricks,
    ) -> Result<Option<Bytes>, StoreError> {
        match self.stored {
            StoredBrick::Record {
                header, payload, ..
            } if header.codec == Codec::Zstd
                && frame_qualifies(payload, snap.layout().brick_bytes()) =>
            {
                snap.verified_payload(&self.stored, bricks).map(Some)
            }
            _ => Ok(None),
        }
    }

    /// `voxels` cropped to `extent` (shared as they are when it is the whole brick).
    fn crop(&self, layout: &VolumeLayout, extent: [u32; 3], voxels: Bytes) -> Bytes {
        let b = layout.brick();
        if extent == [b; 3] {
            return voxels;
        }
        crop(&voxels, b, extent, layout.voxel_type().bytes()).into()
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

/// A document of a view, answered.
#[derive(Debug)]
pub struct ViewAnswer {
    /// The version read.
    pub version: u64,
    /// The document.
    pub body: ViewBody,
}

/// The body of a view's document.
#[derive(Debug)]
pub enum ViewBody {
    /// A JSON metadata document.
    Json(Bytes),
    /// A chunk.
    Chunk(Bytes),
    /// A Zarr chunk of fill values only, left out (see [`ViewError::FillValue`]).
    Absent,
}

/// A checked read of a document of a view: its answer, or a chunk that must be made first
/// (decoded, compressed: CPU work the caller runs where it wants, with [`MakeChunk::run`]).
#[derive(Debug)]
pub enum ViewRead {
    /// The answer, which took no work (metadata, a stored frame, a body the cache held).
    Ready(ViewAnswer),
    /// A chunk to make.
    Make(MakeChunk),
}

/// A chunk of a view that is not ready (see [`ViewRead::Make`]).
#[derive(Debug)]
pub struct MakeChunk {
    snap: Arc<Snapshot>,
    key: BrickKey,
    encoding: ChunkEncoding,
}

impl MakeChunk {
    /// Makes the chunk, keeping what it decodes and compresses in `bricks`.
    ///
    /// # Errors
    /// The brick does not decode (the file is damaged).
    pub fn run(self, bricks: &DecodedBricks) -> Result<ViewAnswer, ViewError> {
        let chunk = Chunk {
            key: self.key,
            stored: self.snap.stored(self.key)?,
            encoding: self.encoding,
            view: None,
        };
        Ok(ViewAnswer {
            version: self.snap.version,
            body: ViewBody::Chunk(chunk.body(&self.snap, bricks)?),
        })
    }
}

/// Version `version` of `volume`, for a pinned view.
///
/// # Errors
/// [`ViewError::Compacted`] for a version compaction removed; a version the volume never had.
pub fn pinned_snapshot(volume: &LiveVolume, version: u64) -> Result<Arc<Snapshot>, ViewError> {
    match volume.version(version) {
        Err(VolumeError::NoSuchVersion { oldest, .. }) if version > 0 && version < oldest => {
            Err(ViewError::Compacted { version, oldest })
        }
        other => Ok(other?),
    }
}

/// Checks a read of `path` of view `kind` of `volume` at `version` (the head when `None`) and
/// answers it at once when that takes no work (`bricks` is asked for bodies it holds).
///
/// # Errors
/// See [`pinned_snapshot`] and [`resolve`].
pub fn read(
    volume: &LiveVolume,
    kind: ViewKind,
    version: Option<u64>,
    path: &str,
    bricks: &DecodedBricks,
) -> Result<ViewRead, ViewError> {
    match version {
        // The head is borrowed from the volume's current file: no reference count touched (one
        // shared by every core serving chunks is a cache line they would fight over).
        None => {
            let vod = volume.load();
            read_snapshot(
                vod.head_ref(),
                || vod.head(),
                volume.name(),
                kind,
                path,
                bricks,
            )
        }
        Some(v) => {
            let snap = pinned_snapshot(volume, v)?;
            read_snapshot(&snap, || snap.clone(), volume.name(), kind, path, bricks)
        }
    }
}

fn read_snapshot(
    snap: &Snapshot,
    shared: impl FnOnce() -> Arc<Snapshot>,
    name: &str,
    kind: ViewKind,
    path: &str,
    bricks: &DecodedBricks,
) -> Result<ViewRead, ViewError> {
    let body = match resolve(kind, snap, name, path)? {
        Document::Metadata(json) => ViewBody::Json(json.into()),
        Document::Absent => ViewBody::Absent,
        // A channel's chunk is read through the channel's view (its layout has the channel's type).
        Document::Chunk(chunk) => {
            match chunk.ready_body(chunk.view.map_or(snap, |v| &**v), bricks)? {
                Some(body) => ViewBody::Chunk(body),
                None => {
                    return Ok(ViewRead::Make(MakeChunk {
                        snap: chunk.view.cloned().unwrap_or_else(shared),
                        key: chunk.key,
                        encoding: chunk.encoding,
                    }))
                }
            }
        }
    };
    Ok(ViewRead::Ready(ViewAnswer {
        version: snap.version,
        body,
    }))
}

/// Resolves `path` (relative to the view's root, no leading slash) of view `kind` of `snap`.
///
/// # Errors
/// The path names nothing in the view ([`ViewError::NoSuchDocument`]), is not a chunk's
/// ([`ViewError::NotAChunk`]), or the brick's record is damaged.
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

/// The level a path segment (as sent: see [`crate::decimal`]) names, if the volume has it.
pub(crate) fn level_segment(snap: &Snapshot, segment: &str) -> Result<u8, ViewError> {
    let levels = snap.layout().levels();
    crate::decimal::parse::<u8>(segment)
        .ok()
        .filter(|l| *l < levels)
        .ok_or_else(|| {
            ViewError::NoSuchDocument(format!(
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
