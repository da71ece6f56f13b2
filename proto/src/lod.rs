//! Which tiles a camera needs: the thesis's spherical detail bias, computed from the layout
//! alone, so the server (adaptive meshes) and the client (the streamer's desired set) select
//! the same tiles by the same arithmetic.

use crate::{BrickKey, VolumeLayout};

/// The distance from `camera` to the nearest point of tile `key`'s box, in world units (voxel
/// coordinates times `voxel_scale`); 0 inside the box.
pub fn tile_distance(
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    key: BrickKey,
    camera: [f32; 3],
) -> f32 {
    let span = layout.brick() as f32 * (1u64 << key.level) as f32;
    let mut d2 = 0f32;
    for (a, c) in [key.x, key.y, key.z].into_iter().enumerate() {
        let (lo, hi) = (
            c as f32 * span * voxel_scale[a],
            (c as f32 + 1.0) * span * voxel_scale[a],
        );
        let d = if camera[a] < lo {
            lo - camera[a]
        } else if camera[a] > hi {
            camera[a] - hi
        } else {
            0.0
        };
        d2 += d * d;
    }
    d2.sqrt()
}

/// The tiles the spherical detail bias selects, sorted: with radii `r0 < r1 < ... < r(n-1)`,
/// level k where the tile's nearest point lies within `r(k)` of the camera, level n (or the
/// coarsest, if fewer) beyond the last radius. Walking down from the root, a tile of level k+1
/// is refined into its children when it is within `r(k)`, and always while k+1 > n. The
/// result covers the volume once.
pub fn adaptive_tiles(
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    camera: [f32; 3],
    radii: &[f32],
) -> Vec<BrickKey> {
    let top = layout.levels() - 1;
    let g = layout.grid(top);
    let mut stack = Vec::new();
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                stack.push(BrickKey {
                    level: top,
                    x,
                    y,
                    z,
                });
            }
        }
    }
    let mut out = Vec::new();
    while let Some(k) = stack.pop() {
        let level = k.level as usize;
        let refine = level > radii.len()
            || (level > 0 && tile_distance(layout, voxel_scale, k, camera) <= radii[level - 1]);
        if refine {
            stack.extend(layout.children(k).into_iter().map(|(_, c)| c));
        } else {
            out.push(k);
        }
    }
    out.sort();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::VoxelType;

    #[test]
    fn distances_by_hand() {
        // Brick 8, scale (1, 2, 1): the level-1 tile (1, 0, 0) spans x 16..32, y 0..32.
        let layout = VolumeLayout::new([64, 64, 64], 8, VoxelType::U8).unwrap_or_else(|e| {
            panic!("{e}");
        });
        let k = BrickKey {
            level: 1,
            x: 1,
            y: 0,
            z: 0,
        };
        let s = [1.0, 2.0, 1.0];
        assert_eq!(tile_distance(&layout, s, k, [20.0, 10.0, 5.0]), 0.0);
        assert_eq!(tile_distance(&layout, s, k, [13.0, 36.0, 5.0]), 5.0);
        assert_eq!(tile_distance(&layout, s, k, [20.0, 10.0, -2.0]), 2.0);
    }

    #[test]
    fn radii_pick_the_levels() {
        // Grids 5x3x2, 3x2x1, 2x1x1, 1x1x1.
        let layout = VolumeLayout::new([40, 24, 16], 8, VoxelType::U16).unwrap_or_else(|e| {
            panic!("{e}");
        });
        assert_eq!(layout.levels(), 4);
        // No radius: level 0 everywhere.
        let fine = adaptive_tiles(&layout, [1.0; 3], [0.0; 3], &[]);
        assert_eq!(fine.len(), 5 * 3 * 2);
        assert!(fine.iter().all(|k| k.level == 0));
        // Three radii nothing lies within: the root alone.
        let root = adaptive_tiles(&layout, [1.0; 3], [0.0; 3], &[-1.0; 3]);
        assert_eq!(root.len(), 1);
        assert_eq!(root[0].level, 3);
        // One radius of 4 at the origin corner: levels 3 and 2 are always refined; of the six
        // level-1 tiles (16 voxels wide) only (0,0,0) lies within 4, so it alone is refined into
        // its 8 level-0 children, and the other 5 stay.
        let mixed = adaptive_tiles(&layout, [1.0; 3], [0.0; 3], &[4.0]);
        assert_eq!(mixed.iter().filter(|k| k.level == 0).count(), 8);
        assert_eq!(mixed.iter().filter(|k| k.level == 1).count(), 5);
        assert_eq!(mixed.len(), 13);
    }
}
