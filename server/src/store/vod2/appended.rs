//! The appended-bytes check: a header slot may carry the checksum of the bytes appended with it,
//! which were synced together; a slot whose bytes do not match it is not valid.

use super::SlotState;
use crate::store::StoreError;
use isovox_proto::vod2::HeaderSlot;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

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
pub(super) fn with_appended_bytes(
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
