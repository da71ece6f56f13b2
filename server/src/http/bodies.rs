//! Response bodies by content: a brick's decoded voxels and its lz4 block, made once and
//! shared by every request for that content (the key is the content hash, so an entry never
//! goes stale; edits make new hashes and old entries age out).

use super::ApiError;
use crate::store::lru::ByteLru;
use arc_swap::ArcSwap;
use bytes::Bytes;
use isovox_proto::VolumeLayout;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// Which representation of a brick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodyKind {
    Raw = 0,
    Lz4 = 1,
}

/// Bodies by (content hash, representation), bounded by bytes.
#[derive(Debug)]
pub struct BodyCache {
    lru: ByteLru<Bytes>,
    pub hits: AtomicU64,
    pub misses: AtomicU64,
}

impl BodyCache {
    pub fn new(capacity: usize) -> Self {
        BodyCache {
            lru: ByteLru::new(capacity),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.lru.bytes()
    }

    /// The cached body, or `make`'s (then cached).
    ///
    /// # Errors
    /// Whatever `make` fails with.
    pub fn get_or_make(
        &self,
        hash: u64,
        kind: BodyKind,
        make: impl FnOnce() -> Result<Bytes, ApiError>,
    ) -> Result<Bytes, ApiError> {
        // The hash is uniform in its low bits (they pick the shard); the kind goes on top.
        let key = (hash as u128) | ((kind as u128) << 64);
        if let Some(body) = self.lru.get(key) {
            self.hits.fetch_add(1, Ordering::Relaxed);
            return Ok((*body).clone());
        }
        self.misses.fetch_add(1, Ordering::Relaxed);
        let body = make()?;
        let size = body.len();
        self.lru.put(key, Arc::new(body.clone()), size);
        Ok(body)
    }
}

/// A constant brick's content hash and bodies.
#[derive(Debug, Clone)]
struct ConstantBrick {
    hash: u64,
    raw: Bytes,
    lz4: Bytes,
}

/// Constant bricks kept at most (a u16 volume may hold thousands of distinct constant bricks;
/// past this many, the rest are made per request).
const MAX_CONSTANTS: usize = 256;

/// Constant bricks by (value, brick bytes, voxel bytes): most bricks of a sparse volume are
/// constant, and hashing or compressing 32 KiB per request would dominate. Reads take no lock
/// (the map is replaced whole on the rare insert), so cores serving bricks never wait on each
/// other here.
#[derive(Debug, Default)]
pub struct ConstantBricks {
    map: ArcSwap<HashMap<(u16, usize, usize), ConstantBrick>>,
}

impl ConstantBricks {
    /// Reads the entry for `value` in `layout`'s brick shape (made on first use) with `read`.
    fn with<R>(&self, value: u16, layout: &VolumeLayout, read: impl Fn(&ConstantBrick) -> R) -> R {
        let key = (value, layout.brick_bytes(), layout.voxel_type().bytes());
        if let Some(hit) = self.map.load().get(&key) {
            return read(hit);
        }
        let mut raw = vec![0u8; layout.brick_bytes()];
        crate::store::codec::fill_constant(&mut raw, value, layout.voxel_type());
        let entry = ConstantBrick {
            hash: isovox_proto::vod2::content_hash(&raw),
            lz4: lz4_flex::block::compress(&raw).into(),
            raw: raw.into(),
        };
        let out = read(&entry);
        if self.map.load().len() >= MAX_CONSTANTS {
            return out;
        }
        // A racing insert of the same key makes the same entry: either may win.
        self.map.rcu(|map| {
            let mut map = HashMap::clone(map);
            map.entry(key).or_insert_with(|| entry.clone());
            map
        });
        out
    }

    /// The content hash of the constant brick of `value` in `layout`'s brick shape.
    pub fn hash(&self, value: u16, layout: &VolumeLayout) -> u64 {
        self.with(value, layout, |c| c.hash)
    }

    /// Its body: the voxels (shared), or its lz4 block (copied: it is small, and a copy costs
    /// less than a reference count every core updates).
    pub fn body(&self, value: u16, layout: &VolumeLayout, kind: BodyKind) -> Bytes {
        self.with(value, layout, |c| match kind {
            BodyKind::Raw => c.raw.clone(),
            BodyKind::Lz4 => Bytes::copy_from_slice(&c.lz4),
        })
    }
}
