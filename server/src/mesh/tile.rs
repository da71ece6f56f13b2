//! Mesh tiles: the marching-cubes mesh of one brick at one level, with what it needs to be
//! joined to coarser neighbours.
//!
//! Seam rule within a level: tile (x, y, z) owns the cells whose lower corner lies in
//! `[x * b, (x + 1) * b)` on each axis (and, for the first tile of an axis, also the cell
//! starting at -1, so that a surface touching the volume's low faces is closed). Its cells
//! reach one sample into the +x, +y, +z neighbours, and the normals' central differences one
//! more on every side. Outside the volume every sample is L, so a padded object is watertight.
//! Two tiles that meet compute their shared face's vertices from the same samples with the same
//! formula: the vertices are bit-identical from both sides, with no cracks and no duplicate
//! faces.
//!
//! The samples of level k are its lattice values ([`super::lattice`]): level-0 voxels as they
//! are, coarser levels resampled at level-0 positions `2^k j`, so that the levels' cells nest.
//! A tile of level k reads the stored voxels of its level over `[x * b - 1, (x + 1) * b + 1]`
//! (level 0) or `[x * b - 3, (x + 1) * b + 2]` (coarser; one more below for the first tile), and
//! for its transition strips ([`super::transition`]) the level-(k+1) voxels around its faces.
//!
//! Positions are world coordinates: lattice point j of level k is at level-0 position `2^k j`,
//! times the voxel scale. Every tile goes through that one formula ([`to_world`]), so shared
//! vertices stay bit-identical, across levels too.

use super::lattice::{lattice_field, value_range};
use super::mc::{march, Field, Mesh, Scratch};
use super::transition::{mesh_transitions, TransitionInput, TransitionScratch};
use crate::store::decoded::{decode, DecodedBricks};
use crate::store::{Snapshot, StoreError, StoredBrick};
use isovox_proto::lod::FACE_DIRECTIONS;
use isovox_proto::mesh::{TileMesh, Transitions};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use std::sync::Arc;

/// Reusable memory for meshing tiles one after another on one thread.
#[derive(Debug, Default)]
pub struct TileScratch {
    stored: Vec<f32>,
    field: Vec<f32>,
    coarse: Vec<f32>,
    march: Scratch,
    transitions: TransitionScratch,
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
    /// Triangles made (regular mesh).
    pub triangles: usize,
}

/// The default iso value, S - 0.5 (`docs/icvg.md`).
pub fn default_iso(t: VoxelType) -> f32 {
    t.surface() as f32 - 0.5
}

/// Whether a tile is meshed with its transition data (see [`super::transition`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stitching {
    /// The regular mesh alone: for one level meshed whole.
    None,
    /// The regular mesh, secondary positions and a strip for every face with a neighbour (when
    /// a coarser level exists): a tile that can be drawn next to any neighbours.
    Transitions,
}

/// What a tile's mesh depends on: its level, the iso value, the brick edge and voxel type,
/// whether it is the first tile on an axis (it then owns one more cell), the content of the
/// bricks it reads (content hash, constant value, or outside the volume); with transitions,
/// also which faces have a neighbour, on which side of its parent it lies, and the content of
/// the coarser bricks its strips read.
#[derive(Debug, Clone)]
pub struct TileInputs {
    /// Content key: equal keys give equal local meshes.
    pub key: u128,
    /// Whether the iso value can lie between the samples the tile reads (from brick min/max).
    pub may_cross: bool,
    /// The faces to build strips for (a face mask; 0 without transitions).
    pub faces: u8,
}

/// The cells `[lo, hi)` of tile `key` (grid points of its level) and its frame.
fn cells(layout: &VolumeLayout, key: BrickKey) -> ([i64; 3], [i64; 3], [i64; 3]) {
    let b = layout.brick() as i64;
    let pos = [key.x, key.y, key.z].map(|c| c as i64);
    let lo = pos.map(|c| c * b - i64::from(c == 0));
    let hi = pos.map(|c| (c + 1) * b);
    (lo, hi, pos.map(|c| c * b))
}

/// The stored voxels of `level` whose lattice values cover `[lo, hi]` (inclusive).
fn stored_box(level: u8, lo: [i64; 3], hi: [i64; 3]) -> ([i64; 3], [i64; 3]) {
    if level == 0 {
        (lo, hi)
    } else {
        (lo.map(|c| c - 2), hi.map(|c| c + 1))
    }
}

/// The level-(k+1) lattice points a tile's strips read, `[c, d]`, for cells `[lo, hi)` (see
/// [`super::transition`]).
fn coarse_box(lo: [i64; 3], hi: [i64; 3]) -> ([i64; 3], [i64; 3]) {
    (lo.map(|c| c.div_euclid(2) - 1), hi.map(|c| c / 2 + 1))
}

/// The faces of tile `key` with a neighbouring tile of its level, when a coarser level exists.
fn transition_faces(layout: &VolumeLayout, key: BrickKey) -> u8 {
    if key.level + 1 >= layout.levels() {
        return 0;
    }
    FACE_DIRECTIONS.iter().enumerate().fold(0, |m, (f, d)| {
        m | u8::from(layout.neighbour(key, *d).is_some()) << f
    })
}

/// Adds the content of the bricks of `level` holding the voxels `read` (a box, inclusive) to
/// `desc`, and returns the least and greatest voxel of those among them that hold voxels of
/// `crossing` (the voxels that decide whether the surface can cross the cells).
fn describe_bricks(
    snap: &Snapshot,
    level: u8,
    read: ([i64; 3], [i64; 3]),
    crossing: ([i64; 3], [i64; 3]),
    desc: &mut Vec<u8>,
) -> Result<(u16, u16), StoreError> {
    let layout = snap.layout();
    let b = layout.brick() as i64;
    let grid = layout.grid(level).map(|g| g as i64);
    let bricks =
        |(lo, hi): ([i64; 3], [i64; 3])| (lo.map(|c| c.div_euclid(b)), hi.map(|c| c.div_euclid(b)));
    let (first, last) = bricks(read);
    let (cross_first, cross_last) = bricks(crossing);
    let (mut min, mut max) = (u16::MAX, u16::MIN);
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
                    let stored = snap.stored(k)?;
                    match stored {
                        StoredBrick::Constant(v) => {
                            desc.push(1);
                            desc.extend_from_slice(&v.to_le_bytes());
                        }
                        StoredBrick::Record { header, .. } => {
                            desc.push(2);
                            desc.extend_from_slice(&header.hash.to_le_bytes());
                        }
                    }
                    stored.min_max()
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

/// Computes a tile's inputs from the index and brick headers alone (no voxel decoded).
///
/// # Errors
/// The tile lies outside the volume, or a brick header fails to read.
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
        Stitching::Transitions => transition_faces(layout, key),
    };
    let mut desc = Vec::with_capacity(64 + 2 * 27 * 9);
    desc.push(key.level);
    desc.extend_from_slice(&iso.to_bits().to_le_bytes());
    desc.extend_from_slice(&layout.brick().to_le_bytes());
    desc.push(layout.voxel_type().bytes() as u8);
    desc.extend([key.x, key.y, key.z].map(|c| (c == 0) as u8));
    desc.push(faces);
    // The field march reads (its cells' corners and the normals' halo); the corners alone
    // decide whether a surface crosses the cells.
    let field = stored_box(key.level, lo.map(|c| c - 1), hi.map(|c| c + 1));
    let corners = stored_box(key.level, lo, hi);
    let (min, max) = describe_bricks(snap, key.level, field, corners, &mut desc)?;
    let (mut low, mut high) = value_range(key.level, f32::from(min), f32::from(max));
    if faces != 0 {
        // Which side of its parent the tile lies on fixes where its strips' coarse vertices
        // and moves are; the coarser voxels the strips read.
        desc.extend([key.x, key.y, key.z].map(|c| (c % 2) as u8));
        let (c, d) = coarse_box(lo, hi);
        let coarse = stored_box(key.level + 1, c, d);
        let (min, max) = describe_bricks(snap, key.level + 1, coarse, coarse, &mut desc)?;
        let (l, h) = value_range(key.level + 1, f32::from(min), f32::from(max));
        low = low.min(l);
        high = high.max(h);
    }
    Ok(TileInputs {
        key: xxhash_rust::xxh3::xxh3_128(&desc),
        may_cross: low < iso && high >= iso,
        faces,
    })
}

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

/// Meshes tile `key` of `snap` at `iso` into `out` (cleared first) with its transition data,
/// in world coordinates.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_tile_with_transitions(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    out: &mut TileMesh,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    let inputs = tile_inputs(snap, key, iso, Stitching::Transitions)?;
    let stats = mesh_tile_from(snap, key, iso, &inputs, out, scratch)?;
    tile_to_world(out, key, snap);
    Ok(stats)
}

/// Moves a tile's local mesh (lattice coordinates relative to the tile's frame) to world
/// coordinates: lattice point j of level k at `2^k j` times the voxel scale.
pub fn to_world(mesh: &mut Mesh, key: BrickKey, snap: &Snapshot) {
    let (positions, normals) = (&mut mesh.positions, &mut mesh.normals);
    positions_to_world(positions, key, snap);
    normals_to_world(normals, snap);
}

/// [`to_world`] for a tile with its transition data (vertices, and the moves' offsets).
pub fn tile_to_world(tile: &mut TileMesh, key: BrickKey, snap: &Snapshot) {
    to_world(&mut tile.mesh, key, snap);
    let tr = &mut tile.transitions;
    positions_to_world(&mut tr.positions, key, snap);
    normals_to_world(&mut tr.normals, snap);
    let step = (1u64 << key.level) as f32;
    let scale = snap.header().voxel_scale;
    for m in &mut tr.moves {
        for a in 0..3 {
            m.offset[a] = m.offset[a] * step * scale[a];
        }
    }
}

fn positions_to_world(positions: &mut [[f32; 3]], key: BrickKey, snap: &Snapshot) {
    let b = snap.layout().brick() as f32;
    let origin = [key.x, key.y, key.z].map(|c| c as f32 * b);
    let step = (1u64 << key.level) as f32;
    let scale = snap.header().voxel_scale;
    for p in positions {
        for a in 0..3 {
            p[a] = (p[a] + origin[a]) * step * scale[a];
        }
    }
}

fn normals_to_world(normals: &mut [[f32; 3]], snap: &Snapshot) {
    let scale = snap.header().voxel_scale;
    if scale[0] != scale[1] || scale[1] != scale[2] {
        for n in normals {
            let m = [n[0] / scale[0], n[1] / scale[1], n[2] / scale[2]];
            let len = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
            if len > 0.0 {
                *n = m.map(|c| c / len);
            }
        }
    }
}

/// Meshes tile `key` into `out` (cleared first) in local lattice coordinates (relative to the
/// tile's frame, level-k lattice units), with transition data for the faces `inputs` names.
/// `inputs` comes from [`tile_inputs`] (the cache and the HTTP handler compute it for the key
/// and the ETag; doing it again costs the index lookups).
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
    let (mesh, transitions) = (&mut out.mesh, &mut out.transitions);
    mesh_into(snap, key, iso, inputs, mesh, Some(transitions), scratch)
}

/// The regular mesh into `mesh`, and the transition data into `transitions` when given.
fn mesh_into(
    snap: &Snapshot,
    key: BrickKey,
    iso: f32,
    inputs: &TileInputs,
    mesh: &mut Mesh,
    transitions: Option<&mut Transitions>,
    scratch: &mut TileScratch,
) -> Result<TileStats, StoreError> {
    mesh.clear();
    let transitions = transitions.map(|t| {
        t.clear();
        t
    });
    if !inputs.may_cross {
        return Ok(TileStats {
            skipped: true,
            triangles: 0,
        });
    }
    let layout = snap.layout();
    let (lo, hi, frame) = cells(layout, key);
    let bricks = scratch.bricks.clone();
    let fine = lattice(
        snap,
        key.level,
        (lo.map(|c| c - 1), hi.map(|c| c + 1)),
        bricks.as_deref(),
        &mut scratch.stored,
        &mut scratch.field,
    )?;
    march(&fine, lo, frame, hi, iso, mesh, &mut scratch.march);
    if let Some(transitions) = transitions.filter(|_| inputs.faces != 0) {
        let (c, d) = coarse_box(lo, hi);
        let coarse = lattice(
            snap,
            key.level + 1,
            (c, d),
            bricks.as_deref(),
            &mut scratch.stored,
            &mut scratch.coarse,
        )?;
        let input = TransitionInput {
            fine: &fine,
            coarse: &coarse,
            lo,
            hi,
            frame,
            coarse_frame: [key.x, key.y, key.z].map(|c| i64::from(c / 2) * layout.brick() as i64),
            iso,
            faces: inputs.faces,
        };
        mesh_transitions(
            &input,
            mesh,
            &scratch.march,
            transitions,
            &mut scratch.transitions,
        );
    }
    Ok(TileStats {
        skipped: false,
        triangles: mesh.triangles(),
    })
}

/// The lattice values of `level` over `[lo, hi]` (inclusive), as a field over `out`: the stored
/// voxels themselves at level 0, resampled from the stored voxels around them above.
fn lattice<'o>(
    snap: &Snapshot,
    level: u8,
    (lo, hi): ([i64; 3], [i64; 3]),
    bricks: Option<&DecodedBricks>,
    stored: &mut Vec<f32>,
    out: &'o mut Vec<f32>,
) -> Result<Field<'o>, StoreError> {
    let size = |lo: [i64; 3], hi: [i64; 3]| [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
    if level == 0 {
        gather(snap, level, lo, size(lo, hi), bricks, out)?;
        let out: &'o Vec<f32> = out;
        return Ok(Field {
            origin: lo,
            size: size(lo, hi),
            values: out,
        });
    }
    let (slo, shi) = stored_box(level, lo, hi);
    gather(snap, level, slo, size(slo, shi), bricks, stored)?;
    let field = Field {
        origin: slo,
        size: size(slo, shi),
        values: stored,
    };
    Ok(lattice_field(&field, level, out))
}

/// Writes into `out` the stored voxels of `level` over the box `origin .. origin + size`
/// (L outside the volume), x fastest.
fn gather(
    snap: &Snapshot,
    level: u8,
    origin: [i64; 3],
    size: [usize; 3],
    bricks: Option<&DecodedBricks>,
    out: &mut Vec<f32>,
) -> Result<(), StoreError> {
    let layout = snap.layout();
    let b = layout.brick() as i64;
    let grid = layout.grid(level).map(|g| g as i64);
    out.clear();
    out.resize(size[0] * size[1] * size[2], 0.0);
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
                    level,
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
                            out[row..row + width].fill(v as f32);
                        }
                    }
                    StoredBrick::Record { header, .. } => {
                        let bytes = match bricks {
                            Some(cache) => cache.voxels(header.hash, &stored, layout)?,
                            None => decode(&stored, layout)?,
                        };
                        for (y, z) in rows {
                            let row = at(y, z);
                            let src = (((z - blo[2]) * b + (y - blo[1])) * b + (from[0] - blo[0]))
                                as usize;
                            let dst = &mut out[row..row + width];
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
    Ok(())
}
