//! The octree descent: which desired tiles can have no surface at the iso value, decided from
//! the value ranges (`min`, `max`) of coarser bricks, so that their own grid regions, bricks and
//! mesh tiles are never asked for.
//!
//! A level-(k+1) voxel is the rounded mean (half up) of its 2x2x2 level-k voxels:
//! `p = floor((s + 4) / 8)` with `s` their sum, so `8p - 4 <= s <= 8p + 3`. Each of the eight
//! lies in `0..=H` (H the type's highest value), so each is at most `s <= 8p + 3` and at least
//! `s - 7H >= 8p - 4 - 7H`. A parent brick whose voxels lie in `[lo, hi]` therefore has children
//! whose voxels lie in [`child_bound`]`(lo, hi) = [max(0, 8 lo - 4 - 7H), min(H, 8 hi + 3)]`.
//! That is a bound, not an estimate: the mean can hide a thin feature (one solid voxel among
//! seven of air averages to a low value), and the bound accounts for it. It widens eightfold per
//! level, so it only ever prunes under parents that are nearly all air or nearly all solid
//! (u8 at the default iso 126.5: a parent's `max <= 15` or `min >= 240`), which is what most of
//! a volume is.
//!
//! A brick's bound is its own range when the hash book has it, else its parent's bound carried
//! down one level, as long as that lies wholly on one side of the iso value; otherwise the brick's
//! own grid entry is needed ([`HashBook::bound`] names the brick to ask for). Asking for it only
//! where the bound above straddles the iso value is the descent: the coarsest level's grid first,
//! then finer regions only under bricks that may hold the surface.
//!
//! A tile is skipped when every brick it reads (a mesh tile's bricks and its strips', or for a
//! brick the bricks its mesh tile would read: the surface between two bricks is drawn from both)
//! is bounded wholly below the iso value, or every one wholly above: no cell then has corners on
//! both sides, so there is no surface to draw. A skipped tile is complete without content; an
//! edit that changes what it reads invalidates it and it is decided again.
//!
//! Deciding again needs no grid region when the commit event lists the changed bricks' new
//! ranges. A brick the commit did not change may still have been bounded by a coarser one it
//! changed (the new coarse range may straddle the iso value where the old one did not): its
//! content is what it was, so the bound drawn from the coarser brick's range before the commit
//! still holds, and [`HashBook::bounds_before`] keeps it ([`HashBook::keep_bound`]).

use super::book::{bricks_read, HashBook};
use super::FastSet;
use isovox_proto::tile::GridBox;
use isovox_proto::{BrickKey, VolumeLayout};

/// Most bounds the memo keeps before it starts again.
const MEMO_BOUNDS: usize = 1 << 18;

/// The range of the voxels of any child of a parent brick whose voxels lie in `(lo, hi)`, for
/// values in `0..=high` (see the module documentation).
pub(super) fn child_bound((lo, hi): (u16, u16), high: u16) -> (u16, u16) {
    let h = i64::from(high);
    let lo = (8 * i64::from(lo) - 4 - 7 * h).clamp(0, h);
    let hi = (8 * i64::from(hi) + 3).clamp(0, h);
    (lo as u16, hi as u16)
}

/// Where values in `(lo, hi)` lie with respect to `iso`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Side {
    Below,
    Above,
    /// Some may be below and some above (or equal to it).
    Both,
}

pub(super) fn side((lo, hi): (u16, u16), iso: f32) -> Side {
    if f32::from(hi) < iso {
        Side::Below
    } else if f32::from(lo) > iso {
        Side::Above
    } else {
        Side::Both
    }
}

/// The sides of `iso` the bricks a tile reads lie on, as far as their bounds tell.
#[derive(Debug, Default)]
struct Sides {
    below: bool,
    above: bool,
    /// Some brick's bound straddles `iso`.
    both: bool,
    /// The bricks whose grid entries are needed to tell.
    unknown: Vec<BrickKey>,
}

impl Sides {
    fn add(&mut self, bound: Result<(u16, u16), BrickKey>, iso: f32) {
        match bound.map(|r| side(r, iso)) {
            Ok(Side::Below) => self.below = true,
            Ok(Side::Above) => self.above = true,
            Ok(Side::Both) => self.both = true,
            Err(u) => self.unknown.push(u),
        }
    }

    /// A surface may cross the bricks: one straddles `iso`, or some lie below and some above.
    fn surface(&self) -> bool {
        self.both || (self.below && self.above)
    }
}

/// What the descent decides for a tile.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum Decision {
    /// No surface can cross it: skip it.
    Empty,
    /// It may hold the surface: fetch it as usual.
    Surface,
    /// These bricks' grid entries are needed to decide.
    Unknown(Vec<BrickKey>),
}

impl HashBook {
    /// The bound on brick `b`'s voxels, or the brick whose grid entry is needed first (`b`
    /// itself or an ancestor).
    pub(super) fn bound(
        &self,
        layout: &VolumeLayout,
        b: BrickKey,
        iso: f32,
    ) -> Result<(u16, u16), BrickKey> {
        {
            let mut memo = self.memo.borrow_mut();
            if memo.generation != self.generation() || memo.iso != iso.to_bits() {
                memo.generation = self.generation();
                memo.iso = iso.to_bits();
                memo.bounds.clear();
            } else if let Some(&known) = memo.bounds.get(&b) {
                return known;
            }
        }
        // Not borrowed while working it out: that asks for the parent's bound.
        let bound = self.work_out_bound(layout, b, iso);
        let mut memo = self.memo.borrow_mut();
        // A bound on a bound: a long-lived book does not keep every brick it ever looked at.
        if memo.bounds.len() >= MEMO_BOUNDS {
            memo.bounds.clear();
        }
        memo.bounds.insert(b, bound);
        bound
    }

    /// [`HashBook::bound`] without the memo.
    fn work_out_bound(
        &self,
        layout: &VolumeLayout,
        b: BrickKey,
        iso: f32,
    ) -> Result<(u16, u16), BrickKey> {
        if let Some(r) = self.range(b).or_else(|| self.kept_bound(b)) {
            return Ok(r);
        }
        if b.level + 1 >= layout.levels() {
            return Err(b);
        }
        let parent = BrickKey {
            level: b.level + 1,
            x: b.x / 2,
            y: b.y / 2,
            z: b.z / 2,
        };
        let carried = child_bound(self.bound(layout, parent, iso)?, layout.voxel_type().high());
        match side(carried, iso) {
            Side::Both => Err(b),
            Side::Below | Side::Above => Ok(carried),
        }
    }

    /// The bounds on the children of the bricks a commit `changed` (positions per level) that
    /// hold before it is applied and lie wholly on one side of `iso`: after it, they still
    /// bound the children it did not change (keep them with [`HashBook::keep_bound`]).
    pub(super) fn bounds_before(
        &self,
        layout: &VolumeLayout,
        changed: &[Vec<[u32; 3]>],
        iso: f32,
    ) -> Vec<(BrickKey, (u16, u16))> {
        let high = layout.voxel_type().high();
        let mut bounds = Vec::new();
        for (level, positions) in changed.iter().enumerate().skip(1) {
            if level >= layout.levels() as usize {
                break;
            }
            let changed_below: FastSet<[u32; 3]> = changed[level - 1].iter().copied().collect();
            for &p in positions {
                let parent = BrickKey {
                    level: level as u8,
                    x: p[0],
                    y: p[1],
                    z: p[2],
                };
                let Ok(before) = self.bound(layout, parent, iso) else {
                    continue;
                };
                let carried = child_bound(before, high);
                if side(carried, iso) == Side::Both {
                    continue;
                }
                for (_, child) in layout.children(parent) {
                    if !changed_below.contains(&[child.x, child.y, child.z]) {
                        bounds.push((child, carried));
                    }
                }
            }
        }
        bounds
    }

    /// Whether the bricks `reads` (boxes of brick positions per level, possibly beyond the
    /// grid: read as 0) can hold the surface at `iso`.
    pub(super) fn decide(
        &self,
        layout: &VolumeLayout,
        reads: &[(u8, GridBox)],
        iso: f32,
    ) -> Decision {
        let mut sides = Sides::default();
        for &(level, read) in reads {
            self.box_sides(layout, level, read, iso, &mut sides);
            if sides.surface() {
                return Decision::Surface;
            }
        }
        if !sides.unknown.is_empty() {
            sides.unknown.sort();
            sides.unknown.dedup();
            Decision::Unknown(sides.unknown)
        } else {
            Decision::Empty
        }
    }

    /// Adds the sides of the bricks of `level` in box `lo..=hi` to `sides` (those beyond the
    /// grid read as 0), stopping once they show a surface.
    ///
    /// A tile reads a box of neighbouring bricks, which share parents: where a parent's bound
    /// carried down lies on one side of `iso`, so do all its children's voxels (and so their
    /// own ranges, and any kept bound, which bounds the same voxels), and the children are not
    /// looked up one by one. The decision is the one each brick's [`HashBook::bound`] gives.
    fn box_sides(
        &self,
        layout: &VolumeLayout,
        level: u8,
        (lo, hi): GridBox,
        iso: f32,
        sides: &mut Sides,
    ) {
        if (0..3).any(|a| lo[a] > hi[a]) {
            return;
        }
        let g = layout.grid(level).map(i64::from);
        if (0..3).any(|a| lo[a] < 0 || hi[a] >= g[a]) {
            sides.add(Ok((0, 0)), iso);
        }
        let lo = [0, 1, 2].map(|a| lo[a].max(0));
        let hi = [0, 1, 2].map(|a| hi[a].min(g[a] - 1));
        if (0..3).any(|a| lo[a] > hi[a]) {
            return;
        }
        let brick = |[x, y, z]: [i64; 3], level: u8| BrickKey {
            level,
            x: x as u32,
            y: y as u32,
            z: z as u32,
        };
        let has_parent = level + 1 < layout.levels();
        let step = if has_parent { 2 } else { 1 };
        let high = layout.voxel_type().high();
        for pz in lo[2] / step..=hi[2] / step {
            for py in lo[1] / step..=hi[1] / step {
                for px in lo[0] / step..=hi[0] / step {
                    if has_parent {
                        if let Ok(r) = self.bound(layout, brick([px, py, pz], level + 1), iso) {
                            let carried = child_bound(r, high);
                            if side(carried, iso) != Side::Both {
                                sides.add(Ok(carried), iso);
                                continue;
                            }
                        }
                    }
                    let p = [px, py, pz];
                    let from = [0, 1, 2].map(|a| lo[a].max(p[a] * step));
                    let to = [0, 1, 2].map(|a| hi[a].min(p[a] * step + step - 1));
                    for z in from[2]..=to[2] {
                        for y in from[1]..=to[1] {
                            for x in from[0]..=to[0] {
                                sides.add(self.bound(layout, brick([x, y, z], level), iso), iso);
                            }
                        }
                    }
                    if sides.surface() {
                        return;
                    }
                }
            }
        }
    }

    /// Whether the bricks `reads` are known to lie wholly below `iso`, or wholly above, from
    /// their own ranges alone (never a coarser brick's bound): what a streamer without the
    /// descent knows from the grid regions it asks for anyway. Stops at the first brick whose
    /// range is unknown or straddles `iso`: a replan asks this of every tile it plans.
    pub(super) fn ranges_rule_out_surface(
        &self,
        layout: &VolumeLayout,
        reads: &[(u8, GridBox)],
        iso: f32,
    ) -> bool {
        let (mut below, mut above) = (false, false);
        for b in bricks_read(layout, reads) {
            let range = match b {
                None => (0, 0),
                Some(b) => match self.range(b) {
                    Some(r) => r,
                    None => return false,
                },
            };
            match side(range, iso) {
                Side::Both => return false,
                Side::Below => below = true,
                Side::Above => above = true,
            }
            if below && above {
                return false;
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bound holds for every 2x2x2 a mean can come from, checked exhaustively on the
    /// extreme cases: one voxel at the far end of the range and seven at the near end.
    #[test]
    fn child_bound_contains_every_child_of_a_mean() {
        let high = 255u16;
        for a in 0..=high {
            for b in [0u16, 1, 17, 128, 254, 255] {
                // One voxel `a`, seven `b`: the mean, rounded half up.
                let p = ((u32::from(a) + 7 * u32::from(b) + 4) / 8) as u16;
                let (lo, hi) = child_bound((p, p), high);
                assert!(
                    lo <= a && a <= hi,
                    "voxel {a} under parent {p}: bound {lo}..{hi}"
                );
                assert!(
                    lo <= b && b <= hi,
                    "voxel {b} under parent {p}: bound {lo}..{hi}"
                );
            }
        }
        // And it prunes where it should: parents of only air-ish or solid-ish values.
        assert_eq!(side(child_bound((0, 15), high), 126.5), Side::Below);
        assert_eq!(side(child_bound((0, 16), high), 126.5), Side::Both);
        assert_eq!(side(child_bound((240, 255), high), 126.5), Side::Above);
        assert_eq!(side(child_bound((239, 255), high), 126.5), Side::Both);
    }

    /// The decision by boxes (a parent's carried bound settling its children) is the one each
    /// brick's own bound gives (what `decide` did brick by brick), on books that know random
    /// bricks' ranges on every level, with kept bounds on others.
    #[test]
    fn deciding_by_parents_agrees_with_deciding_brick_by_brick() {
        use super::super::book::bricks_read;
        use isovox_proto::VoxelType;
        use std::collections::HashMap;
        let layout = VolumeLayout::new([160, 96, 128], 8, VoxelType::U8).unwrap();
        let high = 255;
        let iso = 126.5;
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut draw = move |n: u64| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 33) % n
        };
        // The bricks' true ranges, top down: each within the bound its parent's gives (what
        // mean downsampling guarantees), often narrow at one end so that bounds prune.
        let top = layout.levels() - 1;
        for trial in 0..40 {
            let mut truth: HashMap<BrickKey, (u16, u16)> = HashMap::new();
            for level in (0..=top).rev() {
                let g = layout.grid(level);
                for z in 0..g[2] {
                    for y in 0..g[1] {
                        for x in 0..g[0] {
                            let b = BrickKey { level, x, y, z };
                            let (lo, hi) = match level == top {
                                true => (0, high),
                                false => {
                                    let p = BrickKey {
                                        level: level + 1,
                                        x: x / 2,
                                        y: y / 2,
                                        z: z / 2,
                                    };
                                    child_bound(truth[&p], high)
                                }
                            };
                            let span = u64::from(hi - lo) + 1;
                            let (a, c) = match draw(3) {
                                0 => (lo, lo + draw(span.min(12)) as u16),
                                1 => (hi - draw(span.min(12)) as u16, hi),
                                _ => {
                                    let (a, c) = (draw(span) as u16, draw(span) as u16);
                                    (lo + a.min(c), lo + a.max(c))
                                }
                            };
                            truth.insert(b, (a, c));
                        }
                    }
                }
            }
            let mut book = HashBook::new(4);
            for (&b, &r) in &truth {
                match draw(4) {
                    0 | 1 => book.learn(b, 1, (r.0.into(), r.1.into())),
                    // A kept bound: a true one (the parent's carried), one-sided.
                    2 if b.level < top => {
                        let p = BrickKey {
                            level: b.level + 1,
                            x: b.x / 2,
                            y: b.y / 2,
                            z: b.z / 2,
                        };
                        let kept = child_bound(truth[&p], high);
                        if side(kept, iso) != Side::Both {
                            book.keep_bound(b, kept);
                        }
                    }
                    _ => {}
                }
            }
            let mut decided = [0usize; 3];
            for _ in 0..300 {
                let level = draw(u64::from(top) + 1) as u8;
                let g = layout.grid(level).map(i64::from);
                let lo = [0, 1, 2].map(|a| draw(g[a] as u64 + 2) as i64 - 1);
                let hi = [0, 1, 2].map(|a| lo[a] + draw(4) as i64);
                let mut reads = vec![(level, (lo, hi))];
                if level > 0 && draw(2) == 0 {
                    let fine = [0, 1, 2].map(|a| 2 * lo[a] + draw(3) as i64);
                    reads.push((level - 1, (fine, fine.map(|c| c + 1))));
                }
                // Brick by brick, as `decide` did.
                let (mut below, mut above, mut both) = (false, false, false);
                let mut unknown = Vec::new();
                for b in bricks_read(&layout, &reads) {
                    let bound = b.map_or(Ok((0, 0)), |b| book.bound(&layout, b, iso));
                    match bound.map(|r| side(r, iso)) {
                        Ok(Side::Both) => both = true,
                        Ok(Side::Below) => below = true,
                        Ok(Side::Above) => above = true,
                        Err(u) => unknown.push(u),
                    }
                }
                unknown.sort();
                unknown.dedup();
                let want = if both || (below && above) {
                    Decision::Surface
                } else if !unknown.is_empty() {
                    Decision::Unknown(unknown)
                } else {
                    Decision::Empty
                };
                let got = book.decide(&layout, &reads, iso);
                assert_eq!(got, want, "trial {trial}, reads {reads:?}");
                decided[match got {
                    Decision::Empty => 0,
                    Decision::Surface => 1,
                    Decision::Unknown(_) => 2,
                }] += 1;
            }
            // Every kind of decision is made, so the comparison covers them.
            assert!(decided.iter().all(|&n| n > 0), "trial {trial}: {decided:?}");
        }
    }

    /// A commit that changes one of a brick's children, and the brick's range with it: the other
    /// seven keep the bound they had from the brick's old range, and are decided without a grid.
    #[test]
    fn unchanged_children_keep_the_bound_from_before_the_commit() {
        use isovox_proto::VoxelType;
        let layout = VolumeLayout::new([32, 32, 32], 16, VoxelType::U8).unwrap();
        let iso = 126.5;
        let key = |level, x| BrickKey {
            level,
            x,
            y: 0,
            z: 0,
        };
        let mut book = HashBook::new(4);
        // Level 1 (one brick) all air: its eight level-0 children are bounded below the iso
        // value without grid entries of their own.
        book.learn(key(1, 0), 1, (0, 0));
        assert_eq!(book.bound(&layout, key(0, 1), iso), Ok((0, 3)));
        // A commit puts the surface into child (0, 0, 0), and so into the level-1 brick.
        let changed = vec![vec![[0, 0, 0]], vec![[0, 0, 0]]];
        let kept = book.bounds_before(&layout, &changed, iso);
        assert_eq!(kept.len(), 7, "{kept:?}");
        assert!(kept.iter().all(|&(b, r)| b.level == 0 && r == (0, 3)));
        assert!(!kept.iter().any(|&(b, _)| b == key(0, 0)));
        book.learn(key(0, 0), 2, (0, 255));
        book.learn(key(1, 0), 3, (0, 40));
        // Without the kept bounds the unchanged children would need their grid entries.
        assert_eq!(book.bound(&layout, key(0, 1), iso), Err(key(0, 1)));
        for (b, bound) in kept {
            book.keep_bound(b, bound);
        }
        assert_eq!(book.bound(&layout, key(0, 1), iso), Ok((0, 3)));
        assert_eq!(book.bound(&layout, key(0, 0), iso), Ok((0, 255)));
        // A later commit that changes a child drops its kept bound: its range is the event's,
        // or unknown.
        book.forget(key(0, 1));
        assert_eq!(book.bound(&layout, key(0, 1), iso), Err(key(0, 1)));
    }
}
