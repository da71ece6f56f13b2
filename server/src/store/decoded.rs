//! Decoded bricks by content hash, shared by every reader of a process: the HTTP brick bodies
//! (voxels, and lz4 blocks made from them), the chunks of the field's formats' views (voxels,
//! and zstd frames made from them) and the mesher, which reads a halo from up to 26 neighbours
//! of each tile and would otherwise decode them again for every tile. One cache, so the memory
//! all of them take is the one size a server is given.
//!
//! Keys are content, so an entry never goes stale: an edit makes new hashes, and the entries
//! of replaced bricks age out. Everything cached was verified when it was made: voxels are
//! decoded and checked against their content hash, lz4 blocks and zstd frames are made from
//! such voxels, and the payloads of records without a checksum are remembered only once they
//! decoded to their hash ([`DecodedBricks::verify_payload`]).

use super::lru::ByteLru;
use super::vod2::PayloadCheck;
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

/// The cache's other kind of entry, beside the [`Form`]s: a stored payload without a checksum
/// that decoded to its content hash. The key is the payload's xxh3-64 (seeded with its codec),
/// the value the content hash it decoded to.
const VERIFIED_PAYLOAD: u8 = 3;

/// What one remembered payload verification is counted as against the cache's byte budget:
/// about what its entry costs (the key, the 8-byte value, the LRU's bookkeeping).
const VERIFIED_PAYLOAD_COST: usize = 128;

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
        self.get_or_make_sized(hash, brick_bytes, form as u8, make, Bytes::len)
    }

    /// The cached `form` of the content with hash `hash` in bricks of `brick_bytes`, if it is
    /// held (a miss is not counted: the caller makes it through [`Self::get_or_make`]).
    pub fn get(&self, hash: u64, brick_bytes: usize, form: Form) -> Option<Bytes> {
        let body = self.lru.get(key(hash, brick_bytes, form as u8))?;
        self.hits.fetch_add(1, Ordering::Relaxed);
        Some((*body).clone())
    }

    fn get_or_make_sized<E>(
        &self,
        hash: u64,
        brick_bytes: usize,
        kind: u8,
        make: impl FnOnce() -> Result<Bytes, E>,
        cost: impl FnOnce(&Bytes) -> usize,
    ) -> Result<Bytes, E> {
        let key = key(hash, brick_bytes, kind);
        if let Some(body) = self.lru.get(key) {
            self.hits.fetch_add(1, Ordering::Relaxed);
            return Ok((*body).clone());
        }
        self.misses.fetch_add(1, Ordering::Relaxed);
        let body = make()?;
        let size = cost(&body);
        self.lru.put(key, Arc::new(body.clone()), size);
        Ok(body)
    }

    /// Verifies a stored payload before it is sent as it is: against the checksum stored after
    /// it (no decoding); a record written before payload checksums is decoded and checked
    /// against its content hash the first time, and the result remembered by the xxh3-64 of
    /// its payload bytes (and codec), so that a hot brick of an old file is decoded once, not on every
    /// request (the same payload bytes always decode to the same content).
    ///
    /// # Errors
    /// [`StoreError::Corrupt`]: the payload is not what was stored.
    pub fn verify_payload(
        &self,
        stored: &StoredBrick<'_>,
        layout: &VolumeLayout,
    ) -> Result<(), StoreError> {
        let StoredBrick::Record {
            offset,
            header,
            payload,
            ..
        } = *stored
        else {
            return Ok(());
        };
        if stored.check_payload()? == PayloadCheck::Verified {
            return Ok(());
        }
        // Seeded with the codec: the same bytes under another codec are other content.
        let payload_hash = xxhash_rust::xxh3::xxh3_64_with_seed(payload, header.codec as u64);
        let decoded_to = self.get_or_make_sized(
            payload_hash,
            layout.brick_bytes(),
            VERIFIED_PAYLOAD,
            || {
                decode(stored, layout)?;
                Ok::<_, StoreError>(Bytes::copy_from_slice(&header.hash.to_le_bytes()))
            },
            |_| VERIFIED_PAYLOAD_COST,
        )?;
        // These payload bytes decoded to this content once; a record claiming other content
        // for them is damaged.
        if decoded_to[..] != header.hash.to_le_bytes() {
            return Err(StoreError::corrupt(
                offset,
                format!("a payload of content hash {:#018x}", header.hash),
                "one that decodes to other content",
            ));
        }
        Ok(())
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

/// The LRU key of one kind of entry (a [`Form`], or [`VERIFIED_PAYLOAD`]) for some content.
/// The hash is uniform in its low bits (they pick the LRU's shard). The brick size goes above
/// it (equal hashes of different sizes are different content; a brick is at most 2^25 bytes),
/// the kind on top (two bits).
fn key(hash: u64, brick_bytes: usize, kind: u8) -> u128 {
    u128::from(hash) | ((brick_bytes as u128) << 64) | (u128::from(kind) << 126)
}

/// A stored brick's voxels in a new buffer, checked against its content hash.
///
/// # Errors
/// The record does not decode to its hash.
pub fn decode(stored: &StoredBrick<'_>, layout: &VolumeLayout) -> Result<Bytes, StoreError> {
    Ok(super::vod2::decode_stored_new(stored, layout)?.into())
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
