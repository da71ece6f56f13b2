//! Decoded bricks by content hash, shared by every reader of a process: the HTTP brick bodies
//! (voxels, and lz4 blocks made from them), the chunks of the field's formats' views (voxels,
//! and zstd frames made from them) and the mesher, which reads a halo from up to 26 neighbours
//! of each tile and would otherwise decode them again for every tile. One cache, so the memory
//! all of them take is the one size a server is given.
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
    /// One zstd frame of them that records its content size (a Zarr chunk).
    Zstd = 2,
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
        if let Some(body) = self.get(hash, brick_bytes, form) {
            return Ok(body);
        }
        self.misses.fetch_add(1, Ordering::Relaxed);
        let body = make()?;
        let size = body.len();
        self.lru
            .put(key(hash, brick_bytes, form), Arc::new(body.clone()), size);
        Ok(body)
    }

    /// The cached `form` of the content with hash `hash` in bricks of `brick_bytes`, if it is
    /// held (a miss is not counted: the caller makes it through [`Self::get_or_make`]).
    pub fn get(&self, hash: u64, brick_bytes: usize, form: Form) -> Option<Bytes> {
        let body = self.lru.get(key(hash, brick_bytes, form))?;
        self.hits.fetch_add(1, Ordering::Relaxed);
        Some((*body).clone())
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

/// The LRU key of a form of some content. The hash is uniform in its low bits (they pick the
/// LRU's shard). The brick size goes above it (equal hashes of different sizes are different
/// content; a brick is at most 2^25 bytes), the form above that.
fn key(hash: u64, brick_bytes: usize, form: Form) -> u128 {
    u128::from(hash) | ((brick_bytes as u128) << 64) | ((form as u128) << 120)
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn forms_and_brick_sizes_of_one_hash_are_kept_apart() {
        let cache = DecodedBricks::new(1 << 20);
        let make = |bytes: &'static [u8]| move || Ok::<_, StoreError>(Bytes::from_static(bytes));
        let hash = 0x0123_4567_89ab_cdef;
        for (size, form, body) in [
            (4096, Form::Raw, &b"raw"[..]),
            (4096, Form::Lz4, b"lz4"),
            (4096, Form::Zstd, b"zstd"),
            (8192, Form::Raw, b"raw, larger brick"),
        ] {
            assert_eq!(
                cache.get_or_make(hash, size, form, make(body)).unwrap(),
                body
            );
        }
        assert_eq!(cache.misses(), 4);
        assert_eq!(cache.get(hash, 4096, Form::Zstd).unwrap(), &b"zstd"[..]);
        assert_eq!(cache.get(hash, 4096, Form::Lz4).unwrap(), &b"lz4"[..]);
        assert_eq!(
            cache.get(hash, 8192, Form::Raw).unwrap(),
            &b"raw, larger brick"[..]
        );
        assert_eq!(cache.get(hash, 4096, Form::Raw).unwrap(), &b"raw"[..]);
        assert!(cache.get(hash, 8192, Form::Zstd).is_none());
        assert_eq!((cache.hits(), cache.misses()), (4, 4));
    }
}
