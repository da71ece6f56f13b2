//! The shared language of the Isovox server and client.
//!
//! Pure data: no I/O, no async runtime, no memory mapping. Everything here works on values and
//! byte slices, so the server, the client, tools and tests agree on one definition.
//!
//! Layout:
//! - [`api`]: the JSON types of the HTTP API.
//! - [`batch`]: many bricks in one response (the batch route's encoding).
//! - [`channel`]: attribute channels (materials, labels) beside density, and their mode.
//! - [`history`]: who did what: commit notes, history, tags, undo, revert, presence.
//! - [`icvg`]: ICVG terms and edit requests (JSON).
//! - [`voxel`]: voxel types and the ICVG value range (L, H, S).
//! - [`layout`]: the brick octree's geometry: levels, brick grids, [`BrickKey`], node indices.
//! - [`lod`]: which tiles a camera needs (the spherical detail bias), balanced so that
//!   neighbours differ by one level at most, and each tile's face mask.
//! - [`mesh`]: triangle meshes and their wire encodings (compact binary, GLB), and stitching a
//!   tile to coarser neighbours.
//! - [`tile`]: which cells a mesh tile owns and which bricks it reads.
//! - [`vod2`]: the VOD 2 file's on-disk records (header, slots, commits, index, bricks), encoded
//!   and decoded over byte slices with validation. The byte layout is in `docs/vod2.md`.
//! - [`error`]: [`FormatError`], what a malformed record is.

#![warn(missing_docs)]

pub mod api;
pub mod batch;
pub mod channel;
pub mod error;
pub mod geometry;
pub mod history;
pub mod icvg;
pub mod layout;
pub mod lod;
pub mod mesh;
pub mod tile;
pub mod vod2;
pub mod voxel;

pub use error::FormatError;
pub use layout::{BrickKey, VolumeLayout};
pub use voxel::VoxelType;
