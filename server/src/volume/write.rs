//! Writing a served volume: edits checked against a server's limits (applied by the writer in
//! groups, `group.rs`) and compaction; and an edit of a file no server serves.

use super::group::Work;
use super::resolve::DirVolumes;
use super::{LiveVolume, VolumeError, WriterSlot};
use crate::cancel::CancelToken;
use crate::icvg::edit::{apply_edit, Edit, EditOutcome};
use crate::icvg::term::{TermLimits, VolumeResolver};
use crate::progress::Silent;
use crate::store::codec::Compression;
use crate::store::compact::{compact, compact_remote, CompactReport};
use crate::store::remote::backoff::Backoff;
use crate::store::remote::RemoteVolume;
use crate::store::{CheckpointPolicy, StoreError, Vod2, Vod2Writer};
use isovox_proto::api::EditResponse;
use isovox_proto::icvg::EditRequest;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Commits an edit tries against other writers of an object-store volume before it answers
/// that the volume is too busy (503, retry).
const MAX_REMOTE_ATTEMPTS: u32 = 16;

/// The wait after a first lost head race is drawn from [1, 2] ms; each further loss doubles the
/// range, up to [50, 100] ms (at most about 1 s over all the attempts). A race is lost to a
/// commit that just landed, so the next try soon after usually wins.
const LOST_RACE_FIRST_WAIT: Duration = Duration::from_millis(2);
/// See [`LOST_RACE_FIRST_WAIT`].
const LOST_RACE_MAX_WAIT: Duration = Duration::from_millis(100);

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

impl LiveVolume {
    /// An edit of a volume in an object store, holding the writer: catch up with the head,
    /// apply the edit on it, publish; when another writer's commit won the head meanwhile,
    /// catch up and apply the edit again on top of it (a conditional edit is refused instead:
    /// its version is gone). Blocking.
    ///
    /// # Errors
    /// [`VolumeError::Conflict`]; [`StoreError::HeadMoved`] after [`MAX_REMOTE_ATTEMPTS`]
    /// lost races; what applying or the store failed with.
    pub(crate) fn apply_remote(
        &self,
        remote: &Arc<RemoteVolume>,
        slot: &mut WriterSlot,
        work: &mut Work,
        if_match: Option<u64>,
        policy: CheckpointPolicy,
        cancel: &CancelToken,
    ) -> Result<EditResponse, VolumeError> {
        let started = Instant::now();
        let dry_run = matches!(work, Work::Edit { dry_run: true, .. });
        let mut attempt = 0u32;
        let mut lost_races = Backoff::new(LOST_RACE_FIRST_WAIT, LOST_RACE_MAX_WAIT);
        loop {
            // Store calls give up at the edit's deadline (503, the store's fault) rather than
            // wait out a stalled store; the head's PUT alone waits on (see its comment).
            let bounded = crate::store::remote::bound_store_waits(cancel.deadline());
            self.catch_up(slot)?;
            let vod = self.current();
            let head = vod.head();
            if let Some(expected) = if_match.filter(|&v| v != head.version) {
                return Err(VolumeError::Conflict {
                    expected,
                    current: head.version,
                });
            }
            let mut writer = Vod2Writer::remote(&vod, remote.clone());
            let staged = match self.stage_only(&mut writer, &head, work, policy, cancel) {
                // What a remote writer staged stays in its memory until its sync: a dry run
                // drops it.
                Ok(staged) if dry_run => {
                    let mut response = staged.dry_run(head.version + 1, head.version);
                    response.elapsed_us = started.elapsed().as_micros() as u64;
                    return Ok(response);
                }
                Ok(staged) => writer.sync().map(|_| staged).map_err(VolumeError::from),
                Err(e) => Err(e),
            };
            match staged {
                Ok(staged) => {
                    // Committed: what follows must not fail for a slow store.
                    drop(bounded);
                    let committed = writer.head().ok_or_else(|| {
                        StoreError::Internal("a commit left the writer without a head".into())
                    })?;
                    let next = remote.after_commit(&vod)?;
                    let event = self.publish_commit(next, committed.commit)?;
                    let mut response = staged.response(&event, head.version);
                    response.elapsed_us = started.elapsed().as_micros() as u64;
                    return Ok(response);
                }
                Err(VolumeError::Store(StoreError::HeadMoved { .. }))
                    if attempt + 1 < MAX_REMOTE_ATTEMPTS =>
                {
                    attempt += 1;
                    // Writers that collide again and again back off apart: exponentially,
                    // with jitter, so the losers do not all come back at the same instant.
                    std::thread::sleep(lost_races.next_wait());
                }
                Err(e) => return Err(e),
            }
        }
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
