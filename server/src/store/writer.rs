//! Appending to a VOD 2 file: brick records with deduplication, index checkpoints, commits.
//!
//! The commit protocol (crash-safe at any byte):
//! 1. append the new brick records, the index checkpoint if any, and the commit record;
//! 2. write the header slot that is *not* the current head's (sequence number + 1), naming the
//!    new commit and the new committed length, with the checksum of everything appended in 1;
//! 3. `fdatasync` the file, once.
//!
//! A crash before 3 completes may leave any part of it on disk, in any order: a slot whose own
//! checksum or whose appended bytes' checksum fails is ignored, and the old slot, which the
//! previous sync made durable and which this one did not touch, names the old version, intact.
//! Nothing ever overwrites a byte below the committed length. The first commit of a file and a
//! sync of more than [`ONE_SYNC_MAX`] bytes (which an open would have to read again) instead
//! sync the appended bytes before writing the slot, and the slot after, with no checksum.
//!
//! Group commit splits step 1 from steps 2-3: [`Vod2Writer::stage`] appends one version's
//! commit record (its parent the previous staged one), [`Vod2Writer::sync`] makes every version
//! staged since the last sync durable with one slot naming the newest. Until then none of them
//! is visible to a reader opening the file, so a crash anywhere in a group leaves either all of
//! its versions or none. A [`Savepoint`] taken before staging a version lets the writer drop
//! that version's bytes again ([`Vod2Writer::rollback`]) without touching the versions staged
//! before it.

use super::codec::{self, Compression};
use super::pyramid::BrickVoxels;
use super::StoreError;
use super::StoredBrick;
use isovox_proto::vod2::{
    content_hash, payload_check, AppendedCheck, BrickHeader, BrickSummary, Checkpoint, Codec,
    CommitHeader, EncodedChunk, FileHeader, HeaderSlot, NodeEntry, CHUNK_ENTRIES, DATA_START,
    MAX_CONSTANT, SLOT_OFFSETS,
};
use isovox_proto::{VolumeLayout, VoxelType};
use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

/// Append buffer size: large sequential writes, bounded memory.
const FLUSH_AT: usize = 8 << 20;

/// The most bytes a sync makes durable together with its slot in one `fdatasync`: opening the
/// file reads them again to check them, so this bounds what an open reads (an edit group
/// appends kilobytes; an import or a compaction syncs twice).
const ONE_SYNC_MAX: u64 = 16 << 20;

/// A brick made ready for storage off the writer's thread: classified, hashed and (unless a
/// copy with the same hash is already stored) compressed.
#[derive(Debug)]
pub struct PreparedBrick {
    /// Set when every voxel holds this value (at most [`MAX_CONSTANT`]).
    constant: Option<u64>,
    hash: u64,
    min: u64,
    max: u64,
    encoded: Option<(Codec, Vec<u8>)>,
    /// The bytes of a constant brick whose value no index entry holds (a u64 id past
    /// [`MAX_CONSTANT`]): stored as a record.
    expanded: Option<Vec<u8>>,
}

/// Counters of what a writer stored.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct WriteStats {
    /// Bricks that went into the index as constants (no payload).
    pub constant: u64,
    /// Bricks whose content was already stored (by hash and byte comparison).
    pub deduplicated: u64,
    /// Brick records written and their payload bytes (headers not included), by codec:
    /// raw, lz4, zstd, palette (the [`Codec`] values).
    pub stored: [u64; 4],
    /// Their payload bytes, by codec.
    pub stored_bytes: [u64; 4],
    /// Hash matches whose bytes differed (collisions kept apart).
    pub hash_collisions: u64,
}

/// Where a commit is made durable: the seam between the writer and a volume kept elsewhere.
/// A local file needs none (the writer appends to it and switches a header slot); a volume in
/// an object store takes each sync's bytes as one object and advances its head.
pub trait Publish: Send + Sync + std::fmt::Debug {
    /// Makes `appended` (the bytes from offset `from` up to `slot`'s committed length) durable
    /// and `slot` the head, if the head is still `base`.
    ///
    /// # Errors
    /// [`StoreError::HeadMoved`] when another writer moved the head first; the store fails.
    fn publish(
        &self,
        base: Option<HeaderSlot>,
        from: u64,
        appended: &[u8],
        slot: &HeaderSlot,
    ) -> Result<(), StoreError>;
}

/// What a writer appends to.
#[derive(Debug)]
enum Target {
    /// A local file: written as the buffer fills, synced, then a slot switched.
    File(File),
    /// A volume elsewhere: what is appended stays in the buffer until a sync publishes it.
    Remote(std::sync::Arc<dyn Publish>),
}

/// An open VOD 2 file being appended to.
#[derive(Debug)]
pub struct Vod2Writer {
    target: Target,
    path: PathBuf,
    header: FileHeader,
    /// Offset of `buf[0]` in the file; everything below it is written.
    buf_at: u64,
    buf: Vec<u8>,
    /// hash -> offsets of stored brick records with that content hash.
    known: HashMap<u64, Vec<u64>>,
    /// record offset -> its summary, for the records this writer appended, found as
    /// duplicates, or was told of ([`Vod2Writer::learn_summary`]): what the commit records and
    /// checkpoints it writes store beside their entries (revision 5).
    summaries: HashMap<u64, BrickSummary>,
    /// Whether commit records and checkpoints carry summaries: always, except to write a file
    /// as a writer before revision 5 did ([`Vod2Writer::omit_summaries`]).
    write_summaries: bool,
    compression: Compression,
    head: Option<HeaderSlot>,
    /// The newest version staged since the last sync, as the slot that will name it.
    staged: Option<HeaderSlot>,
    /// `(hash, offset)` of every brick record appended since the last sync, in order: what a
    /// rollback takes out of `known` again.
    appended: Vec<(u64, u64)>,
    /// Syncs so far: a savepoint does not outlive the next one.
    syncs: u64,
    /// Version number of the first commit when the file has none yet.
    first_version: u64,
    stats: WriteStats,
}

/// Where a writer stood before a version was staged (see [`Vod2Writer::rollback`]).
#[derive(Debug, Clone, Copy)]
pub struct Savepoint {
    syncs: u64,
    end: u64,
    staged: Option<HeaderSlot>,
    appended: usize,
    stats: WriteStats,
}

impl Vod2Writer {
    /// Creates (or truncates) `path` as an empty VOD 2 file with no commit yet.
    ///
    /// # Errors
    /// The file cannot be created or written.
    pub fn create(
        path: &Path,
        header: FileHeader,
        compression: Compression,
    ) -> Result<Self, StoreError> {
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(path)
            .map_err(StoreError::io_path("cannot create", path))?;
        let mut buf = vec![0u8; DATA_START as usize];
        buf[..isovox_proto::vod2::DATA_PAGE].copy_from_slice(&header.encode_page());
        Ok(Vod2Writer {
            target: Target::File(file),
            path: path.to_path_buf(),
            header,
            buf_at: 0,
            buf,
            known: HashMap::new(),
            summaries: HashMap::new(),
            write_summaries: true,
            compression,
            head: None,
            staged: None,
            appended: Vec::new(),
            syncs: 0,
            first_version: 1,
            stats: WriteStats::default(),
        })
    }

    /// Opens an existing VOD 2 file to append new versions to its head. Bytes past the head's
    /// committed length (an unfinished commit of a crashed writer) are cut off first. The
    /// deduplication table is rebuilt from the head's stored bricks (one pass over the index,
    /// no brick data read).
    ///
    /// Only one writer may append to a file at a time; the caller serializes writers.
    ///
    /// # Errors
    /// The file does not open as VOD 2 or cannot be written.
    pub fn open_append(path: &Path, compression: Compression) -> Result<Self, StoreError> {
        let vod = super::Vod2::open(path)?;
        let head = vod.head_slot();
        let snap = vod.head();
        let mut known: HashMap<u64, Vec<u64>> = HashMap::new();
        let mut seen = std::collections::HashSet::new();
        for stream in snap.streams() {
            for node in 0..stream.layout().node_count() {
                if let NodeEntry::Stored(offset) = stream.entry_at(node)? {
                    if seen.insert(offset) {
                        if let super::StoredBrick::Record { header, .. } =
                            stream.stored_entry(NodeEntry::Stored(offset))?
                        {
                            known.entry(header.hash).or_default().push(offset);
                        }
                    }
                }
            }
        }
        let header = vod.header().clone();
        drop(snap);
        drop(vod);
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(StoreError::io_path("cannot open for writing", path))?;
        file.set_len(head.committed_len)
            .map_err(StoreError::io_path(
                "cannot cut the unfinished tail of",
                path,
            ))?;
        Ok(Vod2Writer {
            target: Target::File(file),
            path: path.to_path_buf(),
            header,
            buf_at: head.committed_len,
            buf: Vec::new(),
            known,
            summaries: HashMap::new(),
            write_summaries: true,
            compression,
            head: Some(head),
            staged: None,
            appended: Vec::new(),
            syncs: 0,
            first_version: 1,
            stats: WriteStats::default(),
        })
    }

    /// A writer of versions on top of `vod`'s head, made durable by `publish` (a volume in an
    /// object store), compressing as local edits do. It deduplicates against the bricks it stores itself, not the volume's
    /// (that would read every brick header from the store).
    pub fn remote(vod: &super::Vod2, publish: std::sync::Arc<dyn Publish>) -> Vod2Writer {
        let head = vod.head_slot();
        Vod2Writer {
            target: Target::Remote(publish),
            path: vod.path().to_path_buf(),
            header: vod.header().clone(),
            buf_at: head.committed_len,
            buf: Vec::new(),
            known: HashMap::new(),
            summaries: HashMap::new(),
            write_summaries: true,
            compression: Compression::for_edits(),
            head: Some(head),
            staged: None,
            appended: Vec::new(),
            syncs: 0,
            first_version: 1,
            stats: WriteStats::default(),
        }
    }

    /// The file's fixed header.
    pub fn header(&self) -> &FileHeader {
        &self.header
    }

    /// Writes commit records and checkpoints without brick summaries from now on, as writers
    /// before revision 5 did: to make the older files that readers must still open (tests,
    /// measurements). Nothing else needs it.
    pub fn omit_summaries(&mut self) {
        self.write_summaries = false;
    }

    /// Whether checkpoints and commit records this writer writes carry brick summaries.
    pub fn writes_summaries(&self) -> bool {
        self.write_summaries
    }

    /// Whether the writer knows the summary of the record at `offset` without reading it.
    pub fn knows_summary(&self, offset: u64) -> bool {
        self.summaries.contains_key(&offset)
    }

    /// Tells the writer the summary of the record at `offset` (a record of an older version an
    /// undo points at again, read by whoever knows the version), for the commit that names it.
    pub fn learn_summary(&mut self, offset: u64, summary: BrickSummary) {
        self.summaries.insert(offset, summary);
    }

    /// The summary to store beside `entry` at file-wide `node`: zeros for a constant (never
    /// read); a record's from what the writer knows, else from its header read back (a local
    /// file). A remote writer must have been told ([`Vod2Writer::learn_summary`]).
    ///
    /// # Errors
    /// The record's header cannot be read back, or is damaged.
    pub fn summary_for(&self, node: u64, entry: NodeEntry) -> Result<BrickSummary, StoreError> {
        let NodeEntry::Stored(offset) = entry else {
            return Ok(BrickSummary::default());
        };
        if let Some(s) = self.summaries.get(&offset) {
            return Ok(*s);
        }
        let voxel_type =
            self.header.stream_of(node).map(|(_, t)| t).ok_or_else(|| {
                StoreError::Internal(format!("node {node} is outside the volume"))
            })?;
        let layout = self.header.layout.with_voxel_type(voxel_type);
        let head = self.read_at(offset, BrickHeader::len_for(voxel_type))?;
        Ok(BrickSummary::of_header(&BrickHeader::decode(
            &head, offset, &layout,
        )?))
    }

    /// Numbers this new file's first commit `version` instead of 1: a compacted copy keeps its
    /// head's number, so versions never go backwards for clients.
    ///
    /// # Errors
    /// The file already has a commit, or `version` is 0.
    pub fn start_at_version(&mut self, version: u64) -> Result<(), StoreError> {
        if self.head.is_some() || version == 0 {
            return Err(StoreError::Internal(format!(
                "cannot start {} at version {version}: it has commits, or 0 was asked",
                self.path.display()
            )));
        }
        self.first_version = version;
        Ok(())
    }

    /// Appends a brick record of another file (of the same shape) with its payload as it is,
    /// for copying distinct records between files without recompressing them. The payload is
    /// verified first ([`verify_stored`]: its checksum, or, in a record written before payload
    /// checksums, its decoded content), so damage is never copied, and the copy has a
    /// checksum whatever the original had. A constant is returned as it is.
    ///
    /// [`verify_stored`]: super::vod2::verify_stored
    ///
    /// # Errors
    /// The payload is not what was stored ([`StoreError::Corrupt`]), or appending fails.
    pub fn copy_record(&mut self, stored: &StoredBrick<'_>) -> Result<NodeEntry, StoreError> {
        match *stored {
            StoredBrick::Constant(v) => Ok(NodeEntry::Constant(v)),
            StoredBrick::Record {
                header, payload, ..
            } => {
                super::vod2::verify_stored(stored, &self.header.layout)?;
                self.append_record(header, payload)
            }
        }
    }

    /// Appends a brick record with a payload checksum; returns its offset.
    fn append_record(
        &mut self,
        header: BrickHeader,
        payload: &[u8],
    ) -> Result<NodeEntry, StoreError> {
        let header = BrickHeader {
            checked: true,
            ..header
        };
        let offset = self.append(&header.encode())?;
        self.append(payload)?;
        self.append(&payload_check(payload).to_le_bytes())?;
        self.stats.stored[header.codec as usize] += 1;
        self.stats.stored_bytes[header.codec as usize] += payload.len() as u64;
        self.remember(header.hash, offset);
        self.summaries
            .insert(offset, BrickSummary::of_header(&header));
        Ok(NodeEntry::Stored(offset))
    }

    /// The slot naming the newest durable commit this writer made or found.
    pub fn head(&self) -> Option<HeaderSlot> {
        self.head
    }

    /// The newest version this writer appended, durable or only staged: what the next staged
    /// version's parent is.
    pub fn tip(&self) -> Option<HeaderSlot> {
        self.staged.or(self.head)
    }

    /// Whether versions are staged that are not durable yet.
    pub fn has_staged(&self) -> bool {
        self.staged.is_some()
    }

    /// A remote writer's bytes appended since its last sync, and the offset of the first: what
    /// its next sync publishes, and what the versions it staged are read from until then.
    /// `None` for a local file (its staged bytes are in the file).
    pub fn unpublished(&self) -> Option<(u64, &[u8])> {
        matches!(self.target, Target::Remote(_)).then_some((self.buf_at, &self.buf[..]))
    }

    fn remember(&mut self, hash: u64, offset: u64) {
        self.known.entry(hash).or_default().push(offset);
        self.appended.push((hash, offset));
    }

    /// What it stored so far.
    pub fn stats(&self) -> WriteStats {
        self.stats
    }

    /// The offset the next appended byte gets.
    pub fn end(&self) -> u64 {
        self.buf_at + self.buf.len() as u64
    }

    fn append(&mut self, bytes: &[u8]) -> Result<u64, StoreError> {
        let at = self.end();
        self.buf.extend_from_slice(bytes);
        if self.buf.len() >= FLUSH_AT {
            self.flush()?;
        }
        Ok(at)
    }

    fn flush(&mut self) -> Result<(), StoreError> {
        let Target::File(file) = &self.target else {
            return Ok(());
        };
        if !self.buf.is_empty() {
            file.write_all_at(&self.buf, self.buf_at)
                .map_err(StoreError::io_path("cannot write", &self.path))?;
            self.buf_at += self.buf.len() as u64;
            self.buf.clear();
        }
        Ok(())
    }

    fn read_at(&self, offset: u64, len: usize) -> Result<Vec<u8>, StoreError> {
        if offset >= self.buf_at {
            let start = (offset - self.buf_at) as usize;
            return Ok(self.buf[start..start + len].to_vec());
        }
        let Target::File(file) = &self.target else {
            return Err(StoreError::Internal(format!(
                "{}: a remote writer read back offset {offset}, below what it appended",
                self.path.display()
            )));
        };
        let mut out = vec![0u8; len];
        file.read_exact_at(&mut out, offset)
            .map_err(StoreError::io_path("cannot read back", &self.path))?;
        Ok(out)
    }

    /// Classifies, hashes and compresses one brick. Pure and thread-safe: call it from rayon
    /// over a batch, then hand the results to [`Vod2Writer::store`] in order.
    pub fn prepare(&self, voxels: &BrickVoxels) -> PreparedBrick {
        self.prepare_as(voxels, self.header.layout.voxel_type())
    }

    /// [`Vod2Writer::prepare`] for a brick of values of `voxel_type` (an attribute channel's).
    pub fn prepare_as(&self, voxels: &BrickVoxels, voxel_type: VoxelType) -> PreparedBrick {
        let layout = self.header.layout.with_voxel_type(voxel_type);
        prepare(voxels, &layout, self.compression, &self.known)
    }

    /// [`Vod2Writer::prepare_as`] compressing an attribute channel's brick as a build does
    /// ([`Compression::for_channels`]).
    pub fn prepare_channel(&self, voxels: &BrickVoxels, voxel_type: VoxelType) -> PreparedBrick {
        prepare(
            voxels,
            &self.header.layout.with_voxel_type(voxel_type),
            self.compression.for_channels(),
            &self.known,
        )
    }

    /// Stores a prepared brick: a constant goes into the index; content already stored is
    /// shared (hash match confirmed byte for byte); anything else is appended.
    ///
    /// # Errors
    /// Reading back a candidate duplicate or appending fails.
    pub fn store(
        &mut self,
        voxels: &BrickVoxels,
        brick: PreparedBrick,
    ) -> Result<NodeEntry, StoreError> {
        let voxel_type = self.header.layout.voxel_type();
        self.store_as(voxels, brick, voxel_type)
    }

    /// [`Vod2Writer::store`] for a brick of values of `voxel_type` (an attribute channel's,
    /// prepared by [`Vod2Writer::prepare_as`]). Records are shared across streams when their
    /// bytes are equal.
    ///
    /// # Errors
    /// As [`Vod2Writer::store`].
    pub fn store_as(
        &mut self,
        voxels: &BrickVoxels,
        brick: PreparedBrick,
        voxel_type: VoxelType,
    ) -> Result<NodeEntry, StoreError> {
        let bytes = match (voxels, brick.constant, brick.expanded.as_deref()) {
            (_, None, Some(expanded)) => expanded,
            (BrickVoxels::Data(d), None, None) => d,
            (_, Some(v), _) => {
                self.stats.constant += 1;
                return Ok(NodeEntry::Constant(v));
            }
            (BrickVoxels::Constant(v), None, None) => {
                return Err(StoreError::Internal(format!(
                    "the constant brick of {v} was not prepared as one"
                )))
            }
        };
        if let Some(candidates) = self.known.get(&brick.hash) {
            for &offset in candidates.clone().iter() {
                if self.stored_equals(offset, bytes, voxel_type)? {
                    self.stats.deduplicated += 1;
                    // Equal bytes: the brick's summary is the record's.
                    let summary = BrickSummary {
                        hash: brick.hash,
                        min: brick.min,
                        max: brick.max,
                    };
                    self.summaries.insert(offset, summary);
                    return Ok(NodeEntry::Stored(offset));
                }
            }
            self.stats.hash_collisions += 1;
        }
        let (codec, payload) = match brick.encoded {
            Some(e) => e,
            None => codec::encode_typed(bytes, voxel_type, self.compression),
        };
        let header = BrickHeader {
            hash: brick.hash,
            stored_len: payload.len() as u32,
            codec,
            min: brick.min,
            max: brick.max,
            checked: true,
            wide: voxel_type.is_wide(),
        };
        self.append_record(header, &payload)
    }

    /// Whether the record at `offset` holds `bytes`. A damaged record holds nothing: the
    /// brick is then stored anew, so later versions do not depend on the damage.
    fn stored_equals(
        &self,
        offset: u64,
        bytes: &[u8],
        voxel_type: VoxelType,
    ) -> Result<bool, StoreError> {
        let head = self.read_at(offset, BrickHeader::len_for(voxel_type))?;
        let layout = self.header.layout.with_voxel_type(voxel_type);
        let h = match BrickHeader::decode(&head, offset, &layout) {
            Ok(h) => h,
            Err(e) => return Ok(damaged(offset, &e.into())),
        };
        let payload = self.read_at(offset + h.header_len() as u64, h.stored_len as usize)?;
        let mut decoded = vec![0u8; bytes.len()];
        if let Err(e) = codec::decode(h.codec, &payload, &mut decoded, offset) {
            return Ok(damaged(offset, &e));
        }
        Ok(decoded == bytes)
    }

    /// Makes everything appended so far durable and switches the head to a new commit:
    /// [`Vod2Writer::stage`] then [`Vod2Writer::sync`].
    ///
    /// # Errors
    /// See [`Vod2Writer::stage`] and [`Vod2Writer::sync`]. The head is then unchanged.
    /// The checkpoint's summaries are found as [`Vod2Writer::summary_for`] does.
    pub fn commit(
        &mut self,
        changes: &[(u64, NodeEntry)],
        checkpoint: Option<&[u64]>,
    ) -> Result<HeaderSlot, StoreError> {
        let full = match checkpoint {
            Some(entries) => Some(CheckpointChunk::all_fresh(
                entries,
                &self.summaries_of(entries)?,
            )),
            None => None,
        };
        self.stage(changes, full, &[])?;
        self.sync()
    }

    /// [`Vod2Writer::summary_for`] of every entry of a full index.
    ///
    /// # Errors
    /// As [`Vod2Writer::summary_for`].
    pub fn summaries_of(&self, entries: &[u64]) -> Result<Vec<BrickSummary>, StoreError> {
        (0u64..)
            .zip(entries)
            .map(|(node, &raw)| {
                let (_, voxel_type) = self.header.stream_of(node).ok_or_else(|| {
                    StoreError::Internal(format!("node {node} is outside the volume"))
                })?;
                let entry = NodeEntry::decode(raw, voxel_type, u64::MAX)?;
                self.summary_for(node, entry)
            })
            .collect()
    }

    /// Appends the next version's commit record (after the newest staged one, or the head):
    /// `checkpoint` is the full index after the commit (written as a checkpoint) with each
    /// entry's summary, or `None` to record only `changes` relative to its parent (each
    /// change's summary found by [`Vod2Writer::summary_for`]); `note` (the commit's
    /// [`CommitNote`](isovox_proto::history::CommitNote) as JSON, or empty) follows the
    /// record. The bytes reach the file (so a mapping of
    /// it can read the new version) but are not durable and not named by a slot until
    /// [`Vod2Writer::sync`]. Returns the slot that will name the version, its committed length
    /// ending with this record.
    ///
    /// # Errors
    /// A change names a node outside the volume, a constant out of range or a brick offset
    /// outside the appended region; the version or slot sequence is exhausted; writing fails.
    /// What was appended is then still there: roll back to a savepoint, or drop the writer.
    pub fn stage(
        &mut self,
        changes: &[(u64, NodeEntry)],
        checkpoint: Option<Vec<CheckpointChunk>>,
        note: &[u8],
    ) -> Result<HeaderSlot, StoreError> {
        let note_len = u32::try_from(note.len())
            .ok()
            .filter(|&n| n <= isovox_proto::vod2::MAX_NOTE_LEN)
            .ok_or_else(|| {
                StoreError::Internal(format!(
                    "a commit note of {} bytes is longer than the format allows",
                    note.len()
                ))
            })?;
        // Every version of a group is named by one slot write, to the slot that does not hold
        // the durable head: the sequence number moves by one per sync, not per version.
        let (parent, version, seq) = match (self.tip(), self.head) {
            (Some(tip), Some(head)) => match (tip.version.checked_add(1), head.seq.checked_add(1)) {
                (Some(version), Some(seq)) => (tip.commit, version, seq),
                _ => {
                    return Err(StoreError::Internal(format!(
                        "{}: version or slot sequence number exhausted (version {}, sequence {}); compact the file",
                        self.path.display(),
                        tip.version,
                        head.seq
                    )))
                }
            },
            (Some(tip), None) => match tip.version.checked_add(1) {
                Some(version) => (tip.commit, version, 1),
                None => {
                    return Err(StoreError::Internal(format!(
                        "{}: version numbers exhausted",
                        self.path.display()
                    )))
                }
            },
            (None, _) => (0, self.first_version, 1),
        };
        for (node, entry) in changes {
            let valid = match (self.header.stream_of(*node), *entry) {
                (None, _) => false,
                (Some((_, voxel_type)), NodeEntry::Constant(v)) => {
                    v <= voxel_type.max_value() && v <= MAX_CONSTANT
                }
                (Some(_), NodeEntry::Stored(offset)) => offset >= DATA_START && offset < self.end(),
            };
            if !valid {
                return Err(StoreError::Internal(format!(
                    "invalid change to node {node}: {entry:?}"
                )));
            }
        }
        // A record without changes has no summaries to carry: no section.
        let change_summaries = match self.write_summaries && !changes.is_empty() {
            true => Some(
                changes
                    .iter()
                    .map(|&(node, entry)| self.summary_for(node, entry))
                    .collect::<Result<Vec<_>, _>>()?,
            ),
            false => None,
        };
        let checkpoint_at = match checkpoint {
            Some(chunks) => {
                self.check_checkpoint(&chunks)?;
                let n_nodes = self.header.node_count();
                self.append(&encode_checkpoint_chunks(
                    n_nodes,
                    chunks,
                    self.write_summaries,
                    self.header.wide_summaries(),
                ))?
            }
            None => {
                if parent == 0 {
                    return Err(StoreError::Internal(
                        "the first commit of a file needs a checkpoint".into(),
                    ));
                }
                0
            }
        };
        let record = CommitHeader {
            version,
            parent,
            timestamp_ms: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_millis() as u64)
                .unwrap_or(0),
            checkpoint: checkpoint_at,
            n_changes: changes.len() as u64,
            note_len,
            summaries: change_summaries.is_some(),
            wide_summaries: self.header.wide_summaries(),
        }
        .encode(changes, note, change_summaries.as_deref());
        let commit_at = self.append(&record)?;
        self.flush()?;
        let slot = HeaderSlot {
            seq,
            commit: commit_at,
            committed_len: self.end(),
            version,
            // Set when the sync writes it.
            appended: None,
        };
        self.staged = Some(slot);
        Ok(slot)
    }

    /// Checks that `chunks` make a checkpoint of this file: one chunk per [`CHUNK_ENTRIES`]
    /// nodes, a fresh one with an entry and a summary per node, a kept one with summaries
    /// exactly when this writer writes them.
    fn check_checkpoint(&self, chunks: &[CheckpointChunk]) -> Result<(), StoreError> {
        let n_nodes = self.header.node_count();
        let wrong = |what: String| {
            Err(StoreError::Internal(format!(
                "a checkpoint of {n_nodes} entries: {what}"
            )))
        };
        if chunks.len() as u64 != Checkpoint::n_chunks(n_nodes) {
            return wrong(format!(
                "{} chunks, {} needed",
                chunks.len(),
                Checkpoint::n_chunks(n_nodes)
            ));
        }
        for (c, chunk) in (0u64..).zip(chunks) {
            let expected = (n_nodes - c * CHUNK_ENTRIES).min(CHUNK_ENTRIES) as usize;
            match chunk {
                CheckpointChunk::Fresh { entries, summaries }
                    if entries.len() != expected || summaries.len() != expected =>
                {
                    return wrong(format!(
                        "chunk {c} has {} entries and {} summaries, {expected} needed",
                        entries.len(),
                        summaries.len()
                    ));
                }
                CheckpointChunk::Kept(kept) if kept.summaries.is_some() != self.write_summaries => {
                    return wrong(format!(
                        "kept chunk {c} has summaries: {}, the writer writes them: {}",
                        kept.summaries.is_some(),
                        self.write_summaries
                    ));
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// Makes every version staged since the last sync durable: the slot naming the newest of
    /// them, then `fdatasync` (see the module's protocol). Returns the new head (the old one
    /// when nothing was staged).
    ///
    /// # Errors
    /// Writing or syncing fails. The head is then unchanged in this writer, but the slot may
    /// or may not have reached the disk: drop the writer and reopen the file.
    pub fn sync(&mut self) -> Result<HeaderSlot, StoreError> {
        let Some(slot) = self.staged else {
            return self.head.ok_or_else(|| {
                StoreError::Internal(format!("{}: nothing to sync", self.path.display()))
            });
        };
        let slot = match &self.target {
            Target::File(_) => {
                self.flush()?;
                self.switch_slot(slot)?
            }
            Target::Remote(publish) => {
                publish.publish(self.head, self.buf_at, &self.buf, &slot)?;
                self.buf_at = slot.committed_len;
                self.buf.clear();
                // What it stored is now below `buf_at`, which it cannot read back.
                self.known.clear();
                self.summaries.clear();
                slot
            }
        };
        self.head = Some(slot);
        self.staged = None;
        self.appended.clear();
        self.syncs += 1;
        Ok(slot)
    }

    /// Where the writer stands now, to [`rollback`](Vod2Writer::rollback) to.
    pub fn savepoint(&self) -> Savepoint {
        Savepoint {
            syncs: self.syncs,
            end: self.end(),
            staged: self.staged,
            appended: self.appended.len(),
            stats: self.stats,
        }
    }

    /// Drops everything appended since `savepoint` (brick records, a checkpoint, a staged
    /// version): the writer is as it was then, the versions staged before it untouched. The
    /// file is cut back to the savepoint; no mapping reaches past it, because the versions
    /// after it were never handed out.
    ///
    /// # Errors
    /// The savepoint is older than the last sync, or the file cannot be cut (drop the writer).
    pub fn rollback(&mut self, savepoint: Savepoint) -> Result<(), StoreError> {
        if savepoint.syncs != self.syncs || savepoint.end > self.end() {
            return Err(StoreError::Internal(format!(
                "{}: cannot roll back to offset {}: a sync came between, or it lies past the end",
                self.path.display(),
                savepoint.end,
            )));
        }
        if savepoint.end >= self.buf_at {
            self.buf.truncate((savepoint.end - self.buf_at) as usize);
        } else {
            let Target::File(file) = &self.target else {
                return Err(StoreError::Internal(format!(
                    "{}: a remote writer cannot cut back below {}",
                    self.path.display(),
                    self.buf_at
                )));
            };
            file.set_len(savepoint.end)
                .map_err(StoreError::io_path("cannot cut back", &self.path))?;
            self.buf.clear();
            self.buf_at = savepoint.end;
        }
        for (hash, offset) in self.appended.drain(savepoint.appended..) {
            // The offset will be another record's.
            self.summaries.remove(&offset);
            if let Some(offsets) = self.known.get_mut(&hash) {
                offsets.retain(|&o| o != offset);
                if offsets.is_empty() {
                    self.known.remove(&hash);
                }
            }
        }
        self.staged = savepoint.staged;
        self.stats = savepoint.stats;
        Ok(())
    }
}

impl Vod2Writer {
    /// The local sync's second half: writes `slot` to the slot that is not the current head's
    /// and makes it durable with everything appended since that head. A group of at most
    /// [`ONE_SYNC_MAX`] bytes goes with its slot in one `fdatasync`, the slot carrying their
    /// checksum (a crash may leave it on disk without them: opening then finds the checksum
    /// wrong and the older slot still names the version before); the first commit of a file
    /// and larger groups are synced before the slot is written, and the slot after. Returns
    /// the slot as written.
    fn switch_slot(&self, slot: HeaderSlot) -> Result<HeaderSlot, StoreError> {
        let Target::File(file) = &self.target else {
            return Err(StoreError::Internal(
                "a remote writer has no header slots".into(),
            ));
        };
        let sync = |file: &File| {
            file.sync_data()
                .map_err(StoreError::io_path("cannot sync", &self.path))
        };
        let slot = match self.head {
            Some(head) if slot.committed_len - head.committed_len <= ONE_SYNC_MAX => HeaderSlot {
                appended: Some(AppendedCheck {
                    from: head.committed_len,
                    checksum: super::vod2::appended_checksum(
                        file,
                        &self.path,
                        head.committed_len,
                        slot.committed_len,
                    )?,
                }),
                ..slot
            },
            _ => {
                sync(file)?;
                slot
            }
        };
        let slot_at = SLOT_OFFSETS[(slot.seq % 2) as usize];
        file.write_all_at(&slot.encode(), slot_at)
            .map_err(StoreError::io_path(
                "cannot write header slot of",
                &self.path,
            ))?;
        sync(file)?;
        Ok(slot)
    }
}

/// Logs a stored record found damaged while deduplicating, and says it holds nothing.
fn damaged(offset: u64, e: &StoreError) -> bool {
    tracing::warn!(offset, error = %super::error_chain(e), "a stored brick record is damaged; storing the brick anew");
    false
}

/// One chunk of a new index checkpoint ([`CHUNK_ENTRIES`] entries, the last chunk possibly
/// fewer).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CheckpointChunk {
    /// A chunk of the previous checkpoint that no commit since has touched, as it is stored
    /// there (checked against its hashes when read). Copying it costs a fraction of encoding
    /// it again, and most chunks of a large volume are untouched between two checkpoints.
    Kept(EncodedChunk),
    /// Entries and their summaries, to encode.
    Fresh {
        /// The raw entries.
        entries: Vec<u64>,
        /// One per entry (a constant's is not read: stored as zeros).
        summaries: Vec<BrickSummary>,
    },
}

impl CheckpointChunk {
    /// A whole index as fresh chunks.
    pub fn all_fresh(entries: &[u64], summaries: &[BrickSummary]) -> Vec<CheckpointChunk> {
        entries
            .chunks(CHUNK_ENTRIES as usize)
            .zip(summaries.chunks(CHUNK_ENTRIES as usize))
            .map(|(e, s)| CheckpointChunk::Fresh {
                entries: e.to_vec(),
                summaries: s.to_vec(),
            })
            .collect()
    }
}

/// Encodes a full index as a checkpoint: chunks of 512 entries, each zstd-compressed when that
/// is smaller (runs of constant entries shrink to a few bytes), each followed by its entries'
/// summaries (revision 5; one per entry, a constant's stored as zeros, so that runs of
/// constants shrink here too).
pub fn encode_checkpoint(entries: &[u64], summaries: &[BrickSummary]) -> Vec<u8> {
    encode_checkpoint_chunks(
        entries.len() as u64,
        CheckpointChunk::all_fresh(entries, summaries),
        true,
        false,
    )
}

/// Encodes a checkpoint of `n_nodes` entries from its chunks: kept chunks as they are, fresh
/// ones encoded (in parallel), with their summaries when `with_summaries` (wide ones when
/// `wide`: the file has a u32 or u64 channel).
pub fn encode_checkpoint_chunks(
    n_nodes: u64,
    chunks: Vec<CheckpointChunk>,
    with_summaries: bool,
    wide: bool,
) -> Vec<u8> {
    use rayon::prelude::*;
    let zstd = Compression::Zstd(codec::DEFAULT_ZSTD_LEVEL);
    let encode = |bytes: Vec<u8>| {
        let hash = xxhash_rust::xxh3::xxh3_64(&bytes);
        let (codec, payload) = codec::encode(&bytes, zstd);
        (codec, payload, hash)
    };
    let chunks: Vec<EncodedChunk> = chunks
        .into_par_iter()
        .map(|chunk| match chunk {
            CheckpointChunk::Kept(kept) => kept,
            CheckpointChunk::Fresh { entries, summaries } => {
                let (codec, payload, hash) =
                    encode(entries.iter().flat_map(|e| e.to_le_bytes()).collect());
                let summaries = with_summaries.then(|| {
                    let zeroed: Vec<BrickSummary> = entries
                        .iter()
                        .zip(&summaries)
                        .map(|(&raw, &s)| match NodeEntry::is_constant(raw) {
                            true => BrickSummary::default(),
                            false => s,
                        })
                        .collect();
                    encode(BrickSummary::encode_all(&zeroed, wide))
                });
                EncodedChunk {
                    codec,
                    payload,
                    hash,
                    summaries,
                    wide_summaries: wide,
                }
            }
        })
        .collect();
    Checkpoint::encode(n_nodes, &chunks)
}

fn prepare(
    voxels: &BrickVoxels,
    layout: &VolumeLayout,
    compression: Compression,
    known: &HashMap<u64, Vec<u64>>,
) -> PreparedBrick {
    let constant = |v| PreparedBrick {
        constant: Some(v),
        hash: 0,
        min: v,
        max: v,
        encoded: None,
        expanded: None,
    };
    let record = |bytes: &[u8], min, max| {
        let hash = content_hash(bytes);
        // Probably a duplicate of a stored brick: compress only if that turns out false.
        let encoded = (!known.contains_key(&hash))
            .then(|| codec::encode_typed(bytes, layout.voxel_type(), compression));
        PreparedBrick {
            constant: None,
            hash,
            min,
            max,
            encoded,
            expanded: None,
        }
    };
    match voxels {
        BrickVoxels::Constant(v) if *v <= MAX_CONSTANT => constant(*v),
        BrickVoxels::Constant(v) => {
            let bytes = voxels
                .clone()
                .into_bytes(layout.brick_voxels(), layout.voxel_type());
            let mut prepared = record(&bytes, *v, *v);
            prepared.expanded = Some(bytes);
            prepared
        }
        BrickVoxels::Data(bytes) => {
            let (min, max) = codec::min_max(bytes, layout.voxel_type());
            if min == max && min <= MAX_CONSTANT {
                return constant(min);
            }
            record(bytes, min, max)
        }
    }
}
