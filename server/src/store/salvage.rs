//! Salvage: writing a new file from the newest intact version of a damaged one.
//!
//! The damaged file is checked whole ([`check`]); the newest version every record of which is
//! intact (or the one asked for, if it is) is written as the only version of a new file,
//! numbered like it, by the compaction's own writer ([`write_version_as`]: records copied with
//! their payloads as they are, each verified again). The new file is written beside its final
//! name and renamed into place; the damaged file is never written to, so nothing of it is lost
//! to a later, more thorough recovery.

use super::build::sibling;
use super::check::{check, CheckReport, Depth, VersionCheck};
use super::compact::write_version_as;
use super::vod2::Vod2File;
use super::StoreError;
use crate::progress::Progress;
use isovox_proto::FormatError;
use std::path::Path;

/// What a salvage did.
#[derive(Debug, Clone)]
pub struct SalvageReport {
    /// The version written (the new file's only one).
    pub version: u64,
    /// Distinct brick records copied.
    pub bricks: u64,
    /// The new file's size.
    pub bytes: u64,
    /// The check of the damaged file that chose the version.
    pub check: CheckReport,
}

/// Writes the newest intact version of the file at `path` (or `version`, which must be
/// intact) to a new file at `out`.
///
/// # Errors
/// `out` is `path`; no version is intact (or `version` is not); the damaged file cannot be
/// read; the new file cannot be written.
pub fn salvage(
    path: &Path,
    out: &Path,
    version: Option<u64>,
    progress: &dyn Progress,
) -> Result<SalvageReport, StoreError> {
    let same = |a: &Path, b: &Path| match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if same(path, out) {
        return Err(StoreError::BadInput(format!(
            "salvage writes a new file: {} is the damaged file itself",
            out.display()
        )));
    }
    let report = check(path, Depth::Everything, progress)?;
    let target: VersionCheck = match version {
        None => report.newest_intact().cloned().ok_or_else(|| {
            StoreError::from(FormatError::invalid(
                "VOD 2 file",
                format!("no version is intact: {}", report.summary()),
            ))
        })?,
        Some(v) => {
            let found = report.version(v).ok_or_else(|| {
                StoreError::Absent(format!("version {v} is not in {}", path.display()))
            })?;
            if !found.intact() {
                return Err(StoreError::BadInput(format!(
                    "version {v} is not intact ({}); the newest intact one is {}",
                    found.index_damage.clone().unwrap_or_else(|| format!(
                        "{} of its bricks are damaged",
                        found.damaged_bricks
                    )),
                    report
                        .newest_intact()
                        .map_or("none".to_string(), |n| n.version.to_string())
                )));
            }
            found.clone()
        }
    };
    let snap = Vod2File::open(path)?.snapshot_at(target.commit)?;
    let (bricks, bytes) = write_version_as(&snap, out, &sibling(out, ".isovox-tmp"), progress)?;
    Ok(SalvageReport {
        version: target.version,
        bricks,
        bytes,
        check: report,
    })
}
