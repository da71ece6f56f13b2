//! Undo and redo of one edit, revert, and tags: commits that the writer stages like an edit,
//! computed from the history instead of a term (`docs/editing.md`, "History and undo").
//!
//! **The model.** The content of every brick is its content at some base version with the
//! edits in effect after it applied in version order. Edits are deterministic functions of the
//! voxels before them (a `volume` leaf reads the version its commit recorded), so undoing the
//! edit E recomputes only the bricks E's box meets: from a base version P before E, at which
//! every edit meeting those bricks was in effect exactly as it will be after the undo, replay
//! the edits after P that stay in effect. P is E - 1 unless an edit before E meeting the same
//! bricks was undone or redone since; then P moves before that edit. Redo is the same with E in
//! effect again. A revert restores a version's index (and what was in effect then); a tag is a
//! commit that changes no brick.

use super::history::{in_effect, CommitRecord};
use super::{EditLimits, LiveVolume, VolumeError};
use crate::cancel::CancelToken;
use crate::geometry::Box3;
use crate::icvg::edit::{bricks_meeting, channel_voxels, edit_voxels, note_bytes, Edit};
use crate::icvg::term::{PinnedReads, VolumeResolver};
use crate::store::transaction::{Committed, Transaction};
use crate::store::{BrickVoxels, CheckpointPolicy, Snapshot, Vod2Writer};
use isovox_proto::history::{CommitInfo, CommitKind, CommitNote};
use isovox_proto::vod2::{CommitHeader, NodeEntry};
use isovox_proto::BrickKey;
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

/// An undo (or redo) asked for: the version whose commit is taken back, and who asks.
pub struct UndoJob {
    /// An edit's version (undo it), an undo's (redo its edit) or a redo's (undo it again).
    pub version: u64,
    /// Who asks: they must be the edit's author, unless `admin`.
    pub user: String,
    /// Whether they may undo anyone's edit.
    pub admin: bool,
    /// The new commit's message.
    pub message: Option<String>,
    /// What one edit may cost: the replay is held to it.
    pub limits: EditLimits,
    /// Where replayed edits find the volumes they read.
    pub volumes: Arc<dyn VolumeResolver + Send + Sync>,
}

impl std::fmt::Debug for UndoJob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UndoJob")
            .field("version", &self.version)
            .field("user", &self.user)
            .finish_non_exhaustive()
    }
}

/// What staging an undo, revert or tag made.
pub(super) struct StagedCommit {
    pub committed: Committed,
    /// Later edits applied again (undo and redo).
    pub replayed: Option<u64>,
    /// Level-0 bricks whose voxels were evaluated.
    pub evaluated: u64,
}

fn kind_name(kind: Option<CommitKind>) -> &'static str {
    match kind {
        Some(CommitKind::Edit) => "an edit",
        Some(CommitKind::Undo) => "an undo",
        Some(CommitKind::Redo) => "a redo",
        Some(CommitKind::Revert) => "a revert",
        Some(CommitKind::Tag) => "a tag",
        None => "a commit that recorded no edit (an import, or made before commits kept notes)",
    }
}

/// The brick-aligned box of the level-0 bricks `b` meets.
fn brick_area(snap: &Snapshot, b: &Box3) -> Box3 {
    let e = i64::from(snap.layout().brick());
    let align = |v: i64, up: bool| {
        if up {
            (v + e - 1).div_euclid(e) * e
        } else {
            v.div_euclid(e) * e
        }
    };
    Box3::new(
        b.min.map(|v| align(v, false)),
        b.max.map(|v| align(v, true)),
    )
    .intersect(&Box3::of_volume(snap.layout()))
}

fn op_box(r: &CommitRecord) -> Option<Box3> {
    r.info.op.as_ref().map(|op| op.bbox)
}

fn meets(r: &CommitRecord, area: &Box3) -> bool {
    op_box(r).is_some_and(|b| !b.intersect(area).is_empty())
}

impl LiveVolume {
    /// Stages the undo (or redo) `job` on `head`, the served head (an undo is a group of its
    /// own: it reads the history up to the head).
    pub(super) fn stage_undo(
        &self,
        writer: &mut Vod2Writer,
        head: &Snapshot,
        job: &UndoJob,
        policy: CheckpointPolicy,
        cancel: &CancelToken,
    ) -> Result<StagedCommit, VolumeError> {
        let layout = head.layout();
        let records = self.records_until(head.version)?;
        let oldest = records.first().map_or(head.version, |r| r.version);
        let at = |v: u64| -> Result<&Arc<CommitRecord>, VolumeError> {
            v.checked_sub(oldest)
                .and_then(|i| records.get(usize::try_from(i).ok()?))
                .ok_or(VolumeError::NoSuchVersion {
                    version: v,
                    oldest,
                    head: head.version,
                })
        };
        let asked = at(job.version)?;
        let (edit_version, redo) = match (asked.info.kind, asked.info.target) {
            (Some(CommitKind::Edit), _) => (asked.version, false),
            (Some(CommitKind::Undo), Some(edit)) => (edit, true),
            (Some(CommitKind::Redo), Some(edit)) => (edit, false),
            (kind, _) => {
                return Err(VolumeError::NotUndoable(format!(
                    "version {} is {}: only an edit, or an undo or redo of one, can be undone",
                    job.version,
                    kind_name(kind)
                )))
            }
        };
        let edit = at(edit_version)?;
        let Some(edit_box) = op_box(edit) else {
            return Err(VolumeError::NotUndoable(format!(
                "version {edit_version} recorded no box for its edit"
            )));
        };
        if edit.info.author.as_deref() != Some(job.user.as_str()) && !job.admin {
            return Err(VolumeError::NotAllowed(format!(
                "the edit of version {edit_version} is {}'s: only its author or a user with the admin role may undo or redo it",
                edit.info.author.as_deref().unwrap_or("no one's")
            )));
        }
        let now = in_effect(&records, head.version);
        let in_effect_now = now.get(&edit_version).copied().unwrap_or(false);
        if redo && in_effect_now {
            return Err(VolumeError::NotUndoable(format!(
                "the edit of version {edit_version} is in effect: there is nothing to redo"
            )));
        }
        if !redo && !in_effect_now {
            return Err(VolumeError::NotUndoable(format!(
                "the edit of version {edit_version} is undone already (or reverted away)"
            )));
        }
        let mut wanted = now;
        wanted.insert(edit_version, redo);
        let area = brick_area(head, &edit_box);
        let base = base_version(&records, oldest, edit_version, &area, &wanted)?;
        // Every commit after the base that changed bricks must be one the model knows.
        if let Some(r) = records
            .iter()
            .rev()
            .find(|r| r.version > base && r.info.kind.is_none() && r.bricks_changed > 0)
        {
            return Err(VolumeError::NotUndoable(format!(
                "version {} changed the volume without recording what it did (an import or an older server): revert to a version instead",
                r.version
            )));
        }
        let replays: Vec<&Arc<CommitRecord>> = records
            .iter()
            .filter(|r| {
                r.version > base
                    && r.info.kind == Some(CommitKind::Edit)
                    && wanted.get(&r.version).copied().unwrap_or(false)
                    && meets(r, &area)
            })
            .collect();
        let keys = bricks_meeting(layout, &area);
        let brick_voxels = u64::from(layout.brick()).pow(3);
        let voxels: u64 = keys
            .iter()
            .map(|&k| {
                let b = Box3::of_brick(layout, k);
                let n = replays.iter().filter(|r| meets(r, &b)).count() as u64;
                (n + 1) * brick_voxels
            })
            .sum();
        if let Some(max) = job.limits.max_voxels.filter(|&max| voxels > max) {
            return Err(VolumeError::UndoTooLarge { voxels, max });
        }
        let mut edits = Vec::with_capacity(replays.len());
        for r in &replays {
            let note = self.note(r.version)?;
            let request = note.request.ok_or_else(|| {
                VolumeError::NotUndoable(format!(
                    "version {} recorded no request to apply again",
                    r.version
                ))
            })?;
            let pinned = PinnedReads::new(job.volumes.as_ref(), &note.reads);
            let mut e = Edit::for_volume(
                &request,
                head.header(),
                &job.limits.term,
                &pinned,
                job.limits.max_voxels,
                cancel,
            )?;
            e.prepare_eval(layout, cancel)?;
            let target = e.target(layout);
            edits.push((e, target, op_box(r).unwrap_or(target)));
        }
        let from = self.version(base)?;
        // Every stream of a brick (density, then each channel) is replayed together: an edit's
        // channel values depend on the density before it.
        let channels = &head.header().channels;
        let results: Vec<(BrickKey, Vec<Option<BrickVoxels>>)> = keys
            .par_iter()
            .map(|&key| {
                cancel.check()?;
                let brick = Box3::of_brick(layout, key);
                let mut streams = from
                    .streams()
                    .map(|s| s.voxels(key))
                    .collect::<Result<Vec<_>, _>>()?;
                for (e, target, reach) in &edits {
                    if reach.intersect(&brick).is_empty() {
                        continue;
                    }
                    for (i, channel) in channels.iter().enumerate() {
                        let (density, values) = (&streams[0], &streams[i + 1]);
                        if let Some(next) =
                            channel_voxels(e, density, values, layout, channel, target, key)?
                        {
                            streams[i + 1] = next;
                        }
                    }
                    if let Some(next) = edit_voxels(e, &streams[0], layout, target, key)? {
                        streams[0] = next;
                    }
                }
                let changed = head
                    .streams()
                    .zip(streams)
                    .map(|(now, replayed)| Ok((replayed != now.voxels(key)?).then_some(replayed)))
                    .collect::<Result<Vec<_>, crate::store::StoreError>>()?;
                Ok((key, changed))
            })
            .collect::<Result<_, crate::icvg::term::EvalError>>()?;
        let mut level0: Vec<Vec<(BrickKey, BrickVoxels)>> = vec![Vec::new(); 1 + channels.len()];
        for (key, streams) in results {
            for (stream, v) in streams.into_iter().enumerate() {
                if let Some(v) = v {
                    level0[stream].push((key, v));
                }
            }
        }
        let replayed = replays.iter().filter(|r| r.version != edit_version).count() as u64;
        let note = CommitNote {
            info: CommitInfo {
                author: Some(job.user.clone()),
                message: job.message.clone(),
                kind: Some(if redo {
                    CommitKind::Redo
                } else {
                    CommitKind::Undo
                }),
                op: edit.info.op.clone(),
                target: Some(edit_version),
                replayed: Some(replayed),
                ..CommitInfo::default()
            },
            ..CommitNote::default()
        };
        let mut transaction = Transaction::on(writer, head);
        transaction.set_note(note_bytes(&note));
        let mut level0 = level0.into_iter();
        // A replay changes bricks wherever the edits it replays reached: no bound tighter than
        // the volume is kept for them.
        let everywhere = Box3::of_volume(head.layout());
        transaction.update_level0(level0.next().unwrap_or_default(), &everywhere)?;
        for (view, changed) in head.channel_views().iter().zip(level0) {
            transaction.update_channel_level0(view, changed, &everywhere)?;
        }
        Ok(StagedCommit {
            committed: transaction.stage(policy)?,
            replayed: Some(replayed),
            evaluated: keys.len() as u64,
        })
    }

    /// Stages a revert to version `to` on `head`: every node an edit after `to` changed gets
    /// its entry of `to` back (the bricks are in the file already: nothing is copied).
    pub(super) fn stage_revert(
        &self,
        writer: &mut Vod2Writer,
        head: &Snapshot,
        to: u64,
        mut note: CommitNote,
        policy: CheckpointPolicy,
    ) -> Result<StagedCommit, VolumeError> {
        if to > head.version {
            return Err(VolumeError::NoSuchVersion {
                version: to,
                oldest: self.oldest(),
                head: head.version,
            });
        }
        if to == head.version {
            return Err(VolumeError::NotUndoable(format!(
                "version {to} is the head: there is nothing to revert"
            )));
        }
        let target = self.version(to)?;
        let vod = self.current();
        let mut nodes = BTreeSet::new();
        for v in to + 1..=head.version {
            let (_, record) = vod.commit_at(self.record(v)?.offset)?;
            nodes.extend(CommitHeader::changes(record).map(|(node, _)| node));
        }
        note.info.kind = Some(CommitKind::Revert);
        note.info.to = Some(to);
        let mut transaction = Transaction::on(writer, head);
        transaction.set_note(note_bytes(&note));
        // Nodes are file-wide: each belongs to one stream's pyramid (density, or a channel).
        let per_stream = head.layout().node_count();
        let (heads, targets): (Vec<&Snapshot>, Vec<&Snapshot>) =
            (head.streams().collect(), target.streams().collect());
        for node in nodes {
            let (stream, local) = ((node / per_stream) as usize, node % per_stream);
            let (Some(now), Some(then)) = (heads.get(stream), targets.get(stream)) else {
                continue;
            };
            let entry: NodeEntry = then.entry_at(local)?;
            transaction.set_in(now, local, entry)?;
        }
        Ok(StagedCommit {
            committed: transaction.stage(policy)?,
            replayed: None,
            evaluated: 0,
        })
    }

    /// Stages a tag: a commit that changes no brick and names `version` as `tag`.
    pub(super) fn stage_tag(
        &self,
        writer: &mut Vod2Writer,
        head: &Snapshot,
        tag: &str,
        version: u64,
        mut note: CommitNote,
        policy: CheckpointPolicy,
    ) -> Result<StagedCommit, VolumeError> {
        let oldest = self.oldest();
        if version > head.version || version < oldest {
            return Err(VolumeError::NoSuchVersion {
                version,
                oldest,
                head: head.version,
            });
        }
        note.info.kind = Some(CommitKind::Tag);
        note.info.tag = Some(tag.to_string());
        note.info.to = Some(version);
        let mut transaction = Transaction::on(writer, head);
        transaction.set_note(note_bytes(&note));
        Ok(StagedCommit {
            committed: transaction.stage(policy)?,
            replayed: None,
            evaluated: 0,
        })
    }
}

/// The newest version before `edit` from which the bricks of `area` can be recomputed: every
/// edit up to it that meets `area` was then in effect as `wanted` says it will be.
fn base_version(
    records: &[Arc<CommitRecord>],
    oldest: u64,
    edit: u64,
    area: &Box3,
    wanted: &BTreeMap<u64, bool>,
) -> Result<u64, VolumeError> {
    let mut base = edit.saturating_sub(1);
    loop {
        if base < oldest {
            return Err(VolumeError::NotUndoable(format!(
                "undoing this edit needs the volume as it was at version {base}, which was compacted away: revert instead"
            )));
        }
        let then = in_effect(records, base);
        let differs = records
            .iter()
            .take_while(|r| r.version <= base)
            .filter(|r| r.info.kind == Some(CommitKind::Edit) && meets(r, area))
            .find(|r| {
                then.get(&r.version).copied().unwrap_or(false)
                    != wanted.get(&r.version).copied().unwrap_or(false)
            });
        match differs {
            None => return Ok(base),
            Some(r) => base = r.version - 1,
        }
    }
}
