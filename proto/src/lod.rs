//! Which tiles a camera needs: the thesis's spherical detail bias, computed from the layout
//! alone, so the server (adaptive meshes) and the client (the streamer's desired set) select
//! the same tiles by the same arithmetic; and how those tiles are stitched: face-adjacent tiles
//! differ by at most one level (the 2:1 rule, [`balance`]), and each tile's 6-bit
//! [`face_masks`] says which of its faces touch a coarser neighbour, the faces whose transition
//! strips it draws (`crate::mesh::stitch`).
//!
//! Face mask bits: bit 2a is the face at the low end of axis a (x, y, z), bit 2a + 1 the face at
//! the high end (`crate::mesh::FACE_NAMES`).

use crate::{BrickKey, VolumeLayout};

/// The tile sets of a selection too large for [`Members`]' bits: foldhash, not the standard
/// library's SipHash (the keys come from the layout, so resistance to chosen keys buys
/// nothing).
type TileSet = std::collections::HashSet<BrickKey, foldhash::fast::RandomState>;

/// Pyramids of at most this many bricks keep a selection's members as one bit per brick (2 MiB
/// at most; a 2048^3 volume in bricks of 16 has 2.4 M bricks, 300 KB); larger ones in a hash
/// set.
const MEMBER_BITS_MAX: u64 = 1 << 24;

/// The tiles of a selection, for the membership tests of [`balance`] and [`face_masks`]: tens
/// per tile (each of its 26 neighbours, and their ancestors up to the tile that covers them),
/// so they are a bit test where the pyramid allows, with each level's grid computed once. A
/// streamer selects thousands of tiles on every camera move; with a hash set and the layout's
/// checked neighbour lookups a selection took 3.1 times as long
/// (`cargo bench -p isovox-tools -- selection`). Keys outside the layout are never members.
struct Members<'a> {
    layout: &'a VolumeLayout,
    grids: Vec<[u32; 3]>,
    index: MemberIndex,
}

enum MemberIndex {
    /// Bit `base[level] + x + gx (y + gy z)`, as [`VolumeLayout::node_index`] numbers bricks.
    Bits {
        base: Vec<u64>,
        bits: Vec<u64>,
    },
    Set(TileSet),
}

impl<'a> Members<'a> {
    /// `tiles` as members, as bits when `bits` (and the pyramid has at most
    /// [`MEMBER_BITS_MAX`] bricks), else in a hash set.
    fn new(layout: &'a VolumeLayout, tiles: &[BrickKey], bits: bool) -> Members<'a> {
        let grids: Vec<[u32; 3]> = (0..layout.levels()).map(|l| layout.grid(l)).collect();
        let index = if bits && layout.node_count() <= MEMBER_BITS_MAX {
            let base = (0..layout.levels())
                .map(|l| layout.level_range(l).0)
                .collect();
            let words = layout.node_count().div_ceil(64) as usize;
            MemberIndex::Bits {
                base,
                bits: vec![0; words],
            }
        } else {
            MemberIndex::Set(TileSet::default())
        };
        let mut members = Members {
            layout,
            grids,
            index,
        };
        for &k in tiles {
            members.insert(k);
        }
        members
    }

    /// Whether `key` lies in the layout.
    fn inside(grids: &[[u32; 3]], key: BrickKey) -> bool {
        grids
            .get(usize::from(key.level))
            .is_some_and(|g| key.x < g[0] && key.y < g[1] && key.z < g[2])
    }

    /// The word and bit of `key`; `None` outside the layout.
    fn bit(grids: &[[u32; 3]], base: &[u64], key: BrickKey) -> Option<(usize, u64)> {
        if !Members::inside(grids, key) {
            return None;
        }
        let g = grids[usize::from(key.level)];
        let i = base[usize::from(key.level)]
            + u64::from(key.x)
            + u64::from(g[0]) * (u64::from(key.y) + u64::from(g[1]) * u64::from(key.z));
        Some(((i / 64) as usize, 1 << (i % 64)))
    }

    fn contains(&self, key: BrickKey) -> bool {
        match &self.index {
            MemberIndex::Bits { base, bits } => {
                Members::bit(&self.grids, base, key).is_some_and(|(w, b)| bits[w] & b != 0)
            }
            MemberIndex::Set(set) => set.contains(&key),
        }
    }

    fn insert(&mut self, key: BrickKey) {
        match &mut self.index {
            MemberIndex::Bits { base, bits } => {
                if let Some((w, b)) = Members::bit(&self.grids, base, key) {
                    bits[w] |= b;
                }
            }
            MemberIndex::Set(set) => {
                if Members::inside(&self.grids, key) {
                    set.insert(key);
                }
            }
        }
    }

    fn remove(&mut self, key: BrickKey) {
        match &mut self.index {
            MemberIndex::Bits { base, bits } => {
                if let Some((w, b)) = Members::bit(&self.grids, base, key) {
                    bits[w] &= !b;
                }
            }
            MemberIndex::Set(set) => {
                set.remove(&key);
            }
        }
    }

    /// [`VolumeLayout::neighbour`], with the grids computed once.
    fn neighbour(&self, key: BrickKey, d: [i32; 3]) -> Option<BrickKey> {
        Members::step(&self.grids, key, d)
    }

    /// The neighbour of `key` in direction `d` in a layout of level grids `grids`.
    fn step(grids: &[[u32; 3]], key: BrickKey, d: [i32; 3]) -> Option<BrickKey> {
        let g = grids.get(usize::from(key.level))?;
        let step = |c: u32, d: i32, n: u32| c.checked_add_signed(d).filter(|&c| c < n);
        Some(BrickKey {
            level: key.level,
            x: step(key.x, d[0], g[0])?,
            y: step(key.y, d[1], g[1])?,
            z: step(key.z, d[2], g[2])?,
        })
    }

    /// The member whose region contains tile `key`'s: `key` itself or an ancestor; `None`
    /// when that region is divided into finer members.
    fn covering(&self, key: BrickKey) -> Option<BrickKey> {
        let mut k = key;
        loop {
            if self.contains(k) {
                return Some(k);
            }
            k = self.layout.parent(k)?;
        }
    }
}

/// Sorts tiles in [`BrickKey`]'s order (level, x, y, z), compared as one integer: a camera
/// move re-selects thousands of tiles, and comparing four fields was most of a streamer's
/// selection time.
fn sort_tiles(tiles: &mut [BrickKey]) {
    tiles.sort_unstable_by_key(|k| {
        u128::from(k.level) << 96 | u128::from(k.x) << 64 | u128::from(k.y) << 32 | u128::from(k.z)
    });
}

/// The face directions in face-mask order: -x, +x, -y, +y, -z, +z.
pub const FACE_DIRECTIONS: [[i32; 3]; 6] = [
    [-1, 0, 0],
    [1, 0, 0],
    [0, -1, 0],
    [0, 1, 0],
    [0, 0, -1],
    [0, 0, 1],
];

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

/// The tiles to stitch for `camera`: [`adaptive_tiles`], then [`balance`] refines where a tile
/// would touch one two or more levels finer. The result covers the volume once, tiles that touch
/// differ by at most one level, and [`face_masks`] gives each its strips. Sorted.
///
/// Radii far enough apart ([`radii_keep_balance`]) select balanced tiles by themselves, and are
/// not balanced again.
pub fn balanced_tiles(
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    camera: [f32; 3],
    radii: &[f32],
) -> Vec<BrickKey> {
    let tiles = adaptive_tiles(layout, voxel_scale, camera, radii);
    if radii_keep_balance(layout, voxel_scale, camera, radii) {
        tiles
    } else {
        balance(layout, tiles)
    }
}

/// [`balanced_tiles`] and their [`face_masks`], as a streamer of mesh tiles needs them on every
/// camera move. Where [`radii_keep_balance`] holds, a mask bit is read off the radii: the tile
/// across a face is coarser exactly when that tile's parent was not refined, so no membership
/// test is made. That is what lets 50 streamers of one process select 10 times a second on a
/// 2048^3 world (`cargo bench -p isovox-tools -- selection`).
pub fn stitched_tiles(
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    camera: [f32; 3],
    radii: &[f32],
) -> (Vec<BrickKey>, Vec<u8>) {
    let tiles = adaptive_tiles(layout, voxel_scale, camera, radii);
    if !radii_keep_balance(layout, voxel_scale, camera, radii) {
        let tiles = balance(layout, tiles);
        let masks = face_masks(layout, &tiles);
        return (tiles, masks);
    }
    let grids: Vec<[u32; 3]> = (0..layout.levels()).map(|l| layout.grid(l)).collect();
    let masks = tiles
        .iter()
        .map(|&tile| {
            let mut mask = 0u8;
            let parent = layout.parent(tile);
            for (f, d) in FACE_DIRECTIONS.into_iter().enumerate() {
                // Balanced, the region across face f is covered by the neighbour itself, finer
                // tiles, or the neighbour's parent: the parent when the walk from the root
                // stopped there. The tile's own parent was refined (half the faces: no distance
                // to compute).
                let coarser = Members::step(&grids, tile, d)
                    .and_then(|n| layout.parent(n))
                    .is_some_and(|p| {
                        Some(p) != parent && !refined(layout, voxel_scale, camera, radii, p)
                    });
                mask |= u8::from(coarser) << f;
            }
            mask
        })
        .collect();
    (tiles, masks)
}

/// Whether [`adaptive_tiles`] refines tile `key`: always above the last radius's level, else
/// when its nearest point lies within the radius of the level below it (never at level 0).
fn refined(
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    camera: [f32; 3],
    radii: &[f32],
    key: BrickKey,
) -> bool {
    let level = usize::from(key.level);
    level > radii.len()
        || (level > 0 && tile_distance(layout, voxel_scale, key, camera) <= radii[level - 1])
}

/// Whether [`adaptive_tiles`] is balanced (2:1 across faces, edges and corners) for any camera
/// near the volume because each radius exceeds the one before by more than the diagonal of a
/// tile of its level: `r(j) - r(j-1) > d(j)` for every `j >= 1`.
///
/// Why: let tile T of level k touch a tile F of level k - 2 or finer. F's ancestor A of level
/// k - 1 was refined, so its nearest point p lies within `r(k-2)` of the camera. A touches T
/// (it holds F and is not inside T, which would then have been refined), so some point of T lies
/// within `d(k-1)` of p: T's distance is at most `r(k-2) + d(k-1) < r(k-1)`, and T was refined
/// too, not selected. Distances are computed in `f32`: the margin (1% of the diagonal, and a
/// millionth of the coordinates' size) covers their rounding.
pub fn radii_keep_balance(
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    camera: [f32; 3],
    radii: &[f32],
) -> bool {
    let size = (0..3)
        .map(|a| {
            f64::from(camera[a]).abs()
                + f64::from(layout.dims()[a]) * f64::from(voxel_scale[a]).abs()
        })
        .fold(0.0, f64::max);
    radii.windows(2).enumerate().all(|(i, r)| {
        let span = f64::from(layout.brick()) * (1u64 << (i + 1)) as f64;
        let diagonal = (0..3)
            .map(|a| (span * f64::from(voxel_scale[a])).powi(2))
            .sum::<f64>()
            .sqrt();
        f64::from(r[1]) - f64::from(r[0]) > diagonal * 1.01 + size * 1e-6
    })
}

/// The tiles the spherical detail bias selects, sorted: with radii `r0 < r1 < ... < r(n-1)`,
/// level k where the tile's nearest point lies within `r(k)` of the camera, level n (or the
/// coarsest, if fewer) beyond the last radius. Walking down from the root, a tile of level k+1
/// is refined into its children when it is within `r(k)`, and always while k+1 > n. The result
/// covers the volume once; neighbours may differ by more than one level (see
/// [`balanced_tiles`]).
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
        if refined(layout, voxel_scale, camera, radii, k) {
            stack.extend(layout.children(k).into_iter().map(|(_, c)| c));
        } else {
            out.push(k);
        }
    }
    sort_tiles(&mut out);
    out
}

/// Refines `tiles` (a set covering the volume once) until no two tiles that touch, across a
/// face, an edge or a corner, differ by more than one level: a tile with a neighbour two or more
/// levels finer is split into its children, repeatedly. Splitting only adds detail, so every
/// tile is at most as coarse as it was. Returns the tiles sorted.
///
/// Edges and corners count because at most two levels may meet at any point for the stitching
/// to close: a tile's transition strips end on its edges, where they meet the strips of the
/// tiles around that edge, all of them one level finer than the coarse tile they border.
pub fn balance(layout: &VolumeLayout, tiles: Vec<BrickKey>) -> Vec<BrickKey> {
    balance_with(layout, tiles, true)
}

/// [`balance`], its members as bits when `bits` allows (the tests compare both ways).
fn balance_with(layout: &VolumeLayout, tiles: Vec<BrickKey>, bits: bool) -> Vec<BrickKey> {
    let mut members = Members::new(layout, &tiles, bits);
    // Every tile that was a member at some point; those split are left out at the end.
    let mut seen = tiles.clone();
    let mut work = tiles;
    let around: Vec<[i32; 3]> = (0..27)
        .map(|i| [i % 3 - 1, i / 3 % 3 - 1, i / 9 - 1])
        .filter(|d| *d != [0, 0, 0])
        .collect();
    while let Some(fine) = work.pop() {
        if !members.contains(fine) {
            continue;
        }
        for &d in &around {
            let Some(n) = members.neighbour(fine, d) else {
                continue;
            };
            let Some(coarse) = members.covering(n) else {
                continue;
            };
            if coarse.level >= fine.level + 2 {
                members.remove(coarse);
                for (_, child) in layout.children(coarse) {
                    members.insert(child);
                    work.push(child);
                    seen.push(child);
                }
                work.push(fine); // its neighbour across d may still be too coarse
                break;
            }
        }
    }
    seen.retain(|&k| members.contains(k));
    sort_tiles(&mut seen);
    seen.dedup();
    seen
}

/// For each tile of `tiles` (a balanced selection covering the volume once, as
/// [`balanced_tiles`] returns), its face mask: bit f set when the tile across face f is one
/// level coarser, so the tile draws its transition strip there and moves its vertices out of
/// the strip's way. Faces on the volume's boundary, or touching tiles of the same or a finer
/// level, have no bit.
pub fn face_masks(layout: &VolumeLayout, tiles: &[BrickKey]) -> Vec<u8> {
    face_masks_with(layout, tiles, true)
}

/// [`face_masks`], the members as bits when `bits` allows (the tests compare both ways).
fn face_masks_with(layout: &VolumeLayout, tiles: &[BrickKey], bits: bool) -> Vec<u8> {
    let members = Members::new(layout, tiles, bits);
    tiles
        .iter()
        .map(|&tile| {
            let mut mask = 0u8;
            for (f, d) in FACE_DIRECTIONS.into_iter().enumerate() {
                let coarser = members
                    .neighbour(tile, d)
                    .and_then(|n| members.covering(n))
                    .is_some_and(|c| c.level > tile.level);
                mask |= u8::from(coarser) << f;
            }
            mask
        })
        .collect()
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

    /// A deterministic xorshift for the random cameras.
    fn rng(seed: u64) -> impl FnMut() -> f32 {
        let mut s = seed | 1;
        move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// Each level-0 brick of the grid, the level of the tile owning it (or 255 when none),
    /// and how many tiles own it: a raster of the selection computed from the keys alone.
    fn raster(layout: &VolumeLayout, tiles: &[BrickKey]) -> (Vec<u8>, Vec<u8>) {
        let g = layout.grid(0).map(|c| c as usize);
        let mut level = vec![255u8; g[0] * g[1] * g[2]];
        let mut owners = vec![0u8; g[0] * g[1] * g[2]];
        for t in tiles {
            let span = 1usize << t.level;
            let lo = [t.x, t.y, t.z].map(|c| c as usize * span);
            for z in lo[2]..(lo[2] + span).min(g[2]) {
                for y in lo[1]..(lo[1] + span).min(g[1]) {
                    for x in lo[0]..(lo[0] + span).min(g[0]) {
                        let i = (z * g[1] + y) * g[0] + x;
                        level[i] = t.level;
                        owners[i] += 1;
                    }
                }
            }
        }
        (level, owners)
    }

    #[test]
    fn random_cameras_give_balanced_covers_and_consistent_masks() {
        // Odd grids too: 13x10x7 bricks of 8 has levels 0..=4 with partial parents.
        let layouts = [
            VolumeLayout::new([512, 512, 512], 16, VoxelType::U8),
            VolumeLayout::new([104, 80, 56], 8, VoxelType::U8),
        ];
        let mut next = rng(0x15);
        let mut unbalanced_before = 0;
        for layout in layouts {
            let layout = layout.unwrap_or_else(|e| panic!("{e}"));
            let g = layout.grid(0).map(|c| c as usize);
            let dims = layout.dims().map(|d| d as f32);
            for _ in 0..150 {
                let camera = [0, 1, 2].map(|a| (next() * 1.6 - 0.3) * dims[a]);
                let r0 = 4.0 + next() * dims[0] * 0.3;
                let radii = [r0, r0 * (1.0 + next() * 1.5), r0 * (2.5 + next() * 2.0)];
                let before = adaptive_tiles(&layout, [1.0; 3], camera, &radii);
                let tiles = balanced_tiles(&layout, [1.0; 3], camera, &radii);
                // The hash set that pyramids too large for bits use gives the same tiles.
                assert_eq!(balance_with(&layout, before.clone(), false), tiles);
                let (level, owners) = raster(&layout, &tiles);
                assert!(
                    owners.iter().all(|&n| n == 1),
                    "the tiles cover the grid once"
                );
                // Balancing only refines: every level-0 brick is at most as coarse as before.
                let (level_before, _) = raster(&layout, &before);
                assert!(level.iter().zip(&level_before).all(|(a, b)| a <= b));
                // 2:1 between level-0 bricks touching by a face, an edge or a corner, read off
                // the raster.
                let mut worst_before = 0;
                for z in 0..g[2] {
                    for y in 0..g[1] {
                        for x in 0..g[0] {
                            let i = (z * g[1] + y) * g[0] + x;
                            for d in (0..27usize).filter(|&d| d != 13) {
                                let o = [d % 3, d / 3 % 3, d / 9];
                                let p = [x + o[0], y + o[1], z + o[2]];
                                if (0..3).any(|a| p[a] < 1 || p[a] > g[a]) {
                                    continue;
                                }
                                let j = ((p[2] - 1) * g[1] + p[1] - 1) * g[0] + p[0] - 1;
                                assert!(level[i].abs_diff(level[j]) <= 1, "2:1 broken");
                                worst_before =
                                    worst_before.max(level_before[i].abs_diff(level_before[j]));
                            }
                        }
                    }
                }
                if worst_before > 1 {
                    unbalanced_before += 1;
                }
                // Masks: bit f of a tile is set exactly when the level-0 bricks just across
                // face f belong to tiles one level coarser (all of them: a face touches one
                // coarser tile, or same-level or finer ones).
                let masks = face_masks(&layout, &tiles);
                assert_eq!(face_masks_with(&layout, &tiles, false), masks);
                // Where the radii keep the balance, the masks read off the radii are the same.
                assert_eq!(
                    stitched_tiles(&layout, [1.0; 3], camera, &radii),
                    (tiles.clone(), masks.clone())
                );
                for (t, &mask) in tiles.iter().zip(&masks) {
                    let span = 1i64 << t.level;
                    let lo = [t.x, t.y, t.z].map(|c| c as i64 * span);
                    for (f, d) in FACE_DIRECTIONS.iter().enumerate() {
                        let a = f / 2;
                        let across = if d[a] > 0 { lo[a] + span } else { lo[a] - 1 };
                        if across < 0 || across >= g[a] as i64 {
                            assert_eq!(mask >> f & 1, 0, "no bit on the volume's boundary");
                            continue;
                        }
                        let (b, c) = ((a + 1) % 3, (a + 2) % 3);
                        let mut levels = Vec::new();
                        for u in lo[b]..(lo[b] + span).min(g[b] as i64) {
                            for v in lo[c]..(lo[c] + span).min(g[c] as i64) {
                                let mut p = [0i64; 3];
                                p[a] = across;
                                p[b] = u;
                                p[c] = v;
                                let p = p.map(|x| x as usize);
                                levels.push(level[(p[2] * g[1] + p[1]) * g[0] + p[0]]);
                            }
                        }
                        let coarser = levels.iter().all(|&l| l == t.level + 1);
                        assert!(coarser || levels.iter().all(|&l| l <= t.level));
                        assert_eq!(mask >> f & 1 == 1, coarser, "tile {t}, face {f}");
                    }
                }
            }
        }
        // The cameras exercise the rule: without it some selections break 2:1.
        assert!(unbalanced_before > 0);
    }

    #[test]
    fn radii_a_diagonal_apart_keep_the_balance() {
        // Brick 16, scale 1: a level-1 tile's diagonal is 32 sqrt 3 = 55.43, with the 1% margin
        // 55.98; a level-2 tile's 110.85 (111.96).
        let layout = VolumeLayout::new([256, 256, 256], 16, VoxelType::U8).unwrap_or_else(|e| {
            panic!("{e}");
        });
        let keeps = |radii: &[f32], scale| radii_keep_balance(&layout, scale, [0.0; 3], radii);
        assert!(keeps(&[100.0, 156.0], [1.0; 3]));
        assert!(!keeps(&[100.0, 155.0], [1.0; 3]));
        assert!(keeps(&[100.0, 156.0, 268.0], [1.0; 3]));
        assert!(!keeps(&[100.0, 156.0, 267.0], [1.0; 3]));
        // One radius, or none: nothing to balance.
        assert!(keeps(&[5.0], [1.0; 3]));
        assert!(keeps(&[], [1.0; 3]));
        // Voxels twice as tall: the diagonal is 32 sqrt 6 = 78.38 (79.17).
        assert!(keeps(&[100.0, 179.2], [1.0, 2.0, 1.0]));
        assert!(!keeps(&[100.0, 179.1], [1.0, 2.0, 1.0]));
    }

    #[test]
    fn radii_that_keep_the_balance_select_as_balancing_does() {
        // Random cameras in and around odd grids with anisotropic voxels, radii each a random
        // 1-3 diagonals beyond the last: the tiles equal the balanced ones and the masks read
        // off the radii equal those found by membership, on both membership paths.
        let layouts = [
            (
                VolumeLayout::new([512, 384, 512], 16, VoxelType::U8),
                [1.0, 1.0, 1.0],
            ),
            (
                VolumeLayout::new([104, 80, 56], 8, VoxelType::U8),
                [0.5, 1.5, 1.0],
            ),
        ];
        let mut next = rng(0x51);
        let mut mixed = 0;
        for (layout, scale) in layouts {
            let layout = layout.unwrap_or_else(|e| panic!("{e}"));
            let extent = [0, 1, 2].map(|a| layout.dims()[a] as f32 * scale[a]);
            for _ in 0..100 {
                let camera = [0, 1, 2].map(|a| (next() * 1.6 - 0.3) * extent[a]);
                let mut radii = vec![2.0 + next() * extent[0] * 0.1];
                for j in 1..layout.levels() as u32 {
                    let span = layout.brick() as f32 * (1u32 << j) as f32;
                    let diagonal = (0..3)
                        .map(|a| (span * scale[a]).powi(2))
                        .sum::<f32>()
                        .sqrt();
                    radii.push(radii[radii.len() - 1] + diagonal * (1.02 + 2.0 * next()));
                }
                assert!(radii_keep_balance(&layout, scale, camera, &radii));
                let before = adaptive_tiles(&layout, scale, camera, &radii);
                let (tiles, masks) = stitched_tiles(&layout, scale, camera, &radii);
                assert_eq!(tiles, before, "no tile split");
                for bits in [true, false] {
                    assert_eq!(balance_with(&layout, before.clone(), bits), tiles);
                    assert_eq!(face_masks_with(&layout, &tiles, bits), masks);
                }
                if masks.iter().any(|&m| m != 0) {
                    mixed += 1;
                }
            }
        }
        // Most selections mix levels, so the masks are tested, not only zeros.
        assert!(mixed > 150, "{mixed} selections with a coarser face");
    }

    #[test]
    fn keys_outside_the_layout_are_no_tiles() {
        let layout = VolumeLayout::new([64, 64, 64], 8, VoxelType::U8).unwrap_or_else(|e| {
            panic!("{e}");
        });
        let outside = [
            BrickKey {
                level: 9,
                x: 0,
                y: 0,
                z: 0,
            },
            BrickKey {
                level: 0,
                x: 8,
                y: 0,
                z: 0,
            },
        ];
        for bits in [true, false] {
            assert_eq!(face_masks_with(&layout, &outside, bits), vec![0, 0]);
            assert_eq!(balance_with(&layout, outside.to_vec(), bits), Vec::new());
        }
    }

    #[test]
    fn balance_and_masks_by_hand() {
        // 64^3, brick 8: grids 8^3, 4^3, 2^3, 1. A cover with level 0 in one corner: the 8
        // level-0 children of level-1 tile (0,0,0), the other 7 level-1 children of level-2
        // tile (0,0,0), the other 7 level-2 tiles. Neighbours differ by one level: balanced.
        let layout = VolumeLayout::new([64, 64, 64], 8, VoxelType::U8).unwrap_or_else(|e| {
            panic!("{e}");
        });
        let key = |level, x, y, z| BrickKey { level, x, y, z };
        let children = |k: BrickKey| layout.children(k).into_iter().map(|(_, c)| c);
        let mut tiles: Vec<BrickKey> = children(key(1, 0, 0, 0)).collect();
        tiles.extend(children(key(2, 0, 0, 0)).skip(1));
        tiles.extend(children(key(3, 0, 0, 0)).skip(1));
        assert_eq!(tiles.len(), 8 + 7 + 7);
        assert_eq!(balance(&layout, tiles.clone()).len(), tiles.len());
        // Refine level-1 tile (1,0,0) too: level-0 tile (3,0,0) now touches level-2 tile
        // (1,0,0) across +x, two levels coarser, which splits into its 8 level-1 children.
        tiles.retain(|k| *k != key(1, 1, 0, 0));
        tiles.extend(children(key(1, 1, 0, 0)));
        let balanced = balance(&layout, tiles);
        assert!(!balanced.contains(&key(2, 1, 0, 0)));
        let count = |l| balanced.iter().filter(|k| k.level == l).count();
        assert_eq!((count(0), count(1), count(2)), (16, 6 + 8, 6));
        // Level-0 tile (3,1,1): level 0 across -x, -y, -z; across +x level-1 (2,0,0), across
        // +y level-1 (1,1,0), across +z level-1 (1,0,1): bits 1, 3 and 5.
        let masks = face_masks(&layout, &balanced);
        let i = balanced
            .iter()
            .position(|k| *k == key(0, 3, 1, 1))
            .unwrap_or(usize::MAX);
        assert_eq!(masks[i], 0b10_1010);
        // Level-1 tile (2,1,0), a child of the split tile: level 1 across -x, +x, -y and +z,
        // the volume's boundary across -z, level-2 tile (1,1,0) across +y: bit 3 alone.
        let j = balanced
            .iter()
            .position(|k| *k == key(1, 2, 1, 0))
            .unwrap_or(usize::MAX);
        assert_eq!(masks[j], 0b00_1000);
    }
}
