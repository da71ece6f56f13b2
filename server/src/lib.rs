//! Isovox: serves large, editable volumes over HTTP.
//!
//! This crate is the server side: the storage engine, the volume algebra, and the `isovox`
//! command-line tool that drives them. Data flows one way: command or request -> handler ->
//! store / icvg -> bytes.
//!
//! Layout:
//! - [`store`]: VOD 1 and VOD 2 files, brick index, deduplication, commits (the foundation).
//! - [`icvg`]: primitives of the volume algebra (`spec/icvg.md`).
//! - [`generate`]: synthetic data sets (ellipsoid, Perlin-noise world).
//! - [`catalog`]: the volumes a server serves.
//! - [`voxelize`]: meshes into volumes (solid voxelization by parity, density, conservative fills).
//! - [`volume`]: one served volume: current version, single writer, history, change feed.
//! - [`formats`]: the field's formats: Neuroglancer precomputed and OME-Zarr views, imports, exports.
//! - [`http`]: the axum router, thin handlers, errors as responses.
//! - [`cli`]: the `isovox` subcommands.

pub mod catalog;
pub mod cli;
pub mod formats;
pub mod generate;
pub mod http;
pub mod icvg;
pub mod mesh;
pub mod store;
pub mod volume;
pub mod voxelize;
