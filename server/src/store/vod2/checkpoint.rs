//! How a version's index is built: the newest index checkpoint at or before it (its chunks
//! decoded and checked against their hashes on first use) plus an overlay of the changes of the
//! commits since.

use super::snapshot::commit_record;
use super::Snapshot;
use crate::store::codec;
use crate::store::region::MappedRegion;
use crate::store::StoreError;
use isovox_proto::vod2::{
    Checkpoint, CommitHeader, FileHeader, CHECKPOINT_FIXED_LEN, CHUNK_ENTRIES, CHUNK_REF_LEN,
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
        let mut chain: Vec<&[u8]> = Vec::new();
        let mut at = commit_at;
        let (head, record) = commit_record(&map, at)?;
        let (mut h, mut record) = (head, record);
        let checkpoint_at = loop {
            chain.push(record);
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
        for record in chain.iter().rev().skip(1) {
            apply_changes(record, nodes, &mut overlay, |_| ())?;
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
                self.hand_down_hashes(&snap, CommitHeader::changes(record))?;
            }
            return Ok(snap);
        }
        let mut overlay = (*self.overlay).clone();
        let mut added = Vec::new();
        apply_changes(record, self.header.node_count(), &mut overlay, |change| {
            added.push(change)
        })?;
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

    /// Every index entry of this version (every stream's) in node order, raw (as a checkpoint stores them): the
    /// checkpoint's chunks (each checked against its hash when first used) with the overlay
    /// applied (each entry checked when its commit was read). What a new checkpoint is written
    /// from: copying chunks costs a fraction of looking up and decoding each entry.
    ///
    /// # Errors
    /// A checkpoint chunk fails its hash, or the chunks do not hold one entry per node.
    pub fn raw_entries(&self) -> Result<Vec<u64>, StoreError> {
        let nodes = self.header.node_count();
        let mut entries = Vec::with_capacity(usize::try_from(nodes).unwrap_or(0));
        for c in 0..self.index.chunks.len() {
            entries.extend_from_slice(self.index.chunk(&self.map, c)?);
        }
        if entries.len() as u64 != nodes {
            return Err(StoreError::Internal(format!(
                "the index checkpoint holds {} entries for {nodes} nodes",
                entries.len()
            )));
        }
        for (&node, &raw) in self.overlay.iter() {
            let slot = entries.get_mut(node as usize).ok_or_else(|| {
                StoreError::Internal(format!("node {node} is outside the volume"))
            })?;
            *slot = raw;
        }
        Ok(entries)
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

/// Applies a commit record's changes to `overlay` (node index -> raw entry), checking each node
/// against the file's `nodes`, and hands each (node, entry) to `added`.
fn apply_changes(
    record: &[u8],
    nodes: u64,
    overlay: &mut HashMap<u64, u64>,
    mut added: impl FnMut((u64, u64)),
) -> Result<(), StoreError> {
    for (node, entry) in CommitHeader::changes(record) {
        if node >= nodes {
            return Err(FormatError::invalid(
                "commit record",
                format!("change to node {node}, the file has {nodes}"),
            )
            .into());
        }
        overlay.insert(node, entry);
        added((node, entry));
    }
    Ok(())
}

/// The entries of an index checkpoint, decoded chunk by chunk on first use and then kept.
#[derive(Debug)]
pub(super) struct IndexChunks {
    base: u64,
    n_nodes: u64,
    chunks: Vec<OnceLock<Box<[u64]>>>,
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
        })
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
        map.ensure(self.base + r.offset, r.stored_len as u64)?;
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
