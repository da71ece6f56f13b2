//! A tile's regular mesh (marching cubes over its cells), and its moves.

use super::geometry::{field_size, tile_faces};
use super::inputs::tile_inputs;
use super::voxels::{gather_voxels, lattice, BrickWindow, StoredVoxel};
use super::world::{tile_to_world, to_world};
use super::{Stitching, TileInputs, TileScratch, TileStats};
use crate::mesh::mc::{march, Field, Mesh, Sample, Scratch};
use crate::mesh::transition::tile_moves;
use crate::store::{Snapshot, StoreError};
use isovox_proto::mesh::{TileMesh, VertexMove};
use isovox_proto::tile::{cells, field_box, GridBox};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};

/// Meshes tile `key` of `snap` at `iso` into `out` (cleared first), its regular mesh alone, in
/// world coordinates.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tile(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    out: &mut Mesh,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    let inputs = tile_inputs(snap, key, iso, Stitching::None)?;
    let stats = mesh_into(snap, key, iso, &inputs, out, None, scratch)?;
    to_world(out, key, snap);
    Ok(stats)
}

/// Meshes tile `key` of `snap` at `iso` into `out` (cleared first) with its moves, in world
/// coordinates.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tile_with_moves(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    out: &mut TileMesh,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    let inputs = tile_inputs(snap, key, iso, Stitching::Moves)?;
    let stats = mesh_tile_from(snap, key, iso, &inputs, out, scratch)?;
    tile_to_world(out, key, snap);
    Ok(stats)
}

/// Meshes tile `key` into `out` (cleared first) in local lattice coordinates (relative to the
/// tile's frame, level-k lattice units), with the moves of the faces `inputs` names. `inputs`
/// comes from [`tile_inputs`] (the cache and the HTTP handler compute it for the key and the
/// ETag; doing it again costs the index lookups).
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tile_from(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    inputs: &TileInputs,
    out: &mut TileMesh,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    let (mesh, moves) = (&mut out.mesh, &mut out.moves);
    mesh_into(snap, key, iso, inputs, mesh, Some(moves), scratch)
}

/// The regular mesh into `mesh`, and the moves into `moves` when given.
fn mesh_into(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    inputs: &TileInputs,
    mesh: &mut Mesh,
    moves: Option<&mut Vec<VertexMove>>,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    mesh.clear();
    let mut moves = moves;
    if let Some(m) = moves.as_deref_mut() {
        m.clear();
    }
    if !inputs.may_cross {
        return Ok(TileStats {
            skipped: true,
            triangles: 0,
        });
    }
    let layout = snap.layout();
    let (lo, hi, frame) = cells(layout, key);
    let bricks = scratch.bricks.clone();
    let points = field_box(layout, key);
    if key.level == 0 {
        // Level 0's lattice is its voxels: marched as they are stored, with no conversion.
        let window = &mut scratch.fine_bricks;
        window.open(snap, 0, points, bricks.as_deref())?;
        let cells = (lo, frame, hi, iso);
        match layout.voxel_type() {
            VoxelType::U8 => {
                march_stored(
                    window,
                    layout,
                    points,
                    &mut scratch.voxels_u8,
                    cells,
                    mesh,
                    &mut scratch.march,
                );
            }
            VoxelType::U16 => {
                march_stored(
                    window,
                    layout,
                    points,
                    &mut scratch.voxels_u16,
                    cells,
                    mesh,
                    &mut scratch.march,
                );
            }
            wide => {
                return Err(StoreError::Internal(format!(
                    "a mesh of {wide} values: density is u8 or u16"
                )))
            }
        }
    } else {
        let fine = lattice(
            snap,
            key.level,
            points,
            bricks.as_deref(),
            (
                &mut scratch.fine_bricks,
                &mut scratch.stored,
                &mut scratch.lattice,
            ),
            &mut scratch.field,
        )?;
        march(&fine, lo, frame, hi, iso, mesh, &mut scratch.march);
    }
    if let Some(moves) = moves.filter(|_| inputs.faces != 0) {
        tile_moves(
            &tile_faces(layout, key, inputs.faces),
            &scratch.march,
            moves,
        );
    }
    Ok(TileStats {
        skipped: false,
        triangles: mesh.triangles(),
    })
}

/// Marches the cells `(lo, frame, hi, iso)` of a level-0 tile over the voxels of `points` as
/// `window` stores them, gathered into `buffer`.
fn march_stored<V: StoredVoxel + Sample>(
    window: &BrickWindow,
    layout: &VolumeLayout,
    points: GridBox,
    buffer: &mut Vec<V>,
    (lo, frame, hi, iso): ([i64; 3], [i64; 3], [i64; 3], f32),
    mesh: &mut Mesh,
    scratch: &mut Scratch,
) {
    let (origin, size) = (points.0, field_size(points));
    gather_voxels(window, layout, origin, size, buffer);
    let field = Field {
        origin,
        size,
        values: &buffer[..],
    };
    march(&field, lo, frame, hi, iso, mesh, scratch);
}
