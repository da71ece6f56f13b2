//! Writing a served volume: edits (checked against a server's limits, applied by the single
//! writer, published to readers and the feed) and compaction; and an edit of a file no server
//! serves.

use super::resolve::DirVolumes;
use super::{change_event, FeedItem, History, LiveVolume, VolumeError, WriterSlot};
use crate::icvg::edit::{apply_edit, Edit, EditOutcome};
use crate::icvg::term::{TermLimits, VolumeResolver};
use crate::progress::Silent;
use crate::store::codec::Compression;
use crate::store::compact::{compact, CompactReport};
use crate::store::{CheckpointPolicy, StoreError, Vod2, Vod2Writer};
use isovox_proto::api::EditResponse;
use isovox_proto::icvg::EditRequest;
use std::path::Path;
use std::sync::Arc;
use tokio::sync::OwnedMutexGuard;

/// What one edit may ask for.
#[derive(Debug, Clone, Copy, Default)]
pub struct EditLimits {
    /// Limits on the term itself.
    pub term: TermLimits,
    /// Level-0 voxels one edit may evaluate; `None`: no limit.
    pub max_voxels: Option<u64>,
}

impl LiveVolume {
    /// Checks and compiles an edit request for this volume: against the limits, and (with
    /// `if_match`) against the head's version. CPU work (a mesh leaf is voxelized here): call it
    /// off the async runtime.
    ///
    /// # Errors
    /// [`VolumeError::InvalidEdit`], [`VolumeError::EditTooLarge`], [`VolumeError::Conflict`].
    pub fn prepare_edit(
        &self,
        request: &EditRequest,
        limits: &EditLimits,
        volumes: &dyn VolumeResolver,
        if_match: Option<u64>,
    ) -> Result<Edit, VolumeError> {
        let head = self.head();
        let layout = head.layout();
        let edit = Edit::from_request(request, layout.voxel_type(), &limits.term, volumes)?;
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
    /// edits already wait) and waits for the writer, in arrival order.
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

    /// Applies `edit` to the head and commits it as the next version, holding the writer.
    /// Blocking (evaluates on rayon, syncs the file): call it off the async runtime.
    ///
    /// # Errors
    /// `If-Match` mismatch, or reading or committing failed (the head is then unchanged and
    /// the writer is reopened on the next edit, cutting off whatever the failed commit
    /// appended).
    pub fn apply(
        &self,
        slot: &mut WriterSlot,
        edit: &Edit,
        if_match: Option<u64>,
        policy: CheckpointPolicy,
    ) -> Result<EditResponse, VolumeError> {
        let vod = self.current();
        let head = vod.head();
        if let Some(expected) = if_match.filter(|&v| v != head.version) {
            return Err(VolumeError::Conflict {
                expected,
                current: head.version,
            });
        }
        let writer = match &mut slot.writer {
            Some(w) => w,
            empty => empty.insert(Vod2Writer::open_append(vod.path(), Compression::default())?),
        };
        if writer.head().map(|h| h.commit) != Some(head.commit_offset()) {
            slot.writer = None;
            return Err(StoreError::Internal(
                "the writer and the served head disagree; reopening the writer".into(),
            )
            .into());
        }
        let outcome = match apply_edit(writer, &head, edit, policy) {
            Ok(o) => o,
            Err(e) => {
                slot.writer = None;
                return Err(e.into());
            }
        };
        let Some(committed) = writer.head() else {
            slot.writer = None;
            return Err(
                StoreError::Internal("a commit left the writer without a head".into()).into(),
            );
        };
        // The commit is durable: from here on, failing to publish it would hide an edit that a
        // restart would show, so fall back to reopening the file.
        let next = vod
            .advance(committed)
            .or_else(|e| {
                tracing::warn!(error = %crate::store::error_chain(&e), "cannot extend the head; reopening the file");
                Vod2::open(vod.path())
            })?;
        let event = change_event(&next, committed.commit)?;
        {
            let mut history = self.history.write().unwrap_or_else(|p| p.into_inner());
            if history.offsets.is_empty() {
                history.oldest = committed.version;
            }
            history.offsets.push(committed.commit);
        }
        self.current.store(Arc::new(next));
        let json = serde_json::to_string(&event).unwrap_or_default();
        // No subscriber is not an error.
        let _ = self.feed.send(Arc::new(FeedItem {
            version: event.version,
            json,
        }));
        Ok(EditResponse {
            version: event.version,
            previous: head.version,
            changed: event.changed,
            evaluated: outcome.evaluated as u64,
            new_records: outcome.new_records,
            checkpoint: outcome.checkpoint,
            elapsed_us: outcome.elapsed.as_micros() as u64,
        })
    }

    /// Rewrites the file with only the head version and serves the result, holding the writer.
    /// Blocking: call it off the async runtime.
    ///
    /// # Errors
    /// Compaction failed (the old file is then still served) or the new file does not open.
    pub fn compact(&self, slot: &mut WriterSlot) -> Result<CompactReport, StoreError> {
        let vod = self.current();
        let head = vod.head();
        // The writer's dedup table names offsets of the old file.
        slot.writer = None;
        let report = compact(&vod, &head, &Silent)?;
        let fresh = Vod2::open(vod.path())?;
        let history = History::read(&fresh)?;
        *self.history.write().unwrap_or_else(|p| p.into_inner()) = history;
        self.current.store(Arc::new(fresh));
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
    let edit = Edit::from_request(
        request,
        snap.layout().voxel_type(),
        &TermLimits::default(),
        &DirVolumes { dir },
    )?;
    let mut writer = Vod2Writer::open_append(path, Compression::default())?;
    Ok(apply_edit(
        &mut writer,
        &snap,
        &edit,
        CheckpointPolicy::default(),
    )?)
}
