//! One version's index: a [`Snapshot`], its entry lookups, and the content hashes of its bricks
//! and its ancestors' (found by hash).

use super::checkpoint::{IndexChunks, Overlaid};
use super::StoredBrick;
use crate::store::codec;
use crate::store::region::MappedRegion;
use crate::store::StoreError;
use isovox_proto::vod2::{
    BrickSummary, CommitHeader, FileHeader, NodeEntry, COMMIT_HAS_NOTE, COMMIT_HAS_SUMMARIES,
    COMMIT_WIDE_SUMMARIES, MAX_NOTE_LEN, NOTE_FRAMING_LEN,
};
use isovox_proto::{BrickKey, FormatError, VolumeLayout};
use std::collections::HashMap;
use std::sync::{Arc, OnceLock};

/// One version of a volume: an immutable index over the shared mapping.
#[derive(Debug)]
pub struct Snapshot {
    pub(super) header: Arc<FileHeader>,
    pub(super) map: Arc<MappedRegion>,
    /// The version.
    pub version: u64,
    /// When it was committed (Unix milliseconds).
    pub timestamp_ms: u64,
    pub(super) commit_offset: u64,
    pub(super) index: Arc<IndexChunks>,
    /// Entries changed by the commits after the checkpoint: node index (of the file's whole
    /// index, every stream) -> raw entry and its summary.
    pub(super) overlay: Arc<HashMap<u64, Overlaid>>,
    /// Which stream of the file this is a view of: 0 density, `i + 1` attribute channel `i`
    /// (its `header`'s layout then has the channel's value type).
    pub(super) stream: usize,
    /// The views of the attribute channels of this version, made on first use (density's only).
    pub(super) channel_views: OnceLock<Vec<Arc<Snapshot>>>,
    /// Content hash -> entry, built on first use by [`Snapshot::find_by_hash`] (or carried over
    /// from the parent version and extended).
    pub(super) by_hash: OnceLock<HashIndex>,
    /// Commits replayed on top of the checkpoint.
    pub(super) chain_len: usize,
}

impl Snapshot {
    /// Gives `child` this version's blob index (when it was built) plus the entries its commit
    /// `added`: bricks replaced by the commit stay findable by hash.
    pub(super) fn hand_down_hashes(
        &self,
        child: &Snapshot,
        added: impl Iterator<Item = (u64, Overlaid)>,
    ) -> Result<(), StoreError> {
        let Some(parent_hashes) = self.by_hash.get() else {
            return Ok(());
        };
        let mut hashes = parent_hashes.child();
        let (voxel_type, mapped) = (self.layout().voxel_type(), child.map.len());
        let mine = self.nodes_of_stream();
        for (_, o) in added.filter(|(node, _)| mine.contains(node)) {
            let entry = NodeEntry::decode(o.raw, voxel_type, mapped)?;
            hashes.insert(child.summarized_hash(entry, o.summary)?, entry);
        }
        let _ = child.by_hash.set(hashes);
        Ok(())
    }

    /// Dimensions, brick edge and voxel type (of this stream's values: an attribute channel's
    /// view has the channel's type).
    pub fn layout(&self) -> &VolumeLayout {
        &self.header.layout
    }

    /// Which stream this is a view of: 0 density, `i + 1` the file's attribute channel `i`.
    pub fn stream(&self) -> usize {
        self.stream
    }

    /// The nodes of the file's whole index that hold this stream's pyramid.
    pub(super) fn nodes_of_stream(&self) -> std::ops::Range<u64> {
        let n = self.layout().node_count();
        let base = self.stream as u64 * n;
        base..base + n
    }

    /// The same version of the attribute channel named `name`, as a snapshot of its own: its
    /// layout has the channel's value type, and every read (entries, bricks, hashes) is of the
    /// channel's pyramid. `None` when the file has no such channel.
    pub fn channel(&self, name: &str) -> Option<Arc<Snapshot>> {
        let stream = self.header.stream_named(name)?;
        self.channel_views().get(stream - 1).cloned()
    }

    /// The view of the attribute channel named `name`, borrowed (see [`Snapshot::channel`]).
    pub fn channel_view(&self, name: &str) -> Option<&Arc<Snapshot>> {
        let stream = self.header.stream_named(name)?;
        self.channel_views().get(stream - 1)
    }

    /// The names of the file's attribute channels, in stream order (for messages).
    pub fn channel_names(&self) -> Vec<&str> {
        self.header
            .channels
            .iter()
            .map(|c| c.name.as_str())
            .collect()
    }

    /// This version of every stream of the file: itself (density), then each channel's view.
    pub fn streams(&self) -> impl Iterator<Item = &Snapshot> {
        std::iter::once(self).chain(self.channel_views().iter().map(|v| &**v))
    }

    /// The views of every attribute channel of this version, in stream order.
    pub fn channel_views(&self) -> &[Arc<Snapshot>] {
        self.channel_views.get_or_init(|| {
            (1..=self.header.channels.len())
                .filter_map(|stream| {
                    let layout = self.header.stream_layout(stream)?;
                    Some(Arc::new(Snapshot {
                        header: Arc::new(FileHeader {
                            layout,
                            ..(*self.header).clone()
                        }),
                        map: self.map.clone(),
                        version: self.version,
                        timestamp_ms: self.timestamp_ms,
                        commit_offset: self.commit_offset,
                        index: self.index.clone(),
                        overlay: self.overlay.clone(),
                        stream,
                        channel_views: OnceLock::new(),
                        by_hash: OnceLock::new(),
                        chain_len: self.chain_len,
                    }))
                })
                .collect()
        })
    }

    /// The file's fixed header.
    pub fn header(&self) -> &FileHeader {
        &self.header
    }

    /// Offset of this version's commit record.
    pub fn commit_offset(&self) -> u64 {
        self.commit_offset
    }

    /// The index entry at a node index.
    ///
    /// # Errors
    /// The node is out of range, its checkpoint chunk fails its hash, or the entry is invalid.
    pub fn entry_at(&self, node: u64) -> Result<NodeEntry, StoreError> {
        let layout = self.layout();
        if node >= layout.node_count() {
            return Err(FormatError::invalid(
                "node index",
                format!("{node} >= {}", layout.node_count()),
            )
            .into());
        }
        let node = self.stream as u64 * layout.node_count() + node;
        let raw = match self.overlay.get(&node) {
            Some(o) => o.raw,
            None => self.index.entry(&self.map, node)?,
        };
        Ok(NodeEntry::decode(raw, layout.voxel_type(), self.map.len())?)
    }

    /// What a client choosing bricks needs of the brick at a node of this stream: its content
    /// hash and value range. From the index (revision 5: the checkpoint chunk's summaries or
    /// the overlay's), so no brick record is read; a constant's follow from its value; only an
    /// entry written before revision 5 costs a read of its record's header.
    ///
    /// # Errors
    /// See [`Snapshot::entry_at`]; also a summary block that fails its hash or range check, or
    /// (without a summary) a brick header that fails its checks.
    pub fn summary_at(&self, node: u64) -> Result<BrickSummary, StoreError> {
        let entry = self.entry_at(node)?;
        let global = self.stream as u64 * self.layout().node_count() + node;
        match entry {
            NodeEntry::Constant(v) => Ok(self.constant_summary(v)),
            NodeEntry::Stored(_) => match self.indexed_summary(global)? {
                Some(s) => Ok(s),
                None => self.entry_summary(entry),
            },
        }
    }

    /// [`Snapshot::summary_at`] of a brick.
    ///
    /// # Errors
    /// See [`Snapshot::summary_at`]; the key must come from this volume's layout.
    pub fn summary(&self, key: BrickKey) -> Result<BrickSummary, StoreError> {
        self.summary_at(self.node_of(key)?)
    }

    /// The index node of a brick of this volume.
    fn node_of(&self, key: BrickKey) -> Result<u64, StoreError> {
        let layout = self.layout();
        if !layout.contains(key) {
            return Err(StoreError::OutOfRange(format!(
                "brick {key} is outside the volume"
            )));
        }
        Ok(layout.node_index(key))
    }

    /// The summary of the brick behind an entry read from its record's header (a constant's
    /// from its value): for entries the index gives no summary of.
    ///
    /// # Errors
    /// See [`Snapshot::stored_entry`].
    pub fn entry_summary(&self, entry: NodeEntry) -> Result<BrickSummary, StoreError> {
        Ok(match self.stored_entry(entry)? {
            StoredBrick::Record { header, .. } => BrickSummary::of_header(&header),
            StoredBrick::Constant(v) => self.constant_summary(v),
        })
    }

    fn constant_summary(&self, v: u64) -> BrickSummary {
        BrickSummary {
            hash: codec::constant_hash(v, self.layout()),
            min: v,
            max: v,
        }
    }

    /// The content hash of `entry`, from `summary` when the index gave one (a stored entry's),
    /// else from its record's header.
    fn summarized_hash(
        &self,
        entry: NodeEntry,
        summary: Option<BrickSummary>,
    ) -> Result<u64, StoreError> {
        match (entry, summary) {
            (NodeEntry::Stored(_), Some(s)) => Ok(s.hash),
            _ => self.entry_hash(entry),
        }
    }

    /// The index entry of a brick.
    ///
    /// # Errors
    /// See [`Snapshot::entry_at`]; the key must come from this volume's layout.
    pub fn entry(&self, key: BrickKey) -> Result<NodeEntry, StoreError> {
        self.entry_at(self.node_of(key)?)
    }

    /// An entry with content hash `hash` among the bricks of this version and of every older
    /// version the file still holds, if any. The first call scans the oldest version's index
    /// and the commit records since (their summaries; brick headers only for entries written
    /// before revision 5, never payloads) and keeps a hash table; a version built from its
    /// parent by [`Vod2::advance`] inherits the parent's.
    ///
    /// [`Vod2::advance`]: super::Vod2::advance
    ///
    /// Why older versions too: a client that learned a hash from a grid at `?version=N` (a
    /// streamer catching up one version at a time) asks for it by hash, and the answer must not
    /// depend on whether this process saw the commits after N or opened the file after them.
    ///
    /// # Errors
    /// A commit record, an entry or a brick header on the way is malformed.
    pub fn find_by_hash(&self, hash: u64) -> Result<Option<NodeEntry>, StoreError> {
        if let Some(index) = self.by_hash.get() {
            return Ok(index.get(hash));
        }
        let index = HashIndex {
            base: Arc::new(self.history_hashes()?),
            added: HashMap::new(),
        };
        let found = index.get(hash);
        let _ = self.by_hash.set(index);
        Ok(found)
    }

    /// Content hash -> entry over every brick of this version and its ancestors in the file:
    /// the oldest version's index plus every entry a commit since then wrote (each version is
    /// the oldest one with those changes applied).
    fn history_hashes(&self) -> Result<HashMap<u64, NodeEntry>, StoreError> {
        let mut records = Vec::new();
        let mut at = self.commit_offset;
        let oldest = loop {
            let (h, record) = commit_record(&self.map, at)?;
            records.push((record, commit_summaries(&self.map, at, &h)));
            if h.parent == 0 {
                break at;
            }
            at = h.parent;
        };
        let oldest = Snapshot::load(self.header.clone(), self.map.clone(), oldest)?;
        let oldest = Snapshot {
            stream: self.stream,
            ..oldest
        };
        let mut map = HashMap::new();
        let mut constants = std::collections::HashSet::new();
        let mut add = |entry: NodeEntry, summary: Option<BrickSummary>| -> Result<(), StoreError> {
            let first_sight = match entry {
                NodeEntry::Constant(v) => constants.insert(v),
                NodeEntry::Stored(_) => true,
            };
            if first_sight {
                map.entry(self.summarized_hash(entry, summary)?)
                    .or_insert(entry);
            }
            Ok(())
        };
        for node in 0..self.layout().node_count() {
            let entry = oldest.entry_at(node)?;
            let summary = match entry {
                NodeEntry::Constant(_) => None,
                NodeEntry::Stored(_) => Some(oldest.summary_at(node)?),
            };
            add(entry, summary)?;
        }
        let (voxel_type, mapped) = (self.layout().voxel_type(), self.map.len());
        let mine = self.nodes_of_stream();
        for (record, summaries) in records.iter().rev() {
            for (i, (node, raw)) in CommitHeader::changes(record).enumerate() {
                if !mine.contains(&node) {
                    continue;
                }
                let entry = NodeEntry::decode(raw, voxel_type, mapped)?;
                let summary = match (entry, summaries.as_ref().and_then(|s| s.get(i))) {
                    (NodeEntry::Stored(offset), Some(s)) => {
                        Some(s.validate(voxel_type, "commit summaries", offset)?)
                    }
                    _ => None,
                };
                add(entry, summary)?;
            }
        }
        Ok(map)
    }

    /// The content hash of the brick behind an entry (for a constant, of its expanded bytes).
    ///
    /// # Errors
    /// See [`Snapshot::stored_entry`].
    pub fn entry_hash(&self, entry: NodeEntry) -> Result<u64, StoreError> {
        Ok(match self.stored_entry(entry)? {
            StoredBrick::Record { header, .. } => header.hash,
            StoredBrick::Constant(v) => codec::constant_hash(v, self.layout()),
        })
    }

    /// The content hash of a brick (for a constant, the hash of its expanded bytes).
    ///
    /// # Errors
    /// See [`Snapshot::stored`].
    pub fn hash(&self, key: BrickKey) -> Result<u64, StoreError> {
        self.entry_hash(self.entry(key)?)
    }
}

/// The commit record at `at` (its fixed part fetched first for the change count, then the
/// whole record), decoded and checked.
///
/// # Errors
/// `at` lies past the committed region, the record cannot be fetched, or it is malformed.
pub(super) fn commit_record(
    map: &MappedRegion,
    at: u64,
) -> Result<(CommitHeader, &[u8]), StoreError> {
    let bytes = map.bytes();
    let avail = bytes.get(at as usize..).ok_or_else(|| {
        StoreError::from(FormatError::invalid(
            "commit chain",
            format!("offset {at} past the committed length {}", bytes.len()),
        ))
    })?;
    map.ensure(at, CommitHeader::record_len(0))?;
    if let Some(n) = avail.get(40..48) {
        let n_changes = u64::from_le_bytes([n[0], n[1], n[2], n[3], n[4], n[5], n[6], n[7]]);
        let len = CommitHeader::record_len(n_changes.min(avail.len() as u64));
        map.ensure(at, len)?;
        // A note (revision 3) follows: its length, then the note and its checksum.
        let flags = avail
            .get(4..8)
            .map_or(0, |f| u32::from_le_bytes([f[0], f[1], f[2], f[3]]));
        let mut end = len;
        if flags & COMMIT_HAS_NOTE != 0 {
            map.ensure(at, len + 4)?;
            let note_len = usize::try_from(len)
                .ok()
                .and_then(|l| avail.get(l..l + 4))
                .map_or(0, |n| u32::from_le_bytes([n[0], n[1], n[2], n[3]]))
                .min(MAX_NOTE_LEN);
            end += NOTE_FRAMING_LEN as u64 + u64::from(note_len);
            map.ensure(at, end)?;
        }
        // The summaries (revision 5) follow the note: fetched with the record, since whatever
        // replays the record's changes keeps them.
        if flags & COMMIT_HAS_SUMMARIES != 0 {
            let n = n_changes.min(avail.len() as u64);
            let wide = flags & COMMIT_WIDE_SUMMARIES != 0;
            map.ensure(at, end + CommitHeader::summaries_len(n, wide))?;
        }
    }
    Ok(CommitHeader::decode(avail, at)?)
}

/// The summaries of the changes of the commit record at `at` (`h` as [`commit_record`]
/// returned it, which fetched and checked them), `None` when it has none.
pub(super) fn commit_summaries(
    map: &MappedRegion,
    at: u64,
    h: &CommitHeader,
) -> Option<Vec<BrickSummary>> {
    h.summaries_in(map.bytes().get(at as usize..)?)
}

/// Content hash -> entry for [`Snapshot::find_by_hash`]: a shared base plus what later versions
/// added, so a commit extends its parent's table instead of rescanning the index. Entries of
/// bricks an edit replaced stay findable: their records are still in the file, and content
/// named by its hash is the same whichever version holds it.
#[derive(Debug)]
pub(super) struct HashIndex {
    base: Arc<HashMap<u64, NodeEntry>>,
    added: HashMap<u64, NodeEntry>,
}

impl HashIndex {
    /// Additions past this size are folded into a new base (one copy of the table).
    const MAX_ADDED: usize = 4096;

    fn get(&self, hash: u64) -> Option<NodeEntry> {
        self.added
            .get(&hash)
            .or_else(|| self.base.get(&hash))
            .copied()
    }

    /// A copy for a child version (cheap: the base is shared).
    fn child(&self) -> HashIndex {
        if self.added.len() < Self::MAX_ADDED {
            return HashIndex {
                base: self.base.clone(),
                added: self.added.clone(),
            };
        }
        let mut base = (*self.base).clone();
        base.extend(self.added.iter().map(|(h, e)| (*h, *e)));
        HashIndex {
            base: Arc::new(base),
            added: HashMap::new(),
        }
    }

    fn insert(&mut self, hash: u64, entry: NodeEntry) {
        if self.base.get(&hash) != Some(&entry) {
            self.added.entry(hash).or_insert(entry);
        }
    }
}
