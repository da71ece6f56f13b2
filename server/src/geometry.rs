//! Boxes of voxels: the geometry the volume algebra, the edits and the generators share.

use isovox_proto::{BrickKey, VolumeLayout};

/// A box of world voxels: `min` inclusive, `max` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Box3 {
    /// The first voxel (inclusive).
    pub min: [i64; 3],
    /// The end (exclusive).
    pub max: [i64; 3],
}

impl Box3 {
    /// The box `[min, max)`.
    pub fn new(min: [i64; 3], max: [i64; 3]) -> Self {
        Box3 { min, max }
    }

    /// Whether it holds no voxel.
    pub fn is_empty(&self) -> bool {
        (0..3).any(|a| self.min[a] >= self.max[a])
    }

    /// The voxels in both boxes (maybe empty).
    pub fn intersect(&self, o: &Box3) -> Box3 {
        Box3 {
            min: [0, 1, 2].map(|a| self.min[a].max(o.min[a])),
            max: [0, 1, 2].map(|a| self.max[a].min(o.max[a])),
        }
    }

    /// The smallest box holding both.
    pub fn hull(&self, o: &Box3) -> Box3 {
        Box3 {
            min: [0, 1, 2].map(|a| self.min[a].min(o.min[a])),
            max: [0, 1, 2].map(|a| self.max[a].max(o.max[a])),
        }
    }

    /// The box grown by `r` voxels on every side.
    pub fn grow(&self, r: i64) -> Box3 {
        Box3 {
            min: self.min.map(|c| c - r),
            max: self.max.map(|c| c + r),
        }
    }

    /// Whether voxel `v` is in the box.
    pub fn contains(&self, v: [i64; 3]) -> bool {
        (0..3).all(|a| v[a] >= self.min[a] && v[a] < self.max[a])
    }

    /// Voxels in the box (0 when empty), saturating.
    pub fn voxels(&self) -> u128 {
        if self.is_empty() {
            return 0;
        }
        (0..3)
            .map(|a| (self.max[a] - self.min[a]) as u128)
            .product()
    }
}

impl Box3 {
    /// The whole volume at level 0.
    pub fn of_volume(layout: &VolumeLayout) -> Box3 {
        Box3::new([0; 3], layout.dims().map(|d| d as i64))
    }

    /// The level-0 voxels of level-0 brick `key`, the brick's whole edge even where it passes the
    /// volume's far faces (clip it with [`Box3::of_volume`]).
    pub fn of_brick(layout: &VolumeLayout, key: BrickKey) -> Box3 {
        let b = layout.brick() as i64;
        let min = [key.x, key.y, key.z].map(|c| c as i64 * b);
        Box3::new(min, min.map(|c| c + b))
    }
}

/// The one value of every voxel of `b`, for a field that is `low` outside `bbox`, when that is
/// certain without sampling: `low` when `b` misses `bbox`; else `inside`'s answer for the part
/// of `b` within `bbox`, when that part is all of `b` or the answer is `low` anyway.
pub fn constant_over(
    bbox: &Box3,
    b: &Box3,
    low: u16,
    inside: impl FnOnce(&Box3) -> Option<u16>,
) -> Option<u16> {
    let within = b.intersect(bbox);
    if within.is_empty() {
        return Some(low);
    }
    let v = inside(&within)?;
    (within == *b || v == low).then_some(v)
}
