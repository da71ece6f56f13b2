//! ICVG: the volume algebra of the papers (`spec/icvg.md`).
//!
//! Layout:
//! - [`primitives`]: virtual volume sampling functions, placed in the world by an offset.
//! - [`ops`]: binary and unary operators on voxel values.
//! - [`term`]: CVG terms compiled for evaluation (validation, B-boxes, evaluation over boxes).
//! - [`edit`]: applying an edit to a stored volume brick by brick, with LOD upkeep and a commit.

pub mod edit;
pub mod ops;
pub mod primitives;
pub mod term;
