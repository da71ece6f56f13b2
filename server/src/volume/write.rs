//! Writing a served volume: edits checked against a server's limits (applied by the writer in
//! groups, `group.rs`) and compaction; and an edit of a file no server serves.

use super::resolve::DirVolumes;
use super::{LiveVolume, VolumeError, WriterSlot};
use crate::cancel::CancelToken;
use crate::icvg::edit::{apply_edit, Edit, EditOutcome};
use crate::icvg::term::{TermLimits, VolumeResolver};
use crate::progress::Silent;
use crate::store::codec::Compression;
use crate::store::compact::{compact, compact_remote, CompactReport};
use crate::store::{CheckpointPolicy, Vod2, Vod2Writer};
use isovox_proto::icvg::EditRequest;
use std::path::Path;
use std::time::Duration;

/// How long objects a compaction of an object-store volume made garbage stay, for replicas
/// still reading the old head.
pub const GC_GRACE: Duration = Duration::from_secs(15 * 60);
use tokio::sync::OwnedMutexGuard;

/// What one edit may ask for.
#[derive(Debug, Clone, Copy, Default)]
pub struct EditLimits {
    /// Limits on the term itself.
    pub term: TermLimits,
    /// Voxels one edit may evaluate (its bricks' level-0 voxels, and what its term samples
    /// besides: mesh leaves, morphology arguments); `None`: no limit.
    pub max_voxels: Option<u64>,
}

impl LiveVolume {
    /// Checks and compiles an edit request for this volume: against the limits, and (with
    /// `if_match`) against the head's version. CPU work (a mesh leaf is voxelized here, within
    /// the edit's box only): call it off the async runtime; `cancel` stops it.
    ///
    /// # Errors
    /// [`VolumeError::ReadOnly`], [`VolumeError::InvalidEdit`], [`VolumeError::EditTooLarge`],
    /// [`VolumeError::Conflict`], [`VolumeError::Stopped`].
    pub fn prepare_edit(
        &self,
        request: &EditRequest,
        limits: &EditLimits,
        volumes: &dyn VolumeResolver,
        if_match: Option<u64>,
        cancel: &CancelToken,
    ) -> Result<Edit, VolumeError> {
        self.check_writable()?;
        let head = self.head();
        let layout = head.layout();
        let edit = Edit::for_volume(
            request,
            head.header(),
            &limits.term,
            volumes,
            limits.max_voxels,
            cancel,
        )?;
        let voxels = edit.evaluated_voxels(layout);
        if let Some(max) = limits.max_voxels.filter(|&max| voxels > max) {
            return Err(VolumeError::EditTooLarge { voxels, max });
        }
        if let Some(expected) = if_match.filter(|&v| v != head.version) {
            return Err(VolumeError::Conflict {
                expected,
                current: head.version,
            });
        }
        Ok(edit)
    }

    /// Takes a place in the writer's queue ([`VolumeError::WriterBusy`] when `max_waiting`
    /// edits and compactions already wait) and waits for the writer lock, between two groups
    /// of edits: what a compaction holds.
    ///
    /// # Errors
    /// [`VolumeError::WriterBusy`].
    pub async fn wait_for_writer(
        &self,
        max_waiting: usize,
    ) -> Result<OwnedMutexGuard<WriterSlot>, VolumeError> {
        let ticket = self.enqueue(max_waiting).ok_or(VolumeError::WriterBusy)?;
        let writer = self.lock_writer().await;
        drop(ticket);
        Ok(writer)
    }

    /// Rewrites the file with only the head version and serves the result, holding the writer.
    /// Blocking: call it off the async runtime.
    ///
    /// # Errors
    /// The volume is read-only ([`VolumeError::ReadOnly`]: compacting would rewrite its file
    /// without the damaged versions; `isovox salvage` writes a new file instead), compaction
    /// failed (the old file is then still served) or the new file does not open.
    pub fn compact(&self, slot: &mut WriterSlot) -> Result<CompactReport, VolumeError> {
        self.check_writable()?;
        if let Some(remote) = self.remote() {
            self.catch_up(slot)?;
            let vod = self.current();
            let report = compact_remote(remote, &vod, GC_GRACE)?;
            self.catch_up(slot)?;
            return Ok(report);
        }
        let vod = self.current();
        let head = vod.head();
        // The writer's dedup table names offsets of the old file.
        slot.writer = None;
        let report = compact(&vod, &head, &Silent)?;
        self.reload()?;
        Ok(report)
    }
}

/// Applies one edit request to the file at `path` (served by no one) and commits it. Volumes
/// the term names are the `NAME.vod` files beside it; meshes those uploaded to a server on the
/// same directory (`DIR/meshes`).
///
/// # Errors
/// The file does not open, the edit is invalid, or the commit fails.
pub fn edit_file(path: &Path, request: &EditRequest) -> Result<EditOutcome, VolumeError> {
    let vod = Vod2::open(path)?;
    let snap = vod.head();
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let never = CancelToken::never();
    let mut edit = Edit::for_volume(
        request,
        snap.header(),
        &TermLimits::default(),
        &DirVolumes { dir },
        None,
        &never,
    )?;
    let mut writer = Vod2Writer::open_append(path, Compression::for_edits())?;
    apply_edit(
        &mut writer,
        &snap,
        &mut edit,
        CheckpointPolicy::default(),
        &never,
    )
    .map_err(VolumeError::from)
}
