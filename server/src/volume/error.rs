//! What can go wrong with an operation on a served volume, and whose fault it is.

use crate::icvg::term::TermError;
use crate::store::StoreError;

/// Why an operation on a served volume was not carried out. The HTTP layer decides the status
/// of each variant in one place (`http/error.rs`); this type says only what happened.
#[derive(Debug, thiserror::Error)]
pub enum VolumeError {
    /// No volume is served under this name.
    #[error("no volume named {0:?}")]
    NoSuchVolume(String),
    /// The version is not (or no longer) in the volume's file.
    #[error("version {version} is not in this volume (it holds {oldest}..={head})")]
    NoSuchVersion {
        /// The version asked for.
        version: u64,
        /// The oldest version the file holds.
        oldest: u64,
        /// The head.
        head: u64,
    },
    /// A brick, tile or level outside the volume.
    #[error("{0}")]
    OutOfRange(String),
    /// The request's arguments make no sense (a malformed region, an unknown format, ...).
    #[error("{0}")]
    BadRequest(String),
    /// The answer would be larger than the server gives in one response.
    #[error("{0}")]
    TooLarge(String),
    /// The edit does not compile (or names what is not there).
    #[error("invalid edit: {0}")]
    InvalidEdit(#[from] TermError),
    /// The edit would evaluate more voxels than the server allows per edit.
    #[error("the edit reaches {voxels} voxels; this server allows {max} per edit (give a region, or split it)")]
    EditTooLarge {
        /// Voxels the edit would evaluate.
        voxels: u64,
        /// Voxels allowed.
        max: u64,
    },
    /// A conditional edit named another version than the head.
    #[error("If-Match names version {expected}; the volume is at version {current}")]
    Conflict {
        /// The version named.
        expected: u64,
        /// The head.
        current: u64,
    },
    /// `since` lies after the head.
    #[error("since = {since} is after the current version {head}")]
    SinceAfterHead {
        /// The version asked to list after.
        since: u64,
        /// The head.
        head: u64,
    },
    /// Versions after `since` were compacted away.
    #[error("versions before {oldest} were compacted away; reload the volume (metadata, then bricks by hash) and follow from version {head}")]
    Compacted {
        /// The oldest version the file holds now.
        oldest: u64,
        /// The head.
        head: u64,
    },
    /// The volume is served read-only (its newest durable version is damaged): no edit, no
    /// compaction.
    #[error("volume {volume:?} is read-only: {cause}")]
    ReadOnly {
        /// The volume.
        volume: String,
        /// Why: what is damaged, what is served, how to recover.
        cause: String,
    },
    /// Too many edits already wait for the volume's writer.
    #[error("too many edits are waiting for this volume")]
    WriterBusy,
    /// The storage engine failed (its variant says whether the caller or the file is at fault).
    #[error(transparent)]
    Store(#[from] StoreError),
}
