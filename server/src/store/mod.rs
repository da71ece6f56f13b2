//! The storage engine: VOD 1 and VOD 2 files, the brick index, deduplication and commits.
//!
//! Layout:
//! - [`mapping`]: the one memory-mapping module (every `unsafe` block of the project).
//! - [`codec`]: per-brick payload encoding (constant, raw, lz4).
//! - [`pyramid`]: bricks of voxels, the level-of-detail mean, sources of level-0 voxels.
//! - [`vod2`]: opening a VOD 2 file and reading any brick of any version by random access.
//! - [`writer`]: appending bricks with deduplication, index checkpoints and atomic commits.
//! - [`compact`]: rewriting a file with only its head version.
//! - [`build`]: building a whole volume (all levels) from a level-0 source, streaming.
//! - [`vod1`]: the thesis's VOD 1 layout, read and write.
//! - [`raw`]: RAW and RAWVOX input and output.
//! - [`inspect`]: whole-file statistics (bricks by codec, unique bricks, garbage bytes).
//! - [`lru`]: a content-keyed LRU bounded by bytes (decoded bricks, mesh tiles).

pub mod build;
pub mod codec;
pub mod compact;
pub mod inspect;
pub mod lru;
pub mod mapping;
pub mod pyramid;
pub mod raw;
pub mod vod1;
pub mod vod2;
pub mod writer;

pub use build::{build_vod2, stream_pyramid, BuildOptions, BuildReport, MemorySink, SlabSink};
pub use pyramid::{BrickSource, BrickVoxels, DenseGrid};
pub use vod2::{Snapshot, SnapshotSource, StoredBrick, Vod2};
pub use writer::Vod2Writer;

use isovox_proto::FormatError;
use std::io;
use std::path::Path;
use thiserror::Error;

/// Errors of the storage engine.
#[derive(Debug, Error)]
pub enum StoreError {
    /// An operating-system error, with what was being done.
    #[error("{context}")]
    Io {
        context: String,
        #[source]
        source: io::Error,
    },
    /// A record of the file is malformed.
    #[error("malformed file")]
    Format(#[from] FormatError),
    /// A brick's payload does not decode to what its header promises.
    #[error("corrupt brick at offset {offset}: {detail}")]
    Corrupt { offset: u64, detail: String },
    /// The request cannot be carried out with these arguments (wrong RAW size, a VOD 1 file
    /// over 4 GiB, ...).
    #[error("{0}")]
    Invalid(String),
}

/// An error and all its sources, joined with ": " (what `{:#}` prints for anyhow errors).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut out = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        out.push_str(": ");
        out.push_str(&s.to_string());
        source = s.source();
    }
    out
}

impl StoreError {
    pub(crate) fn corrupt(offset: u64, detail: impl Into<String>) -> Self {
        StoreError::Corrupt {
            offset,
            detail: detail.into(),
        }
    }

    pub(crate) fn io(context: impl Into<String>) -> impl FnOnce(io::Error) -> StoreError {
        let context = context.into();
        move |source| StoreError::Io { context, source }
    }

    pub(crate) fn io_path(what: &str, path: &Path) -> impl FnOnce(io::Error) -> StoreError {
        Self::io(format!("{what} {}", path.display()))
    }
}
