//! Writing a view to a directory, so a volume can be published on any static host.
//!
//! Every file is made by the same [`super::view::resolve`] the server answers with, so an
//! export holds exactly the bytes `isovox serve` sends for that version. The tree is written
//! beside the destination (`DEST.isovox-tmp`) and renamed into place when complete: an
//! interrupted export never leaves a tree under the final name.

use super::view::{resolve, Document, ViewKind};
use super::FormatsError;
use crate::progress::Progress;
use crate::store::build::sibling;
use crate::store::decoded::DecodedBricks;
use crate::store::Snapshot;
use isovox_proto::{BrickKey, VolumeLayout};
use rayon::prelude::*;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

/// What an export wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExportReport {
    /// Chunk files written.
    pub chunks: u64,
    /// Chunks left out because they hold only the fill value (Zarr reads them as such).
    pub absent: u64,
    /// Bytes of every file written.
    pub bytes: u64,
}

/// The path of brick `key`'s chunk in view `kind`, relative to the view's root.
pub fn chunk_path(kind: ViewKind, layout: &VolumeLayout, key: BrickKey) -> String {
    match kind {
        ViewKind::Zarr => format!("{}/c/{}/{}/{}", key.level, key.z, key.y, key.x),
        ViewKind::Precomputed => format!(
            "{}/{}",
            key.level,
            super::precomputed::chunk_name(layout, key.level, [key.x, key.y, key.z])
        ),
    }
}

/// The metadata documents of view `kind` of `snap`, relative to its root: density's, then each
/// attribute channel's (a label image under `labels/` in Zarr, a data source of its own in
/// precomputed).
fn metadata_paths(kind: ViewKind, snap: &Snapshot) -> Vec<String> {
    let levels = |prefix: &str| {
        (0..snap.layout().levels())
            .map(|k| format!("{prefix}{k}/zarr.json"))
            .collect::<Vec<_>>()
    };
    let mut paths = match kind {
        ViewKind::Zarr => std::iter::once("zarr.json".to_string())
            .chain(levels(""))
            .collect(),
        ViewKind::Precomputed => vec!["info".into()],
    };
    if kind == ViewKind::Zarr && !snap.header().channels.is_empty() {
        paths.push("labels/zarr.json".into());
    }
    for (prefix, _) in sources(kind, snap).into_iter().skip(1) {
        match kind {
            ViewKind::Zarr => {
                paths.push(format!("{prefix}zarr.json"));
                paths.extend(levels(&prefix));
            }
            ViewKind::Precomputed => paths.push(format!("{prefix}info")),
        }
    }
    paths
}

/// The data sources of view `kind` of `snap`, each with the path its documents start with:
/// density (at the root), then each attribute channel's view.
fn sources(kind: ViewKind, snap: &Snapshot) -> Vec<(String, &Snapshot)> {
    let channels = snap.header().channels.iter().zip(snap.channel_views());
    std::iter::once((String::new(), snap))
        .chain(channels.map(|(c, view)| {
            let prefix = match kind {
                ViewKind::Zarr => format!("labels/{}/", c.name),
                ViewKind::Precomputed => format!("{}/", c.name),
            };
            (prefix, &**view)
        }))
        .collect()
}

/// Memory for the bodies an export makes once and writes many times: deduplicated bricks (most
/// of all the constant ones) share one content hash, so their chunk is compressed once.
const EXPORT_CACHE_BYTES: usize = 64 << 20;

/// Writes view `kind` of `snap` (volume `name`) as a directory tree at `dest`, which must not
/// exist. `progress` counts bricks.
///
/// # Errors
/// `dest` exists, a brick does not decode, or writing fails; nothing is left at `dest` then.
pub fn export_view(
    snap: &Snapshot,
    kind: ViewKind,
    name: &str,
    dest: &Path,
    progress: &dyn Progress,
) -> Result<ExportReport, FormatsError> {
    if dest.exists() {
        return Err(FormatsError::BadArgument(format!(
            "{} already exists; export writes a new directory",
            dest.display()
        )));
    }
    let tmp = sibling(dest, ".isovox-tmp");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(FormatsError::io_path("cannot remove", &tmp))?;
    }
    progress.start(snap.layout().node_count() * (1 + snap.header().channels.len() as u64));
    let written = write_tree(snap, kind, name, &tmp, progress);
    progress.finish();
    let result = written.and_then(|report| {
        std::fs::rename(&tmp, dest).map_err(FormatsError::io_path("cannot rename into", dest))?;
        Ok(report)
    });
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result
}

fn write_tree(
    snap: &Snapshot,
    kind: ViewKind,
    name: &str,
    root: &Path,
    progress: &dyn Progress,
) -> Result<ExportReport, FormatsError> {
    let layout = snap.layout();
    let bricks = DecodedBricks::new(EXPORT_CACHE_BYTES);
    let write = |rel: &str, bytes: &[u8]| -> Result<(), FormatsError> {
        let path = root.join(rel);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(FormatsError::io_path("cannot create", dir))?;
        }
        std::fs::write(&path, bytes).map_err(FormatsError::io_path("cannot write", &path))
    };
    let mut bytes = 0u64;
    for rel in metadata_paths(kind, snap) {
        match resolve(kind, snap, name, &rel)? {
            Document::Metadata(doc) => {
                write(&rel, &doc)?;
                bytes += doc.len() as u64;
            }
            other => {
                return Err(FormatsError::Internal(format!(
                    "{rel} resolved to {other:?}, not metadata"
                )))
            }
        }
    }
    let (chunks, absent, written) = (AtomicU64::new(0), AtomicU64::new(0), AtomicU64::new(bytes));
    for (prefix, source) in sources(kind, snap) {
        for level in 0..layout.levels() {
            let [gx, gy, gz] = layout.grid(level);
            for z in 0..gz {
                (0..gx * gy).into_par_iter().try_for_each(|i| {
                    let key = BrickKey {
                        level,
                        x: i % gx,
                        y: i / gx,
                        z,
                    };
                    let rel = format!("{prefix}{}", chunk_path(kind, layout, key));
                    match resolve(kind, snap, name, &rel)? {
                        Document::Chunk(chunk) => {
                            let body = chunk.body(source, &bricks)?;
                            write(&rel, &body)?;
                            chunks.fetch_add(1, Ordering::Relaxed);
                            written.fetch_add(body.len() as u64, Ordering::Relaxed);
                        }
                        Document::Absent => {
                            absent.fetch_add(1, Ordering::Relaxed);
                        }
                        Document::Metadata(_) => {
                            return Err(FormatsError::Internal(format!(
                                "{rel} resolved to metadata, not a chunk"
                            )))
                        }
                    }
                    Ok(())
                })?;
                progress.advance(u64::from(gx * gy));
            }
        }
    }
    Ok(ExportReport {
        chunks: chunks.into_inner(),
        absent: absent.into_inner(),
        bytes: written.into_inner(),
    })
}
