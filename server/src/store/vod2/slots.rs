//! Opening a VOD 2 file without choosing a version: its fixed header and both header slots read
//! with `pread` and validated, the committed region mapped; then the version the slots name.

use super::appended::with_appended_bytes;
use super::bricks::stored_record;
use super::{Snapshot, StoredBrick, Vod2};
use crate::store::mapping::Mapping;
use crate::store::region::MappedRegion;
use crate::store::StoreError;
use isovox_proto::vod2::{FileHeader, HeaderSlot, DATA_PAGE, DATA_START, SLOT_LEN, SLOT_OFFSETS};
use isovox_proto::FormatError;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

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
    map: Arc<MappedRegion>,
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
        let header = FileHeader::decode(&read_exact_at(&file, path, 0, DATA_PAGE)?)?;
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
        let map = Arc::new(MappedRegion::whole(
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

    /// [`Vod2File::stored_at`] for a record of the stream whose pyramid has `layout`.
    ///
    /// # Errors
    /// Its header or bounds are invalid.
    pub fn stored_as(
        &self,
        offset: u64,
        layout: &isovox_proto::VolumeLayout,
    ) -> Result<StoredBrick<'_>, StoreError> {
        stored_record(&self.map, layout, offset)
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

fn read_exact_at(file: &File, path: &Path, offset: u64, len: usize) -> Result<Vec<u8>, StoreError> {
    let mut buf = vec![0u8; len];
    file.read_exact_at(&mut buf, offset)
        .map_err(StoreError::io_path("cannot read", path))?;
    Ok(buf)
}

/// Checks that the head loaded through `slot` is the version the slot names.
pub(super) fn check_slot(slot: &HeaderSlot, head: &Snapshot) -> Result<(), StoreError> {
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
