//! The volumes and meshes edit terms name (`{"volume": {"name": ...}}`, `{"mesh": {...}}`):
//! a server's catalog and uploads, or the files beside an edited file.

use crate::catalog::{valid_name, Catalog};
use crate::icvg::term::{TermError, VolumeResolver};
use crate::store::{error_chain, Snapshot, Vod2};
use crate::voxelize::solid::TriMesh;
use crate::voxelize::store::MeshStore;
use std::path::PathBuf;
use std::sync::Arc;

/// A server's volumes at their current version, and its uploaded meshes (none when it keeps
/// no meshes).
#[derive(Debug, Clone)]
pub struct CatalogVolumes {
    /// The volumes.
    pub catalog: Arc<Catalog>,
    /// The uploads; none when the server keeps no meshes.
    pub meshes: Option<Arc<MeshStore>>,
}

impl VolumeResolver for CatalogVolumes {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        self.catalog
            .volume(name)
            .map(|v| v.head())
            .ok_or_else(|| TermError::Unknown(format!("no volume named {name:?}")))
    }

    fn resolve_at(&self, name: &str, version: u64) -> Result<Arc<Snapshot>, TermError> {
        let volume = self
            .catalog
            .volume(name)
            .ok_or_else(|| TermError::Unknown(format!("no volume named {name:?}")))?;
        volume.version(version).map_err(|e| {
            TermError::Volume(format!(
                "volume {name:?} at version {version}: {}",
                error_chain(&e)
            ))
        })
    }

    fn mesh(&self, hash: u64) -> Result<Arc<TriMesh>, TermError> {
        match &self.meshes {
            Some(store) => uploaded(store, hash),
            None => Err(TermError::Unknown("this server keeps no meshes".into())),
        }
    }
}

/// The `NAME.vod` files of a directory, and the meshes a server on it keeps (`DIR/meshes`).
#[derive(Debug, Clone)]
pub struct DirVolumes {
    /// The directory.
    pub dir: PathBuf,
}

impl VolumeResolver for DirVolumes {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        if !valid_name(name) {
            return Err(TermError::Unknown(format!("{name:?} is not a volume name")));
        }
        let path = self.dir.join(format!("{name}.vod"));
        Vod2::open(&path).map(|v| v.head()).map_err(|e| {
            TermError::Volume(format!(
                "volume {name:?} ({}): {}",
                path.display(),
                error_chain(&e)
            ))
        })
    }

    fn resolve_at(&self, name: &str, version: u64) -> Result<Arc<Snapshot>, TermError> {
        if !valid_name(name) {
            return Err(TermError::Unknown(format!("{name:?} is not a volume name")));
        }
        let path = self.dir.join(format!("{name}.vod"));
        Vod2::open(&path)
            .and_then(|v| v.version(version))
            .map_err(|e| {
                TermError::Volume(format!(
                    "volume {name:?} ({}) at version {version}: {}",
                    path.display(),
                    error_chain(&e)
                ))
            })
    }

    fn mesh(&self, hash: u64) -> Result<Arc<TriMesh>, TermError> {
        uploaded(&MeshStore::new(&self.dir.join("meshes")), hash)
    }
}

/// The mesh `store` keeps under `hash`.
fn uploaded(store: &MeshStore, hash: u64) -> Result<Arc<TriMesh>, TermError> {
    store
        .get(hash)
        .map_err(TermError::Mesh)?
        .ok_or_else(|| TermError::Unknown(format!("no mesh {hash:016x} has been uploaded")))
}
