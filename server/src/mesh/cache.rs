//! The mesh cache: tiles keyed by the content of their inputs.
//!
//! The tile key ([`super::tile::tile_inputs`]) is a hash of the 27 bricks' content hashes (or
//! constant values), the level, the iso value and the tile's shape, and the cached mesh is in
//! tile-local coordinates. So identical tiles anywhere, in any volume, are meshed once, and an
//! edit invalidates exactly the tiles whose inputs changed: their key changes; the old entry
//! ages out. The decoded bricks a tile reads come from the scratch's shared brick cache
//! ([`crate::store::decoded`]).

use super::mc::Mesh;
use super::tile::{mesh_tile_from, TileInputs, TileScratch};
use crate::store::lru::ByteLru;
use crate::store::{Snapshot, StoreError};
use isovox_proto::BrickKey;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// A tile's mesh from the cache: local coordinates (see [`super::tile::to_world`]).
#[derive(Debug, Clone)]
pub struct CachedTile {
    /// The tile's content key.
    pub key: u128,
    /// The mesh, in tile-local coordinates.
    pub mesh: Arc<Mesh>,
    /// Whether it came from the cache.
    pub hit: bool,
}

/// Tile meshes, bounded by bytes; thread-safe.
#[derive(Debug)]
pub struct MeshCache {
    tiles: ByteLru<Mesh>,
    hits: AtomicU64,
    misses: AtomicU64,
}

fn mesh_bytes(m: &Mesh) -> usize {
    m.positions.len() * 24 + m.indices.len() * 4 + 64
}

impl MeshCache {
    /// A cache of at most `capacity` bytes of meshes.
    pub fn new(capacity: usize) -> Self {
        MeshCache {
            tiles: ByteLru::new(capacity),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.tiles.bytes()
    }

    /// Tiles answered from the cache so far.
    pub fn hits(&self) -> u64 {
        self.hits.load(Ordering::Relaxed)
    }

    /// Tiles meshed so far.
    pub fn misses(&self) -> u64 {
        self.misses.load(Ordering::Relaxed)
    }

    /// The local mesh of tile `key` with inputs `inputs` (from [`super::tile::tile_inputs`]),
    /// from the cache or meshed now with `scratch` (and then cached).
    ///
    /// # Errors
    /// A brick fails to read.
    pub fn tile(
        &self,
        snap: &Snapshot,
        key: BrickKey,
        iso: f32,
        inputs: &TileInputs,
        scratch: &mut TileScratch,
    ) -> Result<CachedTile, StoreError> {
        if let Some(mesh) = self.tiles.get(inputs.key) {
            self.hits.fetch_add(1, Ordering::Relaxed);
            return Ok(CachedTile {
                key: inputs.key,
                mesh,
                hit: true,
            });
        }
        self.misses.fetch_add(1, Ordering::Relaxed);
        let mut mesh = Mesh::default();
        mesh_tile_from(snap, key, iso, inputs, &mut mesh, scratch)?;
        let mesh = Arc::new(mesh);
        self.tiles.put(inputs.key, mesh.clone(), mesh_bytes(&mesh));
        Ok(CachedTile {
            key: inputs.key,
            mesh,
            hit: false,
        })
    }
}
