//! Bricks of voxels and the level-of-detail rule.
//!
//! A brick of level k+1 is made from its 8 children of level k: each 2x2x2 group of child voxels
//! becomes one voxel, their mean rounded half up, `(sum + 4) / 8` (the thesis's example
//! 4,10,6,8,2,2,4,4 gives 40/8 = 5). A child outside the volume is all L. Because the brick edge
//! is even, every 2x2x2 group lies inside one child, so the rule is the same as downsampling the
//! whole level as one array.

use isovox_proto::geometry::Box3;
use isovox_proto::{BrickKey, VoxelType};
use std::ops::Range;

/// The voxels of one brick: one value everywhere, or the decoded bytes (x fastest, then y, then
/// z; little endian).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BrickVoxels {
    /// Every voxel holds this value.
    Constant(u64),
    /// The voxels' bytes.
    Data(Vec<u8>),
}

impl BrickVoxels {
    /// Turns a decoded brick into `Constant` when all its voxels are equal.
    pub fn from_bytes(bytes: Vec<u8>, voxel_type: VoxelType) -> BrickVoxels {
        let (lo, hi) = super::codec::min_max(&bytes, voxel_type);
        if lo == hi {
            BrickVoxels::Constant(lo)
        } else {
            BrickVoxels::Data(bytes)
        }
    }

    /// Its bytes: a constant brick expanded to `voxels` values of `voxel_type`.
    pub fn into_bytes(self, voxels: usize, voxel_type: VoxelType) -> Vec<u8> {
        match self {
            BrickVoxels::Data(bytes) => bytes,
            BrickVoxels::Constant(v) => {
                let mut bytes = vec![0u8; voxels * voxel_type.bytes()];
                super::codec::fill_constant(&mut bytes, v, voxel_type);
                bytes
            }
        }
    }
}

/// Where the voxels of level 0 come from when a volume is built: a RAW file, a generator, a
/// VOD 1 file. Implementations are called from several threads at once.
pub trait BrickSource: Sync {
    /// Fills `out` (one brick's bytes, zeroed) with the level-0 brick at `key`. Voxels beyond
    /// the volume's dimensions must be left L (zero).
    fn fill(&self, key: BrickKey, out: &mut [u8]);

    /// A cheap answer for bricks known to be constant without looking at their voxels (for
    /// example the air above a terrain). `None` means "fill it and see".
    fn constant(&self, _key: BrickKey) -> Option<u64> {
        None
    }

    /// Whether the source has failed (its error kept for the caller): the build stops at the
    /// next row of bricks instead of building a pyramid that will be thrown away.
    fn failed(&self) -> bool {
        false
    }
}

/// The first error of a [`BrickSource`] that reads from somewhere fallible: `fill` cannot
/// return an error mid-build, so it records it here and the caller checks after the build.
#[derive(Debug, Default)]
pub struct FirstError(std::sync::Mutex<Option<super::StoreError>>);

impl FirstError {
    /// Keeps `e` unless an error was recorded before.
    pub fn record(&self, e: super::StoreError) {
        if let Ok(mut slot) = self.0.lock() {
            slot.get_or_insert(e);
        }
    }

    /// # Errors
    /// The first error recorded.
    pub fn finish(self) -> Result<(), super::StoreError> {
        match self.0.into_inner() {
            Ok(None) => Ok(()),
            Ok(Some(e)) => Err(e),
            Err(_) => Err(super::StoreError::Internal(
                "a reader thread panicked".into(),
            )),
        }
    }
}

/// A dense voxel array, x fastest, then y, then z (the RAW layout), borrowed from a mapped file
/// or owned.
#[derive(Debug, Clone, Copy)]
pub struct DenseGrid<'a> {
    /// Size in voxels.
    pub dims: [u32; 3],
    /// The voxel type.
    pub voxel_type: VoxelType,
    /// The voxels' bytes.
    pub bytes: &'a [u8],
    /// The brick edge it is cut into.
    pub brick: u32,
}

impl<'a> DenseGrid<'a> {
    /// # Panics
    /// `bytes` does not hold exactly the voxels of `dims`; callers check this first.
    pub fn new(dims: [u32; 3], voxel_type: VoxelType, brick: u32, bytes: &'a [u8]) -> Self {
        let expected = dims.iter().map(|&d| d as usize).product::<usize>() * voxel_type.bytes();
        assert_eq!(
            bytes.len(),
            expected,
            "grid bytes do not match its dimensions"
        );
        DenseGrid {
            dims,
            voxel_type,
            bytes,
            brick,
        }
    }
}

impl BrickSource for DenseGrid<'_> {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        let b = self.brick as usize;
        let vb = self.voxel_type.bytes();
        let [dx, dy, dz] = self.dims.map(|d| d as usize);
        let origin = [key.x as usize * b, key.y as usize * b, key.z as usize * b];
        let nx = b.min(dx.saturating_sub(origin[0]));
        let ny = b.min(dy.saturating_sub(origin[1]));
        let nz = b.min(dz.saturating_sub(origin[2]));
        for z in 0..nz {
            for y in 0..ny {
                let src = ((origin[2] + z) * dy + origin[1] + y) * dx + origin[0];
                let dst = (z * b + y) * b;
                out[dst * vb..(dst + nx) * vb]
                    .copy_from_slice(&self.bytes[src * vb..(src + nx) * vb]);
            }
        }
    }
}

/// How a voxel of level k+1 follows from its 2x2x2 voxels of level k.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Downsampling {
    /// The rounded mean, half up: density.
    Mean,
    /// The most frequent value, ties to the smallest; with `sparse`, 0 only when all 8 are 0
    /// ([`isovox_proto::channel::mode_of_8`]): attribute channels, whose values are names.
    Mode {
        /// Whether 0 loses to any other value.
        sparse: bool,
    },
}

impl Downsampling {
    /// How the levels of an attribute channel are made.
    pub fn of_channel(channel: &isovox_proto::channel::ChannelInfo) -> Downsampling {
        Downsampling::Mode {
            sparse: channel.sparse,
        }
    }
}

/// Writes into `out` (the parent brick's bytes) the downsampling of its 8 children, given in
/// octant order (x fastest); a `None` child is outside the volume and counts as all L.
pub fn downsample(
    children: &[Option<&BrickVoxels>; 8],
    brick: u32,
    voxel_type: VoxelType,
    how: Downsampling,
    out: &mut [u8],
) {
    let whole = Box3::new([0; 3], [i64::from(brick); 3]);
    for (octant, child) in children.iter().enumerate() {
        downsample_octant(octant, *child, brick, voxel_type, how, &whole, out);
    }
}

/// The voxels of the next coarser level that a change within `changed` (voxels of one level,
/// in that level's coordinates) can reach: each coarser voxel is made of the 2x2x2 below it.
pub fn coarser(changed: &Box3) -> Box3 {
    Box3::new(
        changed.min.map(|c| c.div_euclid(2)),
        changed.max.map(|c| (c + 1).div_euclid(2)),
    )
}

/// Rewrites in `out`, a parent brick's bytes, only the octants whose child is given, and of
/// those only the voxels in `within` (in the parent brick's own voxels, `0..brick` on each
/// axis): the rest keeps what `out` holds. A parent of which a few children changed is its old
/// content with those octants downsampled again (each octant of a parent depends on its own
/// child only), without reading the children that did not change; where the children changed
/// only within a box, only the parent's voxels above that box ([`coarser`]) can differ.
pub fn downsample_changed(
    changed: &[Option<&BrickVoxels>; 8],
    brick: u32,
    voxel_type: VoxelType,
    how: Downsampling,
    within: &Box3,
    out: &mut [u8],
) {
    for (octant, child) in changed.iter().enumerate() {
        if child.is_some() {
            downsample_octant(octant, *child, brick, voxel_type, how, within, out);
        }
    }
}

/// Voxels of an octant, per axis, relative to the octant's first voxel.
type Span = [Range<usize>; 3];

/// The octant `octant` (x fastest) of a parent brick from its child (`None`: all L), only
/// its voxels in `within` (parent brick coordinates).
fn downsample_octant(
    octant: usize,
    child: Option<&BrickVoxels>,
    brick: u32,
    voxel_type: VoxelType,
    how: Downsampling,
    within: &Box3,
    out: &mut [u8],
) {
    let b = brick as usize;
    let h = b / 2;
    let o = [octant & 1, octant >> 1 & 1, octant >> 2].map(|bit| bit * h);
    let span: Span = std::array::from_fn(|a| {
        let clamp = |c: i64| (c.clamp(o[a] as i64, (o[a] + h) as i64) as usize) - o[a];
        clamp(within.min[a])..clamp(within.max[a])
    });
    if span.iter().any(|r| r.is_empty()) {
        return;
    }
    match (child, how) {
        (None, _) => fill_subcube(out, b, o, &span, 0, voxel_type),
        (Some(BrickVoxels::Constant(v)), _) => fill_subcube(out, b, o, &span, *v, voxel_type),
        (Some(BrickVoxels::Data(d)), Downsampling::Mean) => match voxel_type {
            VoxelType::U8 => mean_subcube_u8(d, out, b, o, &span),
            VoxelType::U16 => mean_subcube_u16(d, out, b, o, &span),
            // Density is never wide; a wide stream is a channel, whose levels take the mode.
            // The mean is still the mean if ever asked for.
            VoxelType::U32 | VoxelType::U64 => mean_subcube_wide(d, out, b, o, &span, voxel_type),
        },
        (Some(BrickVoxels::Data(d)), Downsampling::Mode { sparse }) => {
            mode_subcube(d, out, b, o, &span, voxel_type, sparse)
        }
    }
}

/// The most frequent value of each 2x2x2 of `child` into the octant at `o` of `out`, row by
/// row as the means are (four input rows per output row), typed per voxel size.
fn mode_subcube(
    child: &[u8],
    out: &mut [u8],
    b: usize,
    o: [usize; 3],
    span: &Span,
    voxel_type: VoxelType,
    sparse: bool,
) {
    match voxel_type {
        VoxelType::U8 => mode_rows_of::<1>(child, out, b, o, span, sparse),
        VoxelType::U16 => mode_rows_of::<2>(child, out, b, o, span, sparse),
        VoxelType::U32 => mode_rows_of::<4>(child, out, b, o, span, sparse),
        VoxelType::U64 => mode_rows_of::<8>(child, out, b, o, span, sparse),
    }
}

/// [`mode_rows`] for values of `N` bytes, little endian.
#[inline(always)]
fn mode_rows_of<const N: usize>(
    child: &[u8],
    out: &mut [u8],
    b: usize,
    o: [usize; 3],
    span: &Span,
    sparse: bool,
) {
    mode_rows(
        child,
        out,
        b,
        o,
        span,
        sparse,
        N,
        |r, x| {
            let mut v = [0u8; 8];
            v[..N].copy_from_slice(&r[N * x..N * x + N]);
            u64::from_le_bytes(v)
        },
        |d, x, v| d[N * x..N * x + N].copy_from_slice(&v.to_le_bytes()[..N]),
    )
}

#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn mode_rows(
    child: &[u8],
    out: &mut [u8],
    b: usize,
    o: [usize; 3],
    span: &Span,
    sparse: bool,
    vb: usize,
    get: impl Fn(&[u8], usize) -> u64,
    put: impl Fn(&mut [u8], usize, u64),
) {
    let h = b / 2;
    let row = |y: usize, z: usize| &child[(z * b + y) * b * vb..][..b * vb];
    for z in span[2].clone() {
        for y in span[1].clone() {
            let (r00, r01) = (row(2 * y, 2 * z), row(2 * y + 1, 2 * z));
            let (r10, r11) = (row(2 * y, 2 * z + 1), row(2 * y + 1, 2 * z + 1));
            let dst = &mut out[((o[2] + z) * b + o[1] + y) * b * vb + o[0] * vb..][..h * vb];
            for x in span[0].clone() {
                let group = [
                    get(r00, 2 * x),
                    get(r00, 2 * x + 1),
                    get(r01, 2 * x),
                    get(r01, 2 * x + 1),
                    get(r10, 2 * x),
                    get(r10, 2 * x + 1),
                    get(r11, 2 * x),
                    get(r11, 2 * x + 1),
                ];
                // Most 2x2x2 groups of a material or label brick hold one value: no counting.
                let v = if group.iter().all(|&v| v == group[0]) {
                    group[0]
                } else {
                    isovox_proto::channel::mode_of_8(group, sparse)
                };
                put(dst, x, v);
            }
        }
    }
}

fn fill_subcube(
    out: &mut [u8],
    b: usize,
    o: [usize; 3],
    span: &Span,
    value: u64,
    voxel_type: VoxelType,
) {
    let vb = voxel_type.bytes();
    for z in span[2].clone() {
        for y in span[1].clone() {
            let row = ((o[2] + z) * b + o[1] + y) * b + o[0];
            let (from, to) = (row + span[0].start, row + span[0].end);
            super::codec::fill_constant(&mut out[from * vb..to * vb], value, voxel_type);
        }
    }
}

fn mean_subcube_u8(child: &[u8], out: &mut [u8], b: usize, o: [usize; 3], span: &Span) {
    let h = b / 2;
    for z in span[2].clone() {
        for y in span[1].clone() {
            let r00 = &child[((2 * z) * b + 2 * y) * b..][..b];
            let r01 = &child[((2 * z) * b + 2 * y + 1) * b..][..b];
            let r10 = &child[((2 * z + 1) * b + 2 * y) * b..][..b];
            let r11 = &child[((2 * z + 1) * b + 2 * y + 1) * b..][..b];
            let dst = &mut out[((o[2] + z) * b + o[1] + y) * b + o[0]..][..h];
            for (x, d) in dst
                .iter_mut()
                .enumerate()
                .take(span[0].end)
                .skip(span[0].start)
            {
                let sum = r00[2 * x] as u32
                    + r00[2 * x + 1] as u32
                    + r01[2 * x] as u32
                    + r01[2 * x + 1] as u32
                    + r10[2 * x] as u32
                    + r10[2 * x + 1] as u32
                    + r11[2 * x] as u32
                    + r11[2 * x + 1] as u32;
                *d = ((sum + 4) / 8) as u8;
            }
        }
    }
}

fn mean_subcube_u16(child: &[u8], out: &mut [u8], b: usize, o: [usize; 3], span: &Span) {
    let at = |x: usize, y: usize, z: usize| -> u32 {
        let i = ((z * b + y) * b + x) * 2;
        u16::from_le_bytes([child[i], child[i + 1]]) as u32
    };
    for z in span[2].clone() {
        for y in span[1].clone() {
            for x in span[0].clone() {
                let mut sum = 0u32;
                for (dx, dy, dz) in [
                    (0, 0, 0),
                    (1, 0, 0),
                    (0, 1, 0),
                    (1, 1, 0),
                    (0, 0, 1),
                    (1, 0, 1),
                    (0, 1, 1),
                    (1, 1, 1),
                ] {
                    sum += at(2 * x + dx, 2 * y + dy, 2 * z + dz);
                }
                let v = ((sum + 4) / 8) as u16;
                let i = (((o[2] + z) * b + o[1] + y) * b + o[0] + x) * 2;
                out[i..i + 2].copy_from_slice(&v.to_le_bytes());
            }
        }
    }
}

fn mean_subcube_wide(
    child: &[u8],
    out: &mut [u8],
    b: usize,
    o: [usize; 3],
    span: &Span,
    voxel_type: VoxelType,
) {
    use isovox_proto::voxel::{set_value_at, value_at};
    for z in span[2].clone() {
        for y in span[1].clone() {
            for x in span[0].clone() {
                let mut sum = 0u128;
                for d in 0..8 {
                    let (dx, dy, dz) = (d & 1, d >> 1 & 1, d >> 2);
                    let i = ((2 * z + dz) * b + 2 * y + dy) * b + 2 * x + dx;
                    sum += u128::from(value_at(child, voxel_type, i));
                }
                let i = ((o[2] + z) * b + o[1] + y) * b + o[0] + x;
                set_value_at(out, voxel_type, i, ((sum + 4) / 8) as u64);
            }
        }
    }
}

/// The parent of 8 children without looking at voxels when that is possible: all children
/// constant with one value (or absent, counting as L, when that value is L) gives that value.
pub fn constant_parent(children: &[Option<&BrickVoxels>; 8]) -> Option<u64> {
    let mut value = None;
    for c in children {
        let v = match c {
            None => 0,
            Some(BrickVoxels::Constant(v)) => *v,
            Some(BrickVoxels::Data(_)) => return None,
        };
        match value {
            None => value = Some(v),
            Some(prev) if prev != v => return None,
            _ => {}
        }
    }
    value
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thesis_mean_example() {
        // Thesis section 4.4: 4,10,6,8,2,2,4,4 -> 5. A 2^3 brick whose first child holds these
        // values in x-fastest order: the parent's voxel (0,0,0) is their mean.
        let child = BrickVoxels::Data(vec![4, 10, 6, 8, 2, 2, 4, 4]);
        let children = [Some(&child), None, None, None, None, None, None, None];
        let mut out = vec![0u8; 8];
        downsample(&children, 2, VoxelType::U8, Downsampling::Mean, &mut out);
        assert_eq!(out, vec![5, 0, 0, 0, 0, 0, 0, 0]);
    }

    #[test]
    fn rounding_is_half_up() {
        // sum 12 -> 1.5 -> 2; sum 11 -> 1.375 -> 1; u16 sum 8*65535 -> 65535.
        for (vals, expect) in [
            ([3u8, 3, 3, 3, 0, 0, 0, 0], 2u8),
            ([3, 3, 3, 2, 0, 0, 0, 0], 1),
        ] {
            let child = BrickVoxels::Data(vals.to_vec());
            let mut out = vec![0u8; 8];
            downsample(
                &[Some(&child), None, None, None, None, None, None, None],
                2,
                VoxelType::U8,
                Downsampling::Mean,
                &mut out,
            );
            assert_eq!(out[0], expect);
        }
        let full = BrickVoxels::Data([0xffu8; 16].to_vec());
        let mut out = vec![0u8; 16];
        downsample(
            &[Some(&full), None, None, None, None, None, None, None],
            2,
            VoxelType::U16,
            Downsampling::Mean,
            &mut out,
        );
        assert_eq!(&out[..2], &[0xff, 0xff]);
        assert_eq!(&out[2..4], &[0, 0]);
    }

    #[test]
    fn mode_downsampling_by_hand() {
        // A 4^3 brick of u8 labels whose octant 0 (x, y, z < 2) holds, in x-fastest order,
        // 7 3 3 7 / 3 7 3 3: five 3s. Octant 1 (x >= 2): 1 2 1 2 / 2 1 2 1, a 4-4 tie: 1.
        // Octant 2 (y >= 2): six 0s and two 9s: 0, or 9 when sparse. The rest all 5.
        let mut child = vec![5u8; 64];
        let put = |child: &mut Vec<u8>, o: [usize; 3], vals: [u8; 8]| {
            for (i, v) in vals.iter().enumerate() {
                let (x, y, z) = (o[0] + (i & 1), o[1] + (i >> 1 & 1), o[2] + (i >> 2));
                child[(z * 4 + y) * 4 + x] = *v;
            }
        };
        put(&mut child, [0, 0, 0], [7, 3, 3, 7, 3, 7, 3, 3]);
        put(&mut child, [2, 0, 0], [1, 2, 1, 2, 2, 1, 2, 1]);
        put(&mut child, [0, 2, 0], [0, 0, 9, 0, 0, 0, 9, 0]);
        let child = BrickVoxels::Data(child);
        for (sparse, third) in [(false, 0u8), (true, 9)] {
            let mut out = vec![0u8; 64];
            let kids = [Some(&child), None, None, None, None, None, None, None];
            downsample(
                &kids,
                4,
                VoxelType::U8,
                Downsampling::Mode { sparse },
                &mut out,
            );
            // The parent's octant 0 is the child's 2x2x2 groups: (0,0,0), (1,0,0), (0,1,0), ...
            assert_eq!(out[0], 3);
            assert_eq!(out[1], 1);
            assert_eq!(out[4], third, "sparse {sparse}");
            assert_eq!(out[(4 + 1) * 4 + 1], 5); // group (1,1,1): all 5
            assert_eq!(out[2], 0, "octants without a child are 0");
        }
        // u16: 300 x3, 40000 x3, 7 x2: a tie between 300 and 40000 goes to 300.
        let vals: [u16; 8] = [40000, 300, 7, 300, 40000, 7, 300, 40000];
        let bytes = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        let child = BrickVoxels::Data(bytes);
        let mut out = vec![0u8; 16];
        let kids = [Some(&child), None, None, None, None, None, None, None];
        downsample(
            &kids,
            2,
            VoxelType::U16,
            Downsampling::Mode { sparse: false },
            &mut out,
        );
        assert_eq!(u16::from_le_bytes([out[0], out[1]]), 300);
    }

    #[test]
    fn constant_children_fast_path() {
        let a = BrickVoxels::Constant(9);
        let all9 = [Some(&a); 8];
        assert_eq!(constant_parent(&all9), Some(9));
        let mut mixed = all9;
        mixed[3] = None;
        assert_eq!(constant_parent(&mixed), None);
        let z = BrickVoxels::Constant(0);
        assert_eq!(
            constant_parent(&[Some(&z), None, None, None, None, None, None, None]),
            Some(0)
        );
    }

    #[test]
    fn dense_grid_pads_with_l() {
        // 3x2x1 grid, brick 2: brick (1,0,0) holds voxel x=2 only, the rest L.
        let bytes = [1u8, 2, 3, 4, 5, 6];
        let g = DenseGrid::new([3, 2, 1], VoxelType::U8, 2, &bytes);
        let mut out = vec![0u8; 8];
        g.fill(
            BrickKey {
                level: 0,
                x: 1,
                y: 0,
                z: 0,
            },
            &mut out,
        );
        assert_eq!(out, vec![3, 0, 6, 0, 0, 0, 0, 0]);
    }

    /// A xorshift64 stream from `seed`: test bricks' values.
    fn xorshift(seed: u64) -> impl FnMut() -> u64 {
        let mut state = seed | 1;
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        }
    }

    proptest::proptest! {
        /// Mode downsampling equals the mode of each 2x2x2 group taken one group at a time,
        /// on bricks of few values in blocks (groups of one value) with single voxels changed
        /// at random (groups of several).
        #[test]
        fn mode_downsampling_equals_the_mode_of_each_group(
            seed in proptest::prelude::any::<u64>(),
            wide in proptest::prelude::any::<bool>(),
            small in proptest::prelude::any::<bool>(),
            block in 1usize..6,
            specks in 0usize..40,
            sparse in proptest::prelude::any::<bool>(),
        ) {
            let t = if wide { VoxelType::U16 } else { VoxelType::U8 };
            let b: usize = if small { 4 } else { 32 };
            let mut noise = xorshift(seed);
            let choices: [u16; 4] = [0, 6, 200, if wide { 40_000 } else { 77 }];
            let palette: Vec<u16> = (0..3).map(|_| choices[(noise() % 4) as usize]).collect();
            let mut values: Vec<u16> = (0..b * b * b)
                .map(|i| {
                    let (x, y, z) = (i % b / block, i / b % b / block, i / (b * b) / block);
                    palette[(x * 7 + y * 3 + z * 5 + (seed as usize)) % palette.len()]
                })
                .collect();
            for _ in 0..specks {
                let at = noise() as usize % values.len();
                values[at] = (noise() % 4) as u16;
            }
            let bytes: Vec<u8> = match t {
                VoxelType::U8 => values.iter().map(|&v| v as u8).collect(),
                _ => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            };
            let child = BrickVoxels::Data(bytes);
            let mut out = vec![0u8; b * b * b * t.bytes()];
            let kids = [None, None, None, None, None, None, None, Some(&child)];
            downsample(&kids, b as u32, t, Downsampling::Mode { sparse }, &mut out);
            let h = b / 2;
            for (z, y, x) in (0..h).flat_map(|z| (0..h).flat_map(move |y| (0..h).map(move |x| (z, y, x)))) {
                let group: [u64; 8] = std::array::from_fn(|i| {
                    let (dx, dy, dz) = (i & 1, i >> 1 & 1, i >> 2);
                    let v = values[((2 * z + dz) * b + 2 * y + dy) * b + 2 * x + dx];
                    u64::from(v)
                });
                let expected = isovox_proto::channel::mode_of_8(group, sparse);
                // Octant 7: the parent's x, y, z >= h.
                let at = ((h + z) * b + h + y) * b + h + x;
                let got = match t {
                    VoxelType::U8 => u64::from(out[at]),
                    _ => u64::from(u16::from_le_bytes([out[2 * at], out[2 * at + 1]])),
                };
                proptest::prop_assert_eq!(got, expected, "group ({}, {}, {})", x, y, z);
            }
        }

        /// A parent updated only where children changed equals the parent downsampled from
        /// all its children again, whatever the children (data, constant, absent) and whichever
        /// of them changed.
        #[test]
        fn updating_changed_octants_equals_downsampling_all(
            seed in proptest::prelude::any::<u64>(),
            wide in proptest::prelude::any::<bool>(),
            kinds in proptest::collection::vec(0u8..3, 8),
            changed_mask in 0u8..=255,
        ) {
            let t = if wide { VoxelType::U16 } else { VoxelType::U8 };
            let b = 4u32;
            let bytes = (b * b * b) as usize * t.bytes();
            let mut noise = xorshift(seed);
            let mut brick = |kind: u64| match kind {
                0 => Some(BrickVoxels::Data((0..bytes).map(|_| noise() as u8).collect())),
                1 => Some(BrickVoxels::Constant(noise() & 0xff)),
                _ => None,
            };
            let old: Vec<Option<BrickVoxels>> =
                kinds.iter().map(|&k| brick(u64::from(k))).collect();
            // Changed children are new bricks (data or constant, by the seed); an absent child
            // stays absent (outside the volume).
            let new: Vec<Option<BrickVoxels>> = (0..8)
                .map(|o| match &old[o] {
                    Some(_) if changed_mask >> o & 1 == 1 => brick((seed >> o) & 1),
                    other => other.clone(),
                })
                .collect();
            fn refs(v: &[Option<BrickVoxels>]) -> [Option<&BrickVoxels>; 8] {
                std::array::from_fn(|o| v[o].as_ref())
            }
            // Means (density) and modes (channels) alike.
            for how in [Downsampling::Mean, Downsampling::Mode { sparse: false }, Downsampling::Mode { sparse: true }] {
                let mut parent = vec![0u8; bytes];
                downsample(&refs(&old), b, t, how, &mut parent);
                let mut expected = vec![0u8; bytes];
                downsample(&refs(&new), b, t, how, &mut expected);
                let changed: [Option<&BrickVoxels>; 8] = std::array::from_fn(|o| {
                    new[o].as_ref().filter(|_| old[o].is_some() && changed_mask >> o & 1 == 1)
                });
                let whole = Box3::new([0; 3], [i64::from(b); 3]);
                downsample_changed(&changed, b, t, how, &whole, &mut parent);
                proptest::prop_assert_eq!(parent, expected);
            }
        }

        /// Where the children changed only within a box, the parent updated only over that
        /// box ([`coarser`]) equals the parent downsampled from all the new children: the box
        /// at odd and even corners, in one child or across several.
        #[test]
        fn updating_within_the_changed_box_equals_downsampling_all(
            seed in proptest::prelude::any::<u64>(),
            wide in proptest::prelude::any::<bool>(),
            corner in proptest::collection::vec(0i64..16, 3),
            extent in proptest::collection::vec(1i64..9, 3),
        ) {
            let t = if wide { VoxelType::U16 } else { VoxelType::U8 };
            let b = 8usize;
            let mut noise = xorshift(seed);
            // The 8 children as one 16^3 grid of values (in the children's level coordinates).
            let old: Vec<u16> = (0..8 * b * b * b).map(|_| (noise() % 4) as u16 * 60).collect();
            let changed_box = Box3::new(
                [0, 1, 2].map(|a| corner[a]),
                [0, 1, 2].map(|a| (corner[a] + extent[a]).min(16)),
            );
            let mut new = old.clone();
            for (i, v) in new.iter_mut().enumerate() {
                let p = [i % 16, i / 16 % 16, i / 256].map(|c| c as i64);
                if changed_box.contains(p) {
                    *v = (noise() % 5) as u16 * 50;
                }
            }
            let bricks = |grid: &[u16]| -> Vec<BrickVoxels> {
                (0..8)
                    .map(|octant| {
                        let o = [octant & 1, octant >> 1 & 1, octant >> 2].map(|c| c * b);
                        let values = (0..b * b * b).map(|i| {
                            let (x, y, z) = (o[0] + i % b, o[1] + i / b % b, o[2] + i / (b * b));
                            grid[(z * 16 + y) * 16 + x]
                        });
                        BrickVoxels::Data(match t {
                            VoxelType::U8 => values.map(|v| v as u8).collect(),
                            _ => values.flat_map(u16::to_le_bytes).collect(),
                        })
                    })
                    .collect()
            };
            let (old_kids, new_kids) = (bricks(&old), bricks(&new));
            fn all(kids: &[BrickVoxels]) -> [Option<&BrickVoxels>; 8] {
                std::array::from_fn(|o| Some(&kids[o]))
            }
            let bytes = b * b * b * t.bytes();
            for how in [Downsampling::Mean, Downsampling::Mode { sparse: false }, Downsampling::Mode { sparse: true }] {
                let mut parent = vec![0u8; bytes];
                downsample(&all(&old_kids), b as u32, t, how, &mut parent);
                let mut expected = vec![0u8; bytes];
                downsample(&all(&new_kids), b as u32, t, how, &mut expected);
                downsample_changed(&all(&new_kids), b as u32, t, how, &coarser(&changed_box), &mut parent);
                proptest::prop_assert_eq!(&parent, &expected);
            }
        }
    }
}
