//! Group commit: the edits waiting for a volume's writer are applied in arrival order and made
//! durable together, with one sync.
//!
//! An edit joins the volume's queue ([`LiveVolume::submit`]); while the queue is not empty, one
//! task per volume takes up to [`GroupCommit::max_group`] edits from its front and commits them
//! as a group ([`LiveVolume::commit_group`]):
//!
//! 1. each edit in turn is checked against `If-Match` (the version the edits before it in the
//!    group produced, so a conflict is as exact as without groups), evaluated against that
//!    version, and staged as the next version: its bricks and its own commit record appended,
//!    its parent the record before it. An edit that fails, or is stopped (its deadline passed,
//!    counted from when the writer reaches it, or its client left), is rolled back to the
//!    savepoint taken before it and answered with its error; the others do not notice;
//! 2. one header slot naming the group's last version, then one `fdatasync`
//!    ([`Vod2Writer::sync`]): the whole group is durable, or (crash, failed sync) none of it;
//! 3. each version in order is published to readers, announced on the change feed and
//!    answered: every edit is still its own version with its own event, acknowledged only once
//!    durable, and versions are answered in the order they were made.
//!
//! Nothing of a staged version is visible before step 2 completes: readers are handed the new
//! versions only in step 3, and a reader opening the file finds the slot of the previous group.
//!
//! [`Vod2Writer::sync`]: crate::store::Vod2Writer::sync

use super::undo::{StagedCommit, UndoJob};
use super::{change_event, LiveVolume, VolumeError, WriterSlot};
use crate::cancel::CancelToken;
use crate::icvg::edit::{stage_edit, Edit};
use crate::store::codec::Compression;
use crate::store::transaction::ChangedKeys;
use crate::store::Snapshot;
use crate::store::{error_chain, CheckpointPolicy, StoreError, Vod2, Vod2Writer};
use isovox_proto::api::{ChangeEvent, EditResponse};
use isovox_proto::history::CommitNote;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::oneshot;

/// Edits made durable together at most, by default: enough for many editors at once, few
/// enough that the last edit of a group does not wait long for the others' evaluation.
pub const DEFAULT_MAX_GROUP: usize = 32;

/// How a volume's writer takes its edits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GroupCommit {
    /// Edits waiting for the writer at most; beyond it an edit is refused
    /// ([`VolumeError::WriterBusy`]).
    pub max_waiting: usize,
    /// Edits made durable together at most. 1 is one sync per edit.
    pub max_group: usize,
    /// When a version writes a full index checkpoint.
    pub policy: CheckpointPolicy,
}

impl Default for GroupCommit {
    fn default() -> Self {
        GroupCommit {
            max_waiting: 64,
            max_group: DEFAULT_MAX_GROUP,
            policy: CheckpointPolicy::default(),
        }
    }
}

/// What an edit is answered with.
pub type EditAnswer = Result<EditResponse, VolumeError>;

/// What a request in the writer's queue asks it to commit.
#[derive(Debug)]
pub enum Work {
    /// An edit; with `dry_run`, evaluated and answered but not committed.
    Edit {
        /// The compiled edit (boxed: it is much larger than the other variants).
        edit: Box<Edit>,
        /// Answer what it would change, and roll it back.
        dry_run: bool,
    },
    /// An undo or redo (`undo.rs`).
    Undo(UndoJob),
    /// The content of version `to` as a new version.
    Revert {
        /// The version restored.
        to: u64,
        /// Who asks, and their message.
        note: CommitNote,
    },
    /// A name for a version.
    Tag {
        /// The name.
        tag: String,
        /// The version it names.
        version: u64,
        /// Who asks.
        note: CommitNote,
    },
}

impl Work {
    /// `edit`, committed or (`dry_run`) only evaluated and answered.
    pub fn edit(edit: Edit, dry_run: bool) -> Work {
        Work::Edit {
            edit: Box::new(edit),
            dry_run,
        }
    }

    /// Whether it may share a group with the edits around it. Undos, reverts and tags read
    /// the history up to the served head, which versions staged in a group are not yet part
    /// of: each is a group of its own.
    pub(super) fn groups(&self) -> bool {
        matches!(self, Work::Edit { .. })
    }
}

/// A request waiting for the writer, with where its answer goes.
#[derive(Debug)]
pub struct PendingEdit {
    pub(super) work: Work,
    pub(super) if_match: Option<u64>,
    pub(super) cancel: CancelToken,
    answer: oneshot::Sender<EditAnswer>,
}

impl PendingEdit {
    /// `work`, to apply only if the volume is then at version `if_match` (when given), and the
    /// receiver of its answer. Dropping the receiver before the writer reaches the work
    /// withdraws it (it is then never applied); cancelling `cancel` stops its evaluation, and
    /// its deadline (if any) starts again when the writer reaches it.
    pub fn new(
        work: Work,
        if_match: Option<u64>,
        cancel: CancelToken,
    ) -> (PendingEdit, oneshot::Receiver<EditAnswer>) {
        let (answer, receiver) = oneshot::channel();
        (
            PendingEdit {
                work,
                if_match,
                cancel,
                answer,
            },
            receiver,
        )
    }

    /// Whether its client left (nobody waits for the answer).
    pub(super) fn withdrawn(&self) -> bool {
        self.answer.is_closed()
    }

    pub(super) fn answer(self, answer: EditAnswer) {
        // A receiver that is gone had its client leave: nobody to tell.
        let _ = self.answer.send(answer);
    }
}

/// The edits waiting for a volume's writer.
#[derive(Debug, Default)]
pub(super) struct EditQueue {
    edits: VecDeque<PendingEdit>,
    /// Whether a task is taking groups from the queue (at most one per volume).
    writing: bool,
}

impl EditQueue {
    pub(super) fn len(&self) -> usize {
        self.edits.len()
    }

    /// Whether edits wait; when none does, the writer is marked stopped, so that the next
    /// edit starts it again.
    fn edits_wait(&mut self) -> bool {
        let waiting = !self.edits.is_empty();
        if !waiting {
            self.writing = false;
        }
        waiting
    }
}

/// Held by a writer task while it runs: should the task be dropped before it ends by itself
/// (its runtime stopped), the volume's writer is marked stopped, so that the next edit starts
/// a new one instead of queueing for a writer that is gone.
struct StillWriting(Option<Arc<LiveVolume>>);

impl Drop for StillWriting {
    fn drop(&mut self) {
        if let Some(volume) = self.0.take() {
            tracing::warn!(volume = %volume.name, "the volume's writer task was dropped");
            volume.queue().writing = false;
        }
    }
}

/// Why the writer's blocking thread stopped taking groups.
enum Continue {
    /// No edit waits: the writer stops until the next one.
    QueueEmpty,
    /// A compaction waits for the writer: it takes it before the next group.
    YieldToCompaction,
}

/// A version staged in a group, not yet durable.
struct Staged {
    pending: PendingEdit,
    vod: Arc<Vod2>,
    event: ChangeEvent,
    response: EditResponse,
    started: Instant,
}

/// What staging a group left: its versions, and the answers not given by a version of it
/// (conflicts, failures, dry runs), by the position among the versions they come at.
struct StagedGroup {
    staged: Vec<Staged>,
    answered: Vec<(usize, PendingEdit, EditAnswer)>,
}

/// The writer could not roll back, or sync: it no longer knows what its file holds.
struct WriterLost;

impl LiveVolume {
    pub(super) fn queue(&self) -> std::sync::MutexGuard<'_, EditQueue> {
        // Every update of the queue is one push, one drain or one flag: a panic cannot leave
        // it half-changed, so a poisoned lock is still sound to use.
        self.edits.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues `edit` for the writer and waits until it is durable (or refused). The volume's
    /// writer task is started on `runtime` when it is not running; it takes groups from the
    /// queue as `settings` say until the queue is empty. `cancel` stops the edit's evaluation
    /// (see [`PendingEdit::new`]).
    ///
    /// `runtime` is the server's main runtime, not the caller's: a writer task spawned on a
    /// connection thread would compete with that thread's connections and die with it.
    ///
    /// # Errors
    /// [`VolumeError::WriterBusy`] when `settings.max_waiting` edits already wait;
    /// [`VolumeError::Conflict`] when `if_match` is not the version the edit would follow;
    /// [`VolumeError::Stopped`]; what applying or committing failed with.
    pub async fn submit(
        self: &Arc<Self>,
        work: Work,
        if_match: Option<u64>,
        cancel: CancelToken,
        settings: GroupCommit,
        runtime: &tokio::runtime::Handle,
    ) -> Result<EditResponse, VolumeError> {
        if let Work::Edit { edit, .. } = &work {
            if let Some(unchanged) = self.unchanged(edit) {
                return Ok(unchanged);
            }
        }
        let (pending, answer) = PendingEdit::new(work, if_match, cancel);
        {
            let mut queue = self.queue();
            if queue.len() + self.compactions_waiting() >= settings.max_waiting {
                return Err(VolumeError::WriterBusy);
            }
            queue.edits.push_back(pending);
            if !queue.writing {
                queue.writing = true;
                runtime.spawn(self.clone().write_groups(settings));
            }
        }
        answer.await.map_err(|_| {
            VolumeError::Store(StoreError::Internal(
                "the writer stopped before answering this edit (see the log)".into(),
            ))
        })?
    }

    /// The volume's writer task: takes groups from the queue until it is empty.
    ///
    /// The groups that follow one another without a pause are committed on one blocking
    /// thread, one after the other: the next group is taken as soon as the last one is
    /// answered. Going back through the runtime between groups (this task woken on a worker,
    /// then a blocking thread woken for the next group) left the writer idle for a large share
    /// of its time under many editors and subscribers. A compaction waiting for the writer
    /// still takes it between two groups.
    async fn write_groups(self: Arc<Self>, settings: GroupCommit) {
        let mut running = StillWriting(Some(self.clone()));
        self.take_groups(settings).await;
        // Ended by itself: the queue was found empty, and `writing` cleared, under its lock.
        running.0 = None;
    }

    /// [`LiveVolume::write_groups`]' loop.
    async fn take_groups(self: Arc<Self>, settings: GroupCommit) {
        loop {
            // Compaction takes the writer between groups.
            let mut slot = self.lock_writer().await;
            let vol = self.clone();
            let done = tokio::task::spawn_blocking(move || {
                while let Some(group) = vol.next_group(settings) {
                    vol.commit_group(&mut slot, group, settings.policy);
                    if vol.compactions_waiting() > 0 {
                        return Continue::YieldToCompaction;
                    }
                }
                Continue::QueueEmpty
            })
            .await;
            match done {
                Ok(Continue::QueueEmpty) => return,
                Ok(Continue::YieldToCompaction) => {}
                Err(e) => {
                    // The group's edits are answered with an error when their senders drop;
                    // the writer is reopened by the next group (it finds versions staged).
                    tracing::error!(volume = %self.name, error = %e, "an edit group failed");
                    if self.queue().edits_wait() {
                        continue;
                    }
                    return;
                }
            }
        }
    }

    /// The next group from the front of the queue, or `None` (and the writer marked stopped,
    /// so the next edit starts it again) when the queue is empty.
    fn next_group(&self, settings: GroupCommit) -> Option<Vec<PendingEdit>> {
        let mut queue = self.queue();
        if !queue.edits_wait() {
            return None;
        }
        let n = queue
            .edits
            .iter()
            .take(settings.max_group.max(1))
            .take_while(|p| p.work.groups())
            .count()
            .max(1);
        Some(queue.edits.drain(..n).collect())
    }

    /// Applies `group` in order and commits it with one sync, holding the writer;
    /// answers every edit (see the module's documentation). Edits whose receiver is gone
    /// before the writer reaches them are skipped. Blocking (evaluates on rayon, syncs the
    /// file): call it off the async runtime.
    pub fn commit_group(
        &self,
        slot: &mut WriterSlot,
        group: Vec<PendingEdit>,
        policy: CheckpointPolicy,
    ) {
        let began = Instant::now();
        if let Some(cause) = self.read_only_cause() {
            // Never open a writer on a file served read-only: opening cuts off what lies past
            // the version it serves, and the damaged versions are there.
            for pending in group {
                pending.answer(Err(VolumeError::ReadOnly {
                    volume: self.name.clone(),
                    cause: cause.to_string(),
                }));
            }
            return;
        }
        if let Some(remote) = self.remote().cloned() {
            self.commit_group_remote(&remote, slot, group, policy);
            return;
        }
        let (writer, base) = match self.writer_and_base(slot) {
            Ok(at) => at,
            Err(e) => {
                for pending in group {
                    pending.answer(Err(copy_of(&e).into()));
                }
                return;
            }
        };
        let outcome = self
            .stage_group(writer, base, group, policy)
            .and_then(|stage| self.sync_and_answer(writer, stage, began));
        if let Err(WriterLost) = outcome {
            // Every edit was answered. The next group reopens the file, cutting off everything
            // staged, and learns what reached the disk.
            slot.writer = None;
        }
    }

    /// The volume's writer, opened if needed, and the version to build on: the served head,
    /// reloaded from the file first when the file holds versions the volume does not serve (a
    /// group that stopped after its sync).
    fn writer_and_base<'a>(
        &self,
        slot: &'a mut WriterSlot,
    ) -> Result<(&'a mut Vod2Writer, Arc<Vod2>), StoreError> {
        let mut base = self.current();
        let writer_head = writer_at(slot, &base)?.head().map(|h| h.commit);
        if writer_head != Some(base.head_ref().commit_offset()) {
            tracing::error!(volume = %self.name, "the served head is behind the file; reloading it");
            base = self.reload().inspect_err(|_| slot.writer = None)?;
        }
        let writer = slot
            .writer
            .as_mut()
            .ok_or_else(|| StoreError::Internal("the writer was not opened".into()))?;
        Ok((writer, base))
    }

    /// Stages the edits of `group` in order on `base`, each on the one before: versions for
    /// the edits that make one, answers by position for the others (conflicts, failures, dry
    /// runs). `Err` when the writer could not roll back a dry run or a failed edit: every edit
    /// of the group is then answered.
    fn stage_group(
        &self,
        writer: &mut Vod2Writer,
        base: Arc<Vod2>,
        group: Vec<PendingEdit>,
        policy: CheckpointPolicy,
    ) -> Result<StagedGroup, WriterLost> {
        // The newest version so far: the served head, then each staged one.
        let mut tip = base;
        let mut staged: Vec<Staged> = Vec::new();
        let mut answered: Vec<(usize, PendingEdit, EditAnswer)> = Vec::new();
        let mut edits = group.into_iter();
        while let Some(mut pending) = edits.next() {
            if pending.answer.is_closed() {
                continue;
            }
            let started = Instant::now();
            let head = tip.head_ref();
            if let Some(expected) = pending.if_match.filter(|&v| v != head.version) {
                let current = head.version;
                answered.push((
                    staged.len(),
                    pending,
                    Err(VolumeError::Conflict { expected, current }),
                ));
                continue;
            }
            let savepoint = writer.savepoint();
            let cancel = pending.cancel.restarted();
            let dry_run = matches!(pending.work, Work::Edit { dry_run: true, .. });
            let staging = self.stage_work(writer, &tip, &mut pending.work, policy, &cancel);
            // A dry run's version, or a failed edit's bytes, are taken back.
            let undo = match &staging {
                Ok(_) if !dry_run => None,
                Ok(_) => Some("cannot roll back a dry run"),
                Err(_) => Some("cannot roll back a failed edit"),
            };
            if let Some(what) = undo {
                if let Err(cut) = writer.rollback(savepoint) {
                    tracing::error!(volume = %self.name, error = %error_chain(&cut), "{what}");
                    let answer = match staging {
                        Err(e) => Err(e),
                        Ok(_) => Err(copy_of(&cut).into()),
                    };
                    pending.answer(answer);
                    fail_all(staged, answered, edits, &cut);
                    return Err(WriterLost);
                }
            }
            match staging {
                Ok((_, _, mut response)) if dry_run => {
                    response.dry_run = true;
                    response.committed = false;
                    response.elapsed_us = micros(started.elapsed());
                    answered.push((staged.len(), pending, Ok(response)));
                }
                Ok((vod, event, response)) => {
                    tip = vod.clone();
                    staged.push(Staged {
                        pending,
                        vod,
                        event,
                        response,
                        started,
                    });
                }
                Err(e) => answered.push((staged.len(), pending, Err(e))),
            }
        }
        Ok(StagedGroup { staged, answered })
    }

    /// Makes the staged versions durable with one sync, then publishes them and answers every
    /// edit in order (the other answers at their places among the versions). A failed sync
    /// fails the group: `Err`, since the versions may or may not have reached the disk.
    fn sync_and_answer(
        &self,
        writer: &mut Vod2Writer,
        stage: StagedGroup,
        began: Instant,
    ) -> Result<(), WriterLost> {
        let StagedGroup { staged, answered } = stage;
        if !staged.is_empty() {
            let synced = Instant::now();
            if let Err(e) = writer.sync() {
                tracing::error!(volume = %self.name, error = %error_chain(&e), "cannot make an edit group durable");
                fail_all(staged, answered, std::iter::empty(), &e);
                return Err(WriterLost);
            }
            tracing::debug!(
                volume = %self.name,
                edits = staged.len(),
                staging_us = micros(synced - began),
                sync_us = micros(synced.elapsed()),
                "edit group durable"
            );
        }
        let mut answered = answered.into_iter().peekable();
        for (i, s) in staged.into_iter().enumerate() {
            while let Some((_, pending, a)) = answered.next_if(|(at, _, _)| *at <= i) {
                pending.answer(a);
            }
            self.publish(s.vod, s.event);
            let mut response = s.response;
            response.elapsed_us = micros(s.started.elapsed());
            s.pending.answer(Ok(response));
        }
        for (_, pending, a) in answered {
            pending.answer(a);
        }
        Ok(())
    }

    /// Applies one edit as a group of its own (one sync), holding the writer; what
    /// the edits of a file served by no task take. Blocking; never cancelled.
    ///
    /// # Errors
    /// See [`LiveVolume::submit`].
    pub fn apply(
        &self,
        slot: &mut WriterSlot,
        edit: Edit,
        if_match: Option<u64>,
        policy: CheckpointPolicy,
    ) -> Result<EditResponse, VolumeError> {
        if let Some(unchanged) = self.unchanged(&edit) {
            return Ok(unchanged);
        }
        let work = Work::edit(edit, false);
        let (pending, mut answer) = PendingEdit::new(work, if_match, CancelToken::never());
        self.commit_group(slot, vec![pending], policy);
        answer.try_recv().map_err(|_| {
            VolumeError::Store(StoreError::Internal("the edit was not answered".into()))
        })?
    }

    /// The answer to an edit that reaches no voxel of the volume ([`Edit::reaches_nothing`]),
    /// which is not queued and commits nothing: it names the served version, and the change
    /// feed announces nothing. `None` for every other edit.
    fn unchanged(&self, edit: &Edit) -> Option<EditResponse> {
        let head = self.head();
        edit.reaches_nothing(head.layout()).then(|| EditResponse {
            version: head.version,
            previous: head.version,
            changed: vec![Vec::new(); usize::from(head.layout().levels())],
            evaluated: 0,
            new_records: 0,
            checkpoint: false,
            elapsed_us: 0,
            committed: false,
            replayed: None,
            dry_run: false,
            voxels_changed: Some(0),
            channels: Default::default(),
        })
    }

    /// Serves a durable version: readers get it, the history lists it, the feed announces it.
    pub(super) fn publish(&self, vod: Arc<Vod2>, event: ChangeEvent) {
        {
            let mut history = self.history.write().unwrap_or_else(|p| p.into_inner());
            if history.offsets.is_empty() {
                history.oldest = event.version;
            }
            history.offsets.push(vod.head_slot().commit);
        }
        self.current.store(vod);
        self.announce(&event);
    }
}

/// The volume's writer, opened if needed, with nothing staged: reopened when a failed group
/// left versions staged or the writer is not at the served head (opening cuts off what was
/// appended past the file's durable head).
fn writer_at<'a>(slot: &'a mut WriterSlot, base: &Vod2) -> Result<&'a mut Vod2Writer, StoreError> {
    let at_head = slot.writer.as_ref().is_some_and(|w| {
        !w.has_staged() && w.head().map(|h| h.commit) == Some(base.head_ref().commit_offset())
    });
    if !at_head {
        if slot.writer.is_some() {
            tracing::warn!(path = %base.path().display(), "the writer and the served head disagree; reopening the writer");
        }
        slot.writer = None;
    }
    match &mut slot.writer {
        Some(w) => Ok(w),
        empty => Ok(empty.insert(Vod2Writer::open_append(
            base.path(),
            Compression::for_edits(),
        )?)),
    }
}

impl LiveVolume {
    /// Stages `work` on `tip`: the next version's file (mapped up to its commit record, not
    /// yet durable), its change event read back from the record, and the answer.
    fn stage_work(
        &self,
        writer: &mut Vod2Writer,
        tip: &Vod2,
        work: &mut Work,
        policy: CheckpointPolicy,
        cancel: &CancelToken,
    ) -> Result<(Arc<Vod2>, ChangeEvent, EditResponse), VolumeError> {
        let head = tip.head_ref();
        let staged = self.stage_only(writer, head, work, policy, cancel)?;
        let slot = writer.tip().ok_or_else(|| {
            StoreError::Internal("staging left the writer without a version".into())
        })?;
        let next = tip.advance(slot)?;
        let event = change_event(&next, slot.commit)?;
        let response = staged.response(&event, head.version);
        Ok((Arc::new(next), event, response))
    }

    /// Stages `work` on `head` in `writer`: the commit's bytes appended, the version not yet
    /// readable (a remote writer keeps them until its sync) nor durable.
    pub(super) fn stage_only(
        &self,
        writer: &mut Vod2Writer,
        head: &Snapshot,
        work: &mut Work,
        policy: CheckpointPolicy,
        cancel: &CancelToken,
    ) -> Result<StagedWork, VolumeError> {
        Ok(match work {
            Work::Edit { edit, .. } => {
                let outcome = stage_edit(writer, head, edit, policy, cancel)?;
                StagedWork {
                    changed: outcome.changed,
                    new_records: outcome.new_records,
                    checkpoint: outcome.checkpoint,
                    evaluated: outcome.evaluated as u64,
                    replayed: None,
                    voxels_changed: Some(outcome.voxels_changed),
                    channels: outcome.channels,
                }
            }
            Work::Undo(job) => self.stage_undo(writer, head, job, policy, cancel)?.into(),
            Work::Revert { to, note } => self
                .stage_revert(writer, head, *to, note.clone(), policy)?
                .into(),
            Work::Tag { tag, version, note } => self
                .stage_tag(writer, head, tag, *version, note.clone(), policy)?
                .into(),
        })
    }
}

/// What staging a request's work made, before it is durable.
#[derive(Debug)]
pub(super) struct StagedWork {
    /// Changed bricks per level.
    pub changed: ChangedKeys,
    pub new_records: u64,
    pub checkpoint: bool,
    /// Level-0 bricks evaluated.
    pub evaluated: u64,
    /// For undo and redo: other edits applied again.
    pub replayed: Option<u64>,
    /// For an edit: the level-0 voxels whose density it changed.
    pub voxels_changed: Option<u64>,
    /// Changed bricks of attribute channels, by channel name, per level.
    pub channels: std::collections::BTreeMap<String, ChangedKeys>,
}

impl From<StagedCommit> for StagedWork {
    fn from(s: StagedCommit) -> Self {
        StagedWork {
            changed: s.committed.changed,
            new_records: s.committed.new_records,
            checkpoint: s.committed.checkpoint,
            evaluated: s.evaluated,
            replayed: s.replayed,
            voxels_changed: None,
            // An answer after commit takes the channels from its change event; undo, revert
            // and tags have no dry run.
            channels: Default::default(),
        }
    }
}

impl StagedWork {
    /// The answer once committed as `event` on top of `previous`.
    pub(super) fn response(&self, event: &ChangeEvent, previous: u64) -> EditResponse {
        EditResponse {
            version: event.version,
            previous,
            changed: event.changed.clone(),
            evaluated: self.evaluated,
            new_records: self.new_records,
            checkpoint: self.checkpoint,
            elapsed_us: 0,
            committed: true,
            replayed: self.replayed,
            dry_run: false,
            voxels_changed: self.voxels_changed,
            channels: event.channels.clone(),
        }
    }

    /// The answer of a dry run on `previous`: what would be `version`.
    pub(super) fn dry_run(&self, version: u64, previous: u64) -> EditResponse {
        EditResponse {
            version,
            previous,
            changed: self.changed.clone(),
            evaluated: self.evaluated,
            new_records: self.new_records,
            checkpoint: self.checkpoint,
            elapsed_us: 0,
            committed: false,
            replayed: self.replayed,
            dry_run: true,
            voxels_changed: self.voxels_changed,
            channels: self.channels.clone(),
        }
    }
}

pub(super) fn micros(d: Duration) -> u64 {
    u64::try_from(d.as_micros()).unwrap_or(u64::MAX)
}

/// An error like `e` for each of several edits that share it: the same variant, so that each
/// is answered with the status `e` has (a stalled store is a 503 for every edit of the group).
pub(super) fn copy_of(e: &StoreError) -> StoreError {
    match e {
        StoreError::Io { context, source } => StoreError::Io {
            context: context.clone(),
            source: std::io::Error::new(source.kind(), source.to_string()),
        },
        StoreError::Format(f) => StoreError::Format(f.clone()),
        StoreError::Corrupt {
            offset,
            expected,
            found,
        } => StoreError::Corrupt {
            offset: *offset,
            expected: expected.clone(),
            found: found.clone(),
        },
        StoreError::Absent(m) => StoreError::Absent(m.clone()),
        StoreError::OutOfRange(m) => StoreError::OutOfRange(m.clone()),
        StoreError::BadInput(m) => StoreError::BadInput(m.clone()),
        StoreError::ObjectStore { context, source } => StoreError::ObjectStore {
            context: context.clone(),
            source: error_chain(source.as_ref()).into(),
        },
        StoreError::HeadMoved { url } => StoreError::HeadMoved { url: url.clone() },
        StoreError::Stalled { limit } => StoreError::Stalled { limit: *limit },
        StoreError::Internal(m) => StoreError::Internal(m.clone()),
    }
}

/// Answers every edit of a group that failed as a whole (a failed sync, a writer that could
/// not be rolled back) with `e`: none of its versions is served. What was refused before
/// stays refused, but a conflict with (or a dry run on) a version of the group names a
/// version never made.
fn fail_all(
    staged: Vec<Staged>,
    answered: Vec<(usize, PendingEdit, EditAnswer)>,
    unreached: impl Iterator<Item = PendingEdit>,
    e: &StoreError,
) {
    for s in staged {
        s.pending.answer(Err(copy_of(e).into()));
    }
    for (at, pending, answer) in answered {
        let answer = match answer {
            // A dry run, or a conflict, on a version of the group that is never made.
            Ok(_) | Err(VolumeError::Conflict { .. }) if at > 0 => Err(copy_of(e).into()),
            other => other,
        };
        pending.answer(answer);
    }
    for pending in unreached {
        pending.answer(Err(copy_of(e).into()));
    }
}
