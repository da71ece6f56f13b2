//! Whole levels and adaptive selections of tiles, meshed in parallel, stitched and welded.

use super::mc::Mesh;
use super::tile::{mesh_strip_world, mesh_tile, mesh_tile_with_moves, TileScratch};
use crate::progress::Progress;
use crate::store::decoded::DecodedBricks;
use crate::store::{Snapshot, StoreError};
use isovox_proto::mesh::{stitch, TileMesh};
use isovox_proto::BrickKey;
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, TryLockError};

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

/// Runs `mesh` on every item of `tiles` (tiles, or tiles' faces) in parallel, each thread with
/// its own scratch sharing one cache of decoded bricks (each brick is read whole by up to 27
/// tiles), in the order given.
fn in_parallel<I: Copy + Sync, T: Send>(
    tiles: &[I],
    progress: &dyn Progress,
    mesh: impl Fn(&mut TileScratch, I) -> Result<T, StoreError> + Sync,
) -> Result<Vec<T>, StoreError> {
    in_parallel_with(&new_brick_cache(), tiles, progress, mesh)
}

/// A cache of decoded bricks for one meshing pass (or passes that share it).
fn new_brick_cache() -> Arc<DecodedBricks> {
    Arc::new(DecodedBricks::new(BRICK_CACHE_BYTES))
}

/// [`in_parallel`] with the cache of decoded bricks `bricks` (shared with other passes, as the
/// server shares one between requests).
fn in_parallel_with<I: Copy + Sync, T: Send>(
    bricks: &Arc<DecodedBricks>,
    tiles: &[I],
    progress: &dyn Progress,
    mesh: impl Fn(&mut TileScratch, I) -> Result<T, StoreError> + Sync,
) -> Result<Vec<T>, StoreError> {
    progress.start(tiles.len() as u64);
    let parts = each_in_parallel(
        tiles,
        || TileScratch::with_bricks(bricks.clone()),
        |scratch, key| {
            let part = mesh(scratch, key);
            progress.advance(1);
            part
        },
    )?;
    progress.finish();
    Ok(parts)
}

/// Runs `work` on every item of `items` in parallel on the current rayon pool, the results in
/// the order given, each thread reusing one scratch made by `new_scratch`.
///
/// Every item is a job of its own that an idle thread can steal. Tiles differ in cost by
/// orders of magnitude (one that cannot hold the surface is skipped, one full of it marches
/// 32^3 mixed cells), and rayon's default pieces of several tiles, each run through by one
/// thread, left the other thread idle for a large part of a two-thread pass over a scan; a job
/// per tile keeps both busy.
pub fn each_in_parallel<I: Copy + Sync, T: Send, E: Send>(
    items: &[I],
    new_scratch: impl Fn() -> TileScratch + Sync,
    work: impl Fn(&mut TileScratch, I) -> Result<T, E> + Sync,
) -> Result<Vec<T>, E> {
    // One per thread of the pool, each locked only by its own thread.
    let scratches: Vec<Mutex<TileScratch>> = (0..rayon::current_num_threads())
        .map(|_| Mutex::new(new_scratch()))
        .collect();
    items
        .par_iter()
        .with_max_len(1)
        .map(|&item| {
            let thread = rayon::current_thread_index().unwrap_or(0) % scratches.len();
            match scratches[thread].try_lock() {
                Ok(mut scratch) => work(&mut scratch, item),
                Err(TryLockError::Poisoned(poisoned)) => work(&mut poisoned.into_inner(), item),
                // Only if `work` ran rayon jobs itself and this thread took up another item
                // while waiting for them (or the pool is not the one counted): never block.
                Err(TryLockError::WouldBlock) => work(&mut new_scratch(), item),
            }
        })
        .collect()
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

/// Meshes `tiles` in parallel with their moves (world coordinates), in the order given.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tiles_with_moves(
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Vec<TileMesh>, StoreError> {
    tiles_with_moves_in(&new_brick_cache(), snap, tiles, iso, progress)
}

/// [`mesh_tiles_with_moves`] reading decoded bricks through `bricks`.
fn tiles_with_moves_in(
    bricks: &Arc<DecodedBricks>,
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Vec<TileMesh>, StoreError> {
    in_parallel_with(bricks, tiles, progress, |scratch, key| {
        let mut tile = TileMesh::default();
        mesh_tile_with_moves(snap, key, iso, &mut tile, scratch)?;
        Ok(tile)
    })
}

/// Meshes the transition strips `strips` (tile, face) in parallel, as drawn (world
/// coordinates), in the order given.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_strips(
    snap: &Snapshot,
    strips: &[(BrickKey, usize)],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Vec<Mesh>, StoreError> {
    strips_in(&new_brick_cache(), snap, strips, iso, progress)
}

/// [`mesh_strips`] reading decoded bricks through `bricks`.
fn strips_in(
    bricks: &Arc<DecodedBricks>,
    snap: &Snapshot,
    strips: &[(BrickKey, usize)],
    iso: f32,
    progress: &dyn Progress,
) -> Result<Vec<Mesh>, StoreError> {
    in_parallel_with(bricks, strips, progress, |scratch, (key, face)| {
        let mut strip = Mesh::default();
        mesh_strip_world(snap, key, face, iso, &mut strip, scratch)?;
        Ok(strip)
    })
}

/// A balanced selection's tiles, meshed with their moves, their face masks
/// ([`isovox_proto::lod::face_masks`]) and the strips those masks need (world coordinates).
#[derive(Debug, Clone, Default)]
pub struct StitchableParts {
    /// One per tile, in the selection's order.
    pub tiles: Vec<TileMesh>,
    /// Each tile's face mask.
    pub masks: Vec<u8>,
    /// Each tile's strips, for the faces of its mask.
    pub strips: Vec<[Option<Mesh>; 6]>,
}

impl StitchableParts {
    /// Tile `i` as drawn ([`stitch`] with its mask and strips) into `out`.
    pub fn drawn(&self, i: usize, out: &mut Mesh) {
        let strips = std::array::from_fn(|f| self.strips[i][f].as_ref());
        stitch(&self.tiles[i], self.masks[i], strips, out);
    }

    /// The number of strips.
    pub fn strip_count(&self) -> usize {
        self.strips.iter().flatten().flatten().count()
    }
}

/// The faces of a selection's tiles its masks need a strip for: (tile index, face).
fn mask_faces(masks: &[u8]) -> Vec<(usize, usize)> {
    masks
        .iter()
        .enumerate()
        .flat_map(|(i, &m)| (0..6).filter(move |f| m >> f & 1 == 1).map(move |f| (i, f)))
        .collect()
}

/// Meshes `tiles` (a balanced selection, as [`balanced_tiles`] gives) in parallel with their
/// moves, then the strips their face masks need, the two passes sharing one cache of decoded
/// bricks (as the server's requests share one).
///
/// # Errors
/// A brick fails to read.
pub fn mesh_stitchable_parts(
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    progress: &dyn Progress,
) -> Result<StitchableParts, StoreError> {
    let bricks = new_brick_cache();
    let meshed = tiles_with_moves_in(&bricks, snap, tiles, iso, progress)?;
    let masks = isovox_proto::lod::face_masks(snap.layout(), tiles);
    let faces = mask_faces(&masks);
    let keys: Vec<_> = faces.iter().map(|&(i, face)| (tiles[i], face)).collect();
    let made = strips_in(&bricks, snap, &keys, iso, progress)?;
    let mut strips = vec![[(); 6].map(|_| None); tiles.len()];
    for ((i, face), strip) in faces.into_iter().zip(made) {
        strips[i][face] = Some(strip);
    }
    Ok(StitchableParts {
        tiles: meshed,
        masks,
        strips,
    })
}

/// Meshes `tiles` (a balanced selection covering the volume once, as [`balanced_tiles`] gives)
/// and stitches them: each tile drawn with the face mask [`isovox_proto::lod::face_masks`]
/// gives it and those faces' strips, all concatenated (see [`weld`]).
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
    let mut out = Mesh::default();
    let mut drawn = Mesh::default();
    for i in 0..parts.tiles.len() {
        parts.drawn(i, &mut drawn);
        out.append(&drawn);
    }
    Ok(out)
}

/// Merges vertices with bit-identical positions (the seam vertices of neighbouring tiles),
/// keeping the first one's normal and materials, and drops the triangles two of whose corners
/// merge: they have no area. (Within a level no two
/// vertices coincide; a transition strip's end can hold a fine and a coarse crossing that do,
/// joined by a triangle of zero area, see [`super::transition`].)
pub fn weld(mesh: &Mesh) -> Mesh {
    let mut index: HashMap<[u32; 3], u32> = HashMap::with_capacity(mesh.positions.len());
    let mut out = Mesh::default();
    let mut remap = Vec::with_capacity(mesh.positions.len());
    let materials = mesh.materials.len() == mesh.positions.len() && mesh.has_materials();
    for (i, (p, n)) in mesh.positions.iter().zip(&mesh.normals).enumerate() {
        let key = p.map(f32::to_bits);
        let id = *index.entry(key).or_insert_with(|| {
            out.positions.push(*p);
            out.normals.push(*n);
            if materials {
                // The first of the merged vertices' materials (a tile's and its strip's copy
                // of a vertex carry the same).
                out.materials.push(mesh.materials[i]);
            }
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
