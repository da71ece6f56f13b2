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
use crate::store::{Snapshot, StoreError, StoredBrick};
use isovox_proto::{BrickKey, VoxelType};

/// Reusable memory for meshing tiles one after another on one thread.
#[derive(Debug, Default)]
pub struct TileScratch {
    field: Vec<f32>,
    brick: Vec<u8>,
    march: Scratch,
}

/// What meshing one tile did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TileStats {
    /// The tile was skipped from brick min/max alone, without decoding a voxel.
    pub skipped: bool,
    pub triangles: usize,
}

/// The default iso value, S - 0.5 (`spec/icvg.md`).
pub fn default_iso(t: VoxelType) -> f32 {
    t.surface() as f32 - 0.5
}

/// Meshes tile `key` of `snap` at `iso` into `out` (cleared first).
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
    out.clear();
    let layout = snap.layout();
    if !layout.contains(key) {
        return Err(StoreError::Invalid(format!(
            "tile {key} is outside the volume"
        )));
    }
    let b = layout.brick() as i64;
    let pos = [key.x, key.y, key.z].map(|c| c as i64);
    let lo = [0, 1, 2].map(|a| pos[a] * b - i64::from(pos[a] == 0));
    let hi = pos.map(|c| (c + 1) * b);
    // Bricks holding the cells' corner samples [lo, hi]: can the iso value lie between them?
    let grid = layout.grid(key.level).map(|g| g as i64);
    let brick_range =
        |a: usize, from: i64, to: i64| (from.div_euclid(b)..=to.div_euclid(b)).map(move |c| (a, c));
    let (mut any_below, mut any_above) = (false, false);
    let mut corners = Vec::with_capacity(8);
    for (_, bz) in brick_range(2, lo[2], hi[2]) {
        for (_, by) in brick_range(1, lo[1], hi[1]) {
            for (_, bx) in brick_range(0, lo[0], hi[0]) {
                corners.push([bx, by, bz]);
            }
        }
    }
    for c in &corners {
        let inside_grid = (0..3).all(|a| c[a] >= 0 && c[a] < grid[a]);
        // Outside the grid every sample is L; padding inside a brick is L and counted in its min.
        let (min, max) = if inside_grid {
            snap.stored(BrickKey {
                level: key.level,
                x: c[0] as u32,
                y: c[1] as u32,
                z: c[2] as u32,
            })?
            .min_max()
        } else {
            (0, 0)
        };
        any_below |= (min as f32) < iso;
        any_above |= (max as f32) >= iso;
    }
    if !(any_below && any_above) {
        return Ok(TileStats {
            skipped: true,
            triangles: 0,
        });
    }
    // Gather the field [lo - 1, hi + 1].
    let origin = lo.map(|c| c - 1);
    let size = [0, 1, 2].map(|a| (hi[a] + 1 - origin[a] + 1) as usize);
    scratch.field.clear();
    scratch.field.resize(size[0] * size[1] * size[2], 0.0);
    let t = layout.voxel_type();
    scratch.brick.resize(layout.brick_bytes(), 0);
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
                let constant = match stored {
                    StoredBrick::Constant(v) => Some(v as f32),
                    _ => {
                        crate::store::vod2::decode_stored(&stored, layout, &mut scratch.brick)?;
                        None
                    }
                };
                if constant == Some(0.0) {
                    continue;
                }
                let blo = c.map(|v| v * b);
                let from = [0, 1, 2].map(|a| blo[a].max(origin[a]));
                let to = [0, 1, 2].map(|a| (blo[a] + b).min(end[a]));
                for z in from[2]..to[2] {
                    for y in from[1]..to[1] {
                        let row = (((z - origin[2]) as usize * size[1]) + (y - origin[1]) as usize)
                            * size[0];
                        let src = (((z - blo[2]) * b + (y - blo[1])) * b) as usize;
                        for x in from[0]..to[0] {
                            let v = match constant {
                                Some(v) => v,
                                None => {
                                    let i = src + (x - blo[0]) as usize;
                                    match t {
                                        VoxelType::U8 => scratch.brick[i] as f32,
                                        VoxelType::U16 => u16::from_le_bytes([
                                            scratch.brick[2 * i],
                                            scratch.brick[2 * i + 1],
                                        ])
                                            as f32,
                                    }
                                }
                            };
                            scratch.field[row + (x - origin[0]) as usize] = v;
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
    march(&field, lo, hi, iso, out, &mut scratch.march);
    // To world coordinates; normals through the inverse scale.
    let step = (1u64 << key.level) as f32;
    let scale = snap.header().voxel_scale;
    for p in &mut out.positions {
        for a in 0..3 {
            p[a] = ((p[a] + 0.5) * step - 0.5) * scale[a];
        }
    }
    if scale[0] != scale[1] || scale[1] != scale[2] {
        for n in &mut out.normals {
            let m = [n[0] / scale[0], n[1] / scale[1], n[2] / scale[2]];
            let len = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
            *n = m.map(|c| c / len);
        }
    }
    Ok(TileStats {
        skipped: false,
        triangles: out.triangles(),
    })
}
