//! A served volume: its current version, its single writer, its history and its change feed.
//!
//! Readers call [`LiveVolume::current`] and get the open file as of the newest commit (an
//! `Arc` swapped atomically): they never wait for the writer. Edits wait in the volume's queue
//! and are applied by its single writer in arrival order, several at a time ([`group`]): each
//! is evaluated against the version before it, staged as the next version and turned into the
//! next [`Vod2`] by [`Vod2::advance`]; the group is made durable at once; then each version is
//! recorded in the history, published to readers, announced on the change feed and answered,
//! in that order.
//!
//! The change feed is a `tokio::sync::broadcast` channel: sending never waits, and a subscriber
//! that falls more than [`FEED_CAPACITY`] versions behind learns it (`Lagged`) instead of
//! slowing anyone down. What it announces is read back from the commit record, the same
//! source `changes?since=N` reads, so the live feed and the catch-up list cannot disagree.
//!
//! Layout: this file holds the volume's versions, history and feed; [`read`] the reads a
//! server answers (batches, levels, mesh tiles), checked first and run later off the async
//! runtime; [`write`] checking edits against a server's limits, and compaction; [`group`] the
//! edit queue and group commit; [`resolve`] the volumes
//! and meshes edit terms name; [`segments`] the segments of categorical channels, kept per
//! commit; [`error`] what can go wrong.

pub mod error;
pub mod follow;
pub mod group;
pub mod history;
pub mod presence;
pub mod read;
mod remote_group;
pub mod resolve;
pub mod segments;
pub mod undo;
pub mod write;

pub use error::VolumeError;
pub use group::{GroupCommit, PendingEdit};
pub(crate) use history::change_event;
pub use write::{edit_file, EditLimits};

use crate::store::remote::{Refreshed, RemoteVolume};
use crate::store::{Snapshot, StoreError, Vod2, Vod2Writer};
use arc_swap::ArcSwap;
use isovox_proto::api::{ChangeEvent, ChangeList, ChangedBricks};
use isovox_proto::VolumeLayout;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};
use std::time::{Duration, Instant};
use tokio::sync::broadcast;

/// Versions a subscriber may fall behind before it is told to resync.
pub const FEED_CAPACITY: usize = 1024;

/// One committed version on the change feed, with its JSON made once for every subscriber.
#[derive(Debug)]
pub struct FeedItem {
    /// The version.
    pub version: u64,
    /// Its change event as JSON.
    pub json: String,
}

/// Older versions kept loaded (see [`LiveVolume::version`]).
pub const OLDER_VERSIONS_KEPT: usize = 4;

/// Versions listed by one `changes` answer, by default and at most.
pub const DEFAULT_CHANGES: usize = 1000;
/// See [`DEFAULT_CHANGES`].
pub const MAX_CHANGES: usize = 10_000;

/// Commit offsets by version: `offsets[v - oldest]` is version `v`'s commit record.
#[derive(Debug, Clone, Default)]
struct History {
    oldest: u64,
    offsets: Vec<u64>,
    /// Why the versions before `oldest` cannot be listed when a damaged commit record ended
    /// the walk (they are not compacted away: asking for them is a server error, not a 410).
    damaged: Option<String>,
}

impl History {
    /// Walks the commit chain of `vod` once (at start and after compaction), as far as the
    /// records read: damage in an old commit record costs the versions before it, not the
    /// volume.
    fn read(name: &str, vod: &Vod2) -> History {
        let (mut commits, damage) = vod.commits_until_damage();
        commits.reverse();
        let damaged = damage.map(|e| {
            let cause = crate::store::error_chain(&e);
            tracing::error!(volume = name, error = %cause, "a commit record is damaged: the versions before it cannot be listed or read (`isovox check` reports every damaged record)");
            cause
        });
        History {
            oldest: commits.first().map_or(0, |(_, h)| h.version),
            offsets: commits.into_iter().map(|(at, _)| at).collect(),
            damaged,
        }
    }

    /// The error for versions before the oldest one listed, when damage is why.
    fn damage_before(&self, version: u64) -> Option<StoreError> {
        let cause = self.damaged.as_ref().filter(|_| version < self.oldest)?;
        Some(StoreError::corrupt(
            self.offsets.first().copied().unwrap_or(0),
            format!("the commit records before version {}", self.oldest),
            cause.clone(),
        ))
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
    /// Why the volume takes no edits, when it is served read-only (its newest durable version
    /// is damaged and an older, intact one is served).
    read_only: Option<String>,
    current: ArcSwap<Vod2>,
    writer: Arc<tokio::sync::Mutex<WriterSlot>>,
    /// Edits waiting for the writer.
    edits: std::sync::Mutex<group::EditQueue>,
    /// Compactions waiting for the writer lock.
    waiting: AtomicUsize,
    history: RwLock<History>,
    /// What each commit's note says, by version, once read.
    records: Mutex<history::RecordCache>,
    /// Who is looking at the volume now.
    presence: presence::Presences,
    /// The older versions read last, most recent first: loading one walks its commits back to
    /// a checkpoint and decodes index chunks again, and pinned readers (a `?version=N` client,
    /// a version-pinned view) ask for the same few versions request after request.
    older: Mutex<VecDeque<Arc<Snapshot>>>,
    feed: broadcast::Sender<Arc<FeedItem>>,
    /// Where the volume is kept when it is not a local file (an object store).
    remote: Option<Arc<RemoteVolume>>,
    /// The segments of its channels, per channel, kept from the first request on
    /// ([`segments`]).
    segments: segments::SegmentIndexes,
}

/// A place in the writer's queue; dropping it leaves the queue.
#[derive(Debug)]
pub struct QueueTicket<'a>(&'a AtomicUsize);

impl Drop for QueueTicket<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// The stream of `snap` that `channel` names: density when `None`, else its attribute channel
/// of that name.
///
/// # Errors
/// [`VolumeError::OutOfRange`], naming the channels there are, when it has none of that name.
pub fn stream_of(snap: Arc<Snapshot>, channel: Option<&str>) -> Result<Arc<Snapshot>, VolumeError> {
    let Some(name) = channel else {
        return Ok(snap);
    };
    snap.channel(name).ok_or_else(|| {
        VolumeError::OutOfRange(format!(
            "this volume has no channel {name:?} (density and {:?})",
            snap.channel_names()
        ))
    })
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
    /// Serves `vod` as `name`. A damaged commit record on its chain costs the versions before
    /// it (logged), not the volume.
    ///
    /// # Errors
    /// None today; the signature leaves room for checks at opening.
    pub fn new(name: &str, vod: Vod2) -> Result<LiveVolume, StoreError> {
        Self::with_state(name, vod, None)
    }

    /// Serves `vod` as `name`, read-only: every edit and compaction is refused with
    /// [`VolumeError::ReadOnly`] and `cause` (for a file whose newest durable version is
    /// damaged, opened at an older intact one; writing on top of it would bury the damaged
    /// versions under new ones).
    ///
    /// # Errors
    /// See [`LiveVolume::new`].
    pub fn read_only(name: &str, vod: Vod2, cause: String) -> Result<LiveVolume, StoreError> {
        Self::with_state(name, vod, Some(cause))
    }

    fn with_state(
        name: &str,
        vod: Vod2,
        read_only: Option<String>,
    ) -> Result<LiveVolume, StoreError> {
        let history = History::read(name, &vod);
        Ok(LiveVolume {
            name: name.to_string(),
            read_only,
            current: ArcSwap::from_pointee(vod),
            writer: Arc::default(),
            edits: Default::default(),
            waiting: AtomicUsize::new(0),
            history: RwLock::new(history),
            records: Mutex::default(),
            presence: presence::Presences::default(),
            older: Mutex::default(),
            feed: broadcast::channel(FEED_CAPACITY).0,
            remote: None,
            segments: segments::SegmentIndexes::default(),
        })
    }

    /// Serves `vod`, a volume kept in an object store as `remote`, as `name`.
    ///
    /// # Errors
    /// The commit chain is malformed.
    pub fn with_remote(
        name: &str,
        vod: Vod2,
        remote: Arc<RemoteVolume>,
    ) -> Result<LiveVolume, StoreError> {
        let mut volume = LiveVolume::new(name, vod)?;
        volume.remote = Some(remote);
        Ok(volume)
    }

    /// The object-store volume behind it, if it is one.
    pub fn remote(&self) -> Option<&Arc<RemoteVolume>> {
        self.remote.as_ref()
    }

    fn announce(&self, event: &ChangeEvent) {
        let json = serde_json::to_string(event).unwrap_or_default();
        // No subscriber is not an error.
        let _ = self.feed.send(Arc::new(FeedItem {
            version: event.version,
            json,
        }));
    }

    /// Follows the head of an object-store volume (nothing for a local file): when other
    /// writers committed, serves the new head and announces each new version on the change
    /// feed, oldest first. Holds the writer (`_writer`), so that an edit of this process and
    /// what others committed are published in commit order. Blocking.
    ///
    /// # Errors
    /// The store fails or what it holds is malformed (the served head stays as it was).
    pub fn catch_up(&self, _writer: &mut WriterSlot) -> Result<(), StoreError> {
        let Some(remote) = &self.remote else {
            return Ok(());
        };
        let vod = self.current();
        let before = vod.head().version;
        match remote.refresh(&vod)? {
            Refreshed::Same => {}
            Refreshed::Advanced(next) => {
                // The commits between the old head and the new one, newest first.
                let stop = vod.head().commit_offset();
                let mut chain = Vec::new();
                let mut at = next.head().commit_offset();
                while at != stop {
                    let (h, _) = next.commit_at(at)?;
                    chain.push(at);
                    if h.parent == 0 || h.version <= before + 1 {
                        break;
                    }
                    at = h.parent;
                }
                let next = Arc::new(next);
                let mut events = Vec::with_capacity(chain.len());
                {
                    let mut history = self.history.write().unwrap_or_else(|p| p.into_inner());
                    for &at in chain.iter().rev() {
                        let event = change_event(&next, at)?;
                        if history.offsets.is_empty() {
                            history.oldest = event.version;
                        }
                        history.offsets.push(at);
                        events.push(event);
                    }
                }
                self.current.store(next);
                for event in &events {
                    self.announce(event);
                }
            }
            Refreshed::Replaced(next) => {
                let history = History::read(&self.name, &next);
                let news: Vec<u64> = (before + 1..=next.head().version)
                    .filter_map(|v| history.offset(v))
                    .collect();
                let next = Arc::new(next);
                let events = news
                    .into_iter()
                    .map(|at| change_event(&next, at))
                    .collect::<Result<Vec<_>, _>>()?;
                *self.history.write().unwrap_or_else(|p| p.into_inner()) = history;
                self.current.store(next);
                for event in &events {
                    self.announce(event);
                }
            }
        }
        Ok(())
    }

    /// [`LiveVolume::catch_up`] from a thread that may block, taking the writer first. Its
    /// store calls are given up after `limit` ([`StoreError::Stalled`]): edits queue for the
    /// writer it holds, and a poll that waited out a stalled store's own retries (minutes)
    /// would hold them past their edit timeout, unanswered.
    ///
    /// # Errors
    /// See [`LiveVolume::catch_up`].
    pub fn follow_blocking(&self, limit: Duration) -> Result<(), StoreError> {
        let mut writer = self.writer.blocking_lock();
        let _bounded =
            crate::store::remote::bound_store_waits(Some((Instant::now() + limit, limit)));
        self.catch_up(&mut writer)
    }

    /// The name it is served under.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Why the volume is served read-only, if it is.
    pub fn read_only_cause(&self) -> Option<&str> {
        self.read_only.as_deref()
    }

    /// Refuses a write to a read-only volume.
    ///
    /// # Errors
    /// [`VolumeError::ReadOnly`].
    pub fn check_writable(&self) -> Result<(), VolumeError> {
        match &self.read_only {
            Some(cause) => Err(VolumeError::ReadOnly {
                volume: self.name.clone(),
                cause: cause.clone(),
            }),
            None => Ok(()),
        }
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
    /// [`VolumeError::NoSuchVersion`] when the file no longer (or not yet) holds it; a
    /// malformed commit record.
    pub fn version(&self, version: u64) -> Result<Arc<Snapshot>, VolumeError> {
        let vod = self.current();
        let head = vod.head();
        if version == head.version {
            return Ok(head);
        }
        let history = self.history_read();
        if let Some(damage) = history.damage_before(version) {
            return Err(damage.into());
        }
        let at = history.offset(version).filter(|_| version < head.version);
        drop(history);
        let Some(at) = at else {
            return Err(VolumeError::NoSuchVersion {
                version,
                oldest: self.oldest(),
                head: head.version,
            });
        };
        if let Some(kept) = self.kept_version(version) {
            return Ok(kept);
        }
        let snap = Arc::new(vod.snapshot_at(at)?);
        let mut older = self.older_lock();
        older.retain(|s| s.version != version);
        older.push_front(snap.clone());
        older.truncate(OLDER_VERSIONS_KEPT);
        Ok(snap)
    }

    /// Version `version` if it is among the older versions kept (then the most recent of them).
    fn kept_version(&self, version: u64) -> Option<Arc<Snapshot>> {
        let mut older = self.older_lock();
        let i = older.iter().position(|s| s.version == version)?;
        let snap = older.remove(i)?;
        older.push_front(snap.clone());
        Some(snap)
    }

    fn older_lock(&self) -> MutexGuard<'_, VecDeque<Arc<Snapshot>>> {
        // Every update leaves the list whole (a removal, a push, a truncation), so a poisoned
        // lock is still sound to use.
        self.older.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Forgets the older versions kept (compaction replaced the file they read).
    fn forget_older(&self) {
        self.older_lock().clear();
    }

    /// Version `version`, or the head when `None`.
    ///
    /// # Errors
    /// See [`LiveVolume::version`].
    pub fn snapshot(&self, version: Option<u64>) -> Result<Arc<Snapshot>, VolumeError> {
        match version {
            Some(v) => self.version(v),
            None => Ok(self.head()),
        }
    }

    /// [`LiveVolume::snapshot`] of the stream `channel` names: density when `None`, else the
    /// attribute channel of that name (a 404 naming the channels there are when it has none).
    ///
    /// # Errors
    /// As [`LiveVolume::snapshot`]; [`VolumeError::OutOfRange`] for an unknown channel.
    pub fn snapshot_of(
        &self,
        version: Option<u64>,
        channel: Option<&str>,
    ) -> Result<Arc<Snapshot>, VolumeError> {
        let snap = self.snapshot(version)?;
        stream_of(snap, channel)
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
                        StoreError::Absent(format!("version {version} is not in this volume"))
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

    /// Checks that the versions after `since` can be listed.
    ///
    /// # Errors
    /// [`VolumeError::SinceAfterHead`] past the head, [`VolumeError::Compacted`] when
    /// compaction dropped some of them, a storage error when a damaged commit record hides
    /// them.
    pub fn check_since(&self, since: u64) -> Result<(), VolumeError> {
        let head = self.head().version;
        let oldest = self.oldest();
        if since > head {
            return Err(VolumeError::SinceAfterHead { since, head });
        }
        if since.saturating_add(1) < oldest {
            if let Some(damage) = self.history_read().damage_before(since.saturating_add(1)) {
                return Err(damage.into());
            }
            return Err(VolumeError::Compacted { oldest, head });
        }
        Ok(())
    }

    /// The catch-up list: the versions after `since` (everything the file holds when `None`),
    /// at most `limit` of them ([`DEFAULT_CHANGES`] when `None`). Blocking: it reads commit
    /// records.
    ///
    /// # Errors
    /// A limit outside `1..=MAX_CHANGES`, a `since` that cannot be listed (see
    /// [`LiveVolume::check_since`]), or a malformed commit record.
    pub fn change_list(
        &self,
        since: Option<u64>,
        limit: Option<usize>,
    ) -> Result<ChangeList, VolumeError> {
        let since = since.unwrap_or_else(|| self.oldest().saturating_sub(1));
        let limit = limit.unwrap_or(DEFAULT_CHANGES);
        if !(1..=MAX_CHANGES).contains(&limit) {
            return Err(VolumeError::BadRequest(format!(
                "limit must be in 1..={MAX_CHANGES}"
            )));
        }
        self.check_since(since)?;
        let (changes, more) = self.changes(since, limit)?;
        // Read after the listing: the head is at least the last version listed.
        let head = self.head().version;
        Ok(ChangeList {
            since,
            head: changes.last().map_or(head, |c| c.version.max(head)),
            oldest: self.oldest(),
            more,
            changes,
        })
    }

    /// Serves the file as it is on disk now: its head and history read afresh (after a
    /// compaction replaced it, or when the served head fell behind the file).
    ///
    /// # Errors
    /// The file does not open, or its commit chain is malformed (the served state is then
    /// unchanged).
    pub fn reload(&self) -> Result<Arc<Vod2>, StoreError> {
        let fresh = Arc::new(Vod2::open(self.current.load().path())?);
        let history = History::read(&self.name, &fresh);
        *self.history.write().unwrap_or_else(|p| p.into_inner()) = history;
        self.current.store(fresh.clone());
        // The file may be a new one (compaction): the older versions kept map the old one.
        // After a compaction none can be asked for again (the history says so first);
        // forgetting them unmaps the old file sooner.
        self.forget_older();
        Ok(fresh)
    }

    /// Subscribes to the change feed: every version committed from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<FeedItem>> {
        self.feed.subscribe()
    }

    /// Joins the queue for the writer lock (a compaction) unless `max_waiting` edits and
    /// compactions already wait.
    pub fn enqueue(&self, max_waiting: usize) -> Option<QueueTicket<'_>> {
        let before = self.waiting.fetch_add(1, Ordering::AcqRel);
        let ticket = QueueTicket(&self.waiting);
        (before + self.queue().len() < max_waiting).then_some(ticket)
    }

    pub(super) fn compactions_waiting(&self) -> usize {
        self.waiting.load(Ordering::Acquire)
    }

    /// Change-feed subscribers connected now.
    pub fn subscribers(&self) -> usize {
        self.feed.receiver_count()
    }

    /// Edits (and compactions) waiting for the writer now.
    pub fn queue_depth(&self) -> usize {
        self.queue().len() + self.compactions_waiting()
    }

    /// Waits for the writer lock (in queue order).
    pub async fn lock_writer(&self) -> tokio::sync::OwnedMutexGuard<WriterSlot> {
        self.writer.clone().lock_owned().await
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::store::{build_vod2, BuildOptions, DenseGrid};
    use isovox_proto::icvg::{EditRequest, Term};
    use isovox_proto::{BrickKey, VoxelType};

    /// A 16^3 volume of 9s, then one edit per version (a small ball added at a new place), so
    /// every version has content of its own.
    fn volume_with_versions(path: &std::path::Path, versions: u64) -> LiveVolume {
        let layout = VolumeLayout::new([16; 3], 16, VoxelType::U8).unwrap();
        let voxels = vec![9u8; 16 * 16 * 16];
        let grid = DenseGrid::new([16; 3], VoxelType::U8, 16, &voxels);
        build_vod2(path, &layout, [1.0; 3], &grid, &BuildOptions::default()).unwrap();
        for v in 1..versions as i64 {
            let request = EditRequest {
                op: "union".into(),
                term: Some(Term::Ellipsoid {
                    center: [v * 2, 8, 8],
                    radii: [1, 1, 1],
                }),
                s_l: None,
                k: None,
                region: None,
                message: None,
                channel: None,
                overwrite: None,
            };
            write::edit_file(path, &request).unwrap();
        }
        LiveVolume::new("v", Vod2::open(path).unwrap()).unwrap()
    }

    const BRICK: BrickKey = BrickKey {
        level: 0,
        x: 0,
        y: 0,
        z: 0,
    };

    #[test]
    fn older_versions_are_kept_a_few_at_a_time_and_forgotten_on_compaction() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.vod");
        let volume = volume_with_versions(&path, 8);
        assert_eq!(volume.head().version, 8);
        // What each version holds, loaded independently (a fresh open of the file).
        let fresh = Vod2::open(&path).unwrap();
        let hashes: Vec<u64> = (1..=8)
            .map(|v| fresh.version(v).unwrap().hash(BRICK).unwrap())
            .collect();
        let mut distinct = hashes.clone();
        distinct.sort_unstable();
        distinct.dedup();
        assert_eq!(distinct.len(), 8, "every version has content of its own");

        let first = volume.version(2).unwrap();
        // Asked again: the same snapshot, not one loaded anew.
        assert!(Arc::ptr_eq(&first, &volume.version(2).unwrap()));
        // Every version reads its own content, kept or not, in any order.
        for v in [1, 7, 3, 2, 6, 5, 4, 8, 1, 7] {
            let snap = volume.version(v).unwrap();
            assert_eq!(snap.version, v);
            assert_eq!(
                snap.hash(BRICK).unwrap(),
                hashes[v as usize - 1],
                "version {v}"
            );
        }
        // Other versions were read since 2, more than are kept: it was let go.
        const { assert!(OLDER_VERSIONS_KEPT < 6) };
        assert!(!Arc::ptr_eq(&first, &volume.version(2).unwrap()));
        // The one read last is kept.
        let recent = volume.version(7).unwrap();
        assert!(Arc::ptr_eq(&recent, &volume.version(7).unwrap()));
        // After compaction no older version is served, kept or not.
        volume.compact(&mut WriterSlot::default()).unwrap();
        assert!(volume.older_lock().is_empty());
        for v in [2, 7] {
            assert!(matches!(
                volume.version(v),
                Err(VolumeError::NoSuchVersion { oldest: 8, .. })
            ));
        }
        assert_eq!(volume.version(8).unwrap().hash(BRICK).unwrap(), hashes[7]);
    }
}
