//! The volumes a server serves: every VOD 2 file of its data directory, named after the file.

use crate::store::{check, StoreError, Vod2};
use crate::volume::{LiveVolume, VolumeError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Volumes by name.
#[derive(Debug, Default)]
pub struct Catalog {
    volumes: BTreeMap<String, Arc<LiveVolume>>,
}

/// Whether `name` is acceptable as a volume name (and so as a file stem and URL segment).
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 128
        && !name.starts_with('.')
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'.')
}

/// Opens the file at `path` as the volume `name`: at its newest durable version, or, when
/// that version is damaged, read-only at the newest version that reads (with a loud warning):
/// a damaged commit record or checkpoint costs the versions that need it, not the volume.
///
/// # Errors
/// The file cannot be read, is not VOD 2, or no version of it reads.
pub fn open_volume(name: &str, path: &Path) -> Result<LiveVolume, StoreError> {
    let damage = match Vod2::open(path) {
        Ok(vod) => return LiveVolume::new(name, vod),
        Err(e) if e.is_damage() => e,
        Err(e) => return Err(e),
    };
    let (vod, report) = check::open_newest_readable(path).inspect_err(|_| {
        tracing::error!(path = %path.display(), error = %crate::store::error_chain(&damage), "the newest version is damaged, and no older one reads");
    })?;
    let served = vod.head_ref().version;
    let head = report
        .head
        .map_or("the newest version".to_string(), |v| format!("version {v}"));
    // Clients see this (edits answer 409 with it): no path of the server's.
    let cause = format!(
        "{head} is damaged ({}); version {served}, the newest that reads, is served read-only; an operator lists the damage with `isovox check` and writes a repaired copy with `isovox salvage`",
        crate::store::error_chain(&damage),
    );
    tracing::error!(volume = name, path = %path.display(), damaged_records = report.damage.len(), "SERVING READ-ONLY: {cause}");
    LiveVolume::read_only(name, vod, cause)
}

impl Catalog {
    /// Opens every `*.vod` VOD 2 file in `dir` (see [`open_volume`]). A file that does not
    /// open is reported and left out, so one damaged volume does not take the others down.
    ///
    /// # Errors
    /// The directory cannot be read.
    pub fn open_dir(dir: &Path) -> Result<Catalog, StoreError> {
        let mut volumes = BTreeMap::new();
        let entries = std::fs::read_dir(dir)
            .map_err(StoreError::io_path("cannot read the data directory", dir))?;
        let mut paths: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "vod"))
            .collect();
        paths.sort();
        for path in paths {
            let Some(name) = path
                .file_stem()
                .and_then(|s| s.to_str())
                .map(str::to_string)
            else {
                continue;
            };
            if !valid_name(&name) {
                tracing::warn!(path = %path.display(), "skipping a volume whose name is not [A-Za-z0-9_.-]");
                continue;
            }
            match open_volume(&name, &path) {
                Ok(volume) => {
                    volumes.insert(name, Arc::new(volume));
                }
                Err(e) => {
                    tracing::error!(path = %path.display(), error = %crate::store::error_chain(&e), "cannot open volume; not serving it")
                }
            }
        }
        Ok(Catalog { volumes })
    }

    /// Serves exactly these volumes (for tests and embedding).
    ///
    /// # Errors
    /// A volume's commit chain is malformed.
    pub fn from_volumes(
        volumes: impl IntoIterator<Item = (String, Vod2)>,
    ) -> Result<Catalog, StoreError> {
        let volumes = volumes
            .into_iter()
            .map(|(n, v)| Ok((n.clone(), Arc::new(LiveVolume::new(&n, v)?))))
            .collect::<Result<_, StoreError>>()?;
        Ok(Catalog { volumes })
    }

    /// The volume `name`, borrowed (no reference count touched: on the brick routes, a count
    /// shared by every core is a cache line they fight over).
    pub fn volume(&self, name: &str) -> Option<&Arc<LiveVolume>> {
        self.volumes.get(name)
    }

    /// The volume `name`, borrowed.
    ///
    /// # Errors
    /// [`VolumeError::NoSuchVolume`].
    pub fn get(&self, name: &str) -> Result<&Arc<LiveVolume>, VolumeError> {
        self.volumes
            .get(name)
            .ok_or_else(|| VolumeError::NoSuchVolume(name.to_string()))
    }

    /// The volumes with their names, in name order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &Arc<LiveVolume>)> {
        self.volumes.iter().map(|(n, v)| (n.as_str(), v))
    }

    /// How many volumes.
    pub fn len(&self) -> usize {
        self.volumes.len()
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.volumes.is_empty()
    }
}
