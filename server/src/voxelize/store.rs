//! Uploaded meshes, kept by content hash in a directory (`DATA/meshes/HASH.EXT`), so an edit
//! can name a model as a term leaf (`{"mesh": {"hash": ..., "offset": [...], "scale": s}}`).
//!
//! A mesh is checked when it is stored (it must load and be watertight), so a term never names
//! a model whose inside is undefined. Loaded meshes are kept in memory by hash.

use super::load::load_model;
use super::solid::{odd_edges, TriMesh};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// The formats an upload may be in (the extension it is stored under).
pub const FORMATS: [&str; 4] = ["stl", "obj", "ply", "glb"];

/// What storing a mesh found.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MeshInfo {
    /// The model's content hash.
    #[serde(serialize_with = "hex")]
    pub hash: u64,
    /// Its triangles.
    pub triangles: usize,
    /// Its vertices.
    pub vertices: usize,
    /// Its bounds' low corner.
    pub min: [f32; 3],
    /// Its bounds' high corner.
    pub max: [f32; 3],
}

fn hex<S: serde::Serializer>(h: &u64, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&format!("{h:016x}"))
}

/// Meshes in a directory, by content hash.
#[derive(Debug)]
pub struct MeshStore {
    dir: PathBuf,
    loaded: Mutex<HashMap<u64, Arc<TriMesh>>>,
}

impl MeshStore {
    /// Meshes kept in `dir`.
    pub fn new(dir: &Path) -> MeshStore {
        MeshStore {
            dir: dir.to_path_buf(),
            loaded: Mutex::default(),
        }
    }

    /// Stores a model given as the bytes of a file in `format`.
    ///
    /// # Errors
    /// An unknown format, a model that does not load, has no triangles or is not watertight, or
    /// the directory cannot be written. Nothing is kept then.
    pub fn store(&self, bytes: &[u8], format: &str) -> Result<MeshInfo, String> {
        if !FORMATS.contains(&format) {
            return Err(format!("format {format:?}: expected one of {FORMATS:?}"));
        }
        std::fs::create_dir_all(&self.dir)
            .map_err(|e| format!("cannot create the mesh directory: {e}"))?;
        let hash = xxhash_rust::xxh3::xxh3_64(bytes);
        let path = self.dir.join(format!("{hash:016x}.{format}"));
        let tmp = self.dir.join(format!("{hash:016x}.upload.{format}"));
        std::fs::write(&tmp, bytes).map_err(|e| format!("cannot write the upload: {e}"))?;
        let checked = load_model(&tmp)
            .map_err(|e| e.to_string())
            .and_then(|mesh| {
                let (odd, edges) = odd_edges(&mesh);
                if mesh.triangles.is_empty() {
                    return Err("the model has no triangles".to_string());
                }
                if odd > 0 {
                    return Err(format!(
                        "the model is not watertight: {odd} of its {edges} edges are used by an odd number of triangles"
                    ));
                }
                Ok(mesh)
            });
        let mesh = match checked {
            Ok(m) => m,
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                return Err(e.replace(&tmp.display().to_string(), "the upload"));
            }
        };
        std::fs::rename(&tmp, &path).map_err(|e| format!("cannot keep the upload: {e}"))?;
        let (min, max) = mesh.bounds().unwrap_or(([0.0; 3], [0.0; 3]));
        let info = MeshInfo {
            hash,
            triangles: mesh.triangles.len(),
            vertices: mesh.positions.len(),
            min,
            max,
        };
        if let Ok(mut loaded) = self.loaded.lock() {
            loaded.insert(hash, Arc::new(mesh));
        }
        Ok(info)
    }

    /// The mesh with this content hash.
    ///
    /// # Errors
    /// No stored mesh has it, or its file no longer loads.
    pub fn get(&self, hash: u64) -> Result<Arc<TriMesh>, String> {
        if let Some(m) = self.loaded.lock().ok().and_then(|l| l.get(&hash).cloned()) {
            return Ok(m);
        }
        let path = FORMATS
            .iter()
            .map(|f| self.dir.join(format!("{hash:016x}.{f}")))
            .find(|p| p.exists())
            .ok_or_else(|| format!("no mesh {hash:016x} has been uploaded"))?;
        let mesh = Arc::new(load_model(&path).map_err(|e| e.to_string())?);
        if let Ok(mut loaded) = self.loaded.lock() {
            loaded.insert(hash, mesh.clone());
        }
        Ok(mesh)
    }
}
