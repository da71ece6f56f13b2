//! A served volume: its current version, its single writer, its history and its change feed.
//!
//! Readers call [`LiveVolume::current`] and get the open file as of the newest commit (an
//! `Arc` swapped atomically): they never wait for the writer. Edits are serialized by the
//! writer lock; each one is evaluated against the head snapshot, committed (durable before the
//! call returns), turned into the next [`Vod2`] by [`Vod2::advance`], recorded in the version
//! history, published to readers, and announced on the change feed, in that order.
//!
//! The change feed is a `tokio::sync::broadcast` channel: sending never waits, and a subscriber
//! that falls more than [`FEED_CAPACITY`] versions behind learns it (`Lagged`) instead of
//! slowing anyone down. What it announces is read back from the commit record, the same
//! source `changes?since=N` reads, so the live feed and the catch-up list cannot disagree.

use crate::icvg::edit::{apply_edit, CheckpointPolicy, Edit};
use crate::store::codec::Compression;
use crate::store::compact::{compact, CompactReport};
use crate::store::{Snapshot, StoreError, Vod2, Vod2Writer};
use arc_swap::ArcSwap;
use isovox_proto::api::{ChangeEvent, ChangedBricks, EditResponse};
use isovox_proto::vod2::CommitHeader;
use isovox_proto::{FormatError, VolumeLayout};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, RwLock};
use tokio::sync::broadcast;

/// Versions a subscriber may fall behind before it is told to resync.
pub const FEED_CAPACITY: usize = 1024;

/// One committed version on the change feed, with its JSON made once for every subscriber.
#[derive(Debug)]
pub struct FeedItem {
    pub version: u64,
    pub json: String,
}

/// Why an edit was not applied.
#[derive(Debug, thiserror::Error)]
pub enum EditError {
    /// `If-Match` named another version.
    #[error("the volume is at version {current}, not {expected}")]
    Conflict { expected: u64, current: u64 },
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// Commit offsets by version: `offsets[v - oldest]` is version `v`'s commit record.
#[derive(Debug, Clone, Default)]
struct History {
    oldest: u64,
    offsets: Vec<u64>,
}

impl History {
    /// Walks the commit chain of `vod` once (at start and after compaction).
    fn read(vod: &Vod2) -> Result<History, StoreError> {
        let mut commits = vod.commits()?;
        commits.reverse();
        let oldest = commits.first().map_or(0, |(_, h)| h.version);
        for (i, (_, h)) in commits.iter().enumerate() {
            if h.version != oldest + i as u64 {
                return Err(FormatError::invalid(
                    "commit chain",
                    format!(
                        "version {} where {} was expected",
                        h.version,
                        oldest + i as u64
                    ),
                )
                .into());
            }
        }
        Ok(History {
            oldest,
            offsets: commits.into_iter().map(|(at, _)| at).collect(),
        })
    }

    fn offset(&self, version: u64) -> Option<u64> {
        let i = version.checked_sub(self.oldest)?;
        self.offsets.get(usize::try_from(i).ok()?).copied()
    }
}

/// The single writer of a volume, opened on the first edit (opening rebuilds its
/// deduplication table from the index).
#[derive(Debug, Default)]
pub struct WriterSlot {
    writer: Option<Vod2Writer>,
}

/// A volume the server serves and edits.
#[derive(Debug)]
pub struct LiveVolume {
    name: String,
    current: ArcSwap<Vod2>,
    writer: Arc<tokio::sync::Mutex<WriterSlot>>,
    /// Edits waiting for the writer lock.
    waiting: AtomicUsize,
    history: RwLock<History>,
    feed: broadcast::Sender<Arc<FeedItem>>,
}

/// A place in the writer's queue; dropping it leaves the queue.
#[derive(Debug)]
pub struct QueueTicket<'a>(&'a AtomicUsize);

impl Drop for QueueTicket<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// The changed bricks of a commit, by level, each level sorted by z, then y, then x.
pub fn changed_bricks(layout: &VolumeLayout, nodes: impl Iterator<Item = u64>) -> ChangedBricks {
    let mut changed: ChangedBricks = vec![Vec::new(); layout.levels() as usize];
    for node in nodes {
        if let Ok(k) = layout.key_of(node) {
            changed[k.level as usize].push([k.x, k.y, k.z]);
        }
    }
    for level in &mut changed {
        level.sort_by_key(|k| (k[2], k[1], k[0]));
        level.dedup();
    }
    changed
}

impl LiveVolume {
    /// Serves `vod` as `name`.
    ///
    /// # Errors
    /// The commit chain is malformed.
    pub fn new(name: &str, vod: Vod2) -> Result<LiveVolume, StoreError> {
        let history = History::read(&vod)?;
        Ok(LiveVolume {
            name: name.to_string(),
            current: ArcSwap::from_pointee(vod),
            writer: Arc::default(),
            waiting: AtomicUsize::new(0),
            history: RwLock::new(history),
            feed: broadcast::channel(FEED_CAPACITY).0,
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// The file as of the newest commit.
    pub fn current(&self) -> Arc<Vod2> {
        self.current.load_full()
    }

    /// The current file, borrowed for as long as the guard lives (cheaper than [`Self::current`]:
    /// no shared reference count is touched).
    pub fn load(&self) -> arc_swap::Guard<Arc<Vod2>> {
        self.current.load()
    }

    /// The head snapshot.
    pub fn head(&self) -> Arc<Snapshot> {
        self.current.load().head()
    }

    /// Version `version`, while the file holds it.
    ///
    /// # Errors
    /// [`StoreError::Invalid`] when the file no longer (or not yet) holds it.
    pub fn version(&self, version: u64) -> Result<Arc<Snapshot>, StoreError> {
        let vod = self.current();
        let head = vod.head();
        if version == head.version {
            return Ok(head);
        }
        let at = self
            .history_read()
            .offset(version)
            .filter(|_| version < head.version);
        match at {
            Some(at) => Ok(Arc::new(vod.snapshot_at(at)?)),
            None => Err(StoreError::Invalid(format!(
                "version {version} is not in this volume (it holds {}..={})",
                self.oldest(),
                head.version
            ))),
        }
    }

    /// The oldest version the file holds.
    pub fn oldest(&self) -> u64 {
        self.history_read().oldest
    }

    fn history_read(&self) -> std::sync::RwLockReadGuard<'_, History> {
        // A panic while holding the lock cannot leave the history half-written (every update
        // is one push or one assignment), so a poisoned lock is still sound to read.
        self.history.read().unwrap_or_else(|p| p.into_inner())
    }

    /// The versions after `since`, oldest first, at most `limit` of them, read from their
    /// commit records; and whether more follow.
    ///
    /// # Errors
    /// `since` is not in `oldest - 1 ..= head` (the caller checks first), or a record is
    /// malformed.
    pub fn changes(
        &self,
        since: u64,
        limit: usize,
    ) -> Result<(Vec<ChangeEvent>, bool), StoreError> {
        let vod = self.current();
        let head = vod.head().version;
        let last = head.min(since.saturating_add(limit as u64));
        // Only the offsets asked for are copied (the history grows with every commit).
        let offsets: Vec<u64> = {
            let history = self.history_read();
            (since + 1..=last)
                .map(|version| {
                    history.offset(version).ok_or_else(|| {
                        StoreError::Invalid(format!("version {version} is not in this volume"))
                    })
                })
                .collect::<Result<_, _>>()?
        };
        let out = offsets
            .into_iter()
            .map(|at| change_event(&vod, at))
            .collect::<Result<Vec<_>, _>>()?;
        Ok((out, last < head))
    }

    /// Subscribes to the change feed: every version committed from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<FeedItem>> {
        self.feed.subscribe()
    }

    /// Joins the queue for the writer unless `max_waiting` edits already wait.
    pub fn enqueue(&self, max_waiting: usize) -> Option<QueueTicket<'_>> {
        let before = self.waiting.fetch_add(1, Ordering::AcqRel);
        let ticket = QueueTicket(&self.waiting);
        (before < max_waiting).then_some(ticket)
    }

    /// Change-feed subscribers connected now.
    pub fn subscribers(&self) -> usize {
        self.feed.receiver_count()
    }

    /// Edits waiting for the writer now.
    pub fn queue_depth(&self) -> usize {
        self.waiting.load(Ordering::Acquire)
    }

    /// Waits for the writer lock (in queue order).
    pub async fn lock_writer(&self) -> tokio::sync::OwnedMutexGuard<WriterSlot> {
        self.writer.clone().lock_owned().await
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
    ) -> Result<EditResponse, EditError> {
        let vod = self.current();
        let head = vod.head();
        if let Some(expected) = if_match.filter(|&v| v != head.version) {
            return Err(EditError::Conflict {
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
            return Err(StoreError::Invalid(
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
                StoreError::Invalid("a commit left the writer without a head".into()).into(),
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
        let report = compact(&vod, &head, &indicatif::ProgressBar::hidden())?;
        let fresh = Vod2::open(vod.path())?;
        let history = History::read(&fresh)?;
        *self.history.write().unwrap_or_else(|p| p.into_inner()) = history;
        self.current.store(Arc::new(fresh));
        Ok(report)
    }
}

/// The change-feed event of the commit record at `at`.
fn change_event(vod: &Vod2, at: u64) -> Result<ChangeEvent, StoreError> {
    let bytes = vod.mapped();
    let record = bytes
        .get(at as usize..)
        .ok_or_else(|| StoreError::Invalid(format!("commit offset {at} past the mapped length")))?;
    let (h, changes) = CommitHeader::decode(record, at)?;
    Ok(ChangeEvent {
        version: h.version,
        timestamp_ms: h.timestamp_ms,
        changed: changed_bricks(
            vod.layout(),
            CommitHeader::changes(changes).map(|(node, _)| node),
        ),
    })
}
