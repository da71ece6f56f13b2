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
use super::mc::{march, Field, Kernel, Mesh, Sample, Scratch};
use super::transition::{mesh_strip, tile_moves, TileFaces, TransitionInput, TransitionScratch};
use crate::store::codec::min_max;
use crate::store::decoded::{decode, DecodedBricks};
use crate::store::{Snapshot, StoreError, StoredBrick};
use bytes::Bytes;
use isovox_proto::lod::FACE_DIRECTIONS;
use isovox_proto::mesh::{apply_moves, TileMesh, VertexMove};
use isovox_proto::tile::{
    bricks_of, cells, coarse_box, field_box, has_transitions, stored_box, strip_coarse_box,
    strip_field_box, GridBox,
};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use std::sync::Arc;

/// Reusable memory for meshing tiles one after another on one thread.
#[derive(Debug, Default)]
pub struct TileScratch {
    /// A level-0 tile's voxels as stored, for the type of its volume.
    voxels_u8: Vec<u8>,
    voxels_u16: Vec<u16>,
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
    /// The regular mesh of the layer of cells a strip is built along.
    layer: Mesh,
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

/// Whether a tile is meshed with its moves (see [`super::transition`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stitching {
    /// The regular mesh alone: for one level meshed whole.
    None,
    /// The regular mesh and the moves (secondary positions) of every face with a neighbour
    /// (when a coarser level exists): a tile that can be drawn next to any neighbours, with
    /// the strips of the faces that touch a coarser one ([`mesh_strip_from`]).
    Moves,
}

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
        Stitching::Moves => transition_faces(layout, key),
    };
    let mut desc = describe_tile(layout, key, iso, faces);
    // The field march reads (its cells' corners and the normals' halo); the corners alone
    // decide whether a surface crosses the cells.
    let field = stored_box(key.level, field_box(layout, key));
    let corners = stored_box(key.level, (lo, hi));
    let (min, max) = describe_bricks(snap, key.level, field, corners, &mut desc)?;
    let (low, high) = value_range(key.level, f32::from(min), f32::from(max));
    // At or below L every voxel, and the padding outside the volume, is inside: there is no
    // surface.
    let surface_possible = iso > layout.voxel_type().low() as f32;
    Ok(TileInputs {
        key: xxhash_rust::xxh3::xxh3_128(&desc),
        may_cross: surface_possible && low < iso && high >= iso,
        faces,
    })
}

/// Computes the inputs of the strip of face `face` (0..6) of tile `key` from the index and
/// brick headers alone.
///
/// # Errors
/// The tile lies outside the volume, the face is not one of six, or a brick header fails to
/// read.
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
    let (mut low, mut high) = value_range(key.level, f32::from(min), f32::from(max));
    let coarse = stored_box(key.level + 1, strip_coarse_box(layout, key, face));
    let (min, max) = describe_bricks(snap, key.level + 1, coarse, coarse, &mut desc)?;
    let (l, h) = value_range(key.level + 1, f32::from(min), f32::from(max));
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

/// Meshes the transition strip of face `face` of tile `key` into `out` (cleared first), in
/// world coordinates, as drawn: its vertices moved (see [`strip_to_world`]).
///
/// # Errors
/// The face is not one of six; a brick fails to read.
pub fn mesh_strip_world(
    snap: &Snapshot,
    key: BrickKey,
    face: usize,
    iso: f32,
    out: &mut Mesh,
    scratch: &mut TileScratch,
) -> Result<(), StoreError> {
    let inputs = strip_inputs(snap, key, face, iso)?;
    let mut strip = TileMesh::default();
    mesh_strip_from(snap, key, face, iso, &inputs, &mut strip, scratch)?;
    *out = strip_to_world(strip, key, snap);
    Ok(())
}

/// Moves a tile's local mesh (lattice coordinates relative to the tile's frame) to world
/// coordinates: lattice point j of level k at `2^k j` times the voxel scale.
pub fn to_world(mesh: &mut Mesh, key: BrickKey, snap: &Snapshot) {
    let (positions, normals) = (&mut mesh.positions, &mut mesh.normals);
    positions_to_world(positions, key, snap);
    normals_to_world(normals, snap);
}

/// [`to_world`] for a tile with its moves (their distances too).
pub fn tile_to_world(tile: &mut TileMesh, key: BrickKey, snap: &Snapshot) {
    to_world(&mut tile.mesh, key, snap);
    let step = (1u64 << key.level) as f32;
    let scale = snap.header().voxel_scale;
    for m in &mut tile.moves {
        m.distance = m.distance * step * scale[usize::from(m.face / 2)];
    }
}

/// A local strip ([`mesh_strip_from`]) in world coordinates, as drawn: [`tile_to_world`], then
/// its moves applied exactly as a viewer applies the tile's (`isovox_proto::mesh::stitch`), so
/// that its copies of the tile's vertices are the tile's moved vertices bit for bit.
pub fn strip_to_world(mut strip: TileMesh, key: BrickKey, snap: &Snapshot) -> Mesh {
    tile_to_world(&mut strip, key, snap);
    apply_moves(&mut strip.mesh.positions, &strip.moves, 0x3f);
    strip.mesh
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

/// Where tile `key` lies among its neighbours, for its moves and strips.
fn tile_faces(layout: &VolumeLayout, key: BrickKey, faces: u8) -> TileFaces {
    let (lo, hi, frame) = cells(layout, key);
    TileFaces {
        lo,
        hi,
        frame,
        coarse_frame: [key.x, key.y, key.z].map(|c| i64::from(c / 2) * layout.brick() as i64),
        faces,
    }
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

/// Meshes the transition strip of face `face` of tile `key` into `out` (cleared first), in
/// local lattice coordinates as the tile is: its mesh, with the moves of its vertices along
/// the face (see [`super::transition::mesh_strip`]; [`strip_to_world`] draws it). `inputs`
/// comes from [`strip_inputs`]. Only the layer of the tile's cells along the face is meshed
/// again, not the tile.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_strip_from(
    snap: &Snapshot,
    key: BrickKey,
    face: usize,
    iso: f32,
    inputs: &StripInputs,
    out: &mut TileMesh,
    scratch: &mut TileScratch,
) -> Result<(), StoreError> {
    out.mesh.clear();
    out.moves.clear();
    if !inputs.may_cross || face >= 6 || inputs.faces >> face & 1 == 0 {
        return Ok(());
    }
    let layout = snap.layout();
    let (lo, hi, frame) = cells(layout, key);
    let bricks = scratch.bricks.clone();
    // The layer of cells along the face: its vertices on the face's plane are the tile's there,
    // bit for bit (the same samples, the same formula, the same frame).
    let axis = face / 2;
    let (mut layer_lo, mut layer_hi) = (lo, hi);
    if face & 1 == 1 {
        layer_lo[axis] = hi[axis] - 1;
    } else {
        layer_hi[axis] = lo[axis] + 1;
    }
    // Most faces that can have a strip have none: every fine and coarse sample on the face lies
    // on one side of the iso value, which the ranges of the stored voxels under the face
    // usually show before any lattice value is computed or cell marched.
    let coarse_level = key.level + 1;
    let (c, d) = coarse_box(layout, key);
    let points = face_points(face, (c, d));
    let fine_points = (points.0.map(|v| 2 * v), points.1.map(|v| 2 * v));
    let fine_read = stored_box(key.level, fine_points);
    scratch
        .fine_bricks
        .open(snap, key.level, fine_read, bricks.as_deref())?;
    let (min, max) = voxel_range(&scratch.fine_bricks, layout, fine_read);
    let (fine_low, fine_high) = value_range(key.level, f32::from(min), f32::from(max));
    let (slo, shi) = stored_box(coarse_level, strip_coarse_box(layout, key, face));
    scratch
        .coarse_bricks
        .open(snap, coarse_level, (slo, shi), bricks.as_deref())?;
    let coarse_read = stored_box(coarse_level, points);
    let (min, max) = voxel_range(&scratch.coarse_bricks, layout, coarse_read);
    let (coarse_low, coarse_high) = value_range(coarse_level, f32::from(min), f32::from(max));
    let (low, high) = (fine_low.min(coarse_low), fine_high.max(coarse_high));
    if low >= iso || high < iso {
        return Ok(());
    }
    let fine_box = strip_field_box(layout, key, face);
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
    // `march` appends: without this, the layer kept every earlier strip's vertices, and each
    // strip cleared a table as long as all of them (a pass of many strips grew quadratically).
    scratch.layer.clear();
    march(
        &fine,
        layer_lo,
        frame,
        layer_hi,
        iso,
        &mut scratch.layer,
        &mut scratch.march,
    );
    // The coarser level's lattice values the strip reads: the face's plane and one point on
    // each side of it (normals). Most faces near a surface have no strip: their fine samples
    // are all on one side, and so are the coarse ones, which the range of the coarse voxels
    // under the face usually shows without computing a lattice value.
    let size = field_size((c, d));
    scratch.coarse.clear();
    scratch.coarse.resize(size[0] * size[1] * size[2], f32::NAN);
    // Whether the face's fine samples straddle the iso value: march makes a vertex on every
    // crossed edge between the corners and lists those on the layer's boundary, so the face is
    // mixed exactly when one of them lies in its plane (both ends on it). The face's samples
    // are corners, unless the tile is first on an axis: its faces start one point lower there,
    // and are read one by one.
    let fine_side = if lo.iter().all(|c| c.rem_euclid(2) == 0) {
        let mixed = scratch
            .march
            .border
            .iter()
            .fold(0u8, |m, b| m | (b.faces[0] & b.faces[1]));
        (mixed >> face & 1 == 0).then(|| fine.value(points.0.map(|v| 2 * v)) >= iso)
    } else {
        fine_face_side(&fine, points, face, iso)
    };
    if let Some(inside) = fine_side {
        // All on one side: the stored voxels' range bounds the lattice values.
        let read = stored_box(coarse_level, points);
        let (min, max) = voxel_range(&scratch.coarse_bricks, layout, read);
        let (low, high) = value_range(coarse_level, f32::from(min), f32::from(max));
        if (inside && low >= iso) || (!inside && high < iso) {
            return Ok(());
        }
    }
    // One read of the stored voxels under the face's plane and the planes beside it, then the
    // plane's values (with the ring around the face the normals read).
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
        axis,
        coarse_level,
        layout.voxel_type(),
        &mut scratch.lattice,
        &mut scratch.region,
    );
    let plane_size = field_size(plane_box);
    let outside = layout.voxel_type().low() as f32;
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
            return Ok(());
        }
    }
    copy_into(&mut scratch.coarse, (c, size), &plane);
    // The points beside the plane, for the normals the strip computes: where a coarse or
    // connecting edge of the face is crossed, at both ends. Computed point by point: the few
    // the strip reads, not the two planes.
    let fine_flags = match fine_side {
        Some(inside) => Err(inside),
        None => Ok(&fine),
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
    let weights = weights(coarse_level);
    for &q in &scratch.beside {
        for step in [-1, 1] {
            let mut p = q;
            p[axis] += step;
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
    let coarse = Field {
        origin: c,
        size,
        values: &scratch.coarse,
    };
    let input = TransitionInput {
        tile: tile_faces(layout, key, inputs.faces),
        fine: &fine,
        coarse: &coarse,
        iso,
    };
    mesh_strip(
        &input,
        face,
        &scratch.layer,
        &scratch.march,
        out,
        &mut scratch.transitions,
    );
    Ok(())
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

/// A voxel type as a tile's samples hold it.
trait StoredVoxel: Copy + Default {
    /// The value of a constant brick (or of L outside the volume).
    fn from_constant(v: u16) -> Self;
    /// Copies a row of stored voxels (little-endian for u16) into `dst`.
    fn copy_row(dst: &mut [Self], stored: &[u8]);
}

impl StoredVoxel for u8 {
    fn from_constant(v: u16) -> Self {
        // A u8 volume's values fit a u8.
        v as u8
    }

    fn copy_row(dst: &mut [u8], stored: &[u8]) {
        dst.copy_from_slice(stored);
    }
}

impl StoredVoxel for u16 {
    fn from_constant(v: u16) -> Self {
        v
    }

    fn copy_row(dst: &mut [u16], stored: &[u8]) {
        for (d, s) in dst.iter_mut().zip(stored.chunks_exact(2)) {
            *d = u16::from_le_bytes([s[0], s[1]]);
        }
    }
}

/// Writes into `out` the stored voxels over the box `origin .. origin + size` (within
/// `window`; L outside the volume), x fastest, as they are stored ([`gather`] converts them to
/// f32). Every value is written once.
fn gather_voxels<V: StoredVoxel>(
    window: &BrickWindow,
    layout: &VolumeLayout,
    origin: [i64; 3],
    size: [usize; 3],
    out: &mut Vec<V>,
) {
    out.resize(size[0] * size[1] * size[2], V::default());
    for_each_row(window, layout, origin, size, |at, width, row| {
        let dst = &mut out[at..at + width];
        match row {
            Row::Constant(v) => dst.fill(V::from_constant(v)),
            Row::Voxels(bytes) => V::copy_row(dst, bytes),
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests fail loudly on purpose

    use super::*;
    use crate::generate::WorldSource;
    use crate::store::{build_vod2, BuildOptions, Vod2};

    /// One scratch reused over every strip of a pass holds what the strip in hand needs, as a
    /// fresh one does: nothing of the strips before it.
    #[test]
    fn a_reused_scratch_holds_only_the_current_strips_layer() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.vod");
        let layout = VolumeLayout::new([64, 48, 64], 8, VoxelType::U8).unwrap();
        let source = WorldSource::new(layout.clone(), 3);
        build_vod2(&path, &layout, [1.0; 3], &source, &BuildOptions::default()).unwrap();
        let vod = Vod2::open(&path).unwrap();
        let snap = vod.head();
        let iso = default_iso(VoxelType::U8);
        let mut reused = TileScratch::default();
        let mut with_a_layer = 0;
        for (x, y, z) in
            (0..8).flat_map(|x| (0..6).flat_map(move |y| (0..8).map(move |z| (x, y, z))))
        {
            let key = BrickKey { level: 0, x, y, z };
            for face in 0..6 {
                let (mut a, mut b) = (Mesh::default(), Mesh::default());
                mesh_strip_world(&snap, key, face, iso, &mut a, &mut reused).unwrap();
                let mut fresh = TileScratch::default();
                mesh_strip_world(&snap, key, face, iso, &mut b, &mut fresh).unwrap();
                assert_eq!(a, b, "strip {face} of {key:?}");
                if fresh.layer.positions.is_empty() {
                    continue;
                }
                with_a_layer += 1;
                assert_eq!(
                    reused.layer.positions.len(),
                    fresh.layer.positions.len(),
                    "the layer of strip {face} of {key:?}"
                );
            }
        }
        assert!(
            with_a_layer > 10,
            "only {with_a_layer} strips marched a layer"
        );
    }
}
