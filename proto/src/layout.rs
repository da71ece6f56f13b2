//! The geometry of a brick octree: levels of detail, their brick grids, and brick addressing.
//!
//! A volume of `dims` voxels is cut into cubic bricks of `brick` voxels per side. Level 0 holds
//! the original bricks; a voxel of level k+1 is the rounded mean of a 2x2x2 group of level-k
//! voxels, so a brick of level k covers `(brick * 2^k)^3` voxels of level 0. Levels go up until
//! one brick covers the whole volume.
//!
//! The pyramidal pointer array (thesis section 4.1) is the concatenation of every level's brick
//! grid, level 0 first, each grid x fastest, then y, then z. [`VolumeLayout::node_index`] maps a
//! [`BrickKey`] to its position in that array in O(1), and so are its neighbours.

use crate::error::FormatError;
use crate::voxel::VoxelType;
use serde::{Deserialize, Serialize};
use std::fmt;

/// Smallest and largest brick edge accepted (a power of two in between).
pub const MIN_BRICK: u32 = 2;
/// The largest brick edge accepted.
pub const MAX_BRICK: u32 = 256;
/// Upper bound on the number of nodes of a volume's pyramid. It bounds every allocation that
/// depends on a header's dimensions (2^32 nodes of 8 bytes is already 32 GiB of index).
pub const MAX_NODES: u64 = 1 << 32;

/// The shape of a volume: dimensions, brick size and voxel type. Constructed only through
/// [`VolumeLayout::new`], which validates it, so every other method can rely on its invariants.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VolumeLayout {
    dims: [u32; 3],
    brick: u32,
    voxel_type: VoxelType,
    /// For each level, its first node index in the pyramid; one extra entry holds the total.
    level_base: Vec<u64>,
}

/// The address of one brick: a level of detail and a position in that level's brick grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct BrickKey {
    /// The level (0 = full resolution).
    pub level: u8,
    /// The brick's x in the level's grid.
    pub x: u32,
    /// The brick's y in the level's grid.
    pub y: u32,
    /// The brick's z in the level's grid.
    pub z: u32,
}

impl fmt::Display for BrickKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}/{}/{}", self.level, self.x, self.y, self.z)
    }
}

fn div_ceil(a: u64, b: u64) -> u64 {
    a.div_ceil(b)
}

impl VolumeLayout {
    /// A validated layout.
    ///
    /// # Errors
    /// Density of a type other than u8 or u16, any dimension is zero, the brick edge is not a power of two in `[2, 256]`, or the pyramid
    /// would have more than [`MAX_NODES`] nodes.
    pub fn new(dims: [u32; 3], brick: u32, voxel_type: VoxelType) -> Result<Self, FormatError> {
        if !voxel_type.is_density() {
            return Err(FormatError::invalid(
                "voxel type",
                format!("density is u8 or u16, not {voxel_type} (u32 and u64 are for channels)"),
            ));
        }
        if dims.contains(&0) {
            return Err(FormatError::invalid(
                "volume dimensions",
                format!("{dims:?} has a zero side"),
            ));
        }
        if !brick.is_power_of_two() || !(MIN_BRICK..=MAX_BRICK).contains(&brick) {
            return Err(FormatError::invalid(
                "brick size",
                format!("{brick} is not a power of two in [{MIN_BRICK}, {MAX_BRICK}]"),
            ));
        }
        let mut level_base = vec![0u64];
        let mut total = 0u64;
        let mut level = 0u32;
        loop {
            let span = (brick as u64) << level;
            let g = dims.map(|d| div_ceil(d as u64, span));
            total = total.saturating_add(g[0].saturating_mul(g[1]).saturating_mul(g[2]));
            if total > MAX_NODES {
                return Err(FormatError::invalid(
                    "volume dimensions",
                    format!("{dims:?} with brick {brick} needs more than {MAX_NODES} bricks"),
                ));
            }
            level_base.push(total);
            if g == [1, 1, 1] {
                break;
            }
            level += 1;
        }
        Ok(VolumeLayout {
            dims,
            brick,
            voxel_type,
            level_base,
        })
    }

    /// The same shape with values of another type (an attribute channel's pyramid).
    pub fn with_voxel_type(&self, voxel_type: VoxelType) -> VolumeLayout {
        VolumeLayout {
            voxel_type,
            ..self.clone()
        }
    }

    /// Level-0 size in voxels.
    pub fn dims(&self) -> [u32; 3] {
        self.dims
    }

    /// Brick edge in voxels.
    pub fn brick(&self) -> u32 {
        self.brick
    }

    /// The voxel type.
    pub fn voxel_type(&self) -> VoxelType {
        self.voxel_type
    }

    /// Number of levels of detail (level 0 up to the single root brick); at least 1.
    pub fn levels(&self) -> u8 {
        (self.level_base.len() - 1) as u8
    }

    /// Voxels in one brick.
    pub fn brick_voxels(&self) -> usize {
        (self.brick as usize).pow(3)
    }

    /// Bytes of one decoded brick.
    pub fn brick_bytes(&self) -> usize {
        self.brick_voxels() * self.voxel_type.bytes()
    }

    /// Total number of bricks (nodes) over all levels.
    pub fn node_count(&self) -> u64 {
        self.level_base[self.level_base.len() - 1]
    }

    /// Bytes of the original volume as RAW.
    pub fn raw_bytes(&self) -> u64 {
        self.dims.iter().map(|&d| d as u64).product::<u64>() * self.voxel_type.bytes() as u64
    }

    /// The brick grid of `level`: bricks per axis. Panics if `level >= levels()`.
    pub fn grid(&self, level: u8) -> [u32; 3] {
        assert!(level < self.levels(), "level {level} out of range");
        let span = (self.brick as u64) << level;
        self.dims.map(|d| div_ceil(d as u64, span) as u32)
    }

    /// The extent of meaningful voxels at `level`: `ceil(dims / 2^level)`. Voxels of the level's
    /// bricks beyond it are L (they only average L voxels).
    pub fn level_dims(&self, level: u8) -> [u32; 3] {
        self.dims
            .map(|d| div_ceil(d as u64, 1u64 << level).max(1) as u32)
    }

    /// First node index of `level` in the pyramid, and the number of its bricks.
    pub fn level_range(&self, level: u8) -> (u64, u64) {
        let l = level as usize;
        (
            self.level_base[l],
            self.level_base[l + 1] - self.level_base[l],
        )
    }

    /// A validated key.
    ///
    /// # Errors
    /// The level or a coordinate is outside the pyramid.
    pub fn key(&self, level: u8, x: u32, y: u32, z: u32) -> Result<BrickKey, FormatError> {
        if level >= self.levels() {
            return Err(FormatError::invalid(
                "brick key",
                format!(
                    "level {level} out of range (volume has {} levels)",
                    self.levels()
                ),
            ));
        }
        let g = self.grid(level);
        if x >= g[0] || y >= g[1] || z >= g[2] {
            return Err(FormatError::invalid(
                "brick key",
                format!(
                    "brick ({x}, {y}, {z}) out of range at level {level} (grid {}x{}x{})",
                    g[0], g[1], g[2]
                ),
            ));
        }
        Ok(BrickKey { level, x, y, z })
    }

    /// Whether `key` lies inside the pyramid.
    pub fn contains(&self, key: BrickKey) -> bool {
        self.key(key.level, key.x, key.y, key.z).is_ok()
    }

    /// The position of `key` in the pyramidal array. Panics if the key is not in the layout;
    /// keys from [`VolumeLayout::key`] always are.
    pub fn node_index(&self, key: BrickKey) -> u64 {
        assert!(self.contains(key), "brick key {key} outside the layout");
        let g = self.grid(key.level);
        self.level_base[key.level as usize]
            + key.x as u64
            + g[0] as u64 * (key.y as u64 + g[1] as u64 * key.z as u64)
    }

    /// The key at a node index, the inverse of [`VolumeLayout::node_index`].
    ///
    /// # Errors
    /// `node` is not below [`VolumeLayout::node_count`].
    pub fn key_of(&self, node: u64) -> Result<BrickKey, FormatError> {
        if node >= self.node_count() {
            return Err(FormatError::invalid(
                "node index",
                format!("{node} >= node count {}", self.node_count()),
            ));
        }
        let level = self.level_base.partition_point(|&base| base <= node) - 1;
        let level = level as u8;
        let g = self.grid(level);
        let local = node - self.level_base[level as usize];
        let (gx, gy) = (g[0] as u64, g[1] as u64);
        Ok(BrickKey {
            level,
            x: (local % gx) as u32,
            y: (local / gx % gy) as u32,
            z: (local / (gx * gy)) as u32,
        })
    }

    /// The brick next to `key` at the same level, offset by `(dx, dy, dz)`, if inside the grid.
    pub fn neighbour(&self, key: BrickKey, d: [i32; 3]) -> Option<BrickKey> {
        let pos = [key.x, key.y, key.z];
        let mut out = [0u32; 3];
        for axis in 0..3 {
            out[axis] = u32::try_from(pos[axis] as i64 + d[axis] as i64).ok()?;
        }
        self.key(key.level, out[0], out[1], out[2]).ok()
    }

    /// The brick of the next coarser level that covers `key`, if `key` is not the root.
    pub fn parent(&self, key: BrickKey) -> Option<BrickKey> {
        (key.level + 1 < self.levels()).then(|| BrickKey {
            level: key.level + 1,
            x: key.x / 2,
            y: key.y / 2,
            z: key.z / 2,
        })
    }

    /// The up to 8 bricks of the next finer level that `key` is made from, in x-fastest order,
    /// each with its octant (0..8, x fastest). Children beyond the grid are left out: they are
    /// all L.
    pub fn children(&self, key: BrickKey) -> Vec<(usize, BrickKey)> {
        if key.level == 0 {
            return Vec::new();
        }
        let mut out = Vec::with_capacity(8);
        for octant in 0..8usize {
            let (ox, oy, oz) = (
                (octant & 1) as u32,
                (octant >> 1 & 1) as u32,
                (octant >> 2) as u32,
            );
            if let Ok(child) = self.key(
                key.level - 1,
                key.x * 2 + ox,
                key.y * 2 + oy,
                key.z * 2 + oz,
            ) {
                out.push((octant, child));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thesis_volume_levels() {
        // 512^3 with brick 16: 32^3 bricks at level 0, a complete octree of 6 levels,
        // (8^6 - 1) / 7 = 37449 nodes.
        let l = VolumeLayout::new([512; 3], 16, VoxelType::U8).unwrap();
        assert_eq!(l.levels(), 6);
        assert_eq!(l.node_count(), 37449);
        assert_eq!(l.grid(0), [32; 3]);
        assert_eq!(l.grid(5), [1; 3]);
    }

    #[test]
    fn uneven_volume_levels() {
        // 200x160x160, brick 16: grids 13x10x10, 7x5x5, 4x3x3, 2x2x2, 1x1x1.
        let l = VolumeLayout::new([200, 160, 160], 16, VoxelType::U8).unwrap();
        assert_eq!(l.levels(), 5);
        assert_eq!(l.grid(0), [13, 10, 10]);
        assert_eq!(l.grid(1), [7, 5, 5]);
        assert_eq!(l.grid(2), [4, 3, 3]);
        assert_eq!(l.grid(3), [2, 2, 2]);
        assert_eq!(l.node_count(), 1300 + 175 + 36 + 8 + 1);
        assert_eq!(l.level_dims(1), [100, 80, 80]);
        assert_eq!(l.level_dims(3), [25, 20, 20]);
    }

    #[test]
    fn single_voxel_volume_has_one_level() {
        let l = VolumeLayout::new([1, 1, 1], 16, VoxelType::U16).unwrap();
        assert_eq!(l.levels(), 1);
        assert_eq!(l.node_count(), 1);
        assert_eq!(l.brick_bytes(), 16 * 16 * 16 * 2);
    }

    #[test]
    fn node_index_round_trips_and_is_dense() {
        let l = VolumeLayout::new([17, 33, 5], 4, VoxelType::U8).unwrap();
        let mut seen = 0u64;
        for level in 0..l.levels() {
            let g = l.grid(level);
            for z in 0..g[2] {
                for y in 0..g[1] {
                    for x in 0..g[0] {
                        let key = l.key(level, x, y, z).unwrap();
                        let n = l.node_index(key);
                        assert_eq!(n, seen, "nodes are dense and in order");
                        assert_eq!(l.key_of(n).unwrap(), key);
                        seen += 1;
                    }
                }
            }
        }
        assert_eq!(seen, l.node_count());
        assert!(l.key_of(seen).is_err());
    }

    #[test]
    fn rejects_bad_layouts() {
        assert!(VolumeLayout::new([0, 1, 1], 16, VoxelType::U8).is_err());
        assert!(VolumeLayout::new([8, 8, 8], 12, VoxelType::U8).is_err());
        assert!(VolumeLayout::new([8, 8, 8], 512, VoxelType::U8).is_err());
        assert!(VolumeLayout::new([u32::MAX; 3], 2, VoxelType::U8).is_err());
    }

    #[test]
    fn keys_are_validated() {
        let l = VolumeLayout::new([40, 40, 40], 16, VoxelType::U8).unwrap();
        assert!(l.key(0, 2, 2, 2).is_ok());
        assert!(l.key(0, 3, 0, 0).is_err());
        assert!(l.key(2, 0, 0, 0).is_ok());
        assert!(l.key(3, 0, 0, 0).is_err());
    }

    #[test]
    fn neighbours_parents_children() {
        let l = VolumeLayout::new([40, 40, 40], 16, VoxelType::U8).unwrap();
        let k = l.key(0, 2, 1, 0).unwrap();
        assert_eq!(l.neighbour(k, [1, 0, 0]), None);
        assert_eq!(l.neighbour(k, [-1, 0, 0]), Some(l.key(0, 1, 1, 0).unwrap()));
        assert_eq!(l.neighbour(k, [0, 0, -1]), None);
        assert_eq!(l.parent(k), Some(l.key(1, 1, 0, 0).unwrap()));
        let root = l.key(2, 0, 0, 0).unwrap();
        assert_eq!(l.parent(root), None);
        // level 1 grid is 2x2x2; brick (1,1,1) has only child (2,2,2) in the 3x3x3 level 0.
        let c = l.children(l.key(1, 1, 1, 1).unwrap());
        assert_eq!(c, vec![(0, l.key(0, 2, 2, 2).unwrap())]);
        assert_eq!(l.children(l.key(1, 0, 0, 0).unwrap()).len(), 8);
    }
}
