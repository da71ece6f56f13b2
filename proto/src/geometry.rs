//! Boxes of voxels, the one shape every part of Isovox cuts volumes by: an edit's region and
//! bounds, the bricks a term can reach, a level's region to export. (A box of lattice points
//! with both ends included, what mesh tiles read, is [`crate::tile::GridBox`].)

use crate::{BrickKey, VolumeLayout};
use serde::{Deserialize, Serialize};

/// A box of voxels: `min` inclusive, `max` exclusive; an axis with `max <= min` holds none.
/// In JSON `{"min": [x, y, z], "max": [x, y, z]}` (an edit's `region`, an operation's bounds).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
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
