//! Response bodies by content: a brick's decoded voxels and its lz4 block, made once and
//! shared by every request for that content (the key is the content hash, so an entry never
//! goes stale; edits make new hashes and old entries age out).

use super::ApiError;
use crate::store::lru::ByteLru;
use bytes::Bytes;
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
