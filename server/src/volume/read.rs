//! The reads a server answers beyond single bricks: many bricks at once, a whole level (or a
//! region of it), a mesh tile. Each is checked first (cheap: index lookups, no voxel decoded),
//! so a caller's mistake is told apart from a busy server, and run afterwards, off the async
//! runtime (decoding, encoding, meshing).

use super::{stream_of, LiveVolume, VolumeError};
use crate::geometry::Box3;
use crate::mesh::cache::MeshCache;
use crate::mesh::tile::{
    check_material_channel, iso_value, strip_inputs, strip_material_key, strip_to_world,
    tile_inputs, tile_material_key, tile_to_world, Stitching, StripInputs, TileInputs, TileScratch,
};
use crate::store::codec::constant_hash;
use crate::store::decoded::{decode, DecodedBricks};
use crate::store::raw::export_raw;
use crate::store::{Snapshot, StoredBrick};
use isovox_proto::api::{LevelBrick, LevelGrid};
use isovox_proto::batch::MAX_BATCH;
use isovox_proto::batch::{encode_batch, BatchCodec, BatchEncoding, BatchEntry, BatchRequest};
use isovox_proto::mesh::{Mesh, TileMesh};
use isovox_proto::vod2::Codec;
use isovox_proto::BrickKey;
use std::sync::Arc;

/// Most decoded bytes one batch or level answer may carry.
pub const MAX_RESPONSE_BYTES: usize = 64 << 20;

impl LiveVolume {
    /// Checks a batch request: at most [`MAX_BATCH`] keys, all in the volume, raw answers up
    /// to [`MAX_RESPONSE_BYTES`].
    ///
    /// # Errors
    /// [`VolumeError::TooLarge`], [`VolumeError::NoSuchVersion`], [`VolumeError::OutOfRange`].
    pub fn batch(
        &self,
        request: &BatchRequest,
        channel: Option<&str>,
    ) -> Result<BatchRead, VolumeError> {
        if request.keys.len() > MAX_BATCH {
            return Err(VolumeError::TooLarge(format!(
                "{} keys; a batch takes at most {MAX_BATCH}",
                request.keys.len()
            )));
        }
        let snap = self.snapshot_of(request.version, channel)?;
        let layout = snap.layout();
        if request.encoding == BatchEncoding::Raw
            && request.keys.len() * layout.brick_bytes() > MAX_RESPONSE_BYTES
        {
            return Err(VolumeError::TooLarge(format!(
                "{} raw bricks of {} bytes exceed {MAX_RESPONSE_BYTES} bytes; ask for fewer or for \"encoding\": \"stored\"",
                request.keys.len(),
                layout.brick_bytes()
            )));
        }
        let keys = request
            .keys
            .iter()
            .map(|&(l, x, y, z)| layout.key(l, x, y, z))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| VolumeError::OutOfRange(e.to_string()))?;
        Ok(BatchRead {
            snap,
            keys,
            encoding: request.encoding,
        })
    }

    /// Checks a level read: the level exists, the region (max exclusive; bricks for a grid,
    /// voxels for voxels; the whole level when `None`) lies in it, voxels up to
    /// [`MAX_RESPONSE_BYTES`]. A region with `max <= min` on an axis selects nothing: its
    /// answer is empty, as a slice `a[3:2]` is.
    ///
    /// # Errors
    /// [`VolumeError::NoSuchVersion`], [`VolumeError::OutOfRange`] (the level, or a region
    /// corner beyond it, as a brick beyond the grid), [`VolumeError::TooLarge`].
    pub fn level(
        &self,
        version: Option<u64>,
        channel: Option<&str>,
        level: u8,
        form: LevelForm,
        region: Option<([u64; 3], [u64; 3])>,
    ) -> Result<LevelRead, VolumeError> {
        let snap = self.snapshot_of(version, channel)?;
        let layout = snap.layout();
        if level >= layout.levels() {
            return Err(VolumeError::OutOfRange(format!(
                "level {level}: the volume has levels 0..{}",
                layout.levels() - 1
            )));
        }
        let extent = match form {
            LevelForm::Grid => layout.grid(level),
            LevelForm::Voxels => layout.level_dims(level),
        };
        let (min, max) = match region {
            None => ([0; 3], extent),
            Some((min, max)) => {
                if (0..3).any(|a| min[a].max(max[a]) > extent[a] as u64) {
                    return Err(VolumeError::OutOfRange(format!(
                        "region {min:?}..{max:?} reaches beyond level {level}'s {} {extent:?}",
                        if form == LevelForm::Grid {
                            "grid"
                        } else {
                            "voxels"
                        }
                    )));
                }
                // Within the extent, so within u32; an axis with max <= min selects nothing.
                let min = min.map(|c| c as u32);
                let max: [u32; 3] = std::array::from_fn(|a| (max[a] as u32).max(min[a]));
                (min, max)
            }
        };
        let count: u64 = (0..3).map(|a| (max[a] - min[a]) as u64).product();
        if form == LevelForm::Voxels
            && count * layout.voxel_type().bytes() as u64 > MAX_RESPONSE_BYTES as u64
        {
            return Err(VolumeError::TooLarge(format!(
                "{count} voxels exceed {MAX_RESPONSE_BYTES} bytes; ask for a region or a coarser level"
            )));
        }
        Ok(LevelRead {
            snap,
            level,
            form,
            min,
            max,
        })
    }

    /// The snapshot, tile key and iso value of a read of mesh tile `(level, x, y, z)` (or of
    /// one of its strips), checked, and the view of `channel` for per-vertex materials.
    #[allow(clippy::type_complexity)]
    fn mesh_read(
        &self,
        version: Option<u64>,
        (level, x, y, z): (u8, u32, u32, u32),
        iso: Option<f32>,
        channel: Option<&str>,
    ) -> Result<(Arc<Snapshot>, BrickKey, f32, Option<Arc<Snapshot>>), VolumeError> {
        let snap = self.snapshot(version)?;
        let channel = match channel {
            None => None,
            Some(name) => {
                let view = stream_of(snap.clone(), Some(name))?;
                check_material_channel(&view)
                    .map_err(|e| VolumeError::Unprocessable(format!("channel {name:?}: {e}")))?;
                Some(view)
            }
        };
        let key = snap
            .layout()
            .key(level, x, y, z)
            .map_err(|e| VolumeError::OutOfRange(e.to_string()))?;
        let iso = iso_value(iso, snap.layout().voxel_type()).map_err(VolumeError::BadRequest)?;
        Ok((snap, key, iso, channel))
    }

    /// Checks a mesh tile read and computes the tile's inputs (27 index lookups, no voxel
    /// decoded): enough to name the result before meshing it. With `channel`, the tile carries
    /// per-vertex materials from that u8 channel, and its inputs name the channel's bricks too.
    ///
    /// # Errors
    /// [`VolumeError::NoSuchVersion`], [`VolumeError::OutOfRange`] (also an unknown channel),
    /// an iso value outside the voxel type's [L, H] ([`VolumeError::BadRequest`]), a channel
    /// that is not u8 ([`VolumeError::Unprocessable`]), a brick header that does not read.
    pub fn mesh_tile(
        &self,
        version: Option<u64>,
        (level, x, y, z): (u8, u32, u32, u32),
        iso: Option<f32>,
        channel: Option<&str>,
    ) -> Result<TileRead, VolumeError> {
        let (snap, key, iso, channel) = self.mesh_read(version, (level, x, y, z), iso, channel)?;
        let inputs = tile_inputs(&snap, key, iso, Stitching::Moves)?;
        let channel = match channel {
            Some(view) => {
                let material_key = tile_material_key(&view, key, &inputs)?;
                Some((view, material_key))
            }
            None => None,
        };
        Ok(TileRead {
            snap,
            key,
            iso,
            inputs,
            channel,
        })
    }

    /// Checks a read of the transition strip of face `face` (0..6) of a mesh tile and computes
    /// its inputs (index lookups, no voxel decoded). A face that can never touch a coarser tile
    /// (the volume's boundary, the coarsest level) has an empty strip. With `channel`, as
    /// [`LiveVolume::mesh_tile`].
    ///
    /// # Errors
    /// As [`LiveVolume::mesh_tile`].
    pub fn mesh_strip(
        &self,
        version: Option<u64>,
        (level, x, y, z): (u8, u32, u32, u32),
        face: usize,
        iso: Option<f32>,
        channel: Option<&str>,
    ) -> Result<StripRead, VolumeError> {
        let (snap, key, iso, channel) = self.mesh_read(version, (level, x, y, z), iso, channel)?;
        let inputs = strip_inputs(&snap, key, face, iso)?;
        let channel = match channel {
            Some(view) => {
                let material_key = strip_material_key(&view, key, face, &inputs)?;
                Some((view, material_key))
            }
            None => None,
        };
        Ok(StripRead {
            snap,
            key,
            face,
            iso,
            inputs,
            channel,
        })
    }
}

/// A checked batch of bricks (see [`LiveVolume::batch`]).
#[derive(Debug)]
pub struct BatchRead {
    snap: Arc<Snapshot>,
    keys: Vec<BrickKey>,
    encoding: BatchEncoding,
}

impl BatchRead {
    /// At least the bytes [`BatchRead::encode`] answers with when that follows from the request
    /// alone (decoded bricks: their size and entry headers), else 0 (stored bricks: their
    /// payloads' size is known only once read).
    pub fn known_bytes(&self) -> usize {
        /// More than a batch's header and one entry's header take (`proto::batch`).
        const HEADERS: usize = 64;
        match self.encoding {
            BatchEncoding::Raw => self.keys.len() * (self.snap.layout().brick_bytes() + HEADERS),
            BatchEncoding::Stored => 0,
        }
    }

    /// The batch in its wire encoding (`proto::batch`): each brick as stored (its payload
    /// verified first, see [`DecodedBricks::verify_payload`]), or decoded (and checked).
    ///
    /// # Errors
    /// A brick fails to read, verify or decode.
    pub fn encode(self, verified: &DecodedBricks) -> Result<Vec<u8>, VolumeError> {
        let layout = self.snap.layout();
        let mut entries = Vec::with_capacity(self.keys.len());
        let raw_entry = |key, stored: &StoredBrick<'_>| -> Result<BatchEntry, VolumeError> {
            Ok(BatchEntry {
                key,
                codec: BatchCodec::Raw,
                hash: stored.content_hash(layout),
                payload: decode(stored, layout)?.to_vec(),
            })
        };
        for key in self.keys {
            let stored = self.snap.stored(key)?;
            let entry = match (self.encoding, stored) {
                (BatchEncoding::Stored, StoredBrick::Constant(v)) => BatchEntry {
                    key,
                    codec: BatchCodec::Constant,
                    hash: constant_hash(v, layout),
                    payload: isovox_proto::batch::constant_payload(v, layout.voxel_type()),
                },
                (
                    BatchEncoding::Stored,
                    StoredBrick::Record {
                        header, payload, ..
                    },
                ) => match sent_as_stored(header.codec) {
                    Some(codec) => BatchEntry {
                        key,
                        codec,
                        hash: header.hash,
                        payload: {
                            verified.verify_payload(&stored, layout)?;
                            payload.to_vec()
                        },
                    },
                    None => raw_entry(key, &stored)?,
                },
                (BatchEncoding::Raw, stored) => raw_entry(key, &stored)?,
            };
            entries.push(entry);
        }
        Ok(encode_batch(&entries))
    }
}

/// What a level read answers with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LevelForm {
    /// The brick grid: each brick's content hash and value range.
    Grid,
    /// The voxels as one array (x fastest).
    Voxels,
}

/// The answer to a level read.
#[derive(Debug)]
pub enum LevelAnswer {
    /// The brick grid.
    Grid(LevelGrid),
    /// The voxels.
    Voxels(Vec<u8>),
}

/// A checked level read (see [`LiveVolume::level`]).
#[derive(Debug)]
pub struct LevelRead {
    snap: Arc<Snapshot>,
    level: u8,
    form: LevelForm,
    min: [u32; 3],
    max: [u32; 3],
}

impl LevelRead {
    /// The bytes [`LevelRead::run`] answers with when that follows from the request alone
    /// (voxels), else 0 (a grid: its JSON's length is known once written).
    pub fn known_bytes(&self) -> usize {
        match self.form {
            LevelForm::Voxels => {
                (0..3)
                    .map(|a| (self.max[a] - self.min[a]) as usize)
                    .product::<usize>()
                    * self.snap.layout().voxel_type().bytes()
            }
            LevelForm::Grid => 0,
        }
    }

    /// A hash of everything the answer depends on: the version read (its number, commit time
    /// and commit record's offset, which tell versions of one volume apart even across a
    /// rewrite), the level, the form and the region. Equal tags, equal bytes; computed without
    /// reading a brick, so a revalidation costs no CPU job.
    pub fn tag(&self) -> u64 {
        let mut tag = Vec::with_capacity(64);
        for n in [
            self.snap.version,
            self.snap.timestamp_ms,
            self.snap.commit_offset(),
        ] {
            tag.extend_from_slice(&n.to_le_bytes());
        }
        tag.push(self.level);
        tag.push(self.form as u8);
        // Each stream of a version has its own answers.
        tag.push(self.snap.stream() as u8);
        for c in self.min.iter().chain(&self.max) {
            tag.extend_from_slice(&c.to_le_bytes());
        }
        xxhash_rust::xxh3::xxh3_64(&tag)
    }

    /// Reads the level's region.
    ///
    /// # Errors
    /// A brick fails to read or decode.
    pub fn run(self) -> Result<LevelAnswer, VolumeError> {
        let (snap, level, min, max) = (&self.snap, self.level, self.min, self.max);
        let layout = snap.layout();
        let count = (0..3)
            .map(|a| (max[a] - min[a]) as usize)
            .product::<usize>();
        if self.form == LevelForm::Voxels {
            let mut out = Vec::with_capacity(count * layout.voxel_type().bytes());
            if count == 0 {
                return Ok(LevelAnswer::Voxels(out));
            }
            export_raw(
                snap,
                level,
                Box3::new(min.map(i64::from), max.map(i64::from)),
                &mut out,
                &crate::progress::Silent,
            )?;
            return Ok(LevelAnswer::Voxels(out));
        }
        let mut bricks = Vec::with_capacity(count);
        for z in min[2]..max[2] {
            for y in min[1]..max[1] {
                for x in min[0]..max[0] {
                    // From the index (revision 5), not the brick records: a grid region
                    // costs its index chunks, however many bricks it lists.
                    let s = snap.summary(BrickKey { level, x, y, z })?;
                    bricks.push(LevelBrick {
                        hash: format!("{:016x}", s.hash),
                        min: s.min,
                        max: s.max,
                    });
                }
            }
        }
        Ok(LevelAnswer::Grid(LevelGrid {
            level,
            grid: layout.grid(level),
            min,
            max,
            version: snap.version,
            bricks,
        }))
    }
}

/// A hash of a mesh answer's content key `inputs`, the tile's position (world coordinates
/// depend on it), the volume's voxel scale and `variant`.
fn mesh_tag(inputs: u128, key: BrickKey, snap: &Snapshot, variant: &[u8]) -> u64 {
    let mut tag = Vec::with_capacity(64);
    tag.extend_from_slice(&inputs.to_le_bytes());
    for c in [key.x, key.y, key.z] {
        tag.extend_from_slice(&c.to_le_bytes());
    }
    for s in snap.header().voxel_scale {
        tag.extend_from_slice(&s.to_le_bytes());
    }
    tag.extend_from_slice(variant);
    xxhash_rust::xxh3::xxh3_64(&tag)
}

/// A checked mesh tile read (see [`LiveVolume::mesh_tile`]).
#[derive(Debug)]
pub struct TileRead {
    snap: Arc<Snapshot>,
    key: BrickKey,
    iso: f32,
    inputs: TileInputs,
    /// The channel of its materials and the content key of the tile with them.
    channel: Option<(Arc<Snapshot>, u128)>,
}

impl TileRead {
    /// Whether a surface can cross the tile's cells (from the bricks' value ranges in the
    /// index): when not, its mesh is empty and making it reads no voxel.
    pub fn may_cross(&self) -> bool {
        self.inputs.may_cross
    }

    /// A hash of everything the tile's encoded mesh depends on (its inputs, with materials the
    /// channel's bricks too, position and the volume's voxel scale) and of `variant` (which
    /// encoding): equal tags, equal bytes.
    pub fn tag(&self, variant: u8) -> u64 {
        match &self.channel {
            None => mesh_tag(self.inputs.key, self.key, &self.snap, &[variant]),
            Some((_, key)) => mesh_tag(*key, self.key, &self.snap, &[variant, b'm']),
        }
    }

    /// The tile in world coordinates, its regular mesh and moves: from `meshes` when
    /// it holds a tile with the same inputs, else meshed now (reading decoded bricks through
    /// `bricks`) and kept there.
    ///
    /// # Errors
    /// A brick fails to read or decode.
    pub fn mesh(
        self,
        meshes: &MeshCache,
        bricks: Arc<DecodedBricks>,
    ) -> Result<TileMesh, VolumeError> {
        let mut scratch = TileScratch::with_bricks(bricks);
        let materials = self.channel.as_ref().map(|(c, k)| (&**c, *k));
        let cached = meshes.tile(
            &self.snap,
            self.key,
            self.iso,
            &self.inputs,
            materials,
            &mut scratch,
        )?;
        let mut tile = (*cached.tile).clone();
        tile_to_world(&mut tile, self.key, &self.snap);
        Ok(tile)
    }
}

/// A checked transition strip read (see [`LiveVolume::mesh_strip`]).
#[derive(Debug)]
pub struct StripRead {
    snap: Arc<Snapshot>,
    key: BrickKey,
    face: usize,
    iso: f32,
    inputs: StripInputs,
    /// The channel of its materials and the content key of the strip with them.
    channel: Option<(Arc<Snapshot>, u128)>,
}

impl StripRead {
    /// Whether a surface can cross the strip (as [`TileRead::may_cross`]; never for a face
    /// that cannot touch a coarser tile): when not, it is empty and making it reads no voxel.
    pub fn may_cross(&self) -> bool {
        self.inputs.may_cross && self.face < 6 && self.inputs.faces >> self.face & 1 == 1
    }

    /// A hash of everything the strip's encoded mesh depends on (its inputs, which name its
    /// face, with materials the channel's bricks too, the tile's position and the volume's
    /// voxel scale) and of `variant` (which encoding): equal tags, equal bytes.
    pub fn tag(&self, variant: u8) -> u64 {
        match &self.channel {
            None => mesh_tag(self.inputs.key, self.key, &self.snap, &[variant, b's']),
            Some((_, key)) => mesh_tag(*key, self.key, &self.snap, &[variant, b's', b'm']),
        }
    }

    /// The strip in world coordinates, as drawn: from `meshes` when it holds one with the same
    /// inputs, else meshed now (reading decoded bricks through `bricks`) and kept there.
    ///
    /// # Errors
    /// A brick fails to read or decode.
    pub fn mesh(self, meshes: &MeshCache, bricks: Arc<DecodedBricks>) -> Result<Mesh, VolumeError> {
        let mut scratch = TileScratch::with_bricks(bricks);
        let materials = self.channel.as_ref().map(|(c, k)| (&**c, *k));
        let cached = meshes.strip(
            &self.snap,
            self.key,
            self.face,
            self.iso,
            &self.inputs,
            materials,
            &mut scratch,
        )?;
        Ok(strip_to_world((*cached.tile).clone(), self.key, &self.snap))
    }
}

/// The batch codec a stored payload of `codec` is sent as, as it is; `None` for a codec the
/// batch encoding has no name for (a palette record: sent decoded, as raw voxels).
fn sent_as_stored(codec: Codec) -> Option<BatchCodec> {
    match codec {
        Codec::Raw => Some(BatchCodec::Raw),
        Codec::Lz4 => Some(BatchCodec::Lz4),
        Codec::Zstd => Some(BatchCodec::Zstd),
        Codec::Palette => None,
    }
}
