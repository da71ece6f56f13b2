//! Isovox: serves large, editable volumes over HTTP.
//!
//! This crate is the server side: the storage engine, the volume algebra, meshing, and the HTTP
//! service. Data flows one way: request -> handler -> volume -> store / icvg / mesh -> bytes.
//! The `isovox` command line is this package's binary (`src/main.rs`, `src/cli/`).
//!
//! Layout:
//! - [`store`]: VOD 1 and VOD 2 files, brick index, deduplication, transactions (the foundation).
//! - [`geometry`]: boxes of voxels, shared by the algebra, edits and generators.
//! - [`icvg`]: the volume algebra: primitives, operators, terms and their compilation, edits.
//! - [`mesh`]: marching cubes per tile, crack-free across tiles; the tile cache; mesh files.
//! - [`voxelize`]: meshes into volumes (solid voxelization by parity, density, conservative fills).
//! - [`generate`]: synthetic data sets (ellipsoid, Perlin-noise world) and the demo scene.
//! - [`volume`]: one served volume: versions, the single writer, reads and edits with their
//!   checks, the change feed; [`volume::VolumeError`] says what went wrong.
//! - [`catalog`]: the volumes a server serves.
//! - [`formats`]: the field's formats: Neuroglancer precomputed and OME-Zarr views of a
//!   snapshot, exports of them, imports from OME-Zarr, Zarr, precomputed, NIfTI-1 and TIFF.
//! - [`http`]: the axum router, thin handlers, errors as responses (`http/error.rs` decides
//!   every status code).
//! - [`progress`]: how long jobs report progress.
//! - [`cancel`]: stopping long CPU work (an edit past its deadline, a client gone, shutdown).
//! - [`client_tls`]: TLS for outgoing requests (imports over https, the object store).
//! - [`decimal`]: numbers in URLs, read in their one canonical spelling.

#![warn(missing_docs)]

pub mod cancel;
pub mod catalog;
pub mod client_tls;
pub mod decimal;
pub mod formats;
pub mod generate;
pub mod geometry;
pub mod http;
pub mod icvg;
pub mod mesh;
pub mod progress;
pub mod store;
pub mod volume;
pub mod voxelize;
