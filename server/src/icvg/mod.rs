//! ICVG: the volume algebra of the papers (`docs/icvg.md`).
//!
//! Layout:
//! - [`primitives`]: virtual volume sampling functions, placed in the world by an offset.
//! - [`ops`]: binary and unary operators on voxel values.
//! - [`term`]: CVG terms ready to evaluate (B-boxes, evaluation over boxes).
//! - [`compile`]: JSON terms checked and compiled into [`term::CompiledTerm`]s.
//! - [`edit`]: applying an edit to a stored volume brick by brick, with LOD upkeep and a commit.

pub mod compile;
pub mod edit;
pub mod ops;
pub mod primitives;
pub mod term;
