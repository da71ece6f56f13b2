//! The mesh cache: tiles keyed by the content of their inputs, and the decoded bricks they read.
//!
//! The tile key ([`super::tile::tile_inputs`]) is a hash of the 27 bricks' content hashes (or
//! constant values), the level, the iso value and the tile's shape, and the cached mesh is in
//! tile-local coordinates. So identical tiles anywhere, in any volume, are meshed once, and an
//! edit invalidates exactly the tiles whose inputs changed: their key changes; the old entry
//! ages out. Decoded bricks are cached by content hash too: a tile reads a one- or two-voxel
//! halo from up to 26 neighbours, which would otherwise be decoded again for every tile.

use super::mc::Mesh;
use super::tile::{mesh_tile_from, tile_inputs, TileInputs, TileScratch};
use crate::store::lru::ByteLru;
use crate::store::{Snapshot, StoreError};
use isovox_proto::BrickKey;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// A tile's mesh from the cache: local coordinates (see [`super::tile::to_world`]).
#[derive(Debug, Clone)]
pub struct CachedTile {
    pub key: u128,
    pub mesh: Arc<Mesh>,
    pub hit: bool,
}

/// Decoded bricks by content hash.
pub type BrickCache = ByteLru<Vec<u8>>;

/// Tile meshes and decoded bricks, each bounded by bytes; thread-safe.
#[derive(Debug)]
pub struct MeshCache {
    tiles: ByteLru<Mesh>,
    pub bricks: Arc<BrickCache>,
    pub hits: AtomicU64,
    pub misses: AtomicU64,
}

fn mesh_bytes(m: &Mesh) -> usize {
    m.positions.len() * 24 + m.indices.len() * 4 + 64
}

impl MeshCache {
    /// A cache of at most `capacity` bytes, a quarter of it for decoded bricks.
    pub fn new(capacity: usize) -> Self {
        MeshCache {
            tiles: ByteLru::new(capacity - capacity / 4),
            bricks: Arc::new(ByteLru::new(capacity / 4)),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        }
    }

    /// Bytes held now (meshes and decoded bricks).
    pub fn bytes(&self) -> usize {
        self.tiles.bytes() + self.bricks.bytes()
    }

    /// The local mesh of tile `key`, from the cache or meshed now (and then cached).
    ///
    /// # Errors
    /// A brick fails to read.
    pub fn tile(
        &self,
        snap: &Snapshot,
        key: BrickKey,
        iso: f32,
        scratch: &mut TileScratch,
    ) -> Result<CachedTile, StoreError> {
        let inputs = tile_inputs(snap, key, iso)?;
        self.tile_with(snap, key, iso, &inputs, scratch)
    }

    /// [`MeshCache::tile`] with the tile's inputs already computed.
    ///
    /// # Errors
    /// A brick fails to read.
    pub fn tile_with(
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
        scratch.bricks = Some(self.bricks.clone());
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
