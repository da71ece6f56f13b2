//! Mesh tiles: the marching-cubes mesh of one brick at one level.
//!
//! Seam rule: tile (x, y, z) of a level owns the cells whose lower corner lies in
//! `[x * b, (x + 1) * b)` on each axis (and, for the first tile of an axis, also the cell starting
//! at -1, so that a surface touching the volume's low faces is closed). Its cells reach one sample
//! into the +x, +y, +z neighbours, and the normals' central differences one more on every side,
//! so a tile reads the samples `[x * b - 1 (or -2), (x + 1) * b + 1]` from up to 27 bricks.
//! Outside the volume every sample is L, so a padded object is watertight. Two tiles that meet
//! compute their shared face's vertices from the same samples with the same formula: the vertices
//! are bit-identical from both sides, with no cracks and no duplicate faces.
//!
//! Positions are world coordinates: level-k voxel `i` is the centre of level-0 voxels
//! `[i 2^k, (i + 1) 2^k)`, at `(i + 0.5) 2^k - 0.5`, times the voxel scale.

use super::mc::{march, Field, Mesh, Scratch};
use crate::store::decoded::{decode, DecodedBricks};
use crate::store::{Snapshot, StoreError, StoredBrick};
use isovox_proto::{BrickKey, VoxelType};
use std::sync::Arc;

/// Reusable memory for meshing tiles one after another on one thread.
#[derive(Debug, Default)]
pub struct TileScratch {
    field: Vec<f32>,
    march: Scratch,
    /// Decoded bricks shared between tiles (and threads); without it each tile decodes its
    /// neighbours itself.
    pub bricks: Option<Arc<DecodedBricks>>,
}

impl TileScratch {
    /// Scratch that shares decoded bricks through `bricks`.
    pub fn with_bricks(bricks: Arc<DecodedBricks>) -> Self {
        TileScratch {
            bricks: Some(bricks),
            ..TileScratch::default()
        }
    }
}

/// What meshing one tile did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TileStats {
    /// The tile was skipped from brick min/max alone, without decoding a voxel.
    pub skipped: bool,
    /// Triangles made.
    pub triangles: usize,
}

/// The default iso value, S - 0.5 (`docs/icvg.md`).
pub fn default_iso(t: VoxelType) -> f32 {
    t.surface() as f32 - 0.5
}

/// What a tile's mesh depends on: its level, the iso value, the brick edge and voxel type,
/// whether it is the first tile on an axis (it then owns one more cell), and the content of the
/// 27 bricks around it (content hash, constant value, or outside the volume).
#[derive(Debug, Clone)]
pub struct TileInputs {
    /// Content key: equal keys give equal local meshes.
    pub key: u128,
    /// Whether the iso value can lie between the samples the cells read (from brick min/max).
    pub may_cross: bool,
}

/// Computes a tile's inputs from the index and brick headers alone (no voxel decoded).
///
/// # Errors
/// A brick header fails to read.
pub fn tile_inputs(snap: &Snapshot, key: BrickKey, iso: f32) -> Result<TileInputs, StoreError> {
    let layout = snap.layout();
    if !layout.contains(key) {
        return Err(StoreError::OutOfRange(format!(
            "tile {key} is outside the volume"
        )));
    }
    let grid = layout.grid(key.level);
    let pos = [key.x, key.y, key.z];
    let mut desc = Vec::with_capacity(32 + 27 * 9);
    desc.push(key.level);
    desc.extend_from_slice(&iso.to_bits().to_le_bytes());
    desc.extend_from_slice(&layout.brick().to_le_bytes());
    desc.push(layout.voxel_type().bytes() as u8);
    desc.extend(pos.map(|c| (c == 0) as u8));
    let (mut any_below, mut any_above) = (false, false);
    for dz in -1i64..=1 {
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                let c = [pos[0] as i64 + dx, pos[1] as i64 + dy, pos[2] as i64 + dz];
                let inside = (0..3).all(|a| c[a] >= 0 && c[a] < grid[a] as i64);
                let (min, max) = if inside {
                    let k = BrickKey {
                        level: key.level,
                        x: c[0] as u32,
                        y: c[1] as u32,
                        z: c[2] as u32,
                    };
                    match snap.stored(k)? {
                        StoredBrick::Constant(v) => {
                            desc.push(1);
                            desc.extend_from_slice(&(v as u64).to_le_bytes());
                            (v, v)
                        }
                        stored @ StoredBrick::Record { header, .. } => {
                            desc.push(2);
                            desc.extend_from_slice(&header.hash.to_le_bytes());
                            stored.min_max()
                        }
                    }
                } else {
                    desc.push(0);
                    (0, 0)
                };
                // The cells read the samples of the bricks at offsets 0..=1 (and -1 for a first
                // tile); the others only feed normals.
                let reads = [dx, dy, dz].iter().zip(pos).all(|(&d, p)| d >= 0 || p == 0);
                if reads {
                    any_below |= (min as f32) < iso;
                    any_above |= (max as f32) >= iso;
                }
            }
        }
    }
    Ok(TileInputs {
        key: xxhash_rust::xxh3::xxh3_128(&desc),
        may_cross: any_below && any_above,
    })
}

/// Meshes tile `key` of `snap` at `iso` into `out` (cleared first), in world coordinates.
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
    let stats = mesh_tile_local(snap, key, iso, out, scratch)?;
    to_world(out, key, snap);
    Ok(stats)
}

/// Moves a tile's local mesh (grid coordinates relative to the tile's first voxel) to world
/// coordinates. Every tile goes through this one formula, so shared seam vertices stay
/// bit-identical whether a tile came from the cache or not.
pub fn to_world(mesh: &mut Mesh, key: BrickKey, snap: &Snapshot) {
    let b = snap.layout().brick() as f32;
    let origin = [key.x, key.y, key.z].map(|c| c as f32 * b);
    let step = (1u64 << key.level) as f32;
    let scale = snap.header().voxel_scale;
    for p in &mut mesh.positions {
        for a in 0..3 {
            p[a] = (((p[a] + origin[a]) + 0.5) * step - 0.5) * scale[a];
        }
    }
    if scale[0] != scale[1] || scale[1] != scale[2] {
        for n in &mut mesh.normals {
            let m = [n[0] / scale[0], n[1] / scale[1], n[2] / scale[2]];
            let len = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
            *n = m.map(|c| c / len);
        }
    }
}

/// Meshes tile `key` into `out` (cleared first) in local grid coordinates: relative to the
/// tile's first voxel, level-k voxel units.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tile_local(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    out: &mut Mesh,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    let inputs = tile_inputs(snap, key, iso)?;
    mesh_tile_from(snap, key, iso, &inputs, out, scratch)
}

/// [`mesh_tile_local`] for a caller that already has the tile's [`TileInputs`] (the cache and
/// the HTTP handler compute them for the key and the ETag; doing it again costs 27 lookups).
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tile_from(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    inputs: &TileInputs,
    out: &mut Mesh,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    out.clear();
    if !inputs.may_cross {
        return Ok(TileStats {
            skipped: true,
            triangles: 0,
        });
    }
    let layout = snap.layout();
    let b = layout.brick() as i64;
    let pos = [key.x, key.y, key.z].map(|c| c as i64);
    let lo = [0, 1, 2].map(|a| pos[a] * b - i64::from(pos[a] == 0));
    let hi = pos.map(|c| (c + 1) * b);
    let grid = layout.grid(key.level).map(|g| g as i64);
    // Gather the field [lo - 1, hi + 1].
    let origin = lo.map(|c| c - 1);
    let size = [0, 1, 2].map(|a| (hi[a] + 1 - origin[a] + 1) as usize);
    scratch.field.clear();
    scratch.field.resize(size[0] * size[1] * size[2], 0.0);
    let t = layout.voxel_type();
    let end = [0, 1, 2].map(|a| origin[a] + size[a] as i64); // exclusive
    for bz in origin[2].div_euclid(b)..=(end[2] - 1).div_euclid(b) {
        for by in origin[1].div_euclid(b)..=(end[1] - 1).div_euclid(b) {
            for bx in origin[0].div_euclid(b)..=(end[0] - 1).div_euclid(b) {
                let c = [bx, by, bz];
                if (0..3).any(|a| c[a] < 0 || c[a] >= grid[a]) {
                    continue; // outside the volume: L, already 0
                }
                let k = BrickKey {
                    level: key.level,
                    x: bx as u32,
                    y: by as u32,
                    z: bz as u32,
                };
                let stored = snap.stored(k)?;
                let blo = c.map(|v| v * b);
                let from = [0, 1, 2].map(|a| blo[a].max(origin[a]));
                let to = [0, 1, 2].map(|a| (blo[a] + b).min(end[a]));
                let width = (to[0] - from[0]) as usize;
                let rows = (from[2]..to[2]).flat_map(|z| (from[1]..to[1]).map(move |y| (y, z)));
                let at = |y: i64, z: i64| {
                    ((((z - origin[2]) as usize * size[1]) + (y - origin[1]) as usize) * size[0])
                        + (from[0] - origin[0]) as usize
                };
                match stored {
                    StoredBrick::Constant(0) => {} // L: the field is already 0
                    StoredBrick::Constant(v) => {
                        for (y, z) in rows {
                            let row = at(y, z);
                            scratch.field[row..row + width].fill(v as f32);
                        }
                    }
                    StoredBrick::Record { header, .. } => {
                        let bytes = match &scratch.bricks {
                            Some(cache) => cache.voxels(header.hash, &stored, layout)?,
                            None => decode(&stored, layout)?,
                        };
                        for (y, z) in rows {
                            let row = at(y, z);
                            let src = (((z - blo[2]) * b + (y - blo[1])) * b + (from[0] - blo[0]))
                                as usize;
                            let dst = &mut scratch.field[row..row + width];
                            match t {
                                VoxelType::U8 => {
                                    for (d, s) in dst.iter_mut().zip(&bytes[src..src + width]) {
                                        *d = *s as f32;
                                    }
                                }
                                VoxelType::U16 => {
                                    for (d, s) in dst
                                        .iter_mut()
                                        .zip(bytes[2 * src..2 * (src + width)].chunks_exact(2))
                                    {
                                        *d = u16::from_le_bytes([s[0], s[1]]) as f32;
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    let field = Field {
        origin,
        size,
        values: &scratch.field,
    };
    march(
        &field,
        lo,
        pos.map(|c| c * b),
        hi,
        iso,
        out,
        &mut scratch.march,
    );
    Ok(TileStats {
        skipped: false,
        triangles: out.triangles(),
    })
}
