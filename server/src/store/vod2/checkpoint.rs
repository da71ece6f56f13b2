//! How a version's index is built: the newest index checkpoint at or before it (its chunks
//! decoded and checked against their hashes on first use) plus an overlay of the changes of the
//! commits since. Revision 5 keeps each entry's brick summary (content hash, value range) beside
//! it, in the checkpoint's chunks and in the overlay, so that what a grid lists needs no brick
//! record.

use super::snapshot::{commit_record, commit_summaries};
use super::Snapshot;
use crate::store::codec;
use crate::store::region::MappedRegion;
use crate::store::writer::CheckpointChunk;
use crate::store::StoreError;
use isovox_proto::vod2::{
    BrickSummary, Checkpoint, CommitHeader, EncodedChunk, FileHeader, NodeEntry,
    CHECKPOINT_FIXED_LEN, CHUNK_ENTRIES, CHUNK_REF_LEN,
};
use isovox_proto::FormatError;
use std::collections::HashMap;
use std::sync::{Arc, OnceLock};

impl Snapshot {
    pub(super) fn load(
        header: Arc<FileHeader>,
        map: Arc<MappedRegion>,
        commit_at: u64,
    ) -> Result<Snapshot, StoreError> {
        // Walk back to the newest checkpoint, keeping each commit's changes; every record is
        // decoded (and checksummed) once.
        let mut chain: Vec<(u64, CommitHeader, &[u8])> = Vec::new();
        let mut at = commit_at;
        let (head, record) = commit_record(&map, at)?;
        let (mut h, mut record) = (head, record);
        let checkpoint_at = loop {
            chain.push((at, h, record));
            if h.checkpoint != 0 {
                break h.checkpoint;
            }
            let (parent, parent_record) = commit_record(&map, h.parent)?;
            if parent.version.checked_add(1) != Some(h.version) {
                return Err(FormatError::invalid(
                    "commit chain",
                    format!(
                        "commit at {at} is version {}, its parent is version {}",
                        h.version, parent.version
                    ),
                )
                .into());
            }
            at = h.parent;
            (h, record) = (parent, parent_record);
        };
        let nodes = header.node_count();
        let index = Arc::new(IndexChunks::open(&map, checkpoint_at, nodes)?);
        let mut overlay = HashMap::new();
        // The checkpoint holds the state after its own commit: apply only the later ones.
        for (at, h, record) in chain.iter().rev().skip(1) {
            let summaries = commit_summaries(&map, *at, h);
            apply_changes(&header, *at, record, summaries, &mut overlay, |_| ())?;
        }
        Ok(Snapshot {
            version: head.version,
            timestamp_ms: head.timestamp_ms,
            commit_offset: commit_at,
            index,
            overlay: Arc::new(overlay),
            stream: 0,
            channel_views: OnceLock::new(),
            chain_len: chain.len() - 1,
            by_hash: OnceLock::new(),
            header,
            map,
        })
    }

    /// The version whose commit record is at `commit_at` in `map`, a child of this one: this
    /// version's index plus the commit's changes (or, when the commit wrote a checkpoint or is
    /// not a child of this version, loaded from the file as [`Vod2::open`] does).
    ///
    /// [`Vod2::open`]: super::Vod2::open
    pub(super) fn extend(
        &self,
        map: Arc<MappedRegion>,
        commit_at: u64,
    ) -> Result<Snapshot, StoreError> {
        let (h, record) = commit_record(&map, commit_at)?;
        let child =
            h.parent == self.commit_offset && self.version.checked_add(1) == Some(h.version);
        if h.checkpoint != 0 || !child {
            let snap = Snapshot::load(self.header.clone(), map.clone(), commit_at)?;
            // A child that wrote a checkpoint still finds what its parents held by hash.
            if child {
                let summaries = commit_summaries(&map, commit_at, &h);
                let added = CommitHeader::changes(record)
                    .enumerate()
                    .map(|(i, (node, raw))| {
                        let summary = summaries.as_ref().and_then(|s| s.get(i).copied());
                        (node, Overlaid { raw, summary })
                    });
                self.hand_down_hashes(&snap, added)?;
            }
            return Ok(snap);
        }
        let mut overlay = (*self.overlay).clone();
        let mut added = Vec::new();
        let summaries = commit_summaries(&map, commit_at, &h);
        apply_changes(
            &self.header,
            commit_at,
            record,
            summaries,
            &mut overlay,
            |change| added.push(change),
        )?;
        let snap = Snapshot {
            version: h.version,
            timestamp_ms: h.timestamp_ms,
            commit_offset: commit_at,
            index: self.index.clone(),
            overlay: Arc::new(overlay),
            stream: self.stream,
            channel_views: OnceLock::new(),
            chain_len: self.chain_len + 1,
            by_hash: OnceLock::new(),
            header: self.header.clone(),
            map,
        };
        self.hand_down_hashes(&snap, added.into_iter())?;
        Ok(snap)
    }

    /// Offset and length of the index checkpoint this version builds on (reads every chunk
    /// reference).
    ///
    /// # Errors
    /// A chunk reference is invalid.
    pub fn checkpoint_span(&self) -> Result<(u64, u64), StoreError> {
        let n_nodes = self.header.node_count();
        self.map
            .ensure(self.index.base, Checkpoint::directory_len(n_nodes))?;
        let cp = self.index.checkpoint(self.map.bytes())?;
        Ok((self.index.base, cp.total_len()?))
    }

    /// Makes `len` bytes from `start` present in the mapping (fetched, for a volume in an
    /// object store; nothing to do for a local file).
    ///
    /// # Errors
    /// The fetch fails.
    pub fn prefetch(&self, start: u64, len: u64) -> Result<(), StoreError> {
        self.map.ensure(start, len)
    }

    /// The chunks of a checkpoint of this version with `changes` applied (in order: a node
    /// changed twice takes the later entry), whose summaries `summary_of` gives. A chunk that
    /// neither the commits since the base checkpoint nor `changes` touch is kept as the base
    /// checkpoint stores it, after checking it against its hashes (decoding is cheap, encoding
    /// is what a checkpoint costs), when it carries summaries exactly when `with_summaries`
    /// says; every other chunk is the base's entries with the overlay and the changes applied,
    /// and their summaries: taken from the index where it has them; an entry without one (a
    /// file written before revision 5) costs a read of its brick record's header, so the first
    /// checkpoint a revision-5 writer writes into an older file reads every stored brick's
    /// header once. With `keep_untouched` false, every chunk is fresh (what encoding the whole
    /// index costs, as `isovox-bench checkpoint` measures against).
    ///
    /// # Errors
    /// A change names a node outside the volume; a checkpoint chunk or summary block fails its
    /// hash; a brick header is damaged; `summary_of` fails.
    pub fn next_checkpoint(
        &self,
        changes: &[(u64, NodeEntry)],
        with_summaries: bool,
        keep_untouched: bool,
        summary_of: impl Fn(u64, NodeEntry) -> Result<BrickSummary, StoreError>,
    ) -> Result<Vec<CheckpointChunk>, StoreError> {
        let nodes = self.header.node_count();
        let n_chunks = self.index.chunks.len();
        let mut changed_in: Vec<Vec<(u64, NodeEntry)>> = vec![Vec::new(); n_chunks];
        for &(node, entry) in changes {
            if node >= nodes {
                return Err(StoreError::Internal(format!(
                    "node {node} is outside the volume ({nodes} nodes)"
                )));
            }
            changed_in[(node / CHUNK_ENTRIES) as usize].push((node, entry));
        }
        let mut overlaid = vec![false; n_chunks];
        for &node in self.overlay.keys() {
            if let Some(touched) = overlaid.get_mut((node / CHUNK_ENTRIES) as usize) {
                *touched = true;
            }
        }
        let mut chunks = Vec::with_capacity(n_chunks);
        for (c, changed) in changed_in.into_iter().enumerate() {
            if keep_untouched && !overlaid[c] && changed.is_empty() {
                if let Some(kept) =
                    self.index
                        .stored_chunk(&self.map, &self.header, c, with_summaries)?
                {
                    chunks.push(CheckpointChunk::Kept(kept));
                    continue;
                }
            }
            let first = c as u64 * CHUNK_ENTRIES;
            let mut entries = self.index.chunk(&self.map, c)?.to_vec();
            for (node, slot) in (first..).zip(entries.iter_mut()) {
                if let Some(o) = self.overlay.get(&node) {
                    *slot = o.raw;
                }
            }
            let mut summaries = Vec::with_capacity(entries.len());
            for (node, &raw) in (first..).zip(&entries) {
                summaries.push(match with_summaries {
                    false => BrickSummary::default(),
                    true => match self.indexed_summary(node)? {
                        Some(s) => s,
                        None => self.summary_from_record(node, raw)?,
                    },
                });
            }
            for (node, entry) in changed {
                let i = (node - first) as usize;
                entries[i] = entry.encode();
                if with_summaries {
                    summaries[i] = summary_of(node, entry)?;
                }
            }
            chunks.push(CheckpointChunk::Fresh { entries, summaries });
        }
        Ok(chunks)
    }

    /// The summary of the entry at file-wide `node` as the index holds it (the overlay's, or
    /// the checkpoint chunk's); `None` when it holds none (written before revision 5).
    pub(super) fn indexed_summary(&self, node: u64) -> Result<Option<BrickSummary>, StoreError> {
        match self.overlay.get(&node) {
            Some(o) => Ok(o.summary),
            None => self.index.summary(&self.map, &self.header, node),
        }
    }

    /// The summary of the raw entry `raw` of file-wide `node`, from its brick record's header
    /// (zeros for a constant, as stored).
    fn summary_from_record(&self, node: u64, raw: u64) -> Result<BrickSummary, StoreError> {
        let (stream, voxel_type) = self
            .header
            .stream_of(node)
            .ok_or_else(|| StoreError::Internal(format!("node {node} is outside the volume")))?;
        match NodeEntry::decode(raw, voxel_type, self.map.len())? {
            NodeEntry::Constant(_) => Ok(BrickSummary::default()),
            NodeEntry::Stored(offset) => {
                let layout = self.header.stream_layout(stream).ok_or_else(|| {
                    StoreError::Internal(format!("stream {stream} has no layout"))
                })?;
                match super::bricks::stored_record(&self.map, &layout, offset)? {
                    super::StoredBrick::Record { header, .. } => {
                        Ok(BrickSummary::of_header(&header))
                    }
                    super::StoredBrick::Constant(_) => Ok(BrickSummary::default()),
                }
            }
        }
    }

    /// Number of entries that differ from the checkpoint.
    pub fn overlay_len(&self) -> usize {
        self.overlay.len()
    }

    /// Number of commits between the checkpoint and this version.
    pub fn chain_len(&self) -> usize {
        self.chain_len
    }
}

/// An entry that differs from the checkpoint: as the commit record that wrote it stored it,
/// with the brick's summary when the record carries one (revision 5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Overlaid {
    /// The raw index entry.
    pub(super) raw: u64,
    /// Its summary, checked (`None` for a constant, or a record written before revision 5).
    pub(super) summary: Option<BrickSummary>,
}

/// Applies the changes of the commit record at `at` (`record`, with `summaries` when it
/// carries them) to `overlay` (file-wide node index -> entry), checking each node against the
/// file's nodes and each stored entry's summary range against its stream's type, and hands
/// each change to `added`.
fn apply_changes(
    header: &FileHeader,
    at: u64,
    record: &[u8],
    summaries: Option<Vec<BrickSummary>>,
    overlay: &mut HashMap<u64, Overlaid>,
    mut added: impl FnMut((u64, Overlaid)),
) -> Result<(), StoreError> {
    let nodes = header.node_count();
    for (i, (node, raw)) in CommitHeader::changes(record).enumerate() {
        let Some((_, voxel_type)) = header.stream_of(node).filter(|_| node < nodes) else {
            return Err(FormatError::invalid(
                "commit record",
                format!("change to node {node}, the file has {nodes}"),
            )
            .into());
        };
        let summary = match summaries.as_ref().and_then(|s| s.get(i)) {
            // A constant's summary is its value; what is stored for it is never read.
            Some(_) if NodeEntry::is_constant(raw) => None,
            Some(s) => Some(s.validate(voxel_type, "commit summaries", at)?),
            None => None,
        };
        let change = Overlaid { raw, summary };
        overlay.insert(node, change);
        added((node, change));
    }
    Ok(())
}

/// The entries of an index checkpoint, decoded chunk by chunk on first use and then kept; and
/// their summaries (revision 5), decoded when first asked for.
#[derive(Debug)]
pub(super) struct IndexChunks {
    base: u64,
    n_nodes: u64,
    chunks: Vec<OnceLock<Box<[u64]>>>,
    /// Per chunk: its summaries, or `None` when it has none (written before revision 5).
    summaries: Vec<OnceLock<Option<Box<[BrickSummary]>>>>,
}

impl IndexChunks {
    /// Checks the checkpoint's fixed fields; chunks are checked when first used.
    fn open(map: &MappedRegion, base: u64, n_nodes: u64) -> Result<IndexChunks, StoreError> {
        map.ensure(base, CHECKPOINT_FIXED_LEN as u64)?;
        let avail = map.bytes().get(base as usize..).ok_or_else(|| {
            StoreError::from(FormatError::invalid(
                "index checkpoint",
                format!("offset {base} past the committed length {}", map.len()),
            ))
        })?;
        Checkpoint::decode(avail, base, n_nodes)?;
        Ok(IndexChunks {
            base,
            n_nodes,
            chunks: (0..Checkpoint::n_chunks(n_nodes))
                .map(|_| OnceLock::new())
                .collect(),
            summaries: (0..Checkpoint::n_chunks(n_nodes))
                .map(|_| OnceLock::new())
                .collect(),
        })
    }

    /// The summary of file-wide `node` as its chunk stores it, `None` when the chunk has no
    /// summaries or the entry is a constant (whose summary is its value). The chunk's
    /// summaries are decoded, hashed and range-checked on first use, then kept.
    pub(super) fn summary(
        &self,
        map: &MappedRegion,
        header: &FileHeader,
        node: u64,
    ) -> Result<Option<BrickSummary>, StoreError> {
        let c = (node / CHUNK_ENTRIES) as usize;
        let i = (node % CHUNK_ENTRIES) as usize;
        let summaries = self.chunk_summaries(map, header, c)?;
        if NodeEntry::is_constant(self.chunk(map, c)?[i]) {
            return Ok(None);
        }
        Ok(summaries.map(|s| s[i]))
    }

    /// Chunk `c`'s summaries (`None` when it has none), decoded, hashed and range-checked on
    /// first use, then kept.
    fn chunk_summaries(
        &self,
        map: &MappedRegion,
        header: &FileHeader,
        c: usize,
    ) -> Result<Option<&[BrickSummary]>, StoreError> {
        if self.summaries[c].get().is_none() {
            let decoded = self.decode_summaries(map, header, c)?;
            let _ = self.summaries[c].set(decoded);
        }
        Ok(self.summaries[c].get().and_then(|s| s.as_deref()))
    }

    fn decode_summaries(
        &self,
        map: &MappedRegion,
        header: &FileHeader,
        c: usize,
    ) -> Result<Option<Box<[BrickSummary]>>, StoreError> {
        // The entries first: their span covers the summary block too (one fetch).
        let entries = self.chunk(map, c)?;
        let cp = self.checkpoint(map.bytes())?;
        let (r, _) = cp.chunk(c as u64)?;
        let Some(block) = cp.summaries(&r)? else {
            return Ok(None);
        };
        if block.wide != header.wide_summaries() {
            return Err(FormatError::invalid(
                "index chunk summaries",
                format!(
                    "at offset {}: {} summaries in a file whose channels need {}",
                    block.offset,
                    if block.wide { "wide" } else { "narrow" },
                    if block.wide { "narrow" } else { "wide" }
                ),
            )
            .into());
        }
        let mut bytes = vec![0u8; entries.len() * BrickSummary::encoded_len(block.wide)];
        codec::decode(block.codec, block.payload, &mut bytes, block.offset)?;
        let hash = xxhash_rust::xxh3::xxh3_64(&bytes);
        if hash != block.hash {
            return Err(FormatError::Checksum {
                what: "index chunk summaries",
                offset: block.offset,
                stored: block.hash,
                computed: hash,
            }
            .into());
        }
        let summaries = BrickSummary::decode_all(&bytes, block.wide);
        let first = c as u64 * CHUNK_ENTRIES;
        for (node, (&raw, s)) in (first..).zip(entries.iter().zip(&summaries)) {
            if NodeEntry::is_constant(raw) {
                continue;
            }
            let (_, voxel_type) = header.stream_of(node).ok_or_else(|| {
                StoreError::Internal(format!("node {node} is outside the volume"))
            })?;
            s.validate(voxel_type, "index chunk summaries", block.offset)?;
        }
        Ok(Some(summaries.into_boxed_slice()))
    }

    /// Chunk `c` as stored (its payload and summary block copied), after checking both
    /// against their hashes (decoded on first use, as any reader does); `None` when it carries
    /// summaries and `with_summaries` is false, or the other way round.
    fn stored_chunk(
        &self,
        map: &MappedRegion,
        header: &FileHeader,
        c: usize,
        with_summaries: bool,
    ) -> Result<Option<EncodedChunk>, StoreError> {
        // Decoding fetches the chunk's bytes, payload and summaries, into the mapping.
        self.chunk(map, c)?;
        self.chunk_summaries(map, header, c)?;
        let cp = self.checkpoint(map.bytes())?;
        let (r, payload) = cp.chunk(c as u64)?;
        let summaries = cp.summaries(&r)?;
        if summaries.is_some() != with_summaries {
            return Ok(None);
        }
        Ok(Some(EncodedChunk {
            codec: r.codec,
            payload: payload.to_vec(),
            hash: r.hash,
            wide_summaries: summaries.is_some_and(|b| b.wide),
            summaries: summaries.map(|b| (b.codec, b.payload.to_vec(), b.hash)),
        }))
    }

    fn checkpoint<'m>(&self, mapped: &'m [u8]) -> Result<Checkpoint<'m>, StoreError> {
        Ok(Checkpoint::decode(
            &mapped[self.base as usize..],
            self.base,
            self.n_nodes,
        )?)
    }

    pub(super) fn entry(&self, map: &MappedRegion, node: u64) -> Result<u64, StoreError> {
        let chunk = self.chunk(map, (node / CHUNK_ENTRIES) as usize)?;
        Ok(chunk[(node % CHUNK_ENTRIES) as usize])
    }

    /// Chunk `c`'s entries, decoded and checked on first use.
    fn chunk(&self, map: &MappedRegion, c: usize) -> Result<&[u64], StoreError> {
        if let Some(chunk) = self.chunks[c].get() {
            return Ok(chunk);
        }
        let decoded = self.decode_chunk(map, c as u64)?;
        // Another reader may have decoded it meanwhile: either copy is the same.
        let _ = self.chunks[c].set(decoded);
        self.chunks[c]
            .get()
            .map(|chunk| &chunk[..])
            .ok_or_else(|| StoreError::Internal("index chunk vanished".into()))
    }

    fn decode_chunk(&self, map: &MappedRegion, c: u64) -> Result<Box<[u64]>, StoreError> {
        map.ensure(self.base, CHECKPOINT_FIXED_LEN as u64)?;
        let cp = self.checkpoint(map.bytes())?;
        map.ensure(
            self.base + (CHECKPOINT_FIXED_LEN + c as usize * CHUNK_REF_LEN) as u64,
            CHUNK_REF_LEN as u64,
        )?;
        let (r, payload) = cp.chunk(c)?;
        // The payload and the summary block after it (revision 5) in one go: a grid needs
        // both, and from a store each separate range costs a request.
        let (at, len) = r.span();
        map.ensure(self.base + at, len)?;
        let mut bytes = vec![0u8; cp.chunk_entries(c) as usize * 8];
        codec::decode(r.codec, payload, &mut bytes, self.base + r.offset)?;
        let hash = xxhash_rust::xxh3::xxh3_64(&bytes);
        if hash != r.hash {
            return Err(FormatError::Checksum {
                what: "index chunk",
                offset: self.base + r.offset,
                stored: r.hash,
                computed: hash,
            }
            .into());
        }
        Ok(bytes
            .chunks_exact(8)
            .map(|e| u64::from_le_bytes([e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7]]))
            .collect())
    }
}
