//! Whole levels and adaptive selections of tiles, meshed in parallel, stitched and welded.

use super::mc::Mesh;
use super::tile::{mesh_tile, mesh_tile_with_transitions, TileScratch};
use crate::progress::Progress;
use crate::store::decoded::DecodedBricks;
use crate::store::{Snapshot, StoreError};
use isovox_proto::mesh::{stitch, TileMesh};
use isovox_proto::BrickKey;
use rayon::prelude::*;
use std::collections::HashMap;

/// Memory for decoded bricks during one [`mesh_tiles`] pass.
const BRICK_CACHE_BYTES: usize = 256 << 20;

/// Every tile of `level`.
pub fn level_tiles(snap: &Snapshot, level: u8) -> Vec<BrickKey> {
    let g = snap.layout().grid(level);
    let mut out = Vec::with_capacity((g[0] * g[1] * g[2]) as usize);
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                out.push(BrickKey { level, x, y, z });
            }
        }
    }
    out
}

/// The tiles the thesis's spherical detail bias selects for `camera` (see
/// [`isovox_proto::lod::adaptive_tiles`]); neighbours may differ by more than one level.
pub fn adaptive_tiles(snap: &Snapshot, camera: [f32; 3], radii: &[f32]) -> Vec<BrickKey> {
    isovox_proto::lod::adaptive_tiles(snap.layout(), snap.header().voxel_scale, camera, radii)
}

/// The tiles to stitch for `camera`: the adaptive selection refined until neighbours differ by
/// at most one level ([`isovox_proto::lod::balanced_tiles`], which the client's streamer and
/// the web viewer use too).
pub fn balanced_tiles(snap: &Snapshot, camera: [f32; 3], radii: &[f32]) -> Vec<BrickKey> {
    isovox_proto::lod::balanced_tiles(snap.layout(), snap.header().voxel_scale, camera, radii)
}

/// Runs `mesh` on every tile of `tiles` in parallel, each thread with its own scratch sharing
/// one cache of decoded bricks (each brick is read whole by up to 27 tiles), in the order given.
fn in_parallel<T: Send>(
    tiles: &[BrickKey],
    progress: &dyn Progress,
    mesh: impl Fn(&mut TileScratch, BrickKey) -> Result<T, StoreError> + Sync,
) -> Result<Vec<T>, StoreError> {
    progress.start(tiles.len() as u64);
    let bricks = std::sync::Arc::new(DecodedBricks::new(BRICK_CACHE_BYTES));
    let parts = tiles
        .par_iter()
        .map_init(
            || TileScratch::with_bricks(bricks.clone()),
            |scratch, &key| {
                let part = mesh(scratch, key)?;
                progress.advance(1);
                Ok(part)
            },
        )
        .collect::<Result<_, StoreError>>()?;
    progress.finish();
    Ok(parts)
}

/// Meshes `tiles` in parallel, one mesh per tile (world coordinates), in the order given.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tile_parts(
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Vec<Mesh>, StoreError> {
    in_parallel(tiles, progress, |scratch, key| {
        let mut m = Mesh::default();
        mesh_tile(snap, key, iso, &mut m, scratch)?;
        Ok(m)
    })
}

/// Meshes `tiles` in parallel and concatenates the results (vertices on tile seams appear once
/// per tile; see [`weld`]).
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tiles(
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Mesh, StoreError> {
    let parts = mesh_tile_parts(snap, tiles, iso, progress)?;
    let mut out = Mesh::default();
    for p in &parts {
        out.append(p);
    }
    Ok(out)
}

/// Meshes `tiles` (a balanced selection, as [`balanced_tiles`] gives) in parallel with their
/// transition data, one tile per key (world coordinates), in the order given.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_stitchable_parts(
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Vec<TileMesh>, StoreError> {
    in_parallel(tiles, progress, |scratch, key| {
        let mut tile = TileMesh::default();
        mesh_tile_with_transitions(snap, key, iso, &mut tile, scratch)?;
        Ok(tile)
    })
}

/// Meshes `tiles` (a balanced selection covering the volume once, as [`balanced_tiles`] gives)
/// and stitches them: each tile drawn with the face mask [`isovox_proto::lod::face_masks`]
/// gives it, all concatenated (see [`weld`]).
///
/// # Errors
/// A brick fails to read.
pub fn mesh_stitched(
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Mesh, StoreError> {
    let parts = mesh_stitchable_parts(snap, tiles, iso, progress)?;
    let masks = isovox_proto::lod::face_masks(snap.layout(), tiles);
    let mut out = Mesh::default();
    let mut drawn = Mesh::default();
    for (tile, &mask) in parts.iter().zip(&masks) {
        stitch(tile, mask, &mut drawn);
        out.append(&drawn);
    }
    Ok(out)
}

/// Merges vertices with bit-identical positions (the seam vertices of neighbouring tiles), and
/// drops the triangles two of whose corners merge: they have no area. (Within a level no two
/// vertices coincide; a transition strip's end can hold a fine and a coarse crossing that do,
/// joined by a triangle of zero area, see [`super::transition`].)
pub fn weld(mesh: &Mesh) -> Mesh {
    let mut index: HashMap<[u32; 3], u32> = HashMap::with_capacity(mesh.positions.len());
    let mut out = Mesh::default();
    let mut remap = Vec::with_capacity(mesh.positions.len());
    for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
        let key = p.map(f32::to_bits);
        let id = *index.entry(key).or_insert_with(|| {
            out.positions.push(*p);
            out.normals.push(*n);
            (out.positions.len() - 1) as u32
        });
        remap.push(id);
    }
    out.indices = mesh
        .indices
        .chunks_exact(3)
        .map(|t| [t[0], t[1], t[2]].map(|i| remap[i as usize]))
        .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        .flatten()
        .collect();
    out
}

/// [`weld`], carrying one flag per triangle (which tile or strip it came from, say) over to the
/// triangles it keeps; also returns how many it dropped.
///
/// # Panics
/// `flags` does not have one flag per triangle.
pub fn weld_flagged(mesh: &Mesh, flags: &[bool]) -> (Mesh, Vec<bool>, usize) {
    assert_eq!(flags.len(), mesh.triangles(), "one flag per triangle");
    let kept: Vec<bool> = mesh
        .indices
        .chunks_exact(3)
        .map(|t| {
            let [a, b, c] =
                [t[0], t[1], t[2]].map(|i| mesh.positions[i as usize].map(f32::to_bits));
            a != b && b != c && a != c
        })
        .collect();
    let flags: Vec<bool> = flags
        .iter()
        .zip(&kept)
        .filter(|(_, &k)| k)
        .map(|(&f, _)| f)
        .collect();
    let welded = weld(mesh);
    debug_assert_eq!(welded.triangles(), flags.len());
    let dropped = kept.iter().filter(|&&k| !k).count();
    (welded, flags, dropped)
}
