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
            .ok_or_else(|| TermError::Volume(format!("no volume named {name:?}")))
    }

    fn mesh(&self, hash: u64) -> Result<Arc<TriMesh>, TermError> {
        match &self.meshes {
            Some(store) => store.get(hash).map_err(TermError::Mesh),
            None => Err(TermError::Mesh("this server keeps no meshes".into())),
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
            return Err(TermError::Volume(format!("{name:?} is not a volume name")));
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

    fn mesh(&self, hash: u64) -> Result<Arc<TriMesh>, TermError> {
        MeshStore::new(&self.dir.join("meshes"))
            .get(hash)
            .map_err(TermError::Mesh)
    }
}
