//! A transaction: the one way a version is written. Bricks are staged (stored through the
//! writer's deduplication, their index entries kept aside), the levels above changed level-0
//! bricks are recomputed, and the commit makes it all durable as the next version.
//!
//! Edits stage level-0 bricks on top of the head ([`Transaction::on`]); a build and a compaction
//! fill every entry of a new file ([`Transaction::first`]), whose first commit is a checkpoint.

use super::pyramid::{
    coarser, constant_parent, downsample, downsample_changed, BrickVoxels, Downsampling,
};
use super::writer::{CheckpointChunk, PreparedBrick, Vod2Writer};
use super::{Snapshot, StoreError, StoredBrick};
use isovox_proto::geometry::Box3;
use isovox_proto::vod2::{HeaderSlot, NodeEntry};
use isovox_proto::BrickKey;
use rayon::prelude::*;
use std::collections::{BTreeMap, HashMap};

/// When to write a full index checkpoint instead of a delta: a reader replays the deltas since
/// the last checkpoint when it opens the file, so their number is bounded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CheckpointPolicy {
    /// Entries changed since the last checkpoint.
    pub max_overlay: usize,
    /// Commits since the last checkpoint.
    pub max_chain: usize,
}

impl Default for CheckpointPolicy {
    fn default() -> Self {
        CheckpointPolicy {
            max_overlay: 1 << 15,
            max_chain: 256,
        }
    }
}

/// Fewest bricks a parallel job of an edit's staging takes (evaluating, compressing,
/// downsampling: tens of microseconds a brick). Handing a job to another rayon thread wakes it,
/// and it spins a while before sleeping again: for a smaller job that costs more than it
/// returns. A small carve (about 8 level-0 bricks, fewer on each level above) so never leaves
/// the writer's thread; `isovox-bench edits` makes as many edits/s as with a one-thread rayon
/// pool, and more than with every loop split.
pub const BRICKS_PER_JOB: usize = 8;

/// Changed bricks per level (level 0 first), as `[x, y, z]`.
pub type ChangedKeys = Vec<Vec<[u32; 3]>>;

/// What a commit wrote (or staged).
#[derive(Debug, Clone)]
pub struct Committed {
    /// The header slot naming the new version (once it is durable).
    pub slot: HeaderSlot,
    /// The bricks whose entries changed, per level (empty for the first commit of a file).
    pub changed: ChangedKeys,
    /// Brick records appended (new unique content).
    pub new_records: u64,
    /// Whether the commit wrote a full index checkpoint.
    pub checkpoint: bool,
    /// The bricks of attribute channels whose entries changed, per stream (1 the first
    /// channel), per level; streams without a change are absent.
    pub channels_changed: BTreeMap<usize, ChangedKeys>,
}

/// What a transaction builds on.
#[derive(Debug)]
enum Base<'a> {
    /// A version of the file: entries not staged stay as they are there.
    Version {
        snap: &'a Snapshot,
        changes: Vec<(u64, NodeEntry)>,
        changed: ChangedKeys,
        /// Changed bricks of attribute channels, by stream.
        channels_changed: BTreeMap<usize, ChangedKeys>,
    },
    /// Nothing (a new file): every entry is staged.
    Empty { entries: Vec<u64> },
}

/// Staged changes to one file, committed at once.
#[derive(Debug)]
pub struct Transaction<'a> {
    writer: &'a mut Vod2Writer,
    base: Base<'a>,
    records_before: u64,
    /// The commit's note (JSON), empty for none.
    note: Vec<u8>,
}

fn records(writer: &Vod2Writer) -> u64 {
    writer.stats().stored.iter().sum()
}

impl<'a> Transaction<'a> {
    /// A transaction on top of `snap`, which must be the writer's newest version (its head, or
    /// the version it staged last).
    pub fn on(writer: &'a mut Vod2Writer, snap: &'a Snapshot) -> Self {
        Transaction {
            records_before: records(writer),
            base: Base::Version {
                snap,
                changes: Vec::new(),
                changed: vec![Vec::new(); snap.layout().levels() as usize],
                channels_changed: BTreeMap::new(),
            },
            writer,
            note: Vec::new(),
        }
    }

    /// The first transaction of a new file: stage every entry before committing.
    pub fn first(writer: &'a mut Vod2Writer) -> Self {
        let nodes = writer.header().node_count() as usize;
        Transaction {
            records_before: records(writer),
            base: Base::Empty {
                entries: vec![0; nodes],
            },
            writer,
            note: Vec::new(),
        }
    }

    /// Records `note` (who made the commit and what it did, as JSON) in the commit record.
    pub fn set_note(&mut self, note: Vec<u8>) {
        self.note = note;
    }

    /// The writer, for preparing bricks in parallel ([`Vod2Writer::prepare`]) before they are
    /// [`put`](Transaction::put) in order.
    pub fn writer(&self) -> &Vod2Writer {
        self.writer
    }

    /// Sets the index entry of `node`; returns whether it differs from the base's.
    ///
    /// # Errors
    /// The base's entry cannot be read.
    pub fn set(&mut self, node: u64, entry: NodeEntry) -> Result<bool, StoreError> {
        match &self.base {
            Base::Version { snap, .. } => {
                let snap: &Snapshot = snap;
                self.set_in(snap, node, entry)
            }
            Base::Empty { .. } => self.set_raw(node, entry),
        }
    }

    /// Sets the entry of node `node` of the stream `view` is a version of (the base version's
    /// density, or one of its channels: [`Snapshot::channel`]); returns whether it differs
    /// from `view`'s.
    ///
    /// # Errors
    /// The view's entry cannot be read, or `node` is outside its pyramid.
    pub fn set_in(
        &mut self,
        view: &Snapshot,
        node: u64,
        entry: NodeEntry,
    ) -> Result<bool, StoreError> {
        let Base::Version {
            changes,
            changed,
            channels_changed,
            ..
        } = &mut self.base
        else {
            return self.set_raw(node, entry);
        };
        if entry == view.entry_at(node)? {
            return Ok(false);
        }
        let layout = view.layout();
        let key = layout.key_of(node)?;
        // The commit stores the brick's summary beside the entry: a record this writer did not
        // store (an undo's, an older version's) is summarized from the version that has it.
        if let NodeEntry::Stored(offset) = entry {
            if !self.writer.knows_summary(offset) {
                let summary = view.entry_summary(entry)?;
                self.writer.learn_summary(offset, summary);
            }
        }
        changes.push((view.stream() as u64 * layout.node_count() + node, entry));
        let keys = match view.stream() {
            0 => changed,
            s => channels_changed
                .entry(s)
                .or_insert_with(|| vec![Vec::new(); layout.levels() as usize]),
        };
        keys[key.level as usize].push([key.x, key.y, key.z]);
        Ok(true)
    }

    /// Sets a file-wide entry of a new file.
    fn set_raw(&mut self, node: u64, entry: NodeEntry) -> Result<bool, StoreError> {
        match &mut self.base {
            Base::Version { .. } => Err(StoreError::Internal(
                "a version's entries are set through its streams".into(),
            )),
            Base::Empty { entries } => {
                let slot = entries.get_mut(node as usize).ok_or_else(|| {
                    StoreError::Internal(format!("node {node} is outside the volume"))
                })?;
                *slot = entry.encode();
                Ok(true)
            }
        }
    }

    /// Stores a prepared brick (deduplicated) as the content of `node`; returns whether the
    /// entry changed.
    ///
    /// # Errors
    /// Storing fails, or the base's entry cannot be read.
    pub fn put(
        &mut self,
        node: u64,
        voxels: &BrickVoxels,
        prepared: PreparedBrick,
    ) -> Result<bool, StoreError> {
        let entry = self.writer.store(voxels, prepared)?;
        self.set(node, entry)
    }

    /// [`Transaction::put`] of a brick of values of `voxel_type` at the file-wide `node` of a
    /// new file (a build's attribute channel).
    ///
    /// # Errors
    /// Storing fails, or this transaction has a base version ([`Transaction::update_stream`]
    /// is how a version changes a channel).
    pub fn put_as(
        &mut self,
        node: u64,
        voxels: &BrickVoxels,
        prepared: PreparedBrick,
        voxel_type: isovox_proto::VoxelType,
    ) -> Result<bool, StoreError> {
        if !matches!(self.base, Base::Empty { .. }) {
            return Err(StoreError::Internal(
                "put_as fills a new file; a version's channels change by update_stream".into(),
            ));
        }
        let entry = self.writer.store_as(voxels, prepared, voxel_type)?;
        self.set(node, entry)
    }

    /// Copies a brick record of another file with its payload as it is (verified first, see
    /// [`Vod2Writer::copy_record`]) and returns its new entry (not yet set on any node: records
    /// shared by several nodes are copied once).
    ///
    /// # Errors
    /// The payload is damaged, or appending fails.
    pub fn copy_record(&mut self, stored: &StoredBrick<'_>) -> Result<NodeEntry, StoreError> {
        self.writer.copy_record(stored)
    }

    /// Stages new contents of level-0 bricks and recomputes every coarser brick above those
    /// whose entry changed: a parent is its base content with the octants under changed
    /// children downsampled again (a parent is the downsampling of its children, octant by
    /// octant, in every version this writer or a build wrote).
    ///
    /// `within` bounds the level-0 voxels that changed (an edit's reach; the whole volume when
    /// unknown): only the parents' voxels above it are downsampled again, so a small edit
    /// recomputes a few voxels of each level rather than whole octants.
    ///
    /// # Errors
    /// A brick of the base fails to read, storing fails, or this is the first transaction of a
    /// file (there is no base to read siblings from).
    pub fn update_level0(
        &mut self,
        level: Vec<(BrickKey, BrickVoxels)>,
        within: &Box3,
    ) -> Result<(), StoreError> {
        let Base::Version { snap, .. } = self.base else {
            return Err(StoreError::Internal(
                "level-of-detail upkeep needs a base version".into(),
            ));
        };
        self.update_stream(snap, level, within, Downsampling::Mean)
    }

    /// [`Transaction::update_level0`] of an attribute channel: `view` is the base version's
    /// channel ([`Snapshot::channel`]), its levels made by `how`.
    ///
    /// # Errors
    /// As [`Transaction::update_level0`].
    pub fn update_channel_level0(
        &mut self,
        view: &Snapshot,
        level: Vec<(BrickKey, BrickVoxels)>,
        within: &Box3,
    ) -> Result<(), StoreError> {
        let stream = view.stream();
        let info = stream
            .checked_sub(1)
            .and_then(|i| view.header().channels.get(i))
            .ok_or_else(|| StoreError::Internal(format!("stream {stream} is no channel")))?;
        self.update_stream(view, level, within, Downsampling::of_channel(info))
    }

    fn update_stream(
        &mut self,
        snap: &Snapshot,
        mut level: Vec<(BrickKey, BrickVoxels)>,
        within: &Box3,
        how: Downsampling,
    ) -> Result<(), StoreError> {
        if !matches!(self.base, Base::Version { .. }) {
            return Err(StoreError::Internal(
                "level-of-detail upkeep needs a base version".into(),
            ));
        }
        let layout = snap.layout();
        let t = layout.voxel_type();
        // The voxels of the current level that can have changed, in that level's coordinates.
        let mut changed_within = *within;
        for lvl in 0..layout.levels() {
            if level.is_empty() {
                break;
            }
            // Store this level's bricks; keep only those whose entry really changed.
            let writer = &*self.writer;
            let prepared: Vec<_> = level
                .par_iter()
                .with_min_len(BRICKS_PER_JOB)
                .map(|(_, v)| writer.prepare_as(v, t))
                .collect();
            let mut kept: HashMap<BrickKey, BrickVoxels> = HashMap::new();
            for ((key, voxels), p) in level.into_iter().zip(prepared) {
                let entry = self.writer.store_as(&voxels, p, t)?;
                if self.set_in(snap, layout.node_index(key), entry)? {
                    kept.insert(key, voxels);
                }
            }
            if lvl + 1 == layout.levels() {
                break;
            }
            let mut parents: Vec<BrickKey> =
                kept.keys().filter_map(|&k| layout.parent(k)).collect();
            parents.sort();
            parents.dedup();
            changed_within = coarser(&changed_within);
            level = parents
                .par_iter()
                .with_min_len(BRICKS_PER_JOB)
                .map(|&parent| -> Result<(BrickKey, BrickVoxels), StoreError> {
                    let kids = layout.children(parent);
                    let mut changed: [Option<&BrickVoxels>; 8] = [None; 8];
                    for (octant, child) in &kids {
                        changed[*octant] = kept.get(child);
                    }
                    let voxels = if kids.iter().all(|(_, child)| kept.contains_key(child)) {
                        // Every child is new (octants without a child are outside: L).
                        match constant_parent(&changed) {
                            Some(v) => BrickVoxels::Constant(v),
                            None => {
                                let mut out = vec![0u8; layout.brick_bytes()];
                                downsample(&changed, layout.brick(), t, how, &mut out);
                                BrickVoxels::from_bytes(out, t)
                            }
                        }
                    } else {
                        // The other octants are those of the parent as it was: one brick read
                        // instead of each unchanged child.
                        let mut out = snap.voxels(parent)?.into_bytes(layout.brick_voxels(), t);
                        let parent_box = Box3::of_brick(layout, parent);
                        let changed_here = changed_within.intersect(&parent_box);
                        let local = Box3::new(
                            [0, 1, 2].map(|a| changed_here.min[a] - parent_box.min[a]),
                            [0, 1, 2].map(|a| changed_here.max[a] - parent_box.min[a]),
                        );
                        downsample_changed(&changed, layout.brick(), t, how, &local, &mut out);
                        BrickVoxels::from_bytes(out, t)
                    };
                    Ok((parent, voxels))
                })
                .collect::<Result<_, _>>()?;
        }
        Ok(())
    }

    /// Makes everything staged durable as the next version: a delta on the base, or a full
    /// index checkpoint when `policy` says the chain of deltas is long enough (always for the
    /// first commit of a file).
    ///
    /// # Errors
    /// Reading the base's index or writing the commit fails (the head is then unchanged).
    pub fn commit(self, policy: CheckpointPolicy) -> Result<Committed, StoreError> {
        self.finish(policy, true)
    }

    /// Appends the next version as [`Transaction::commit`] does, without making it durable:
    /// the writer's next [`Vod2Writer::sync`] does, for every version staged until then (group
    /// commit). The base must be the writer's newest staged version, or its head.
    ///
    /// # Errors
    /// Reading the base's index or appending fails: roll the writer back to a savepoint taken
    /// before the transaction began, or drop it.
    pub fn stage(self, policy: CheckpointPolicy) -> Result<Committed, StoreError> {
        self.finish(policy, false)
    }

    fn finish(self, policy: CheckpointPolicy, durable: bool) -> Result<Committed, StoreError> {
        let (slot, changed, checkpoint, channels_changed) = match self.base {
            Base::Version {
                snap,
                changes,
                changed,
                channels_changed,
            } => {
                let checkpoint = snap.overlay_len() + changes.len() > policy.max_overlay
                    || snap.chain_len() + 1 > policy.max_chain;
                let full = if checkpoint {
                    let writer = &*self.writer;
                    Some(snap.next_checkpoint(
                        &changes,
                        writer.writes_summaries(),
                        true,
                        |node, entry| writer.summary_for(node, entry),
                    )?)
                } else {
                    None
                };
                let slot = self.writer.stage(&changes, full, &self.note)?;
                (slot, changed, checkpoint, channels_changed)
            }
            Base::Empty { entries } => {
                let summaries = self.writer.summaries_of(&entries)?;
                let chunks = CheckpointChunk::all_fresh(&entries, &summaries);
                let slot = self.writer.stage(&[], Some(chunks), &self.note)?;
                (slot, ChangedKeys::new(), true, BTreeMap::new())
            }
        };
        let slot = if durable { self.writer.sync()? } else { slot };
        Ok(Committed {
            slot,
            changed,
            new_records: records(self.writer) - self.records_before,
            checkpoint,
            channels_changed,
        })
    }
}
