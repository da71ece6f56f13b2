//! The field's formats: every volume readable as Neuroglancer precomputed and as OME-Zarr 0.5
//! (read-only views of a snapshot, made from the VOD file on request: no copy, no conversion
//! job), exports of those views to a directory, and imports from the formats users have.
//!
//! Layout:
//! - [`view`]: what the views share: resolving a path to a document of a snapshot, chunk
//!   bodies (the stored zstd frame as it is, or made through the shared cache of decoded
//!   bricks), [`ViewError`].
//! - [`zarr`]: the OME-Zarr 0.5 / Zarr v3 view.
//! - [`precomputed`]: the Neuroglancer precomputed view.
//! - [`export`]: a view written to a directory, byte for byte what the server sends.
//! - [`import`]: OME-Zarr and Zarr v2/v3, Neuroglancer precomputed, NIfTI-1 and TIFF stacks
//!   into a VOD 2 file, streaming by slabs in bounded memory.
//!
//! `docs/formats.md` describes the views, their version-pinned forms and the imports.

pub mod compressed_segmentation;
pub mod export;
pub mod import;
pub mod precomputed;
pub mod view;
pub mod zarr;

pub use view::{ViewError, ViewKind};

use crate::store::StoreError;
use std::io;
use std::path::Path;
use thiserror::Error;

/// Errors of imports and exports. Each variant says whose fault it is: the input's, the
/// caller's, the network's or the system's, or a bug.
#[derive(Debug, Error)]
pub enum FormatsError {
    /// An operating-system error, with what was being done.
    #[error("{context}")]
    Io {
        /// What was being done.
        context: String,
        /// The system's error.
        #[source]
        source: io::Error,
    },
    /// The input is malformed, unsupported or inconsistent; the message says what and where.
    #[error("{0}")]
    BadInput(String),
    /// The caller's arguments cannot be carried out (an export over an existing path, a window
    /// that is not two increasing numbers, ...).
    #[error("{0}")]
    BadArgument(String),
    /// A request to a server failed or was refused.
    #[error("cannot read {url}: {detail}")]
    Fetch {
        /// What was asked for.
        url: String,
        /// Why it failed.
        detail: String,
    },
    /// Zarr metadata or chunks that `zarrs` cannot read.
    #[error("{context}: {detail}")]
    Zarr {
        /// What was being read.
        context: String,
        /// zarrs's error and its causes.
        detail: String,
    },
    /// A broken invariant of this program: neither the input's fault nor the caller's.
    #[error("internal error: {0}")]
    Internal(String),
    /// Writing or reading a VOD 2 file failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A document of a view could not be made (an export).
    #[error(transparent)]
    View(#[from] ViewError),
}

impl FormatsError {
    pub(crate) fn io_path(what: &str, path: &Path) -> impl FnOnce(io::Error) -> FormatsError {
        let context = format!("{what} {}", path.display());
        move |source| FormatsError::Io { context, source }
    }

    pub(crate) fn input(detail: impl Into<String>) -> FormatsError {
        FormatsError::BadInput(detail.into())
    }
}
