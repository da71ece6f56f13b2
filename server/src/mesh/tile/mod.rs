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
//!
//! Layout:
//! - [`inputs`]: what a tile's or a strip's mesh depends on (content keys), from the index
//!   alone (its brick summaries).
//! - [`regular`]: a tile's regular mesh and its moves.
//! - [`strip`]: a tile's transition strips, in named steps.
//! - [`materials`]: per-vertex materials from a u8 channel, and their content keys.
//! - [`geometry`]: the seam arithmetic: which cells and lattice points a tile and its strips
//!   read, and indices into the buffers that hold them.
//! - [`voxels`]: the stored voxels they read (a window of bricks) and the lattice values
//!   resampled from them.
//! - [`world`]: local lattice coordinates to world coordinates.

mod geometry;
mod inputs;
mod materials;
mod regular;
mod strip;
mod voxels;
mod world;

pub use inputs::{strip_inputs, tile_inputs, StripInputs, TileInputs};
pub use materials::{
    blend, check_material_channel, mesh_strip_materials, mesh_tile_materials, strip_material_key,
    tile_material_key,
};
pub use regular::{mesh_tile, mesh_tile_from, mesh_tile_with_moves};
pub use strip::{mesh_strip_from, mesh_strip_world};
pub use world::{strip_to_world, tile_to_world, to_world};

use super::lattice::LatticeScratch;
use super::mc::{Kernel, Mesh, Scratch};
use super::transition::TransitionScratch;
use crate::store::decoded::DecodedBricks;
use isovox_proto::VoxelType;
use std::sync::Arc;
use voxels::BrickWindow;

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
    /// The channel bricks a tile's or a strip's materials read.
    material_bricks: BrickWindow,
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
