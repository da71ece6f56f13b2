//! The bodies of constant bricks. Most bricks of a sparse volume are constant, and expanding,
//! hashing or compressing 32 KiB per request would dominate; their bodies are made once per
//! (value, brick shape) and shared. (Bodies of stored bricks come from the shared cache of
//! decoded bricks, [`crate::store::decoded`].)

use crate::store::codec::{constant_hash, fill_constant};
use arc_swap::ArcSwap;
use bytes::Bytes;
use isovox_proto::VolumeLayout;
use std::collections::HashMap;

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

/// Constant bricks by (value, brick bytes, voxel bytes). Reads take no lock (the map is
/// replaced whole on the rare insert), so cores serving bricks never wait on each other here.
#[derive(Debug, Default)]
pub struct ConstantBricks {
    map: ArcSwap<HashMap<(u64, usize, usize), ConstantBrick>>,
}

impl ConstantBricks {
    /// Reads the entry for `value` in `layout`'s brick shape (made on first use) with `read`.
    fn with<R>(&self, value: u64, layout: &VolumeLayout, read: impl Fn(&ConstantBrick) -> R) -> R {
        let key = (value, layout.brick_bytes(), layout.voxel_type().bytes());
        if let Some(hit) = self.map.load().get(&key) {
            return read(hit);
        }
        let mut raw = vec![0u8; layout.brick_bytes()];
        fill_constant(&mut raw, value, layout.voxel_type());
        let entry = ConstantBrick {
            hash: constant_hash(value, layout),
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
    pub fn hash(&self, value: u64, layout: &VolumeLayout) -> u64 {
        self.with(value, layout, |c| c.hash)
    }

    /// Its voxels (shared).
    pub fn raw(&self, value: u64, layout: &VolumeLayout) -> Bytes {
        self.with(value, layout, |c| c.raw.clone())
    }

    /// Its lz4 block (copied: it is small, and a copy costs less than a reference count every
    /// core updates).
    pub fn lz4(&self, value: u64, layout: &VolumeLayout) -> Bytes {
        self.with(value, layout, |c| Bytes::copy_from_slice(&c.lz4))
    }
}
