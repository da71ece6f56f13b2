//! The storage engine: VOD 1 and VOD 2 files, the brick index, deduplication and commits.
//!
//! Layout:
//! - [`mapping`]: the one memory-mapping module (every `unsafe` block of the library).
//! - [`codec`]: per-brick payload encoding (constant, raw, lz4, zstd).
//! - [`pyramid`]: bricks of voxels, the level-of-detail mean, sources of level-0 voxels.
//! - [`vod2`]: opening a VOD 2 file and reading any brick of any version by random access.
//! - [`writer`]: appending bricks with deduplication, index checkpoints and atomic commits.
//! - [`transaction`]: the one way a version is written: staged bricks, level-of-detail upkeep,
//!   the commit.
//! - [`compact`]: rewriting a file with only its head version.
//! - [`check`]: verifying every record of every version of a file; which versions are intact.
//! - [`salvage`]: writing a new file from the newest intact version of a damaged one.
//! - [`build`]: building a whole volume (all levels) from a level-0 source, streaming.
//! - [`vod1`]: the thesis's VOD 1 layout, read and write.
//! - [`raw`]: RAW and RAWVOX input and output.
//! - [`inspect`]: whole-file statistics (bricks by codec, unique bricks, garbage bytes).
//! - [`decoded`]: decoded bricks by content hash, shared by every reader of a process.
//! - [`lru`]: a content-keyed LRU bounded by bytes (decoded bricks, mesh tiles).
//! - [`region`]: the committed region readers see, [`region::MappedRegion`] (a mapping; for a
//!   mirror, what fills it).
//! - [`remote`]: volumes kept in an object store (S3): objects, the head, replicas' mirrors.

pub mod build;
pub mod check;
pub mod codec;
pub mod compact;
pub mod decoded;
pub mod inspect;
pub mod lru;
pub(crate) mod mapping;
pub mod pyramid;
pub mod raw;
pub mod region;
pub mod remote;
pub mod salvage;
pub mod transaction;
pub mod vod1;
pub mod vod2;
pub mod writer;

pub use build::{
    build_streams, build_vod2, stream_pyramid, BuildOptions, BuildReport, MemorySink, SlabSink,
};
pub use pyramid::{BrickSource, BrickVoxels, DenseGrid};
pub use transaction::{CheckpointPolicy, Committed, Transaction};
pub use vod2::{
    verify_stored, PayloadCheck, SlotState, Snapshot, SnapshotSource, StoredBrick, Vod2, Vod2File,
};
pub use writer::{Publish, Vod2Writer};

use isovox_proto::FormatError;
use std::io;
use std::path::Path;
use thiserror::Error;

/// Errors of the storage engine. Each variant says whose fault it is, so that the layers above
/// can answer a caller's mistake differently from damage or a bug (`docs/errors.md`).
#[derive(Debug, Error)]
pub enum StoreError {
    /// An operating-system error, with what was being done.
    #[error("{context}")]
    Io {
        /// What was being done.
        context: String,
        /// The system's error.
        #[source]
        source: io::Error,
    },
    /// A record of the file is malformed (the format error names the record and where).
    #[error("malformed file")]
    Format(#[from] FormatError),
    /// Stored bytes are not what they must be: at `offset`, `expected` was expected and `found`
    /// was found (a payload that does not decode, or decodes to other content than its hash).
    #[error("corrupt data at offset {offset}: expected {expected}, found {found}")]
    Corrupt {
        /// Where the bytes start in the file.
        offset: u64,
        /// What they must be.
        expected: String,
        /// What they are.
        found: String,
    },
    /// What was asked for is not there (a version the file no longer or not yet holds).
    #[error("{0}")]
    Absent(String),
    /// An address outside the volume: a brick key, a level, a tile.
    #[error("{0}")]
    OutOfRange(String),
    /// The caller's arguments cannot be carried out (a RAW file of the wrong size, a region
    /// outside the level, a VOD 1 file over 4 GiB, ...).
    #[error("{0}")]
    BadInput(String),
    /// The object store failed (unreachable, refused the credentials, lost an object).
    #[error("{context}")]
    ObjectStore {
        /// What was being done.
        context: String,
        /// The store client's error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// Another writer advanced the head of a volume in an object store first: this commit was
    /// not made (its objects are garbage); build on the new head and try again.
    #[error("{url}: another writer committed first")]
    HeadMoved {
        /// The volume.
        url: String,
    },
    /// The object store did not answer a call within the time the work waiting on it had (an
    /// edit's `--edit-timeout`): the store stalled, not the caller's fault; the call was given
    /// up, and nothing it was to write was committed.
    #[error("the object store did not answer within {limit:?}")]
    Stalled {
        /// The time the work had.
        limit: std::time::Duration,
    },
    /// A broken invariant of this program: neither the caller's fault nor the file's.
    #[error("internal error: {0}")]
    Internal(String),
}

impl StoreError {
    /// Whether the error is the caller's to fix (absent, out of range, bad input), as opposed
    /// to damage, the system or a bug.
    pub fn is_caller_error(&self) -> bool {
        matches!(
            self,
            StoreError::Absent(_) | StoreError::OutOfRange(_) | StoreError::BadInput(_)
        )
    }

    /// Whether the error is damage to the file (a malformed record, bytes that are not what
    /// they must be), as opposed to the caller, the system or a bug.
    pub fn is_damage(&self) -> bool {
        matches!(self, StoreError::Format(_) | StoreError::Corrupt { .. })
    }
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
    pub(crate) fn corrupt(
        offset: u64,
        expected: impl Into<String>,
        found: impl Into<String>,
    ) -> Self {
        StoreError::Corrupt {
            offset,
            expected: expected.into(),
            found: found.into(),
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
