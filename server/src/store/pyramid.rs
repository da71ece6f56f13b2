//! Bricks of voxels and the level-of-detail rule.
//!
//! A brick of level k+1 is made from its 8 children of level k: each 2x2x2 group of child voxels
//! becomes one voxel, their mean rounded half up, `(sum + 4) / 8` (the thesis's example
//! 4,10,6,8,2,2,4,4 gives 40/8 = 5). A child outside the volume is all L. Because the brick edge
//! is even, every 2x2x2 group lies inside one child, so the rule is the same as downsampling the
//! whole level as one array.

use isovox_proto::{BrickKey, VoxelType};

/// The voxels of one brick: one value everywhere, or the decoded bytes (x fastest, then y, then
/// z; u16 little endian).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BrickVoxels {
    /// Every voxel holds this value.
    Constant(u16),
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
    fn constant(&self, _key: BrickKey) -> Option<u16> {
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
    for (octant, child) in children.iter().enumerate() {
        downsample_octant(octant, *child, brick, voxel_type, how, out);
    }
}

/// Rewrites in `out`, a parent brick's bytes, only the octants whose child is given: the
/// others keep what `out` holds. A parent of which a few children changed is its old content
/// with those octants downsampled again (each octant of a parent depends on its own child
/// only), without reading the children that did not change.
pub fn downsample_changed(
    changed: &[Option<&BrickVoxels>; 8],
    brick: u32,
    voxel_type: VoxelType,
    how: Downsampling,
    out: &mut [u8],
) {
    for (octant, child) in changed.iter().enumerate() {
        if child.is_some() {
            downsample_octant(octant, *child, brick, voxel_type, how, out);
        }
    }
}

/// The octant `octant` (x fastest) of a parent brick from its child (`None`: all L).
fn downsample_octant(
    octant: usize,
    child: Option<&BrickVoxels>,
    brick: u32,
    voxel_type: VoxelType,
    how: Downsampling,
    out: &mut [u8],
) {
    let b = brick as usize;
    let h = b / 2;
    let (ox, oy, oz) = ((octant & 1) * h, (octant >> 1 & 1) * h, (octant >> 2) * h);
    match (child, how) {
        (None, _) => fill_subcube(out, b, [ox, oy, oz], 0, voxel_type),
        (Some(BrickVoxels::Constant(v)), _) => fill_subcube(out, b, [ox, oy, oz], *v, voxel_type),
        (Some(BrickVoxels::Data(d)), Downsampling::Mean) => match voxel_type {
            VoxelType::U8 => mean_subcube_u8(d, out, b, [ox, oy, oz]),
            VoxelType::U16 => mean_subcube_u16(d, out, b, [ox, oy, oz]),
        },
        (Some(BrickVoxels::Data(d)), Downsampling::Mode { sparse }) => {
            mode_subcube(d, out, b, [ox, oy, oz], voxel_type, sparse)
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
    voxel_type: VoxelType,
    sparse: bool,
) {
    match voxel_type {
        VoxelType::U8 => mode_rows(
            child,
            out,
            b,
            o,
            sparse,
            1,
            |r, x| r[x] as u64,
            |d, x, v| d[x] = v as u8,
        ),
        VoxelType::U16 => mode_rows(
            child,
            out,
            b,
            o,
            sparse,
            2,
            |r, x| u16::from_le_bytes([r[2 * x], r[2 * x + 1]]) as u64,
            |d, x, v| d[2 * x..2 * x + 2].copy_from_slice(&(v as u16).to_le_bytes()),
        ),
    }
}

#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn mode_rows(
    child: &[u8],
    out: &mut [u8],
    b: usize,
    o: [usize; 3],
    sparse: bool,
    vb: usize,
    get: impl Fn(&[u8], usize) -> u64,
    put: impl Fn(&mut [u8], usize, u64),
) {
    let h = b / 2;
    let row = |y: usize, z: usize| &child[(z * b + y) * b * vb..][..b * vb];
    for z in 0..h {
        for y in 0..h {
            let (r00, r01) = (row(2 * y, 2 * z), row(2 * y + 1, 2 * z));
            let (r10, r11) = (row(2 * y, 2 * z + 1), row(2 * y + 1, 2 * z + 1));
            let dst = &mut out[((o[2] + z) * b + o[1] + y) * b * vb + o[0] * vb..][..h * vb];
            for x in 0..h {
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

fn fill_subcube(out: &mut [u8], b: usize, o: [usize; 3], value: u16, voxel_type: VoxelType) {
    let h = b / 2;
    let vb = voxel_type.bytes();
    for z in 0..h {
        for y in 0..h {
            let at = ((o[2] + z) * b + o[1] + y) * b + o[0];
            super::codec::fill_constant(&mut out[at * vb..(at + h) * vb], value, voxel_type);
        }
    }
}

fn mean_subcube_u8(child: &[u8], out: &mut [u8], b: usize, o: [usize; 3]) {
    let h = b / 2;
    for z in 0..h {
        for y in 0..h {
            let r00 = &child[((2 * z) * b + 2 * y) * b..][..b];
            let r01 = &child[((2 * z) * b + 2 * y + 1) * b..][..b];
            let r10 = &child[((2 * z + 1) * b + 2 * y) * b..][..b];
            let r11 = &child[((2 * z + 1) * b + 2 * y + 1) * b..][..b];
            let dst = &mut out[((o[2] + z) * b + o[1] + y) * b + o[0]..][..h];
            for (x, d) in dst.iter_mut().enumerate() {
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

fn mean_subcube_u16(child: &[u8], out: &mut [u8], b: usize, o: [usize; 3]) {
    let h = b / 2;
    let at = |x: usize, y: usize, z: usize| -> u32 {
        let i = ((z * b + y) * b + x) * 2;
        u16::from_le_bytes([child[i], child[i + 1]]) as u32
    };
    for z in 0..h {
        for y in 0..h {
            for x in 0..h {
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

/// The parent of 8 children without looking at voxels when that is possible: all children
/// constant with one value (or absent, counting as L, when that value is L) gives that value.
pub fn constant_parent(children: &[Option<&BrickVoxels>; 8]) -> Option<u16> {
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

    proptest::proptest! {
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
            let mut state = seed | 1;
            let mut noise = move || {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state
            };
            let mut brick = |kind: u64| match kind {
                0 => Some(BrickVoxels::Data((0..bytes).map(|_| noise() as u8).collect())),
                1 => Some(BrickVoxels::Constant(noise() as u16 & 0xff)),
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
                downsample_changed(&changed, b, t, how, &mut parent);
                proptest::prop_assert_eq!(parent, expected);
            }
        }
    }
}
