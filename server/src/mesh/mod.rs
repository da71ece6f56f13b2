//! Meshing: marching cubes per tile, crack-free across tiles.
//!
//! Layout:
//! - [`cache`]: tile meshes keyed by the content of their inputs, an LRU bounded by bytes.
//! - [`files`]: GLB, OBJ and PLY output.
//! - [`level`]: whole levels and adaptive tile selections, welding, closedness checks.
//! - [`mc`]: the kernel over a sample grid.
//! - [`tile`]: one brick's mesh with its halo, in world coordinates (the seam rule).
//! - [`table`]: the case table, generated with a face-consistent rule.

pub mod cache;
pub mod files;
pub mod level;
pub mod mc;
pub mod table;
pub mod tile;
pub mod transition_table;
