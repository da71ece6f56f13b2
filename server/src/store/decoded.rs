//! Decoded bricks by content hash, shared by every reader of a process: the HTTP brick bodies
//! (voxels, and lz4 blocks made from them) and the mesher, which reads a halo from up to 26
//! neighbours of each tile and would otherwise decode them again for every tile.
//!
//! Keys are content, so an entry never goes stale: an edit makes new hashes, and the entries
//! of replaced bricks age out.

use super::lru::ByteLru;
use super::{StoreError, StoredBrick};
use bytes::Bytes;
use isovox_proto::VolumeLayout;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// Which form of a brick's content.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form {
    /// The decoded voxels (x fastest, u16 little endian).
    Raw = 0,
    /// An lz4 block of them.
    Lz4 = 1,
}

/// Brick contents by (content hash, brick size, form), bounded by bytes; thread-safe.
#[derive(Debug)]
pub struct DecodedBricks {
    lru: ByteLru<Bytes>,
    hits: AtomicU64,
    misses: AtomicU64,
}

impl DecodedBricks {
    /// A cache of at most `capacity` bytes.
    pub fn new(capacity: usize) -> Self {
        DecodedBricks {
            lru: ByteLru::new(capacity),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.lru.bytes()
    }

    /// Lookups answered from the cache so far.
    pub fn hits(&self) -> u64 {
        self.hits.load(Ordering::Relaxed)
    }

    /// Lookups that had to make their answer so far.
    pub fn misses(&self) -> u64 {
        self.misses.load(Ordering::Relaxed)
    }

    /// The cached `form` of the content with hash `hash` in bricks of `brick_bytes`, or what
    /// `make` returns (then cached).
    ///
    /// # Errors
    /// Whatever `make` fails with.
    pub fn get_or_make<E>(
        &self,
        hash: u64,
        brick_bytes: usize,
        form: Form,
        make: impl FnOnce() -> Result<Bytes, E>,
    ) -> Result<Bytes, E> {
        // The hash is uniform in its low bits (they pick the LRU's shard). The brick size goes
        // above it: equal hashes of different sizes are different content.
        let key = (hash as u128) | ((brick_bytes as u128) << 64) | ((form as u128) << 127);
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

    /// The decoded voxels of a stored brick record with content hash `hash`, decoded (and
    /// checked against the hash) on a miss.
    ///
    /// # Errors
    /// The record does not decode to its hash.
    pub fn voxels(
        &self,
        hash: u64,
        stored: &StoredBrick<'_>,
        layout: &VolumeLayout,
    ) -> Result<Bytes, StoreError> {
        self.get_or_make(hash, layout.brick_bytes(), Form::Raw, || {
            decode(stored, layout)
        })
    }
}

/// A stored brick's voxels in a new buffer, checked against its content hash.
///
/// # Errors
/// The record does not decode to its hash.
pub fn decode(stored: &StoredBrick<'_>, layout: &VolumeLayout) -> Result<Bytes, StoreError> {
    let mut out = vec![0u8; layout.brick_bytes()];
    super::vod2::decode_stored(stored, layout, &mut out)?;
    Ok(out.into())
}
