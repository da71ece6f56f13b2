//! The content cache: tile content by content key, least recently used first out, bounded by
//! bytes.

use super::FastMap;
use bytes::Bytes;
use isovox_proto::mesh::{Mesh, TileMesh};
use std::collections::BTreeMap;
use std::sync::Arc;

/// What the cache keeps by content key.
#[derive(Debug, Clone)]
pub(super) enum Content {
    Brick(Bytes),
    Mesh(Arc<TileMesh>),
    Strip(Arc<Mesh>),
}

/// Tile content by content key, least recently used first out, bounded by bytes.
#[derive(Debug)]
pub(super) struct Lru {
    cap: usize,
    pub(super) bytes: usize,
    tick: u64,
    map: FastMap<u64, LruEntry>,
    order: BTreeMap<u64, u64>,
}

#[derive(Debug)]
struct LruEntry {
    data: Content,
    size: usize,
    tick: u64,
}

impl Lru {
    pub(super) fn new(cap: usize) -> Lru {
        Lru {
            cap,
            bytes: 0,
            tick: 0,
            map: FastMap::default(),
            order: BTreeMap::new(),
        }
    }

    pub(super) fn contains(&self, key: u64) -> bool {
        self.map.contains_key(&key)
    }

    pub(super) fn get(&mut self, key: u64) -> Option<Content> {
        let e = self.map.get_mut(&key)?;
        self.order.remove(&e.tick);
        self.tick += 1;
        e.tick = self.tick;
        self.order.insert(self.tick, key);
        Some(e.data.clone())
    }

    pub(super) fn put(&mut self, key: u64, data: Content, size: usize) {
        if size > self.cap {
            return;
        }
        if let Some(old) = self.map.remove(&key) {
            self.order.remove(&old.tick);
            self.bytes -= old.size;
        }
        self.tick += 1;
        self.map.insert(
            key,
            LruEntry {
                data,
                size,
                tick: self.tick,
            },
        );
        self.order.insert(self.tick, key);
        self.bytes += size;
        while self.bytes > self.cap {
            let Some((_, victim)) = self.order.pop_first() else {
                break;
            };
            if let Some(e) = self.map.remove(&victim) {
                self.bytes -= e.size;
            }
        }
    }
}
