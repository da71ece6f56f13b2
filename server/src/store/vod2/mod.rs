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
//!
//! Layout:
//! - this file: [`Vod2`], a file open at its head version, and moving that head on.
//! - [`slots`]: opening a file without choosing a version ([`Vod2File`]), and validating its two
//!   header slots.
//! - [`appended`]: the check of the bytes a slot says were synced with it.
//! - [`snapshot`]: one version's index ([`Snapshot`]): entry lookups and content hashes.
//! - [`checkpoint`]: how a version's index is built: the newest checkpoint at or before it, its
//!   chunks decoded on first use, and the overlay of the changes of the commits since.
//! - [`bricks`]: brick records: reading, checking and decoding them, serving payloads.

mod appended;
mod bricks;
mod checkpoint;
mod slots;
mod snapshot;

pub(crate) use appended::appended_checksum;
pub use bricks::{
    decode_stored, decode_stored_new, verify_stored, PayloadCheck, SnapshotSource, StoredBrick,
    SHARE_PAYLOADS_FROM,
};
pub use slots::{SlotState, Vod2File};
pub use snapshot::Snapshot;

use super::mapping::Mapping;
use super::region::{Fill, MappedRegion};
use super::StoreError;
use isovox_proto::vod2::{CommitHeader, FileHeader, HeaderSlot};
use isovox_proto::{FormatError, VolumeLayout};
use slots::check_slot;
use snapshot::commit_record;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// An open VOD 2 file.
#[derive(Debug)]
pub struct Vod2 {
    path: PathBuf,
    header: Arc<FileHeader>,
    map: Arc<MappedRegion>,
    file_len: u64,
    head_slot: HeaderSlot,
    head: Arc<Snapshot>,
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
        let map = Arc::new(MappedRegion::whole(mapping));
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
        let map = Arc::new(MappedRegion::filled(map, fill));
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
        let map = Arc::new(MappedRegion::filled(map, fill));
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

/// Addresses reserved past a file's end when an edit maps its new version: half the file, at
/// least 64 MiB, so a file growing by edits is remapped a number of times logarithmic in its
/// growth (a 1 GiB file by 4 KiB commits: every 131,072 commits or more).
fn room_to_grow(len: u64) -> u64 {
    (len / 2).max(64 << 20)
}
