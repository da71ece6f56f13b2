//! The field's formats: every volume readable as Neuroglancer precomputed and as OME-Zarr 0.5
//! (read-only views of a snapshot, made from the VOD file on request: no copy, no conversion
//! job), exports of those views to a directory, and imports from the formats users have.
//!
//! Layout:
//! - [`view`]: what the views share: resolving a path to a document of a snapshot, chunk
//!   bodies (the stored zstd frame as it is, or decoded), errors.
//! - [`zarr`]: the OME-Zarr 0.5 / Zarr v3 view.
//! - [`precomputed`]: the Neuroglancer precomputed view.
//! - [`export`]: a view written to a directory, byte for byte what the server sends.
//! - [`import`]: OME-Zarr and Zarr v2/v3, Neuroglancer precomputed, NIfTI-1 and TIFF stacks
//!   into a VOD 2 file, streaming by slabs in bounded memory.
//!
//! `docs/formats.md` describes the views, their version-pinned forms and the imports.

pub mod export;
pub mod import;
pub mod precomputed;
pub mod view;
pub mod zarr;

pub use view::{ViewError, ViewKind};

use crate::store::StoreError;
use std::io;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Told (work done, work in all) as a long job goes; units are the job's own (bricks, planes).
pub type Progress<'a> = &'a (dyn Fn(u64, u64) + Sync);

/// Errors of imports and exports.
#[derive(Debug, Error)]
pub enum FormatsError {
    /// An operating-system error, with what was being done.
    #[error("{context}")]
    Io {
        context: String,
        #[source]
        source: io::Error,
    },
    /// The input is malformed, unsupported or inconsistent; the message says what and where.
    #[error("{0}")]
    Input(String),
    /// A request to a server failed or was refused.
    #[error("cannot read {url}: {detail}")]
    Fetch { url: String, detail: String },
    /// Zarr metadata or chunks that `zarrs` cannot read.
    #[error("{context}: {detail}")]
    Zarr { context: String, detail: String },
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    View(#[from] ViewError),
}

impl FormatsError {
    pub(crate) fn io_path(what: &str, path: &Path) -> impl FnOnce(io::Error) -> FormatsError {
        let context = format!("{what} {}", path.display());
        move |source| FormatsError::Io { context, source }
    }

    pub(crate) fn input(detail: impl Into<String>) -> FormatsError {
        FormatsError::Input(detail.into())
    }
}

/// A path with a suffix appended (for temporaries beside an output).
pub(crate) fn sibling(path: &Path, suffix: &str) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}
