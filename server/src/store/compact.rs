//! Compaction: rewriting a file with only its head version, so that the bricks older versions
//! and edits left behind stop taking space.
//!
//! The head's distinct brick records are copied as they are (no recompression; each payload
//! verified first, so damage is never copied, and given a checksum if it had none) into
//! `NAME.vod.compact` beside the file, with one full index checkpoint and one commit numbered like
//! the head; that file is synced and renamed over the original, then the directory is synced.
//! A crash at any point leaves either the old file or the new one, each whole. Readers that still
//! map the old file keep reading it: the rename does not touch its bytes.

use super::remote::{collect_garbage, upload, RemoteVolume};
use super::transaction::{CheckpointPolicy, Transaction};
use super::writer::Vod2Writer;
use super::{Snapshot, StoreError, Vod2};
use crate::progress::Progress;
use isovox_proto::vod2::NodeEntry;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// What a compaction did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CompactReport {
    /// The head version (the compacted file's only one).
    pub version: u64,
    /// The file's size before.
    pub bytes_before: u64,
    /// The file's size after.
    pub bytes_after: u64,
    /// Distinct brick records copied.
    pub bricks: u64,
    /// How long it took.
    pub elapsed: std::time::Duration,
}

/// The temporary file a compaction of `path` writes before renaming it over `path`.
pub fn compact_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".compact");
    path.with_file_name(name)
}

/// Rewrites the file `vod` was opened from with only the version `head` (normally its head),
/// and renames the result over it. The caller makes sure no writer appends meanwhile.
///
/// # Errors
/// Reading the index or a brick record fails (a damaged payload is not copied), or the new
/// file cannot be written, synced or renamed (the original is then untouched).
pub fn compact(
    vod: &Vod2,
    head: &Snapshot,
    progress: &dyn Progress,
) -> Result<CompactReport, StoreError> {
    let start = Instant::now();
    let path = vod.path();
    let (bricks, bytes_after) = write_version_as(head, path, &compact_path(path), progress)?;
    Ok(CompactReport {
        version: head.version,
        bytes_before: vod.file_len(),
        bytes_after,
        bricks,
        elapsed: start.elapsed(),
    })
}

/// Compacts a volume kept in an object store (`vod`, as `remote` serves it): writes the head
/// version alone into a local file, uploads it as the volume's only segment and replaces the
/// head with it (conditional on the head it compacted, so a commit made meanwhile is never
/// lost: the compaction is refused instead), then deletes the objects nothing references that
/// are older than `grace`.
///
/// # Errors
/// The head moved ([`StoreError::HeadMoved`]), or reading, writing or the store fails.
pub fn compact_remote(
    remote: &RemoteVolume,
    vod: &Vod2,
    grace: Duration,
) -> Result<CompactReport, StoreError> {
    let start = Instant::now();
    let head = vod.head();
    let (stored, etag) = remote.read_head()?;
    if stored.version != head.version {
        return Err(StoreError::HeadMoved {
            url: remote.bucket().url().to_string(),
        });
    }
    let tmp = std::env::temp_dir().join(format!(
        "isovox-compact-{}-{}.vod",
        remote.name(),
        std::process::id()
    ));
    let written = write_version(&head, &tmp, &crate::progress::Silent).and_then(|bricks| {
        let len = std::fs::metadata(&tmp)
            .map_err(StoreError::io_path("cannot stat", &tmp))?
            .len();
        upload(remote.bucket(), &tmp, Some(&etag))?;
        Ok((bricks, len))
    });
    let _ = std::fs::remove_file(&tmp);
    let (bricks, bytes_after) = written?;
    let deleted = collect_garbage(remote.bucket(), grace)?;
    tracing::info!(volume = %remote.name(), deleted, "compacted; unreferenced objects past the grace period deleted");
    Ok(CompactReport {
        version: head.version,
        bytes_before: vod.committed_len(),
        bytes_after,
        bricks,
        elapsed: start.elapsed(),
    })
}

/// Writes `version` as the only version of a new file named `dest`, numbered like it: its
/// distinct brick records copied with their payloads as they are (each verified first, and
/// given a payload checksum if it had none), one full index checkpoint and one commit. The
/// file is written as `tmp` (beside `dest`), synced, and renamed over `dest`, so a crash leaves
/// `dest` as it was or whole. Returns the records copied and the new file's size. Compaction
/// and salvage both write through it.
///
/// # Errors
/// Reading the index or a brick record fails, a payload is damaged, or writing, syncing or
/// renaming fails (`dest` is then untouched).
pub fn write_version_as(
    version: &Snapshot,
    dest: &Path,
    tmp: &Path,
    progress: &dyn Progress,
) -> Result<(u64, u64), StoreError> {
    let records = write_version(version, tmp, progress)?;
    let bytes = std::fs::metadata(tmp)
        .map_err(StoreError::io_path("cannot stat", tmp))?
        .len();
    rename_durably(tmp, dest)?;
    Ok((records, bytes))
}

fn write_version(
    version: &Snapshot,
    out: &Path,
    progress: &dyn Progress,
) -> Result<u64, StoreError> {
    let mut writer = Vod2Writer::create(out, version.header().clone(), Default::default())?;
    writer.start_at_version(version.version)?;
    let nodes = version.layout().node_count();
    progress.start(version.header().node_count());
    let mut transaction = Transaction::first(&mut writer);
    let mut moved: HashMap<u64, NodeEntry> = HashMap::new();
    // Density, then each attribute channel: every stream's pyramid, file-wide node by node.
    for (stream, view) in version.streams().enumerate() {
        for node in 0..nodes {
            let entry = view.entry_at(node)?;
            let copied = match entry {
                NodeEntry::Constant(_) => entry,
                NodeEntry::Stored(offset) => match moved.get(&offset) {
                    Some(&e) => e,
                    None => {
                        let e = transaction.copy_record(&view.stored_entry(entry)?)?;
                        moved.insert(offset, e);
                        e
                    }
                },
            };
            transaction.set(stream as u64 * nodes + node, copied)?;
            if node % 4096 == 4095 {
                progress.advance(4096);
            }
        }
        progress.advance(nodes % 4096);
    }
    progress.finish();
    transaction.commit(CheckpointPolicy::default())?;
    Ok(moved.len() as u64)
}

/// Renames `from` over `to` and syncs the directory, so the rename is durable.
fn rename_durably(from: &Path, to: &Path) -> Result<(), StoreError> {
    std::fs::rename(from, to).map_err(StoreError::io_path("cannot rename over", to))?;
    if let Some(dir) = to.parent().filter(|d| !d.as_os_str().is_empty()) {
        // The rename is durable once the directory entry is.
        std::fs::File::open(dir)
            .and_then(|d| d.sync_all())
            .map_err(StoreError::io_path("cannot sync the directory", dir))?;
    }
    Ok(())
}
