//! What a tile's mesh and a strip's depend on: content keys computed from the index alone (its
//! brick summaries; brick headers in files written before revision 5; no voxel decoded), and
//! whether the iso value can cross what they read.

use super::Stitching;
use crate::mesh::lattice::value_range;
use crate::store::{Snapshot, StoreError};
use isovox_proto::lod::FACE_DIRECTIONS;
use isovox_proto::tile::{
    bricks_of, cells, field_box, has_transitions, stored_box, strip_coarse_box, strip_field_box,
    GridBox,
};
use isovox_proto::vod2::NodeEntry;
use isovox_proto::{BrickKey, VolumeLayout};

/// What a tile's mesh depends on: its level, the iso value, the brick edge and voxel type,
/// whether it is the first tile on an axis (it then owns one more cell), the content of the
/// bricks it reads (content hash, constant value, or outside the volume); with moves, also
/// which faces have a neighbour and on which side of its parent it lies.
#[derive(Debug, Clone)]
pub struct TileInputs {
    /// Content key: equal keys give equal local meshes.
    pub key: u128,
    /// Whether the iso value can lie between the samples its cells read (from brick min/max):
    /// whether the tile can hold anything.
    pub may_cross: bool,
    /// The faces to make moves for (a face mask; 0 without moves).
    pub faces: u8,
}

/// What a tile's strip depends on: as [`TileInputs`] with moves, the face, and the content of
/// the bricks the strip reads: the tile's level along the face, the coarser level on and
/// beside the face's plane.
#[derive(Debug, Clone)]
pub struct StripInputs {
    /// Content key: equal keys give equal local strips.
    pub key: u128,
    /// Whether the iso value can lie between the samples the strip reads: whether it can hold
    /// anything (never, for a face that cannot touch a coarser tile).
    pub may_cross: bool,
    /// The tile's faces with a neighbour ([`TileInputs::faces`]).
    pub faces: u8,
}

/// The faces of tile `key` with a neighbouring tile of its level, when a coarser level exists.
fn transition_faces(layout: &VolumeLayout, key: BrickKey) -> u8 {
    if !has_transitions(layout, key) {
        return 0;
    }
    FACE_DIRECTIONS.iter().enumerate().fold(0, |m, (f, d)| {
        m | u8::from(layout.neighbour(key, *d).is_some()) << f
    })
}

/// Adds the content of the bricks of `level` holding the voxels `read` (a box, inclusive) to
/// `desc`, and returns the least and greatest voxel of those among them that hold voxels of
/// `crossing` (the voxels that decide whether the surface can cross the cells).
pub(super) fn describe_bricks(
    snap: &Snapshot,
    level: u8,
    read: GridBox,
    crossing: GridBox,
    desc: &mut Vec<u8>,
) -> Result<(u64, u64), StoreError> {
    let layout = snap.layout();
    let grid = layout.grid(level).map(|g| g as i64);
    let (first, last) = bricks_of(layout.brick(), read);
    let (cross_first, cross_last) = bricks_of(layout.brick(), crossing);
    let (mut min, mut max) = (u64::MAX, u64::MIN);
    for z in first[2]..=last[2] {
        for y in first[1]..=last[1] {
            for x in first[0]..=last[0] {
                let c = [x, y, z];
                let (lo, hi) = if (0..3).all(|a| c[a] >= 0 && c[a] < grid[a]) {
                    let k = BrickKey {
                        level,
                        x: x as u32,
                        y: y as u32,
                        z: z as u32,
                    };
                    // The index's summary (revision 5), not the brick record: the key and
                    // the range of a tile cost no record read.
                    let summary = snap.summary(k)?;
                    match snap.entry(k)? {
                        NodeEntry::Constant(v) => {
                            // Two bytes, as before values were u64 in memory: density's fit,
                            // and the keys (and the tiles' ETags) stay what they were.
                            desc.push(1);
                            desc.extend_from_slice(&(v as u16).to_le_bytes());
                        }
                        NodeEntry::Stored(_) => {
                            desc.push(2);
                            desc.extend_from_slice(&summary.hash.to_le_bytes());
                        }
                    }
                    (summary.min, summary.max)
                } else {
                    desc.push(0);
                    (0, 0)
                };
                if (0..3).all(|a| c[a] >= cross_first[a] && c[a] <= cross_last[a]) {
                    min = min.min(lo);
                    max = max.max(hi);
                }
            }
        }
    }
    Ok((min, max))
}

/// The start of a content key's description: everything but the bricks.
fn describe_tile(layout: &VolumeLayout, key: BrickKey, iso: f32, faces: u8) -> Vec<u8> {
    let mut desc = Vec::with_capacity(64 + 2 * 27 * 9);
    desc.push(key.level);
    desc.extend_from_slice(&iso.to_bits().to_le_bytes());
    desc.extend_from_slice(&layout.brick().to_le_bytes());
    desc.push(layout.voxel_type().bytes() as u8);
    desc.extend([key.x, key.y, key.z].map(|c| (c == 0) as u8));
    desc.push(faces);
    if faces != 0 {
        // Which side of its parent the tile lies on fixes its moves and where its strips'
        // coarse vertices are.
        desc.extend([key.x, key.y, key.z].map(|c| (c % 2) as u8));
    }
    desc
}

/// Computes a tile's inputs from the index alone (its brick summaries; brick headers for
/// entries written before revision 5; no voxel decoded).
///
/// # Errors
/// The tile lies outside the volume, or a summary (or brick header) fails to read.
pub fn tile_inputs(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    stitching: Stitching,
) -> Result<TileInputs, StoreError> {
    let layout = snap.layout();
    if !layout.contains(key) {
        return Err(StoreError::OutOfRange(format!(
            "tile {key} is outside the volume"
        )));
    }
    let (lo, hi, _) = cells(layout, key);
    let faces = match stitching {
        Stitching::None => 0,
        Stitching::Moves => transition_faces(layout, key),
    };
    let mut desc = describe_tile(layout, key, iso, faces);
    // The field march reads (its cells' corners and the normals' halo); the corners alone
    // decide whether a surface crosses the cells.
    let field = stored_box(key.level, field_box(layout, key));
    let corners = stored_box(key.level, (lo, hi));
    let (min, max) = describe_bricks(snap, key.level, field, corners, &mut desc)?;
    let (low, high) = value_range(key.level, min as f32, max as f32);
    // At or below L every voxel, and the padding outside the volume, is inside: there is no
    // surface.
    let surface_possible = iso > layout.voxel_type().low() as f32;
    Ok(TileInputs {
        key: xxhash_rust::xxh3::xxh3_128(&desc),
        may_cross: surface_possible && low < iso && high >= iso,
        faces,
    })
}

/// Computes the inputs of the strip of face `face` (0..6) of tile `key` from the index alone
/// (as [`tile_inputs`]).
///
/// # Errors
/// The tile lies outside the volume, the face is not one of six, or a summary (or brick
/// header) fails to read.
pub fn strip_inputs(
    snap: &Snapshot,
    key: BrickKey,
    face: usize,
    iso: f32,
) -> Result<StripInputs, StoreError> {
    let layout = snap.layout();
    if !layout.contains(key) || face >= 6 {
        return Err(StoreError::OutOfRange(format!(
            "face {face} of tile {key} is outside the volume"
        )));
    }
    let faces = transition_faces(layout, key);
    let mut desc = describe_tile(layout, key, iso, faces);
    desc.extend_from_slice(b"strip");
    desc.push(face as u8);
    if faces >> face & 1 == 0 {
        return Ok(StripInputs {
            key: xxhash_rust::xxh3::xxh3_128(&desc),
            may_cross: false,
            faces,
        });
    }
    let fine = stored_box(key.level, strip_field_box(layout, key, face));
    let (min, max) = describe_bricks(snap, key.level, fine, fine, &mut desc)?;
    let (mut low, mut high) = value_range(key.level, min as f32, max as f32);
    let coarse = stored_box(key.level + 1, strip_coarse_box(layout, key, face));
    let (min, max) = describe_bricks(snap, key.level + 1, coarse, coarse, &mut desc)?;
    let (l, h) = value_range(key.level + 1, min as f32, max as f32);
    low = low.min(l);
    high = high.max(h);
    // At or below L there is no surface; the coarser lattice values can still dip below L
    // (Catmull-Rom's negative weights next to bright voxels), which would draw rings of that
    // undershoot, and strips reaching into the padding where the finer field has no halo for
    // their normals.
    let surface_possible = iso > layout.voxel_type().low() as f32;
    Ok(StripInputs {
        key: xxhash_rust::xxh3::xxh3_128(&desc),
        may_cross: surface_possible && low < iso && high >= iso,
        faces,
    })
}
