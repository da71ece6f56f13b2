//! The mesh cache: tiles keyed by the content of their inputs, bounded by bytes, least recently
//! used out first.
//!
//! The key ([`super::tile::tile_inputs`]) is a hash of the 27 bricks' content hashes (or constant
//! values), the level, the iso value and the tile's shape, and the cached mesh is in tile-local
//! coordinates. So identical tiles anywhere, in any volume, are meshed once, and an edit
//! invalidates exactly the tiles whose inputs changed: their key changes; the old entry ages out.

use super::mc::Mesh;
use super::tile::{mesh_tile_local, tile_inputs, TileScratch};
use crate::store::{Snapshot, StoreError};
use isovox_proto::BrickKey;
use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// A tile's mesh from the cache: local coordinates (see [`super::tile::to_world`]).
#[derive(Debug, Clone)]
pub struct CachedTile {
    pub key: u128,
    pub mesh: Arc<Mesh>,
    pub hit: bool,
}

#[derive(Debug, Default)]
struct Lru {
    entries: HashMap<u128, (Arc<Mesh>, usize, u64)>,
    order: BTreeMap<u64, u128>,
    bytes: usize,
    clock: u64,
}

/// A bounded, thread-safe cache of tile meshes.
#[derive(Debug)]
pub struct MeshCache {
    capacity: usize,
    lru: Mutex<Lru>,
    pub hits: AtomicU64,
    pub misses: AtomicU64,
}

fn mesh_bytes(m: &Mesh) -> usize {
    m.positions.len() * 24 + m.indices.len() * 4 + 64
}

impl MeshCache {
    /// A cache holding at most `capacity` bytes of meshes.
    pub fn new(capacity: usize) -> Self {
        MeshCache {
            capacity,
            lru: Mutex::new(Lru::default()),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.lru.lock().map(|l| l.bytes).unwrap_or(0)
    }

    fn get(&self, key: u128) -> Option<Arc<Mesh>> {
        let mut lru = self.lru.lock().ok()?;
        lru.clock += 1;
        let now = lru.clock;
        let (mesh, old) = {
            let entry = lru.entries.get_mut(&key)?;
            let old = entry.2;
            entry.2 = now;
            (entry.0.clone(), old)
        };
        lru.order.remove(&old);
        lru.order.insert(now, key);
        Some(mesh)
    }

    fn put(&self, key: u128, mesh: Arc<Mesh>) {
        let size = mesh_bytes(&mesh);
        if size > self.capacity {
            return;
        }
        let Ok(mut lru) = self.lru.lock() else { return };
        lru.clock += 1;
        let now = lru.clock;
        if let Some((_, old_size, old_stamp)) = lru.entries.insert(key, (mesh, size, now)) {
            lru.bytes -= old_size;
            lru.order.remove(&old_stamp);
        }
        lru.order.insert(now, key);
        lru.bytes += size;
        while lru.bytes > self.capacity {
            let Some((_, victim)) = lru.order.pop_first() else {
                break;
            };
            if let Some((_, s, _)) = lru.entries.remove(&victim) {
                lru.bytes -= s;
            }
        }
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
        if let Some(mesh) = self.get(inputs.key) {
            self.hits.fetch_add(1, Ordering::Relaxed);
            return Ok(CachedTile {
                key: inputs.key,
                mesh,
                hit: true,
            });
        }
        self.misses.fetch_add(1, Ordering::Relaxed);
        let mut mesh = Mesh::default();
        mesh_tile_local(snap, key, iso, &mut mesh, scratch)?;
        let mesh = Arc::new(mesh);
        self.put(inputs.key, mesh.clone());
        Ok(CachedTile {
            key: inputs.key,
            mesh,
            hit: false,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh(n: usize) -> Arc<Mesh> {
        Arc::new(Mesh {
            positions: vec![[0.0; 3]; n],
            normals: vec![[0.0; 3]; n],
            indices: vec![0; n],
        })
    }

    #[test]
    fn evicts_least_recently_used_within_its_byte_budget() {
        // Each entry of 10 vertices takes 10 * 24 + 10 * 4 + 64 = 344 bytes; room for 3.
        let c = MeshCache::new(1100);
        for k in 1..=3u128 {
            c.put(k, mesh(10));
        }
        assert_eq!(c.bytes(), 3 * 344);
        assert!(c.get(1).is_some()); // 1 is now the most recent; 2 the least
        c.put(4, mesh(10));
        assert!(c.get(2).is_none());
        assert!(c.get(1).is_some() && c.get(3).is_some() && c.get(4).is_some());
        assert!(c.bytes() <= 1100);
        c.put(5, mesh(100)); // larger than the whole budget: not cached
        assert!(c.get(5).is_none());
    }
}
