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

use super::lattice::{
    lattice_field, lattice_plane, lattice_point, value_range, weights, LatticeScratch,
};
use super::mc::{march, Field, Kernel, Mesh, Scratch};
use super::transition::{mesh_transitions, TransitionInput, TransitionScratch};
use crate::store::codec::min_max;
use crate::store::decoded::{decode, DecodedBricks};
use crate::store::{Snapshot, StoreError, StoredBrick};
use bytes::Bytes;
use isovox_proto::lod::FACE_DIRECTIONS;
use isovox_proto::mesh::{TileMesh, Transitions};
use isovox_proto::tile::{
    bricks_of, cells, coarse_box, field_box, has_transitions, stored_box, GridBox,
};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use std::sync::Arc;

/// Reusable memory for meshing tiles one after another on one thread.
#[derive(Debug, Default)]
pub struct TileScratch {
    stored: Vec<f32>,
    field: Vec<f32>,
    coarse: Vec<f32>,
    coarse_voxels: Vec<f32>,
    region: Vec<f32>,
    /// The coarser level's bricks a tile's strips read, and the points beside a face's plane
    /// its strip reads.
    coarse_bricks: BrickWindow,
    beside: Vec<[i64; 3]>,
    flags: Vec<[bool; 2]>,
    /// The bricks of a tile's own level.
    fine_bricks: BrickWindow,
    lattice: LatticeScratch,
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

    /// This scratch, marching with `kernel` (the benchmark times the previous kernel with it).
    pub fn with_kernel(mut self, kernel: Kernel) -> Self {
        self.march.kernel = kernel;
        self
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

/// The iso value to mesh at: `iso`, or [`default_iso`] when none is given.
///
/// # Errors
/// An iso value outside the voxel type's [L, H] (or NaN): every voxel would lie on one side of
/// the surface, and an empty mesh would hide the mistake (a u16 iso asked of a u8 volume, say).
pub fn iso_value(iso: Option<f32>, t: VoxelType) -> Result<f32, String> {
    let iso = iso.unwrap_or_else(|| default_iso(t));
    if !(t.low() as f32..=t.high() as f32).contains(&iso) {
        return Err(format!(
            "iso {iso} is outside the volume's value range [{}, {}]",
            t.low(),
            t.high()
        ));
    }
    Ok(iso)
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
    /// Whether the iso value can lie between the samples the tile reads (from brick min/max):
    /// whether the tile can hold anything.
    pub may_cross: bool,
    /// Whether the iso value can lie between the samples its cells read (its level's alone):
    /// whether its regular mesh can hold anything; when not, [`TileInputs::fine_inside`] says
    /// on which side all of them are.
    pub fine_may_cross: bool,
    /// Without a crossing in the cells: whether all their samples are inside.
    pub fine_inside: bool,
    /// The faces to build strips for (a face mask; 0 without transitions).
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
fn describe_bricks(
    snap: &Snapshot,
    level: u8,
    read: GridBox,
    crossing: GridBox,
    desc: &mut Vec<u8>,
) -> Result<(u16, u16), StoreError> {
    let layout = snap.layout();
    let grid = layout.grid(level).map(|g| g as i64);
    let (first, last) = bricks_of(layout.brick(), read);
    let (cross_first, cross_last) = bricks_of(layout.brick(), crossing);
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
    let field = stored_box(key.level, field_box(layout, key));
    let corners = stored_box(key.level, (lo, hi));
    let (min, max) = describe_bricks(snap, key.level, field, corners, &mut desc)?;
    let (fine_low, fine_high) = value_range(key.level, f32::from(min), f32::from(max));
    let (mut low, mut high) = (fine_low, fine_high);
    if faces != 0 {
        // Which side of its parent the tile lies on fixes where its strips' coarse vertices
        // and moves are; the coarser voxels the strips read.
        desc.extend([key.x, key.y, key.z].map(|c| (c % 2) as u8));
        let coarse = stored_box(key.level + 1, coarse_box(layout, key));
        let (min, max) = describe_bricks(snap, key.level + 1, coarse, coarse, &mut desc)?;
        let (l, h) = value_range(key.level + 1, f32::from(min), f32::from(max));
        low = low.min(l);
        high = high.max(h);
    }
    // At or below L every voxel, and the padding outside the volume, is inside: there is no
    // surface. The coarser lattice values can still dip below L (Catmull-Rom's negative
    // weights next to bright voxels), which would draw rings of that undershoot, and strips
    // reaching into the padding where the finer field has no halo for their normals.
    let surface_possible = iso > layout.voxel_type().low() as f32;
    Ok(TileInputs {
        key: xxhash_rust::xxh3::xxh3_128(&desc),
        may_cross: surface_possible && low < iso && high >= iso,
        fine_may_cross: surface_possible && fine_low < iso && fine_high >= iso,
        fine_inside: fine_low >= iso,
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
        for (c, s) in m.offset.iter_mut().zip(scale) {
            *c = *c * step * s;
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
    let mut transitions = transitions;
    if let Some(t) = transitions.as_deref_mut() {
        t.clear();
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
    let fine_box = field_box(layout, key);
    // The regular mesh, where the cells' samples can straddle the iso value.
    if inputs.fine_may_cross {
        let fine = lattice(
            snap,
            key.level,
            fine_box,
            bricks.as_deref(),
            (
                &mut scratch.fine_bricks,
                &mut scratch.stored,
                &mut scratch.lattice,
            ),
            &mut scratch.field,
        )?;
        march(&fine, lo, frame, hi, iso, mesh, &mut scratch.march);
    } else {
        scratch.march.forget();
    }
    let Some(transitions) = transitions.filter(|_| inputs.faces != 0) else {
        return Ok(TileStats {
            skipped: false,
            triangles: mesh.triangles(),
        });
    };
    // The coarser level's lattice values a strip reads: the face's plane and one point on
    // each side of it (normals), only for the faces whose strips can hold a triangle. Most
    // faces of a tile near a surface have none: their fine samples are all on one side, and
    // so are the coarse ones, which the range of the coarse voxels under the face usually
    // shows without computing a lattice value.
    let coarse_level = key.level + 1;
    let (c, d) = coarse_box(layout, key);
    let size = field_size((c, d));
    scratch.coarse.clear();
    scratch.coarse.resize(size[0] * size[1] * size[2], f32::NAN);
    // The coarser bricks the strips can read, looked up once for all the faces.
    let read = stored_box(coarse_level, (c, d));
    scratch
        .coarse_bricks
        .open(snap, coarse_level, read, bricks.as_deref())?;
    // Which faces' fine samples straddle the iso value: march makes a vertex on every crossed
    // edge between the corners [lo, hi] and lists those on the boundary, so a face is mixed
    // exactly when one of them lies in its plane (both ends on it). The faces' samples are
    // corners, unless the tile is first on an axis: its faces start one point lower there,
    // and are read one by one.
    let fine = |values| Field {
        origin: fine_box.0,
        size: field_size(fine_box),
        values,
    };
    let fine_mixed = if !inputs.fine_may_cross {
        Some(0)
    } else if lo.iter().all(|c| c.rem_euclid(2) == 0) {
        let border = &scratch.march.border;
        Some(
            border
                .iter()
                .fold(0u8, |m, b| m | (b.faces[0] & b.faces[1])),
        )
    } else {
        None
    };
    // A tile without a vertex has all its samples on one side; most such tiles lie far enough
    // from a surface that the coarse voxels around it are all on that side too: one range over
    // them decides every face.
    let one_side = if !inputs.fine_may_cross {
        Some(inputs.fine_inside)
    } else if mesh.positions.is_empty() && fine_mixed.is_some() {
        Some(fine(&scratch.field).value(lo) >= iso)
    } else {
        None
    };
    if let Some(inside) = one_side {
        let (min, max) = voxel_range(&scratch.coarse_bricks, layout, read);
        let (low, high) = value_range(coarse_level, f32::from(min), f32::from(max));
        if (inside && low >= iso) || (!inside && high < iso) {
            // No vertex, no strip: nothing to move or add.
            return Ok(TileStats {
                skipped: false,
                triangles: 0,
            });
        }
    }
    let mut strips = 0u8;
    let weights = weights(coarse_level);
    let outside = layout.voxel_type().low() as f32;
    for face in (0..6).filter(|f| inputs.faces >> f & 1 == 1) {
        let points = face_points(face, (c, d));
        // The fine face's samples, when they straddle the iso value, decide alone; else the
        // coarse plane does, against the side they are all on.
        let fine_side = match fine_mixed {
            _ if !inputs.fine_may_cross => Some(inputs.fine_inside),
            Some(mixed) if mixed >> face & 1 == 1 => None,
            Some(_) => Some(fine(&scratch.field).value(points.0.map(|v| 2 * v)) >= iso),
            None => fine_face_side(&fine(&scratch.field), points, face, iso),
        };
        if let Some(inside) = fine_side {
            // All on one side: the stored voxels' range bounds the lattice values.
            let read = stored_box(coarse_level, points);
            let (min, max) = voxel_range(&scratch.coarse_bricks, layout, read);
            let (low, high) = value_range(coarse_level, f32::from(min), f32::from(max));
            if (inside && low >= iso) || (!inside && high < iso) {
                continue;
            }
        }
        // One read of the stored voxels under the face's plane and the planes beside it, then
        // the plane's values (with the ring around the face the normals read).
        let (slo, shi) = stored_box(coarse_level, face_slab(face, (c, d)));
        let stored_size = field_size((slo, shi));
        gather(
            &scratch.coarse_bricks,
            layout,
            slo,
            stored_size,
            &mut scratch.coarse_voxels,
        );
        let stored = Field {
            origin: slo,
            size: stored_size,
            values: &scratch.coarse_voxels,
        };
        let plane_box = face_plane(face, (c, d));
        lattice_plane(
            &stored,
            plane_box,
            face / 2,
            coarse_level,
            layout.voxel_type(),
            &mut scratch.lattice,
            &mut scratch.region,
        );
        let plane_size = field_size(plane_box);
        pad_outside(
            &mut scratch.region,
            (plane_box.0, plane_size),
            layout.dims(),
            coarse_level,
            outside,
        );
        let plane = Field {
            origin: plane_box.0,
            size: plane_size,
            values: &scratch.region,
        };
        if let Some(inside) = fine_side {
            // The plane's own values say.
            if all_on_side(&plane, points, iso, inside) {
                continue;
            }
        }
        strips |= 1 << face;
        copy_into(&mut scratch.coarse, (c, size), &plane);
        // The points beside the plane, for the normals the strip computes: where a coarse or
        // connecting edge of the face is crossed, at both ends. Computed point by point: the
        // few the strip reads, not the two planes.
        let fine_field = fine(&scratch.field);
        let fine_flags = match fine_side {
            Some(inside) => Err(inside),
            None => Ok(&fine_field),
        };
        scratch.beside.clear();
        crossed_points(
            &plane,
            points,
            face,
            iso,
            fine_flags,
            &mut scratch.flags,
            &mut scratch.beside,
        );
        for &q in &scratch.beside {
            for step in [-1, 1] {
                let mut p = q;
                p[face / 2] += step;
                let at = index_in((c, size), p);
                if scratch.coarse[at].is_nan() {
                    scratch.coarse[at] = if lattice_inside(p, layout.dims(), coarse_level) {
                        lattice_point(&stored, p, weights)
                    } else {
                        outside
                    };
                }
            }
        }
    }
    if strips != 0 && !inputs.fine_may_cross {
        // The strips read the fine face samples too (all on one side, no regular vertex).
        lattice(
            snap,
            key.level,
            fine_box,
            bricks.as_deref(),
            (
                &mut scratch.fine_bricks,
                &mut scratch.stored,
                &mut scratch.lattice,
            ),
            &mut scratch.field,
        )?;
    }
    if strips == 0 && !inputs.fine_may_cross {
        return Ok(TileStats {
            skipped: false,
            triangles: 0,
        });
    }
    let fine = Field {
        origin: fine_box.0,
        size: field_size(fine_box),
        values: &scratch.field,
    };
    let coarse = Field {
        origin: c,
        size,
        values: &scratch.coarse,
    };
    let input = TransitionInput {
        fine: &fine,
        coarse: &coarse,
        lo,
        hi,
        frame,
        coarse_frame: [key.x, key.y, key.z].map(|c| i64::from(c / 2) * layout.brick() as i64),
        iso,
        faces: inputs.faces,
        strips,
    };
    mesh_transitions(
        &input,
        mesh,
        &scratch.march,
        transitions,
        &mut scratch.transitions,
    );
    Ok(TileStats {
        skipped: false,
        triangles: mesh.triangles(),
    })
}

/// The number of points of a box on each axis.
fn field_size((lo, hi): GridBox) -> [usize; 3] {
    [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize)
}

/// The coarser level's lattice points on face `face` of a tile whose strips read `(c, d)`
/// (see [`coarse_box`]): the plane c + 1 on the low side, d - 1 on the high one, over the
/// face's extent `[c + 1, d - 1]`; these decide the strip's cells.
fn face_points(face: usize, (c, d): GridBox) -> GridBox {
    let a = face / 2;
    let (mut lo, mut hi) = (c.map(|v| v + 1), d.map(|v| v - 1));
    let at = if face & 1 == 1 { d[a] - 1 } else { c[a] + 1 };
    lo[a] = at;
    hi[a] = at;
    (lo, hi)
}

/// The coarser level's lattice points a strip of face `face` reads: its plane across the
/// whole box `(c, d)` and the planes on either side (the normals' central differences).
fn face_slab(face: usize, (c, d): GridBox) -> GridBox {
    let a = face / 2;
    let at = if face & 1 == 1 { d[a] - 1 } else { c[a] + 1 };
    let (mut lo, mut hi) = (c, d);
    lo[a] = at - 1;
    hi[a] = at + 1;
    (lo, hi)
}

/// The coarser level's lattice points on the plane of face `face` across the whole box
/// `(c, d)`: the face's points and the ring around them that the normals read.
fn face_plane(face: usize, (c, d): GridBox) -> GridBox {
    let a = face / 2;
    let at = if face & 1 == 1 { d[a] - 1 } else { c[a] + 1 };
    let (mut lo, mut hi) = (c, d);
    lo[a] = at;
    hi[a] = at;
    (lo, hi)
}

/// The index of point `p` in a buffer over the box from `origin` with `size` points per axis.
fn index_in((origin, size): ([i64; 3], [usize; 3]), p: [i64; 3]) -> usize {
    let l = [0, 1, 2].map(|a| (p[a] - origin[a]) as usize);
    (l[2] * size[1] + l[1]) * size[0] + l[0]
}

/// Whether every value of `field` over the box `points` lies on the side `inside` of `iso`.
fn all_on_side(field: &Field<'_>, (lo, hi): GridBox, iso: f32, inside: bool) -> bool {
    let width = (hi[0] - lo[0] + 1) as usize;
    (lo[2]..=hi[2]).all(|z| {
        (lo[1]..=hi[1]).all(|y| {
            let at = field.index([lo[0], y, z]);
            field.values[at..at + width]
                .iter()
                .all(|&v| (v >= iso) == inside)
        })
    })
}

/// The points of a face (`points`, a box one point thick across `face`'s axis, held by
/// `plane`) where an edge of its transition cells' coarse face or a connecting edge is
/// crossed, at either end: where a point's side of `iso` differs from a neighbour's on the
/// face, or from its fine twin's (read from `fine` at twice the point, or `fine_side` for all
/// of them). The strip computes normals there, which read the points beside the plane.
fn crossed_points(
    plane: &Field<'_>,
    (lo, hi): GridBox,
    face: usize,
    iso: f32,
    fine: Result<&Field<'_>, bool>,
    flags: &mut Vec<[bool; 2]>,
    out: &mut Vec<[i64; 3]>,
) {
    // The face's two lateral axes, and the strides along them in each field.
    let (ua, va) = [(1, 2), (0, 2), (0, 1)][face / 2];
    let (nu, nv) = (
        (hi[ua] - lo[ua] + 1) as usize,
        (hi[va] - lo[va] + 1) as usize,
    );
    let stride = |f: &Field<'_>, a: usize| [1, f.size[0], f.size[0] * f.size[1]][a];
    flags.clear();
    let first = plane.index(lo);
    let (su, sv) = (stride(plane, ua), stride(plane, va));
    for v in 0..nv {
        let row = first + v * sv;
        flags.extend((0..nu).map(|u| [plane.values[row + u * su] >= iso, false]));
    }
    match fine {
        Ok(f) => {
            // The fine twins, every other fine point.
            let first = f.index(lo.map(|c| 2 * c));
            let (su, sv) = (2 * stride(f, ua), 2 * stride(f, va));
            for v in 0..nv {
                let row = first + v * sv;
                for (u, flag) in flags[v * nu..][..nu].iter_mut().enumerate() {
                    flag[1] = f.values[row + u * su] >= iso;
                }
            }
        }
        Err(side) => flags.iter_mut().for_each(|flag| flag[1] = side),
    }
    for v in 0..nv {
        for u in 0..nu {
            let at = v * nu + u;
            let here = flags[at][0];
            let differs = |other: usize| flags[other][0] != here;
            let crossed = here != flags[at][1]
                || (u > 0 && differs(at - 1))
                || (u + 1 < nu && differs(at + 1))
                || (v > 0 && differs(at - nu))
                || (v + 1 < nv && differs(at + nu));
            if crossed {
                let mut p = lo;
                p[ua] += u as i64;
                p[va] += v as i64;
                out.push(p);
            }
        }
    }
}

/// Copies the values of `part` into `buffer`, a field over the box from `origin` with `size`
/// points per axis that holds `part`'s box.
fn copy_into(buffer: &mut [f32], (origin, size): ([i64; 3], [usize; 3]), part: &Field<'_>) {
    let width = part.size[0];
    let mut rows = part.values.chunks_exact(width);
    for z in 0..part.size[2] as i64 {
        for y in 0..part.size[1] as i64 {
            let p = [part.origin[0], part.origin[1] + y, part.origin[2] + z];
            let at = (((p[2] - origin[2]) as usize * size[1]) + (p[1] - origin[1]) as usize)
                * size[0]
                + (p[0] - origin[0]) as usize;
            if let Some(src) = rows.next() {
                buffer[at..at + width].copy_from_slice(src);
            }
        }
    }
}

/// The side of the iso value all the fine samples of face `face` lie on (inside: true), or
/// `None` when they straddle it: the fine lattice points twice the coarse face `points`, read
/// from `fine`.
fn fine_face_side(fine: &Field<'_>, points: GridBox, face: usize, iso: f32) -> Option<bool> {
    let (lo, hi) = (points.0.map(|v| 2 * v), points.1.map(|v| 2 * v));
    let base = fine.index(lo);
    let first = fine.values[base] >= iso;
    // Along the face's two lateral axes; its normal axis has one point.
    let (ua, va) = match face / 2 {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let n = fine.size;
    let stride = |a: usize| [1, n[0], n[0] * n[1]][a];
    let (su, sv) = (stride(ua), stride(va));
    let (nu, nv) = ((hi[ua] - lo[ua]) as usize, (hi[va] - lo[va]) as usize);
    let mixed = (0..=nv).any(|v| {
        let row = base + v * sv;
        (0..=nu).any(|u| (fine.values[row + u * su] >= iso) != first)
    });
    (!mixed).then_some(first)
}

/// The lattice values of `level` over `[lo, hi]` (inclusive), as a field over `out`: the stored
/// voxels themselves at level 0, resampled from the stored voxels around them above; L outside
/// the volume at every level.
fn lattice<'o>(
    snap: &Snapshot,
    level: u8,
    (lo, hi): ([i64; 3], [i64; 3]),
    bricks: Option<&DecodedBricks>,
    (window, stored, scratch): (&mut BrickWindow, &mut Vec<f32>, &mut LatticeScratch),
    out: &'o mut Vec<f32>,
) -> Result<Field<'o>, StoreError> {
    let layout = snap.layout();
    let (slo, shi) = stored_box(level, (lo, hi));
    window.open(snap, level, (slo, shi), bricks)?;
    if level == 0 {
        gather(window, layout, lo, field_size((lo, hi)), out);
        let out: &'o Vec<f32> = out;
        return Ok(Field {
            origin: lo,
            size: field_size((lo, hi)),
            values: out,
        });
    }
    gather(window, layout, slo, field_size((slo, shi)), stored);
    let field = Field {
        origin: slo,
        size: field_size((slo, shi)),
        values: stored,
    };
    let t = layout.voxel_type();
    let lattice = lattice_field(&field, (lo, hi), level, t, scratch, &mut *out);
    let (origin, size) = (lattice.origin, lattice.size);
    let low = layout.voxel_type().low() as f32;
    pad_outside(out, (origin, size), layout.dims(), level, low);
    let out: &'o Vec<f32> = out;
    Ok(Field {
        origin,
        size,
        values: out,
    })
}

/// Whether lattice point `j` of `level` lies in the volume (level-0 position `2^k j` inside
/// `[0, dims)` on every axis).
fn lattice_inside(j: [i64; 3], dims: [u32; 3], level: u8) -> bool {
    (0..3).all(|a| (0..i64::from(dims[a])).contains(&(j[a] << level)))
}

/// Sets the lattice points of `level` that lie outside the volume (level-0 position `2^k j`
/// outside `[0, dims)`) to `low`, as level 0's padding is. Resampled there, they would ring
/// past L next to bright voxels (Catmull-Rom's negative weights, squared across an edge of the
/// volume), drawing surfaces in the padding that the finer level, all L there, cannot meet:
/// its transition strips would find crossings where it has no vertices.
fn pad_outside(
    values: &mut [f32],
    (origin, size): ([i64; 3], [usize; 3]),
    dims: [u32; 3],
    level: u8,
    low: f32,
) {
    let step = 1i64 << level;
    let inside = |a: usize, j: i64| (0..i64::from(dims[a])).contains(&(j * step));
    let last = [0, 1, 2].map(|a| origin[a] + size[a] as i64 - 1);
    if (0..3).all(|a| inside(a, origin[a]) && inside(a, last[a])) {
        return;
    }
    for z in 0..size[2] {
        let z_in = inside(2, origin[2] + z as i64);
        for y in 0..size[1] {
            let yz_in = z_in && inside(1, origin[1] + y as i64);
            let row = &mut values[(z * size[1] + y) * size[0]..][..size[0]];
            for (x, v) in row.iter_mut().enumerate() {
                if !(yz_in && inside(0, origin[0] + x as i64)) {
                    *v = low;
                }
            }
        }
    }
}

/// What one brick holds, looked up once.
#[derive(Debug, Clone)]
enum BrickVoxels {
    /// One value throughout: a constant brick, or L outside the volume.
    Constant(u16),
    /// The brick's voxels as stored (little-endian for u16).
    Voxels(Bytes),
}

/// The bricks of one level holding a box of voxels, each looked up (and decoded, or taken from
/// the shared cache) once, so that the many small reads of a tile's strips do not repeat the
/// index lookups.
#[derive(Debug, Default)]
struct BrickWindow {
    /// The first brick position on each axis, and the number of bricks.
    first: [i64; 3],
    count: [usize; 3],
    /// x fastest.
    bricks: Vec<BrickVoxels>,
}

impl BrickWindow {
    /// Looks up the bricks of `level` holding the voxels `(lo, hi)` (inclusive).
    fn open(
        &mut self,
        snap: &Snapshot,
        level: u8,
        voxels: GridBox,
        cache: Option<&DecodedBricks>,
    ) -> Result<(), StoreError> {
        let layout = snap.layout();
        let grid = layout.grid(level).map(i64::from);
        let (first, last) = bricks_of(layout.brick(), voxels);
        self.first = first;
        self.count = [0, 1, 2].map(|a| (last[a] - first[a] + 1) as usize);
        self.bricks.clear();
        for z in first[2]..=last[2] {
            for y in first[1]..=last[1] {
                for x in first[0]..=last[0] {
                    let c = [x, y, z];
                    if !(0..3).all(|a| c[a] >= 0 && c[a] < grid[a]) {
                        self.bricks.push(BrickVoxels::Constant(0)); // outside: L
                        continue;
                    }
                    let key = BrickKey {
                        level,
                        x: x as u32,
                        y: y as u32,
                        z: z as u32,
                    };
                    self.bricks.push(match snap.stored(key)? {
                        StoredBrick::Constant(v) => BrickVoxels::Constant(v),
                        record @ StoredBrick::Record { header, .. } => {
                            BrickVoxels::Voxels(match cache {
                                Some(cache) => cache.voxels(header.hash, &record, layout)?,
                                None => decode(&record, layout)?,
                            })
                        }
                    });
                }
            }
        }
        Ok(())
    }

    /// The brick at position `c` (inside the window).
    fn brick(&self, c: [i64; 3]) -> &BrickVoxels {
        let l = [0, 1, 2].map(|a| (c[a] - self.first[a]) as usize);
        &self.bricks[(l[2] * self.count[1] + l[1]) * self.count[0] + l[0]]
    }
}

/// One row of stored voxels, as its brick holds it.
enum Row<'a> {
    /// One value across the row: a constant brick, or L outside the volume.
    Constant(u16),
    /// The row's voxels as stored (little-endian for u16).
    Voxels(&'a [u8]),
}

/// Visits the stored voxels over the box `origin .. origin + size` (within `window`) row by
/// row, brick by brick: `visit(at, width, row)` for each row piece, `at` its first voxel's
/// index in a buffer over the box (x fastest). Together the pieces cover the box once.
fn for_each_row(
    window: &BrickWindow,
    layout: &VolumeLayout,
    origin: [i64; 3],
    size: [usize; 3],
    mut visit: impl FnMut(usize, usize, Row<'_>),
) {
    let b = layout.brick() as i64;
    let bytes_per_voxel = layout.voxel_type().bytes();
    let end = [0, 1, 2].map(|a| origin[a] + size[a] as i64); // exclusive
    for bz in origin[2].div_euclid(b)..=(end[2] - 1).div_euclid(b) {
        for by in origin[1].div_euclid(b)..=(end[1] - 1).div_euclid(b) {
            for bx in origin[0].div_euclid(b)..=(end[0] - 1).div_euclid(b) {
                let c = [bx, by, bz];
                let blo = c.map(|v| v * b);
                let from = [0, 1, 2].map(|a| blo[a].max(origin[a]));
                let to = [0, 1, 2].map(|a| (blo[a] + b).min(end[a]));
                let width = (to[0] - from[0]) as usize;
                let rows = (from[2]..to[2]).flat_map(|z| (from[1]..to[1]).map(move |y| (y, z)));
                let at = |y: i64, z: i64| {
                    ((((z - origin[2]) as usize * size[1]) + (y - origin[1]) as usize) * size[0])
                        + (from[0] - origin[0]) as usize
                };
                match window.brick(c) {
                    BrickVoxels::Constant(v) => {
                        rows.for_each(|(y, z)| visit(at(y, z), width, Row::Constant(*v)));
                    }
                    BrickVoxels::Voxels(voxels) => {
                        for (y, z) in rows {
                            let src = (((z - blo[2]) * b + (y - blo[1])) * b + (from[0] - blo[0]))
                                as usize;
                            let row = &voxels[src * bytes_per_voxel..][..width * bytes_per_voxel];
                            visit(at(y, z), width, Row::Voxels(row));
                        }
                    }
                }
            }
        }
    }
}

/// Writes into `out` the stored voxels over the box `origin .. origin + size` (within
/// `window`; L outside the volume), x fastest. Every value is written once (no clearing pass).
fn gather(
    window: &BrickWindow,
    layout: &VolumeLayout,
    origin: [i64; 3],
    size: [usize; 3],
    out: &mut Vec<f32>,
) {
    out.resize(size[0] * size[1] * size[2], 0.0);
    let t = layout.voxel_type();
    for_each_row(window, layout, origin, size, |at, width, row| {
        let dst = &mut out[at..at + width];
        match (row, t) {
            (Row::Constant(v), _) => dst.fill(f32::from(v)),
            (Row::Voxels(bytes), VoxelType::U8) => {
                for (d, s) in dst.iter_mut().zip(bytes) {
                    *d = f32::from(*s);
                }
            }
            (Row::Voxels(bytes), VoxelType::U16) => {
                for (d, s) in dst.iter_mut().zip(bytes.chunks_exact(2)) {
                    *d = f32::from(u16::from_le_bytes([s[0], s[1]]));
                }
            }
        }
    });
}

/// The least and greatest stored voxel over the box `(lo, hi)` (within `window`; L outside
/// the volume), read from the bricks as they are.
fn voxel_range(window: &BrickWindow, layout: &VolumeLayout, (lo, hi): GridBox) -> (u16, u16) {
    let t = layout.voxel_type();
    let mut range = (u16::MAX, u16::MIN);
    for_each_row(window, layout, lo, field_size((lo, hi)), |_, _, row| {
        let (l, h) = match row {
            Row::Constant(v) => (v, v),
            Row::Voxels(bytes) => min_max(bytes, t),
        };
        range = (range.0.min(l), range.1.max(h));
    });
    range
}
