//! Who did what: each commit's note read back from its record (`docs/vod2.md`, revision 3),
//! the history list, tags, and which edits are in effect (undone or not).
//!
//! The notes are read from the file, the one source the feed, `changes` and `history` share;
//! what a note says (without the edit's request, read again only to replay it) is kept per
//! version once read, since versions never change.

use super::{changed_bricks, LiveVolume, VolumeError};
use crate::store::{StoreError, Vod2};
use isovox_proto::api::{ChangeEvent, ChangedBricks, LevelBrick, EVENT_GRID_LIMIT};
use isovox_proto::history::{
    CommitInfo, CommitKind, CommitNote, HistoryEntry, HistoryList, Tag, TagList, MAX_TAG_LEN,
};
use isovox_proto::layout::BrickKey;
use isovox_proto::vod2::{BrickSummary, CommitHeader, NodeEntry};
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

/// Commits listed by one `history` answer, by default and at most.
pub const DEFAULT_HISTORY: usize = 100;
/// See [`DEFAULT_HISTORY`].
pub const MAX_HISTORY: usize = 1000;

/// What one commit's record says of it.
#[derive(Debug, Clone)]
pub struct CommitRecord {
    /// The version it made.
    pub version: u64,
    /// When (Unix milliseconds).
    pub timestamp_ms: u64,
    /// Who and what.
    pub info: CommitInfo,
    /// Bricks it changed, over every level.
    pub bricks_changed: u64,
    /// Where its record is, to read the edit's request again.
    pub offset: u64,
}

/// Notes read so far, by version.
#[derive(Debug, Default)]
pub(super) struct RecordCache {
    records: HashMap<u64, Arc<CommitRecord>>,
}

/// The note of the commit record at `at` (an empty note for records without one).
///
/// # Errors
/// The record does not read, or its note is not a commit note (the note's checksum held, so
/// the writer wrote it so: the file is not one this server can trust).
pub fn read_note(vod: &Vod2, at: u64) -> Result<(CommitHeader, CommitNote), StoreError> {
    let (h, _) = vod.commit_at(at)?;
    let bytes = vod
        .mapped()
        .get(at as usize..)
        .map_or(&[][..], |b| h.note(b));
    if bytes.is_empty() {
        return Ok((h, CommitNote::default()));
    }
    let note = serde_json::from_slice(bytes).map_err(|e| {
        StoreError::corrupt(
            at,
            "the note of a commit record",
            format!("not a commit note: {e}"),
        )
    })?;
    Ok((h, note))
}

/// The change-feed event of the commit record at `at`.
///
/// # Errors
/// The record or its note does not read.
pub(crate) fn change_event(vod: &Vod2, at: u64) -> Result<ChangeEvent, StoreError> {
    let (h, note) = read_note(vod, at)?;
    let (_, changes) = vod.commit_at(at)?;
    // Revision 5: the record carries each change's summary, so the event's grid reads no
    // brick record.
    let summaries = vod
        .mapped()
        .get(at as usize..)
        .and_then(|b| h.summaries_in(b));
    let header = vod.header();
    let per_stream = header.layout.node_count();
    let nodes_of = |stream: u64| {
        CommitHeader::changes(changes)
            .map(|(node, _)| node)
            .filter(move |node| node / per_stream == stream)
            .map(move |node| node % per_stream)
    };
    let channels = header
        .channels
        .iter()
        .zip(1u64..)
        .map(|(c, stream)| {
            (
                c.name.clone(),
                changed_bricks(vod.layout(), nodes_of(stream)),
            )
        })
        .filter(|(_, changed)| changed.iter().any(|level| !level.is_empty()))
        .collect();
    let changed = changed_bricks(vod.layout(), nodes_of(0));
    let bricks = changed_grid(vod, at, changes, summaries, &changed)?;
    Ok(ChangeEvent {
        version: h.version,
        timestamp_ms: h.timestamp_ms,
        changed,
        bricks,
        channels,
        info: note.info,
    })
}

/// What each density brick of `changed` holds after the commit at `at` whose record's changes
/// are `changes`: its hash and value range, from the summaries the record carries (revision 5;
/// brick headers for a record without them, never a payload), in `changed`'s order. Empty past
/// [`EVENT_GRID_LIMIT`] bricks.
///
/// # Errors
/// An entry, a summary or a brick header in the record is malformed.
fn changed_grid(
    vod: &Vod2,
    at: u64,
    changes: &[u8],
    summaries: Option<Vec<BrickSummary>>,
    changed: &ChangedBricks,
) -> Result<Vec<Vec<LevelBrick>>, StoreError> {
    if changed.iter().map(Vec::len).sum::<usize>() > EVENT_GRID_LIMIT {
        return Ok(Vec::new());
    }
    let snap = vod.head_ref();
    let layout = snap.layout();
    let per_stream = layout.node_count();
    let mut now = HashMap::new();
    for (i, (node, raw)) in CommitHeader::changes(changes).enumerate() {
        if node >= per_stream {
            continue;
        }
        // A node written twice by one record: the later entry is what the version holds.
        let summary = summaries.as_ref().and_then(|s| s.get(i).copied());
        now.insert(node, (raw, summary));
    }
    changed
        .iter()
        .enumerate()
        .map(|(level, bricks)| {
            bricks
                .iter()
                .map(|&[x, y, z]| {
                    let key = BrickKey {
                        level: level as u8,
                        x,
                        y,
                        z,
                    };
                    let &(raw, summary) = now.get(&layout.node_index(key)).ok_or_else(|| {
                        StoreError::Internal(format!("brick {key} changed but has no entry"))
                    })?;
                    let entry = NodeEntry::decode(raw, layout.voxel_type(), vod.committed_len())?;
                    let s = match (entry, summary) {
                        (NodeEntry::Stored(_), Some(s)) => {
                            s.validate(layout.voxel_type(), "commit summaries", at)?
                        }
                        // A constant's summary is its value; an older record's is its header's.
                        _ => snap.entry_summary(entry)?,
                    };
                    Ok(LevelBrick {
                        hash: format!("{:016x}", s.hash),
                        min: s.min,
                        max: s.max,
                    })
                })
                .collect()
        })
        .collect()
}

/// Whether `tag` may name a version: 1 to 64 of `[A-Za-z0-9._-]`, not all digits (so that
/// `?version=` tells a tag from a number).
pub fn valid_tag(tag: &str) -> bool {
    (1..=MAX_TAG_LEN).contains(&tag.len())
        && tag
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
        && !tag.bytes().all(|b| b.is_ascii_digit())
}

impl LiveVolume {
    /// What the commit of `version` says of itself.
    ///
    /// # Errors
    /// The version is not in the file, or its record does not read.
    pub fn record(&self, version: u64) -> Result<Arc<CommitRecord>, VolumeError> {
        if let Some(r) = self.records_lock().records.get(&version) {
            return Ok(r.clone());
        }
        let vod = self.current();
        let at = self
            .history_read()
            .offset(version)
            .ok_or_else(|| VolumeError::NoSuchVersion {
                version,
                oldest: self.oldest(),
                head: vod.head().version,
            })?;
        let (h, note) = read_note(&vod, at)?;
        let record = Arc::new(CommitRecord {
            version: h.version,
            timestamp_ms: h.timestamp_ms,
            info: note.info,
            bricks_changed: h.n_changes,
            offset: at,
        });
        self.records_lock().records.insert(version, record.clone());
        Ok(record)
    }

    fn records_lock(&self) -> std::sync::MutexGuard<'_, RecordCache> {
        // Every update is one insert: a poisoned lock is still sound.
        self.records.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The records of every version from the oldest the file holds to `head`, oldest first.
    ///
    /// # Errors
    /// A record does not read.
    pub fn records_until(&self, head: u64) -> Result<Vec<Arc<CommitRecord>>, VolumeError> {
        (self.oldest().max(1)..=head)
            .map(|v| self.record(v))
            .collect()
    }

    /// The full note of `version`'s commit, with the edit's request.
    ///
    /// # Errors
    /// The version is not in the file, or its record does not read.
    pub fn note(&self, version: u64) -> Result<CommitNote, VolumeError> {
        let record = self.record(version)?;
        Ok(read_note(&self.current(), record.offset)?.1)
    }

    /// `GET .../history?before=V&limit=N`: the commits before `before` (all when `None`),
    /// newest first. Blocking: it reads commit records.
    ///
    /// # Errors
    /// A limit outside `1..=MAX_HISTORY`; a record that does not read.
    pub fn history(
        &self,
        before: Option<u64>,
        limit: Option<usize>,
    ) -> Result<HistoryList, VolumeError> {
        let limit = limit.unwrap_or(DEFAULT_HISTORY);
        if !(1..=MAX_HISTORY).contains(&limit) {
            return Err(VolumeError::BadRequest(format!(
                "limit must be in 1..={MAX_HISTORY}"
            )));
        }
        let head = self.head().version;
        let oldest = self.oldest().max(1);
        let newest = before.map_or(head, |b| b.saturating_sub(1).min(head));
        let records = self.records_until(head)?;
        let effect = in_effect(&records, head);
        let mut commits = Vec::new();
        let mut v = newest;
        while v >= oldest && commits.len() < limit {
            let r = &records[(v - oldest) as usize];
            commits.push(HistoryEntry {
                version: r.version,
                timestamp_ms: r.timestamp_ms,
                info: r.info.clone(),
                bricks_changed: r.bricks_changed,
                undone: (r.info.kind == Some(CommitKind::Edit))
                    .then(|| !effect.get(&r.version).copied().unwrap_or(false)),
            });
            v -= 1;
        }
        Ok(HistoryList {
            head,
            oldest,
            more: v >= oldest,
            commits,
        })
    }

    /// Every tag, by name: the newest commit that set each.
    ///
    /// # Errors
    /// A record does not read.
    pub fn tags(&self) -> Result<TagList, VolumeError> {
        let head = self.head().version;
        let mut tags: BTreeMap<String, Tag> = BTreeMap::new();
        for r in self.records_until(head)? {
            if let (Some(CommitKind::Tag), Some(tag), Some(to)) =
                (r.info.kind, &r.info.tag, r.info.to)
            {
                tags.insert(
                    tag.clone(),
                    Tag {
                        tag: tag.clone(),
                        version: to,
                        author: r.info.author.clone(),
                        set_at: r.version,
                    },
                );
            }
        }
        Ok(TagList {
            tags: tags.into_values().collect(),
        })
    }

    /// The version `tag` names.
    ///
    /// # Errors
    /// No such tag (a 404); a record does not read.
    pub fn tagged(&self, tag: &str) -> Result<u64, VolumeError> {
        self.tags()?
            .tags
            .into_iter()
            .find(|t| t.tag == tag)
            .map(|t| t.version)
            .ok_or_else(|| VolumeError::OutOfRange(format!("no tag {tag:?} in this volume")))
    }
}

/// Which edits of `records` (oldest first, up to `at`) are in effect at version `at`: made,
/// not undone since (or made again), and not reverted away. Edits older than the records are
/// not listed.
pub fn in_effect(records: &[Arc<CommitRecord>], at: u64) -> BTreeMap<u64, bool> {
    let mut state = BTreeMap::new();
    for r in records.iter().take_while(|r| r.version <= at) {
        match (r.info.kind, r.info.target, r.info.to) {
            (Some(CommitKind::Edit), _, _) => {
                state.insert(r.version, true);
            }
            (Some(CommitKind::Undo), Some(edit), _) => {
                state.insert(edit, false);
            }
            (Some(CommitKind::Redo), Some(edit), _) => {
                state.insert(edit, true);
            }
            // A revert restores what was in effect at its target: the edits after it are
            // not, whatever undos and redos happened between.
            (Some(CommitKind::Revert), _, Some(to)) if to < r.version => {
                state = in_effect(records, to);
            }
            _ => {}
        }
    }
    state
}
