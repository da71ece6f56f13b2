//! The mesh cache: tiles and transition strips keyed by the content of their inputs.
//!
//! The tile key ([`super::tile::tile_inputs`]) is a hash of the content hashes (or constant
//! values) of the bricks the tile reads, the level, the iso value and the tile's shape; a
//! strip's key ([`super::tile::strip_inputs`]) hashes those of the bricks it reads (of the
//! tile's level along its face and of the next coarser one) and its face. Cached tiles (regular
//! mesh and moves) and strips are in tile-local coordinates. So identical tiles anywhere, in any volume, are meshed once, and an
//! edit invalidates exactly the tiles whose inputs changed: their key changes; the old entry
//! ages out. A tile or strip with materials from a channel is an entry of its own, whose key
//! also names the channel bricks its materials read ([`super::tile::tile_material_key`]), so a
//! paint (a channel edit) changes it and not the plain one. The decoded bricks a tile reads come from the scratch's shared brick cache
//! ([`crate::store::decoded`]).

use super::tile::{
    mesh_strip_from, mesh_strip_materials, mesh_tile_from, mesh_tile_materials, StripInputs,
    TileInputs, TileScratch,
};
use crate::store::lru::ByteLru;
use crate::store::{Snapshot, StoreError};
use isovox_proto::mesh::TileMesh;
use isovox_proto::BrickKey;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// A tile from the cache: local coordinates (see [`super::tile::tile_to_world`]).
#[derive(Debug, Clone)]
pub struct CachedTile {
    /// The tile's content key.
    pub key: u128,
    /// The regular mesh and moves (of a strip: its mesh and the moves of its face), in
    /// tile-local coordinates.
    pub tile: Arc<TileMesh>,
    /// Whether it came from the cache.
    pub hit: bool,
}

/// Tile meshes, bounded by bytes; thread-safe.
#[derive(Debug)]
pub struct MeshCache {
    tiles: ByteLru<TileMesh>,
    hits: AtomicU64,
    misses: AtomicU64,
}

fn tile_bytes(t: &TileMesh) -> usize {
    t.mesh.positions.len() * 24
        + t.mesh.materials.len() * 4
        + t.mesh.indices.len() * 4
        + t.moves.len() * std::mem::size_of::<isovox_proto::mesh::VertexMove>()
        + 128
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

    /// The local tile `key` with inputs `inputs` (from [`super::tile::tile_inputs`]), from the
    /// cache or meshed now with `scratch` (and then cached). With `materials`, a u8 channel view
    /// of the same version and its key ([`super::tile::tile_material_key`]): the same geometry
    /// with the channel's per-vertex materials, an entry of its own that names the channel
    /// bricks too.
    ///
    /// # Errors
    /// A brick fails to read.
    pub fn tile(
        &self,
        snap: &Snapshot,
        key: BrickKey,
        iso: f32,
        inputs: &TileInputs,
        materials: Option<(&Snapshot, u128)>,
        scratch: &mut TileScratch,
    ) -> Result<CachedTile, StoreError> {
        match materials {
            None => self.cached(inputs.key, |tile| {
                mesh_tile_from(snap, key, iso, inputs, tile, scratch).map(drop)
            }),
            Some((channel, material_key)) => self.cached(material_key, |tile| {
                mesh_tile_materials(snap, channel, key, iso, inputs, tile, scratch)
            }),
        }
    }

    /// The local strip of face `face` of tile `key` with inputs `inputs` (from
    /// [`super::tile::strip_inputs`]), from the cache or meshed now with `scratch` (and then
    /// cached); `materials` as for [`MeshCache::tile`] (the key from
    /// [`super::tile::strip_material_key`]). Tiles and strips share the cache's bytes; their
    /// keys never meet (a strip's describes its face).
    ///
    /// # Errors
    /// A brick fails to read.
    #[allow(clippy::too_many_arguments)]
    pub fn strip(
        &self,
        snap: &Snapshot,
        key: BrickKey,
        face: usize,
        iso: f32,
        inputs: &StripInputs,
        materials: Option<(&Snapshot, u128)>,
        scratch: &mut TileScratch,
    ) -> Result<CachedTile, StoreError> {
        match materials {
            None => self.cached(inputs.key, |strip| {
                mesh_strip_from(snap, key, face, iso, inputs, strip, scratch)
            }),
            Some((channel, material_key)) => self.cached(material_key, |strip| {
                mesh_strip_materials(snap, channel, key, face, iso, inputs, strip, scratch)
            }),
        }
    }

    /// The entry under content key `key`, or `make`'s (then cached).
    fn cached(
        &self,
        key: u128,
        make: impl FnOnce(&mut TileMesh) -> Result<(), StoreError>,
    ) -> Result<CachedTile, StoreError> {
        if let Some(tile) = self.tiles.get(key) {
            self.hits.fetch_add(1, Ordering::Relaxed);
            return Ok(CachedTile {
                key,
                tile,
                hit: true,
            });
        }
        self.misses.fetch_add(1, Ordering::Relaxed);
        let mut tile = TileMesh::default();
        make(&mut tile)?;
        let tile = Arc::new(tile);
        self.tiles.put(key, tile.clone(), tile_bytes(&tile));
        Ok(CachedTile {
            key,
            tile,
            hit: false,
        })
    }
}
