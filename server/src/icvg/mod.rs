//! ICVG: the volume algebra of the papers (`spec/icvg.md`).
//!
//! Layout:
//! - [`primitives`]: virtual volume sampling functions, placed in the world by an offset.
//!
//! Operators, terms and brick-wise edits come with the editing engine.

pub mod primitives;
