//! Meshing: marching cubes per tile, crack-free across tiles.
//!
//! Layout:
//! - [`cache`]: tile meshes keyed by the content of their inputs, an LRU bounded by bytes.
//! - [`check`]: checks of assembled meshes (closed, enclosed volume, crossing triangles).
//! - [`files`]: GLB, OBJ and PLY output.
//! - [`lattice`]: where each level's samples sit: one nested lattice for all levels.
//! - [`level`]: whole levels and adaptive selections of tiles, stitching, welding.
//! - [`mc`]: the kernel over a sample grid (f32, or a level's voxels as stored): [`mc_rows`] a
//!   row of cells at a time, [`mc_reference`] cell by cell (the previous kernel, the tests'
//!   oracle); [`inside`] classifies a row's samples a vector at a time.
//! - [`tile`]: one brick's mesh with its halo, in world coordinates (the seam rule).
//! - [`table`]: the case table, generated with a face-consistent rule.
//! - [`transition`]: transition strips and secondary positions, the seam rule across levels.
//! - [`transition_table`]: the transition-cell table, generated with the same face rule.

pub mod cache;
pub mod check;
pub mod files;
mod inside;
pub mod lattice;
pub mod level;
pub mod mc;
mod mc_reference;
mod mc_rows;
pub mod table;
pub mod tile;
pub mod transition;
pub mod transition_table;
