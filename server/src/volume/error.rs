//! What can go wrong with an operation on a served volume, and whose fault it is.

use crate::cancel::Stopped;
use crate::icvg::term::{EvalError, TermError};
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
    /// Well-formed, but not something this volume can answer (a u16 channel asked for
    /// per-vertex materials, say): 422.
    #[error("{0}")]
    Unprocessable(String),
    /// The answer would be larger than the server gives in one response.
    #[error("{0}")]
    TooLarge(String),
    /// The edit does not compile (or names what is not there).
    #[error("invalid edit: {0}")]
    InvalidEdit(TermError),
    /// The edit would evaluate more voxels than the server allows per edit.
    #[error("the edit evaluates {voxels} voxels (its bricks, and what its mesh leaves and dilate/erode sample); this server allows {max} per edit (--max-edit-voxels): give a region, or split it")]
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
    /// `since` lies after the head: the caller holds a version this volume does not (it was
    /// replaced by an older copy, say), so it must reload what it caches.
    #[error("since = {since} is after the current version {head}: reload the volume")]
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
    /// The edit's work was stopped: it ran past the server's deadline for edits, its client
    /// left, or the server is shutting down. Nothing was committed.
    #[error("{}", stopped_detail(.0))]
    Stopped(Stopped),
    /// The volume is served read-only (its newest durable version is damaged): no edit, no
    /// compaction.
    #[error("volume {volume:?} is read-only: {cause}")]
    ReadOnly {
        /// The volume.
        volume: String,
        /// Why: what is damaged, what is served, how to recover.
        cause: String,
    },
    /// An undo, redo, revert or tag that cannot be made as asked (the version is not an edit,
    /// is undone already, or a commit under it cannot be replayed).
    #[error("{0}")]
    NotUndoable(String),
    /// The user may not do this (undo another user's edit without the admin role).
    #[error("{0}")]
    NotAllowed(String),
    /// An undo or redo would apply more than the server allows per edit.
    #[error("the undo re-evaluates {voxels} voxels (the edit's bricks, once per edit applied again over them); this server allows {max} per edit (--max-edit-voxels): revert to a version instead")]
    UndoTooLarge {
        /// Voxels it would evaluate.
        voxels: u64,
        /// Voxels allowed.
        max: u64,
    },
    /// What the volume's storage cannot do yet.
    #[error("{0}")]
    Unsupported(String),
    /// Too many edits already wait for the volume's writer.
    #[error("too many edits are waiting for this volume")]
    WriterBusy,
    /// The storage engine failed (its variant says whether the caller or the file is at fault).
    #[error(transparent)]
    Store(#[from] StoreError),
}

fn stopped_detail(stopped: &Stopped) -> String {
    match stopped {
        Stopped::TimedOut(limit) => format!(
            "the edit was stopped after {:.1} s, this server's limit per edit (--edit-timeout); nothing was committed: give a region, a smaller radius or scale, or split it",
            limit.as_secs_f64()
        ),
        Stopped::Cancelled => {
            "the edit was cancelled (the server is shutting down); nothing was committed".into()
        }
    }
}

/// A term that was stopped while compiling is a stopped edit, not an invalid one.
impl From<TermError> for VolumeError {
    fn from(e: TermError) -> Self {
        match e {
            TermError::Stopped(stopped) => VolumeError::Stopped(stopped),
            e => VolumeError::InvalidEdit(e),
        }
    }
}

impl From<EvalError> for VolumeError {
    fn from(e: EvalError) -> Self {
        match e {
            EvalError::Store(e) => VolumeError::Store(e),
            EvalError::Stopped(stopped) => VolumeError::Stopped(stopped),
        }
    }
}
