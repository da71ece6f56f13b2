//! Reading a VOD 2 file by random access.
//!
//! [`Vod2::open`] reads the fixed header and both header slots with `pread`, maps the committed
//! region, and loads the head version's index: the newest checkpoint at or before it (validated
//! through its small chunk-hash table, not entry by entry) plus the changes of the commits since
//! (at most a bounded number). It never reads brick data, so opening costs the same for a 64^3
//! and a 2048^3 volume.
//!
//! A [`Snapshot`] is one version's immutable view: readers hold an `Arc<Snapshot>` and are never
//! blocked by a writer. A brick lookup is an overlay probe, one index entry (its chunk of 512
//! entries is decoded and checked against its hash the first time it is used, then kept), and a
//! slice of the mapping.
//! Every decoded brick is checked against its content hash, so a corrupted file gives an error,
//! never wrong voxels.

use super::codec;
use super::mapping::Mapping;
use super::region::{Fill, Region};
use super::StoreError;
use isovox_proto::vod2::{
    content_hash, payload_check, BrickHeader, Checkpoint, CommitHeader, Fields, FileHeader,
    HeaderSlot, NodeEntry, BRICK_HEADER_LEN, CHECKPOINT_FIXED_LEN, CHUNK_ENTRIES, CHUNK_REF_LEN,
    DATA_START, HEADER_LEN, PAYLOAD_CHECK_LEN, SLOT_LEN, SLOT_OFFSETS,
};
use isovox_proto::{BrickKey, FormatError, VolumeLayout};
use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

/// An open VOD 2 file.
#[derive(Debug)]
pub struct Vod2 {
    path: PathBuf,
    header: Arc<FileHeader>,
    map: Arc<Region>,
    file_len: u64,
    head_slot: HeaderSlot,
    head: Arc<Snapshot>,
}

/// One stored brick as it is in the file: a constant, or a header and its payload (a slice of
/// the mapping, ready to be sent as it is).
#[derive(Debug, Clone, Copy)]
pub enum StoredBrick<'a> {
    /// Every voxel holds this value (no payload).
    Constant(u16),
    /// A brick record.
    Record {
        /// Where the record starts.
        offset: u64,
        /// Its header.
        header: BrickHeader,
        /// Its payload, a slice of the mapping.
        payload: &'a [u8],
        /// The checksum stored after the payload; `None` in records written before payload
        /// checksums.
        checksum: Option<u32>,
    },
}

/// What checking a stored payload against its checksum found (see
/// [`StoredBrick::check_payload`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PayloadCheck {
    /// The payload is what was stored (or there is none: a constant).
    Verified,
    /// The record has no checksum (written before payload checksums): only decoding it and
    /// comparing the content hash tells.
    NoChecksum,
}

impl StoredBrick<'_> {
    /// The brick's smallest and largest voxel value.
    pub fn min_max(&self) -> (u16, u16) {
        match self {
            StoredBrick::Constant(v) => (*v, *v),
            StoredBrick::Record { header, .. } => (header.min, header.max),
        }
    }

    /// The brick's content hash (for a constant, the hash of its expanded bytes).
    pub fn content_hash(&self, layout: &VolumeLayout) -> u64 {
        match self {
            StoredBrick::Constant(v) => codec::constant_hash(*v, layout),
            StoredBrick::Record { header, .. } => header.hash,
        }
    }

    /// Checks the payload against the checksum stored after it (one xxh3 pass over the stored
    /// bytes, no decoding).
    ///
    /// # Errors
    /// [`StoreError::Corrupt`]: the payload differs from what was stored.
    pub fn check_payload(&self) -> Result<PayloadCheck, StoreError> {
        match *self {
            StoredBrick::Constant(_) => Ok(PayloadCheck::Verified),
            StoredBrick::Record { checksum: None, .. } => Ok(PayloadCheck::NoChecksum),
            StoredBrick::Record {
                offset,
                payload,
                checksum: Some(stored),
                ..
            } => {
                let computed = payload_check(payload);
                if computed != stored {
                    return Err(StoreError::corrupt(
                        offset,
                        format!("a brick payload with checksum {stored:#010x}"),
                        format!("one with checksum {computed:#010x}"),
                    ));
                }
                Ok(PayloadCheck::Verified)
            }
        }
    }
}

/// Verifies a stored brick before its payload is copied or sent as it is: against its
/// checksum, or (a record without one) by decoding it and comparing the content hash.
///
/// # Errors
/// [`StoreError::Corrupt`]: the payload is not what was stored.
pub fn verify_stored(stored: &StoredBrick<'_>, layout: &VolumeLayout) -> Result<(), StoreError> {
    match stored.check_payload()? {
        PayloadCheck::Verified => Ok(()),
        PayloadCheck::NoChecksum => {
            let mut out = vec![0u8; layout.brick_bytes()];
            decode_stored(stored, layout, &mut out)
        }
    }
}

fn read_exact_at(file: &File, path: &Path, offset: u64, len: usize) -> Result<Vec<u8>, StoreError> {
    let mut buf = vec![0u8; len];
    file.read_exact_at(&mut buf, offset)
        .map_err(StoreError::io_path("cannot read", path))?;
    Ok(buf)
}

/// xxh3-64 of the file's bytes `[from, to)`, read in pieces (a slot's appended bytes are a
/// group of edits, but nothing bounds them to fit in memory at once).
pub(crate) fn appended_checksum(
    file: &File,
    path: &Path,
    from: u64,
    to: u64,
) -> Result<u64, StoreError> {
    const PIECE: u64 = 1 << 20;
    let mut hasher = xxhash_rust::xxh3::Xxh3::new();
    let mut buf = vec![0u8; PIECE.min(to.saturating_sub(from)) as usize];
    let mut at = from;
    while at < to {
        let piece = &mut buf[..(to - at).min(PIECE) as usize];
        file.read_exact_at(piece, at)
            .map_err(StoreError::io_path("cannot read", path))?;
        hasher.update(piece);
        at += piece.len() as u64;
    }
    Ok(hasher.digest())
}

/// A decoded slot inside the file, checked against the bytes it was synced with when it
/// carries their checksum.
fn with_appended_bytes(
    file: &File,
    path: &Path,
    at: u64,
    slot: HeaderSlot,
) -> Result<SlotState, StoreError> {
    let Some(check) = slot.appended else {
        return Ok(SlotState::Valid(slot));
    };
    if appended_checksum(file, path, check.from, slot.committed_len)? == check.checksum {
        return Ok(SlotState::Valid(slot));
    }
    Ok(SlotState::Invalid(format!(
        "slot at {at} (version {}) names bytes [{}, {}) synced with it, and they do not match \
         its checksum: they had not all reached the disk when the writer stopped, or were \
         damaged since",
        slot.version, check.from, slot.committed_len
    )))
}

/// What one header slot holds, as read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SlotState {
    /// A valid slot (magic, checksum, offsets inside a file of this length, and the bytes
    /// appended with it matching their checksum when it has one).
    Valid(HeaderSlot),
    /// All zero: never written (a file with one commit has written one slot).
    Unused,
    /// Written, but not valid: why.
    Invalid(String),
}

/// A VOD 2 file opened without choosing a version: its header, both header slots as read, and
/// its committed region mapped (the newest valid slot's committed length; the whole file when
/// no slot is valid). [`Vod2::open`] goes through it to the version the slots name; checking
/// and recovery (`store::check`) read versions the slots do not name through it.
#[derive(Debug)]
pub struct Vod2File {
    path: PathBuf,
    header: Arc<FileHeader>,
    map: Arc<Region>,
    file_len: u64,
    slots: [SlotState; 2],
    head_slot: Option<HeaderSlot>,
}

impl Vod2File {
    /// Reads the header and both slots with `pread`, and maps the committed region.
    ///
    /// # Errors
    /// The file cannot be read or mapped, is shorter than the fixed pages, or its file header
    /// is not a valid VOD 2 header (nothing of the file can be read without it).
    pub fn open(path: &Path) -> Result<Vod2File, StoreError> {
        let file = File::open(path).map_err(StoreError::io_path("cannot open", path))?;
        let file_len = file
            .metadata()
            .map_err(StoreError::io_path("cannot stat", path))?
            .len();
        if file_len < DATA_START {
            return Err(FormatError::Truncated {
                what: "VOD 2 file",
                offset: 0,
                needed: DATA_START,
                available: file_len,
            }
            .into());
        }
        let header = FileHeader::decode(&read_exact_at(&file, path, 0, HEADER_LEN)?)?;
        let mut slots = [SlotState::Unused, SlotState::Unused];
        for (state, at) in slots.iter_mut().zip(SLOT_OFFSETS) {
            let bytes = read_exact_at(&file, path, at, SLOT_LEN)?;
            *state = match HeaderSlot::decode(&bytes, at) {
                Ok(s) if s.committed_len > file_len => SlotState::Invalid(format!(
                    "slot at {at} names {} committed bytes, the file has {file_len}",
                    s.committed_len
                )),
                Ok(s) => with_appended_bytes(&file, path, at, s)?,
                Err(_) if bytes.iter().all(|&b| b == 0) => SlotState::Unused,
                Err(e) => SlotState::Invalid(e.to_string()),
            };
        }
        // The valid slot with the highest sequence number names the head.
        let head_slot = slots
            .iter()
            .filter_map(|s| match s {
                SlotState::Valid(s) => Some(*s),
                _ => None,
            })
            .max_by_key(|s| s.seq);
        let committed = head_slot.map_or(file_len, |s| s.committed_len);
        let map = Arc::new(Region::whole(
            Mapping::new(&file, committed).map_err(StoreError::io_path("cannot map", path))?,
        ));
        Ok(Vod2File {
            path: path.to_path_buf(),
            header: Arc::new(header),
            map,
            file_len,
            slots,
            head_slot,
        })
    }

    /// The fixed header.
    pub fn header(&self) -> &FileHeader {
        &self.header
    }

    /// The file's length on disk.
    pub fn file_len(&self) -> u64 {
        self.file_len
    }

    /// Slots A and B as read.
    pub fn slots(&self) -> &[SlotState; 2] {
        &self.slots
    }

    /// The valid slot with the highest sequence number, if any.
    pub fn head_slot(&self) -> Option<HeaderSlot> {
        self.head_slot
    }

    /// The mapped committed region (from offset 0).
    pub fn mapped(&self) -> &[u8] {
        self.map.bytes()
    }

    /// The version whose commit record is at `commit_at`.
    ///
    /// # Errors
    /// Its commit chain or index checkpoint is malformed.
    pub fn snapshot_at(&self, commit_at: u64) -> Result<Snapshot, StoreError> {
        Snapshot::load(self.header.clone(), self.map.clone(), commit_at)
    }

    /// The stored brick record at `offset`, whatever version points at it.
    ///
    /// # Errors
    /// Its header or bounds are invalid.
    pub fn stored_at(&self, offset: u64) -> Result<StoredBrick<'_>, StoreError> {
        stored_record(&self.map, &self.header.layout, offset)
    }

    /// The file opened at the version the slots name as the newest durable one.
    ///
    /// # Errors
    /// No slot is valid, or the head's commit chain or index checkpoint is malformed.
    pub fn into_head(self) -> Result<Vod2, StoreError> {
        let slot = self.head_slot.ok_or_else(|| {
            let problems: Vec<String> = self
                .slots
                .iter()
                .zip(SLOT_OFFSETS)
                .map(|(s, at)| match s {
                    SlotState::Invalid(why) => why.clone(),
                    _ => format!("slot at {at} was never written"),
                })
                .collect();
            StoreError::from(FormatError::invalid(
                "header slots",
                format!("no valid slot: {}", problems.join("; ")),
            ))
        })?;
        for (state, at) in self.slots.iter().zip(SLOT_OFFSETS) {
            if let SlotState::Invalid(why) = state {
                tracing::warn!(
                    path = %self.path.display(),
                    slot = at,
                    version = slot.version,
                    "a header slot is not valid ({why}); opening the version the other slot names"
                );
            }
        }
        let head = self.snapshot_at(slot.commit)?;
        self.into_vod2(slot, head)
    }

    /// The file opened at the version whose commit record is at `commit_at`, as if it were
    /// the head: to read (never to append to) a version the slots do not name, such as the
    /// newest intact one of a damaged file.
    ///
    /// # Errors
    /// No valid commit record there, or its chain or index checkpoint is malformed.
    pub fn into_version(self, commit_at: u64) -> Result<Vod2, StoreError> {
        let head = self.snapshot_at(commit_at)?;
        let slot = HeaderSlot {
            seq: self.head_slot.map_or(0, |s| s.seq),
            commit: commit_at,
            committed_len: self.map.len(),
            version: head.version,
            appended: None,
        };
        self.into_vod2(slot, head)
    }

    fn into_vod2(self, slot: HeaderSlot, head: Snapshot) -> Result<Vod2, StoreError> {
        let head = Arc::new(head);
        check_slot(&slot, &head)?;
        Ok(Vod2 {
            path: self.path,
            header: self.header,
            map: self.map,
            file_len: self.file_len,
            head_slot: slot,
            head,
        })
    }
}

impl Vod2 {
    /// Opens the newest durable version of a VOD 2 file.
    ///
    /// # Errors
    /// The file cannot be read, is not VOD 2, or its header, slots, head commit or index
    /// checkpoint are malformed.
    pub fn open(path: &Path) -> Result<Vod2, StoreError> {
        Vod2File::open(path)?.into_head()
    }

    /// The file after a commit this process appended (`slot`, as [`Vod2Writer::commit`]
    /// returned it): maps the new committed length and builds the new head from the current one
    /// (its decoded index chunks and blob index carried over, the commit's changes added), so
    /// an edit does not pay for reopening the file.
    ///
    /// [`Vod2Writer::commit`]: super::Vod2Writer::commit
    ///
    /// # Errors
    /// The file cannot be mapped, or the new commit record is malformed.
    pub fn advance(&self, slot: HeaderSlot) -> Result<Vod2, StoreError> {
        let file_len = std::fs::metadata(&self.path)
            .map_err(StoreError::io_path("cannot stat", &self.path))?
            .len();
        if slot.committed_len > file_len {
            return Err(StoreError::Internal(format!(
                "{}: commit names {} bytes, the file has {file_len}",
                self.path.display(),
                slot.committed_len
            )));
        }
        // The file's next versions are seen through the same mapping while it has room (see
        // `mapping.rs`); the room grows with the file, so it is remapped rarely.
        let grown = self
            .map
            .whole_mapping()
            .and_then(|m| m.grown(slot.committed_len));
        let mapping = match grown {
            Some(m) => m,
            None => {
                let file = File::open(&self.path)
                    .map_err(StoreError::io_path("cannot open", &self.path))?;
                Mapping::with_room(&file, slot.committed_len, room_to_grow(slot.committed_len))
                    .map_err(StoreError::io_path("cannot map", &self.path))?
            }
        };
        let map = Arc::new(Region::whole(mapping));
        let head = Arc::new(self.head.extend(map.clone(), slot.commit)?);
        check_slot(&slot, &head)?;
        Ok(Vod2 {
            path: self.path.clone(),
            header: self.header.clone(),
            map,
            file_len,
            head_slot: slot,
            head,
        })
    }

    /// A version of a volume kept elsewhere (an object store), read through `map`, a sparse
    /// local mirror of its committed region whose holes `fill` fetches on first use. `name`
    /// stands for the file in messages. Reads the head's commit record and the fixed part of
    /// its index checkpoint, nothing else.
    ///
    /// # Errors
    /// Those records cannot be fetched or are malformed, or `slot` names another version.
    pub(crate) fn open_mirror(
        name: PathBuf,
        header: FileHeader,
        slot: HeaderSlot,
        map: Mapping,
        fill: Arc<dyn Fill>,
    ) -> Result<Vod2, StoreError> {
        let map = Arc::new(Region::filled(map, fill));
        let header = Arc::new(header);
        let head = Arc::new(Snapshot::load(header.clone(), map.clone(), slot.commit)?);
        check_slot(&slot, &head)?;
        Ok(Vod2 {
            path: name,
            header,
            file_len: slot.committed_len,
            map,
            head_slot: slot,
            head,
        })
    }

    /// The mirrored volume after its head moved to `slot` (see [`Vod2::open_mirror`]), built
    /// from the current head as [`Vod2::advance`] does.
    ///
    /// # Errors
    /// The new commit records cannot be fetched or are malformed.
    pub(crate) fn advance_mirror(
        &self,
        slot: HeaderSlot,
        map: Mapping,
        fill: Arc<dyn Fill>,
    ) -> Result<Vod2, StoreError> {
        let map = Arc::new(Region::filled(map, fill));
        let head = Arc::new(self.head.extend(map.clone(), slot.commit)?);
        check_slot(&slot, &head)?;
        Ok(Vod2 {
            path: self.path.clone(),
            header: self.header.clone(),
            file_len: slot.committed_len,
            map,
            head_slot: slot,
            head,
        })
    }

    /// The commit record at `at`, decoded and checked, with its bytes (changes included).
    ///
    /// # Errors
    /// No valid commit record there, or it cannot be fetched.
    pub fn commit_at(&self, at: u64) -> Result<(CommitHeader, &[u8]), StoreError> {
        commit_record(&self.map, at)
    }

    /// The committed length: the bytes versions of this file may reference.
    pub fn committed_len(&self) -> u64 {
        self.map.len()
    }

    /// The header slot the head version was found through.
    pub fn head_slot(&self) -> HeaderSlot {
        self.head_slot
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The fixed header.
    pub fn header(&self) -> &FileHeader {
        &self.header
    }

    /// Dimensions, brick edge and voxel type.
    pub fn layout(&self) -> &VolumeLayout {
        &self.header.layout
    }

    /// The file's length on disk (bytes past the committed length are an unfinished commit).
    pub fn file_len(&self) -> u64 {
        self.file_len
    }

    /// The newest version.
    pub fn head(&self) -> Arc<Snapshot> {
        self.head.clone()
    }

    /// The newest version, borrowed.
    pub fn head_ref(&self) -> &Snapshot {
        &self.head
    }

    /// An older version, while its bricks are still in the file.
    ///
    /// # Errors
    /// No such version, or its records are malformed.
    pub fn version(&self, version: u64) -> Result<Arc<Snapshot>, StoreError> {
        if version == self.head.version {
            return Ok(self.head.clone());
        }
        let mut at = self.head.commit_offset;
        loop {
            let (h, _) = commit_record(&self.map, at)?;
            if h.version == version {
                return Ok(Arc::new(Snapshot::load(
                    self.header.clone(),
                    self.map.clone(),
                    at,
                )?));
            }
            if h.parent == 0 || h.version < version {
                return Err(StoreError::Absent(format!(
                    "version {version} is not in this file (head is {})",
                    self.head.version
                )));
            }
            at = h.parent;
        }
    }

    /// The version whose commit record is at `commit_at` (an offset from the history).
    ///
    /// # Errors
    /// No valid commit record there.
    pub fn snapshot_at(&self, commit_at: u64) -> Result<Snapshot, StoreError> {
        Snapshot::load(self.header.clone(), self.map.clone(), commit_at)
    }

    /// The commit records from the head back to the first, newest first.
    ///
    /// # Errors
    /// A record on the chain is malformed.
    pub fn commits(&self) -> Result<Vec<(u64, CommitHeader)>, StoreError> {
        match self.commits_until_damage() {
            (commits, None) => Ok(commits),
            (_, Some(e)) => Err(e),
        }
    }

    /// The commit records from the head back to the first, newest first, as far as they
    /// read: and, when the walk stopped at a record that does not, why (the error names the
    /// record's offset). The versions after the damage are all the history a server can list.
    pub fn commits_until_damage(&self) -> (Vec<(u64, CommitHeader)>, Option<StoreError>) {
        let mut out: Vec<(u64, CommitHeader)> = Vec::new();
        let mut at = self.head.commit_offset;
        loop {
            let decoded = commit_record(&self.map, at);
            let h = match decoded {
                Ok((h, _)) => h,
                Err(e) => return (out, Some(e)),
            };
            if let Some((child_at, child)) = out.last() {
                if h.version.checked_add(1) != Some(child.version) {
                    let e = FormatError::invalid(
                        "commit chain",
                        format!(
                            "commit at {child_at} is version {}, its parent at {at} is version {}",
                            child.version, h.version
                        ),
                    );
                    return (out, Some(e.into()));
                }
            }
            out.push((at, h));
            if h.parent == 0 {
                return (out, None);
            }
            at = h.parent;
        }
    }

    /// The mapped bytes of the committed region.
    pub fn mapped(&self) -> &[u8] {
        self.map.bytes()
    }
}

/// One version of a volume: an immutable index over the shared mapping.
#[derive(Debug)]
pub struct Snapshot {
    header: Arc<FileHeader>,
    map: Arc<Region>,
    /// The version.
    pub version: u64,
    /// When it was committed (Unix milliseconds).
    pub timestamp_ms: u64,
    commit_offset: u64,
    index: Arc<IndexChunks>,
    /// Entries changed by the commits after the checkpoint: node index -> raw entry.
    overlay: HashMap<u64, u64>,
    /// Content hash -> entry, built on first use by [`Snapshot::find_by_hash`] (or carried over
    /// from the parent version and extended).
    by_hash: OnceLock<HashIndex>,
    /// Commits replayed on top of the checkpoint.
    chain_len: usize,
}

impl Snapshot {
    fn load(
        header: Arc<FileHeader>,
        map: Arc<Region>,
        commit_at: u64,
    ) -> Result<Snapshot, StoreError> {
        let layout = &header.layout;
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
        let index = Arc::new(IndexChunks::open(&map, checkpoint_at, layout.node_count())?);
        let mut overlay = HashMap::new();
        // The checkpoint holds the state after its own commit: apply only the later ones.
        for record in chain.iter().rev().skip(1) {
            apply_changes(record, layout, &mut overlay, |_| ())?;
        }
        Ok(Snapshot {
            version: head.version,
            timestamp_ms: head.timestamp_ms,
            commit_offset: commit_at,
            index,
            overlay,
            chain_len: chain.len() - 1,
            by_hash: OnceLock::new(),
            header,
            map,
        })
    }

    /// The version whose commit record is at `commit_at` in `map`, a child of this one: this
    /// version's index plus the commit's changes (or, when the commit wrote a checkpoint or is
    /// not a child of this version, loaded from the file as [`Vod2::open`] does).
    fn extend(&self, map: Arc<Region>, commit_at: u64) -> Result<Snapshot, StoreError> {
        let (h, record) = commit_record(&map, commit_at)?;
        let child =
            h.parent == self.commit_offset && self.version.checked_add(1) == Some(h.version);
        if h.checkpoint != 0 || !child {
            let snap = Snapshot::load(self.header.clone(), map.clone(), commit_at)?;
            // A child that wrote a checkpoint still finds what its parents held by hash.
            if child {
                self.hand_down_hashes(&snap, CommitHeader::changes(record).map(|(_, e)| e))?;
            }
            return Ok(snap);
        }
        let layout = self.layout();
        let mut overlay = self.overlay.clone();
        let mut added = Vec::new();
        apply_changes(record, layout, &mut overlay, |entry| added.push(entry))?;
        let snap = Snapshot {
            version: h.version,
            timestamp_ms: h.timestamp_ms,
            commit_offset: commit_at,
            index: self.index.clone(),
            overlay,
            chain_len: self.chain_len + 1,
            by_hash: OnceLock::new(),
            header: self.header.clone(),
            map,
        };
        self.hand_down_hashes(&snap, added.into_iter())?;
        Ok(snap)
    }

    /// Gives `child` this version's blob index (when it was built) plus the entries its commit
    /// `added`: bricks replaced by the commit stay findable by hash.
    fn hand_down_hashes(
        &self,
        child: &Snapshot,
        added: impl Iterator<Item = u64>,
    ) -> Result<(), StoreError> {
        let Some(parent_hashes) = self.by_hash.get() else {
            return Ok(());
        };
        let mut hashes = parent_hashes.child();
        let (voxel_type, mapped) = (self.layout().voxel_type(), child.map.len());
        for raw in added {
            let entry = NodeEntry::decode(raw, voxel_type, mapped)?;
            hashes.insert(child.entry_hash(entry)?, entry);
        }
        let _ = child.by_hash.set(hashes);
        Ok(())
    }

    /// Dimensions, brick edge and voxel type.
    pub fn layout(&self) -> &VolumeLayout {
        &self.header.layout
    }

    /// The file's fixed header.
    pub fn header(&self) -> &FileHeader {
        &self.header
    }

    /// Offset of this version's commit record.
    pub fn commit_offset(&self) -> u64 {
        self.commit_offset
    }

    /// Offset and length of the index checkpoint this version builds on (reads every chunk
    /// reference).
    ///
    /// # Errors
    /// A chunk reference is invalid.
    pub fn checkpoint_span(&self) -> Result<(u64, u64), StoreError> {
        let n_nodes = self.layout().node_count();
        self.map
            .ensure(self.index.base, Checkpoint::directory_len(n_nodes))?;
        let cp = self.index.checkpoint(self.map.bytes())?;
        Ok((self.index.base, cp.total_len()?))
    }

    /// Every index entry of this version in node order, raw (as a checkpoint stores them): the
    /// checkpoint's chunks (each checked against its hash when first used) with the overlay
    /// applied (each entry checked when its commit was read). What a new checkpoint is written
    /// from: copying chunks costs a fraction of looking up and decoding each entry.
    ///
    /// # Errors
    /// A checkpoint chunk fails its hash, or the chunks do not hold one entry per node.
    pub fn raw_entries(&self) -> Result<Vec<u64>, StoreError> {
        let nodes = self.layout().node_count();
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
        for (&node, &raw) in &self.overlay {
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
        let raw = match self.overlay.get(&node) {
            Some(&raw) => raw,
            None => self.index.entry(&self.map, node)?,
        };
        Ok(NodeEntry::decode(raw, layout.voxel_type(), self.map.len())?)
    }

    /// The index entry of a brick.
    ///
    /// # Errors
    /// See [`Snapshot::entry_at`]; the key must come from this volume's layout.
    pub fn entry(&self, key: BrickKey) -> Result<NodeEntry, StoreError> {
        let layout = self.layout();
        if !layout.contains(key) {
            return Err(StoreError::OutOfRange(format!(
                "brick {key} is outside the volume"
            )));
        }
        self.entry_at(layout.node_index(key))
    }

    /// The stored form of the brick behind an entry, without decoding it.
    ///
    /// # Errors
    /// The brick header or its payload bounds are invalid.
    pub fn stored_entry(&self, entry: NodeEntry) -> Result<StoredBrick<'_>, StoreError> {
        match entry {
            NodeEntry::Constant(v) => Ok(StoredBrick::Constant(v)),
            NodeEntry::Stored(offset) => stored_record(&self.map, self.layout(), offset),
        }
    }

    /// The stored form of a brick, without decoding it.
    ///
    /// # Errors
    /// See [`Snapshot::entry`] and [`Snapshot::stored_entry`].
    pub fn stored(&self, key: BrickKey) -> Result<StoredBrick<'_>, StoreError> {
        self.stored_entry(self.entry(key)?)
    }

    /// Decodes a brick into `out` (exactly one brick's bytes) and checks its content hash.
    ///
    /// # Errors
    /// See [`Snapshot::stored`]; also a payload that does not decode or does not match its hash.
    pub fn read_into(&self, key: BrickKey, out: &mut [u8]) -> Result<(), StoreError> {
        let stored = self.stored(key)?;
        decode_stored(&stored, self.layout(), out)
    }

    /// A brick's voxels: a constant as it is stored, anything else decoded (and checked).
    ///
    /// # Errors
    /// See [`Snapshot::read_into`].
    pub fn voxels(&self, key: BrickKey) -> Result<super::BrickVoxels, StoreError> {
        Ok(match self.stored(key)? {
            StoredBrick::Constant(v) => super::BrickVoxels::Constant(v),
            record => super::BrickVoxels::Data(decode_stored_new(&record, self.layout())?),
        })
    }

    /// Decodes a brick into a new buffer.
    ///
    /// # Errors
    /// See [`Snapshot::read_into`].
    pub fn read(&self, key: BrickKey) -> Result<Vec<u8>, StoreError> {
        let mut out = vec![0u8; self.layout().brick_bytes()];
        self.read_into(key, &mut out)?;
        Ok(out)
    }

    /// An entry with content hash `hash` among the bricks of this version and of every older
    /// version the file still holds, if any. The first call scans the oldest version's index
    /// and the commit records since (reading brick headers, not payloads) and keeps a hash
    /// table; a version built from its parent by [`Vod2::advance`] inherits the parent's.
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
            records.push(record);
            if h.parent == 0 {
                break at;
            }
            at = h.parent;
        };
        let oldest = Snapshot::load(self.header.clone(), self.map.clone(), oldest)?;
        let mut map = HashMap::new();
        let mut constants = std::collections::HashSet::new();
        let mut add = |entry: NodeEntry| -> Result<(), StoreError> {
            let first_sight = match entry {
                NodeEntry::Constant(v) => constants.insert(v),
                NodeEntry::Stored(_) => true,
            };
            if first_sight {
                map.entry(self.entry_hash(entry)?).or_insert(entry);
            }
            Ok(())
        };
        for node in 0..self.layout().node_count() {
            add(oldest.entry_at(node)?)?;
        }
        let (voxel_type, mapped) = (self.layout().voxel_type(), self.map.len());
        for record in records.iter().rev() {
            for (_, raw) in CommitHeader::changes(record) {
                add(NodeEntry::decode(raw, voxel_type, mapped)?)?;
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

/// The brick record at `offset` of the mapped bytes `mapped`: its header checked, its payload
/// and (in a checked record) the payload's checksum bounds-checked, nothing decoded.
fn stored_record<'m>(
    map: &'m Region,
    layout: &VolumeLayout,
    offset: u64,
) -> Result<StoredBrick<'m>, StoreError> {
    // A record is its header, its payload and (checked records) the payload's checksum, in a
    // row: filled in one go when they share a page, which they mostly do.
    map.ensure(offset, BRICK_HEADER_LEN as u64)?;
    let fields = Fields::new("brick record", map.bytes(), 0);
    let at = usize::try_from(offset).map_err(|_| {
        FormatError::invalid(
            "brick record",
            format!("offset {offset} is not addressable"),
        )
    })?;
    let header = BrickHeader::decode(fields.slice(at, BRICK_HEADER_LEN)?, offset, layout)?;
    let start = at + BRICK_HEADER_LEN;
    let tail = if header.checked { PAYLOAD_CHECK_LEN } else { 0 };
    map.ensure(start as u64, (header.stored_len as usize + tail) as u64)?;
    let payload = fields.slice(start, header.stored_len as usize)?;
    let checksum = match header.checked {
        false => None,
        true => {
            let check = fields.slice(start + payload.len(), PAYLOAD_CHECK_LEN)?;
            Some(u32::from_le_bytes([check[0], check[1], check[2], check[3]]))
        }
    };
    Ok(StoredBrick::Record {
        offset,
        header,
        payload,
        checksum,
    })
}

/// The commit record at `at` (its fixed part fetched first for the change count, then the
/// whole record), decoded and checked.
///
/// # Errors
/// `at` lies past the committed region, the record cannot be fetched, or it is malformed.
fn commit_record(map: &Region, at: u64) -> Result<(CommitHeader, &[u8]), StoreError> {
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
        map.ensure(
            at,
            CommitHeader::record_len(n_changes.min(avail.len() as u64)),
        )?;
    }
    Ok(CommitHeader::decode(avail, at)?)
}

/// Checks that the head loaded through `slot` is the version the slot names.
fn check_slot(slot: &HeaderSlot, head: &Snapshot) -> Result<(), StoreError> {
    if head.version != slot.version {
        return Err(FormatError::invalid(
            "header slot",
            format!(
                "names version {}, its commit record says {}",
                slot.version, head.version
            ),
        )
        .into());
    }
    Ok(())
}

/// Applies a commit record's changes to `overlay` (node index -> raw entry), checking each node
/// against the layout, and hands each entry to `added`.
fn apply_changes(
    record: &[u8],
    layout: &VolumeLayout,
    overlay: &mut HashMap<u64, u64>,
    mut added: impl FnMut(u64),
) -> Result<(), StoreError> {
    for (node, entry) in CommitHeader::changes(record) {
        if node >= layout.node_count() {
            return Err(FormatError::invalid(
                "commit record",
                format!(
                    "change to node {node}, the volume has {}",
                    layout.node_count()
                ),
            )
            .into());
        }
        overlay.insert(node, entry);
        added(entry);
    }
    Ok(())
}

/// Content hash -> entry for [`Snapshot::find_by_hash`]: a shared base plus what later versions
/// added, so a commit extends its parent's table instead of rescanning the index. Entries of
/// bricks an edit replaced stay findable: their records are still in the file, and content
/// named by its hash is the same whichever version holds it.
#[derive(Debug)]
struct HashIndex {
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

/// A range of a mapping that keeps the mapping alive: lets a response carry mapped bytes
/// without copying them.
#[derive(Debug)]
struct MappedRange {
    map: Arc<Region>,
    start: usize,
    end: usize,
}

impl AsRef<[u8]> for MappedRange {
    fn as_ref(&self) -> &[u8] {
        &self.map.bytes()[self.start..self.end]
    }
}

impl Snapshot {
    /// The payload of a brick record of this snapshot (from [`Snapshot::stored`]), verified,
    /// as bytes to send as they are: checked against the checksum stored after it, or, in a
    /// record written before payload checksums, decoded and checked against its content hash
    /// the first time and then remembered by `verified` (see
    /// [`DecodedBricks::verify_payload`]). Payloads up to [`SHARE_PAYLOADS_FROM`] are copied,
    /// larger ones are shared slices of the mapping (no copy; the mapping lives as long as the
    /// bytes do).
    ///
    /// [`DecodedBricks::verify_payload`]: super::decoded::DecodedBricks::verify_payload
    ///
    /// # Errors
    /// [`StoreError::Corrupt`]: the payload is not what was stored. [`StoreError::Internal`]:
    /// a constant (no payload), or a record read from another snapshot's mapping.
    pub fn verified_payload(
        &self,
        stored: &StoredBrick<'_>,
        verified: &super::decoded::DecodedBricks,
    ) -> Result<bytes::Bytes, StoreError> {
        let StoredBrick::Record {
            offset, payload, ..
        } = *stored
        else {
            return Err(StoreError::Internal(
                "a constant brick has no payload to send".into(),
            ));
        };
        let mapped = self.map.bytes();
        let start = offset as usize + BRICK_HEADER_LEN;
        let end = start + payload.len();
        // The bytes checked must be the bytes sent: the payload is this mapping's slice.
        if mapped.get(start..end).map(<[u8]>::as_ptr) != Some(payload.as_ptr()) {
            return Err(StoreError::Internal(format!(
                "the brick record at {offset} was not read from this snapshot's mapping"
            )));
        }
        verified.verify_payload(stored, self.layout())?;
        if end - start < SHARE_PAYLOADS_FROM {
            return Ok(bytes::Bytes::copy_from_slice(payload));
        }
        Ok(bytes::Bytes::from_owner(MappedRange {
            map: self.map.clone(),
            start,
            end,
        }))
    }
}

/// Payloads from this size on are served as shared slices of the mapping; smaller ones are
/// copied. Sharing costs an allocation and two updates of the mapping's reference count, which
/// every core serving bricks touches; for a typical lz4 brick (a few hundred bytes) the copy is
/// cheaper.
pub const SHARE_PAYLOADS_FROM: usize = 4096;

/// A version's level 0 as the source of a build (same brick size): rebuilding a file from its
/// head drops every older version and all garbage.
#[derive(Debug)]
pub struct SnapshotSource {
    snap: Arc<Snapshot>,
    errors: super::pyramid::FirstError,
}

impl SnapshotSource {
    /// A source reading `snap`'s level 0.
    pub fn new(snap: Arc<Snapshot>) -> Self {
        SnapshotSource {
            snap,
            errors: Default::default(),
        }
    }

    /// # Errors
    /// The first brick that failed to read during the build.
    pub fn finish(self) -> Result<(), StoreError> {
        self.errors.finish()
    }
}

impl super::BrickSource for SnapshotSource {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        if let Err(e) = self.snap.read_into(key, out) {
            self.errors.record(e);
        }
    }

    fn constant(&self, key: BrickKey) -> Option<u16> {
        match self.snap.entry(key) {
            Ok(NodeEntry::Constant(v)) => Some(v),
            _ => None,
        }
    }
}

/// The entries of an index checkpoint, decoded chunk by chunk on first use and then kept.
#[derive(Debug)]
struct IndexChunks {
    base: u64,
    n_nodes: u64,
    chunks: Vec<OnceLock<Box<[u64]>>>,
}

impl IndexChunks {
    /// Checks the checkpoint's fixed fields; chunks are checked when first used.
    fn open(map: &Region, base: u64, n_nodes: u64) -> Result<IndexChunks, StoreError> {
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

    fn entry(&self, map: &Region, node: u64) -> Result<u64, StoreError> {
        let chunk = self.chunk(map, (node / CHUNK_ENTRIES) as usize)?;
        Ok(chunk[(node % CHUNK_ENTRIES) as usize])
    }

    /// Chunk `c`'s entries, decoded and checked on first use.
    fn chunk(&self, map: &Region, c: usize) -> Result<&[u64], StoreError> {
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

    fn decode_chunk(&self, map: &Region, c: u64) -> Result<Box<[u64]>, StoreError> {
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

/// Decodes a stored brick into `out` and verifies it against its content hash.
///
/// # Errors
/// The payload does not decode, or decodes to bytes whose hash differs from the header's.
pub fn decode_stored(
    stored: &StoredBrick<'_>,
    layout: &VolumeLayout,
    out: &mut [u8],
) -> Result<(), StoreError> {
    match *stored {
        StoredBrick::Constant(v) => codec::fill_constant(out, v, layout.voxel_type()),
        StoredBrick::Record {
            offset,
            header,
            payload,
            ..
        } => {
            codec::decode(header.codec, payload, out, offset)?;
            check_content(out, header.hash, offset)?;
        }
    }
    Ok(())
}

/// A stored brick's voxels in a new buffer, verified against its content hash
/// ([`decode_stored`] into a buffer it makes).
///
/// # Errors
/// As [`decode_stored`].
pub fn decode_stored_new(
    stored: &StoredBrick<'_>,
    layout: &VolumeLayout,
) -> Result<Vec<u8>, StoreError> {
    match *stored {
        StoredBrick::Constant(_) => {
            let mut out = vec![0; layout.brick_bytes()];
            decode_stored(stored, layout, &mut out)?;
            Ok(out)
        }
        StoredBrick::Record {
            offset,
            header,
            payload,
            ..
        } => {
            let out = codec::decode_new(header.codec, payload, layout.brick_bytes(), offset)?;
            check_content(&out, header.hash, offset)?;
            Ok(out)
        }
    }
}

/// Whether decoded bytes have the content hash their record's header gives.
fn check_content(decoded: &[u8], expected: u64, offset: u64) -> Result<(), StoreError> {
    let hash = content_hash(decoded);
    if hash != expected {
        return Err(StoreError::corrupt(
            offset,
            format!("content hash {expected:#018x}"),
            format!("{hash:#018x}"),
        ));
    }
    Ok(())
}

/// Addresses reserved past a file's end when an edit maps its new version: half the file, at
/// least 64 MiB, so a file growing by edits is remapped a number of times logarithmic in its
/// growth (a 1 GiB file by 4 KiB commits: every 131,072 commits or more).
fn room_to_grow(len: u64) -> u64 {
    (len / 2).max(64 << 20)
}
