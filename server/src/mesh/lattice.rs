//! Where a level's mesh samples sit: one lattice shared by all levels, so tiles of neighbouring
//! levels meet on the same planes and lines.
//!
//! A stored voxel of level k is the mean of a 2x2x2 group of level k-1 voxels, so it sits at the
//! centre of that group: level-k voxel i is at level-0 position `2^k i + (2^k - 1) / 2`, half a
//! level-(k-1) voxel off the finer level's samples. Meshed as they are, the levels' cells would
//! not nest (a coarse tile would overlap its finer neighbour on one side and leave a gap on the
//! other, across edges too), and no transition cell could join them. So level k is meshed on the
//! lattice of level-0 positions `2^k j`, each lattice value interpolated from the stored level-k
//! voxels around that point (Catmull-Rom along each axis over the voxels j - 2 to j + 1: it
//! keeps linear ramps exact and smooths less than trilinear interpolation: on a sphere of
//! radius seven lattice cells at level 3 the enclosed volume is off by 2.3% against 3.4%),
//! rounded half up to an integer. Level 0 is its own lattice. Rounding keeps the
//! values integers, so with the default iso value S - 0.5 no vertex ever lands on a lattice
//! point, as on level 0.
//!
//! Lattice point j of level k+1 is lattice point 2j of level k: a level-(k+1) tile covers
//! exactly its eight children, and its face is a face of theirs.

use super::mc::Field;
use isovox_proto::tile::{stored_box, GridBox};
use isovox_proto::VoxelType;

/// The interpolation weights of stored voxels j - 2, j - 1, j, j + 1 in lattice value j of
/// `level`: Catmull-Rom at the lattice point, which lies at `s = 1/2 + 2^-(level+1)` of the way
/// from voxel j - 1 to voxel j.
pub fn weights(level: u8) -> [f64; 4] {
    let s = 0.5 + 1.0 / f64::from(1u32 << (level + 1));
    let (s2, s3) = (s * s, s * s * s);
    [
        (-s3 + 2.0 * s2 - s) / 2.0,
        (3.0 * s3 - 5.0 * s2 + 2.0) / 2.0,
        (-3.0 * s3 + 4.0 * s2 + s) / 2.0,
        (s3 - s2) / 2.0,
    ]
}

/// Bounds of the lattice values of `level` computed from stored voxels within `[min, max]`:
/// Catmull-Rom's negative weights let a value overshoot the range by a fraction of its width
/// (none when the voxels are all equal), and rounding adds at most a half. Level 0 is exact.
pub fn value_range(level: u8, min: f32, max: f32) -> (f32, f32) {
    if level == 0 {
        return (min, max);
    }
    let w = weights(level);
    let negative: f64 = w.iter().filter(|&&x| x < 0.0).map(|x| -x).sum();
    let positive = 1.0 + negative;
    // The weights of three axes multiply: the products with an odd number of negative factors.
    let overshoot = 3.0 * positive * positive * negative + negative.powi(3);
    let spill = (overshoot * f64::from(max - min)) as f32;
    (min - spill - 0.5, max + spill + 0.5)
}

/// Reusable memory for [`lattice_field`] and [`lattice_plane`]: the first two passes (in f64 or
/// f32, [`exact_passes`]), one chunk's values, and each chunk's one value (when its stored
/// voxels hold one).
#[derive(Debug, Default)]
pub struct LatticeScratch {
    along_x: Vec<f64>,
    along_y: Vec<f64>,
    along_x_f32: Vec<f32>,
    along_y_f32: Vec<f32>,
    chunk: Vec<f32>,
    constants: Vec<Option<f32>>,
}

impl LatticeScratch {
    /// The buffers of the passes along the first two axes, in f64 and in f32.
    fn passes(&mut self) -> (&mut Vec<f64>, &mut Vec<f64>, &mut Vec<f32>, &mut Vec<f32>) {
        (
            &mut self.along_x,
            &mut self.along_y,
            &mut self.along_x_f32,
            &mut self.along_y_f32,
        )
    }
}

/// One Catmull-Rom tap sum, in the one order every lattice value is computed in.
#[inline(always)]
fn taps([w0, w1, w2, w3]: [f64; 4], a: f64, b: f64, c: f64, e: f64) -> f64 {
    w0 * a + w1 * b + w2 * c + w3 * e
}

/// A number type a pass along one axis can run in: f64 always gives the lattice values'
/// bits; f32 gives the same where it is exact ([`exact_passes`]), on twice the lanes.
trait Lane: Copy + std::ops::Mul<Output = Self> + std::ops::Add<Output = Self> + From<f32> {
    fn weights(w: [f64; 4]) -> [Self; 4];
}

impl Lane for f32 {
    fn weights(w: [f64; 4]) -> [f32; 4] {
        w.map(|x| x as f32)
    }
}

impl Lane for f64 {
    fn weights(w: [f64; 4]) -> [f64; 4] {
        w
    }
}

/// [`taps`] in any [`Lane`].
#[inline(always)]
fn taps_in<T: Lane>([w0, w1, w2, w3]: [T; 4], a: T, b: T, c: T, e: T) -> T {
    w0 * a + w1 * b + w2 * c + w3 * e
}

/// How many passes (up to three, one per axis) compute exactly in a float type with a
/// `bits`-bit significand (24: f32, 53: f64) at `level`, from stored voxels that are integers
/// in `[0, high]`.
///
/// The weights are dyadic (`weights`: Catmull-Rom at `s = 1/2 + 2^-(level+1)`), so
/// `w_i = n_i / D` with integer `n_i` and `D` a power of two; after p passes a value is an
/// integer over `D^p` of magnitude at most `high * N^p`, `N = sum |n_i|`, and so are every
/// product and partial sum that make it. Where that integer stays within `2^bits` each
/// operation is exact. Level 1: `D = 128`, `N = 152`; u8 voxels stay within
/// 255 * 152^2 = 5,891,520 < 2^24 over two passes, and every level-1 and level-2 value is
/// exact in f64 (65,535 * 1264^3 < 2^53 at level 2).
fn exact_passes(level: u8, high: f32, bits: i32) -> usize {
    let w = weights(level);
    let Some(d) = (0..=52)
        .map(|j| 2f64.powi(j))
        .find(|d| w.iter().all(|x| (x * d).fract() == 0.0))
    else {
        return 0;
    };
    let n: f64 = w.iter().map(|x| (x * d).abs()).sum();
    let limit = 2f64.powi(bits);
    let high = f64::from(high);
    (1..=3).take_while(|&p| high * n.powi(p) <= limit).count()
}

/// `value + 0.5` rounded down, as f32, without the libm call: truncate, then one down where
/// that rounded up (negative values). Lattice values are far inside i32 (voxels are at most
/// 16-bit, and the weights' absolute values sum to less than 2 per axis).
#[inline(always)]
fn round(value: f64) -> f32 {
    let value = value + 0.5;
    let t = f64::from(value as i32);
    (if t > value { t - 1.0 } else { t }) as f32
}

/// Lattice points per chunk edge at most: the unit in which [`lattice_field`] notices that the
/// stored voxels a region reads hold one value (away from a surface most do).
const CHUNK: usize = 8;

/// Resamples stored voxels of `level` onto the level's lattice: writes into `out` the lattice
/// values of the points `[lo, hi]` (inclusive) and returns them as a field. `stored` must
/// cover the stored voxels `[lo - 2, hi + 1]` (`isovox_proto::tile::stored_box`); it may be
/// larger; its values are voxels of type `voxels` (integers in its range). Level 0 copies the
/// voxels of `[lo, hi]`.
///
/// Separable: along x, then y, then z, each output from its four inputs in one fixed order, so
/// a lattice point gets the same value whatever box it is computed in (tiles of neighbouring
/// levels compute the same points from differently placed boxes). The box is taken in chunks
/// of up to 8^3 points: a chunk whose stored voxels all hold one value gets the value those
/// operations give for it, computed once. When fewer than a third of the chunks are like that,
/// the box is computed whole (chunks read their neighbours' voxels again). Passes that are
/// exact in f32 for such voxels run in f32 (same bits, twice the lanes; [`exact_passes`]).
///
/// # Panics
/// `level > 30`, or `stored` does not cover what the points read.
pub fn lattice_field<'o>(
    stored: &Field<'_>,
    (lo, hi): GridBox,
    level: u8,
    voxels: VoxelType,
    scratch: &mut LatticeScratch,
    out: &'o mut Vec<f32>,
) -> Field<'o> {
    assert!(level <= 30, "level {level} out of range");
    let (slo, shi) = stored_box(level, (lo, hi));
    let n = stored.size;
    assert!(
        (0..3).all(|a| lo[a] <= hi[a]
            && slo[a] >= stored.origin[a]
            && shi[a] < stored.origin[a] + n[a] as i64),
        "the stored voxels do not cover the lattice points"
    );
    assert_eq!(stored.values.len(), n[0] * n[1] * n[2]);
    let size = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
    if level == 0 {
        out.clear();
        out.reserve(size[0] * size[1] * size[2]);
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                let at = stored.index([lo[0], y, z]);
                out.extend_from_slice(&stored.values[at..][..size[0]]);
            }
        }
        return Field {
            origin: lo,
            size,
            values: out,
        };
    }
    let w = weights(level);
    let exact = exact_passes(level, f32::from(voxels.high()), 24);
    // Chunks: each axis cut into pieces of at most CHUNK points, as even as can be.
    let pieces = size.map(|s| s.div_ceil(CHUNK));
    let piece = |a: usize, i: usize| {
        let at = |i: usize| lo[a] + (i * size[a] / pieces[a]) as i64;
        (at(i), at(i + 1) - 1)
    };
    let chunk = |i: [usize; 3]| {
        let ends = [0, 1, 2].map(|a| piece(a, i[a]));
        (ends.map(|e| e.0), ends.map(|e| e.1))
    };
    let all = (0..pieces[2])
        .flat_map(|z| (0..pieces[1]).flat_map(move |y| (0..pieces[0]).map(move |x| [x, y, z])));
    scratch.constants.clear();
    scratch.constants.extend(
        all.clone()
            .map(|i| one_value(stored, stored_box(level, chunk(i)))),
    );
    let constant = scratch.constants.iter().filter(|c| c.is_some()).count();
    if constant * 3 < scratch.constants.len() {
        resample(stored, (lo, hi), w, exact, scratch, out);
        return Field {
            origin: lo,
            size,
            values: out,
        };
    }
    out.resize(size[0] * size[1] * size[2], 0.0);
    let whole: Field<'_> = Field {
        origin: lo,
        size,
        values: &[],
    };
    for (k, i) in all.enumerate() {
        let (clo, chi) = chunk(i);
        let width = (chi[0] - clo[0] + 1) as usize;
        match scratch.constants[k] {
            Some(v) => {
                // What the passes compute from four equal inputs each, three times over.
                let x = taps(w, f64::from(v), f64::from(v), f64::from(v), f64::from(v));
                let y = taps(w, x, x, x, x);
                let value = round(taps(w, y, y, y, y));
                for z in clo[2]..=chi[2] {
                    for y in clo[1]..=chi[1] {
                        let at = whole.index([clo[0], y, z]);
                        out[at..at + width].fill(value);
                    }
                }
            }
            None => {
                let mut values = std::mem::take(&mut scratch.chunk);
                resample(stored, (clo, chi), w, exact, scratch, &mut values);
                let mut rows = values.chunks_exact(width);
                for z in clo[2]..=chi[2] {
                    for y in clo[1]..=chi[1] {
                        let at = whole.index([clo[0], y, z]);
                        if let Some(row) = rows.next() {
                            out[at..at + width].copy_from_slice(row);
                        }
                    }
                }
                scratch.chunk = values;
            }
        }
    }
    Field {
        origin: lo,
        size,
        values: out,
    }
}

/// The lattice values of the points `(lo, hi)`, a box one point thick along axis `normal` (a
/// transition strip's face plane), as [`lattice_field`] gives them, into `out`.
///
/// Where every pass is exact in f64 ([`exact_passes`]: levels 1 and 2, and level 3 for u8)
/// the order of the passes changes no bit, and the pass across the plane goes first: it
/// turns the four planes of stored voxels into one, so that the passes along the plane work
/// on one plane instead of four (for a plane across z, a third of the operations of x, y, z
/// in that order). Elsewhere this is [`lattice_field`].
///
/// # Panics
/// As [`lattice_field`]; also a box more than one point thick along `normal`, or level 0.
pub fn lattice_plane<'o>(
    stored: &Field<'_>,
    (lo, hi): GridBox,
    normal: usize,
    level: u8,
    voxels: VoxelType,
    scratch: &mut LatticeScratch,
    out: &'o mut Vec<f32>,
) -> Field<'o> {
    assert!(
        level >= 1 && lo[normal] == hi[normal],
        "not a plane of a coarser level"
    );
    let high = f32::from(voxels.high());
    if exact_passes(level, high, 53) < 3 {
        return lattice_field(stored, (lo, hi), level, voxels, scratch, out);
    }
    let (slo, shi) = stored_box(level, (lo, hi));
    assert!(
        stored.contains(slo) && stored.contains(shi),
        "the stored voxels do not cover the lattice points"
    );
    let w = weights(level);
    let (along_x, along_y, along_x_f32, along_y_f32) = scratch.passes();
    match exact_passes(level, high, 24) {
        0 => plane_passes(stored, (lo, hi), normal, w, along_x, along_y, out),
        1 => plane_passes(stored, (lo, hi), normal, w, along_x_f32, along_y, out),
        _ => plane_passes(stored, (lo, hi), normal, w, along_x_f32, along_y_f32, out),
    }
    Field {
        origin: lo,
        size: [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize),
        values: out,
    }
}

/// The passes of [`lattice_plane`]: across the plane (in `T`), along its first lateral axis
/// (in `U`), along its second (in f64, rounded).
fn plane_passes<T: Lane, U: Lane + From<T>>(
    stored: &Field<'_>,
    (lo, hi): GridBox,
    normal: usize,
    w: [f64; 4],
    across: &mut Vec<T>,
    along: &mut Vec<U>,
    out: &mut Vec<f32>,
) where
    f64: From<U>,
{
    // The lateral axes, x before y before z: the output's fastest axis first.
    let (a1, a2) = [(1, 2), (0, 2), (0, 1)][normal];
    let (n1, n2) = (
        (hi[a1] - lo[a1] + 1) as usize,
        (hi[a2] - lo[a2] + 1) as usize,
    );
    let (m1, m2) = (n1 + 3, n2 + 3);
    let stride = [1, stored.size[0], stored.size[0] * stored.size[1]];
    let (sn, s1, s2) = (stride[normal], stride[a1], stride[a2]);
    let base = stored.index(lo.map(|c| c - 2));
    let v = stored.values;
    // Across the plane: the four stored planes into one, over the stored lateral extent.
    let wt = T::weights(w);
    across.resize(m1 * m2, wt[0]);
    for (j2, row) in across.chunks_exact_mut(m1).enumerate() {
        let start = base + j2 * s2;
        let [a, b, c, e] = [0, 1, 2, 3].map(|k| start + k * sn);
        for (j1, dst) in row.iter_mut().enumerate() {
            let o = j1 * s1;
            let t = [v[a + o], v[b + o], v[c + o], v[e + o]].map(T::from);
            *dst = taps_in(wt, t[0], t[1], t[2], t[3]);
        }
    }
    // Along the first lateral axis.
    let wu = U::weights(w);
    along.resize(n1 * m2, wu[0]);
    for (j2, row) in along.chunks_exact_mut(n1).enumerate() {
        let src = &across[j2 * m1..][..m1];
        let (a, b, c, e) = (
            &src[..n1],
            &src[1..n1 + 1],
            &src[2..n1 + 2],
            &src[3..n1 + 3],
        );
        for i in 0..n1 {
            let t = [a[i], b[i], c[i], e[i]].map(U::from);
            row[i] = taps_in(wu, t[0], t[1], t[2], t[3]);
        }
    }
    // Along the second, rounded half up.
    out.resize(n1 * n2, 0.0);
    for (i2, row) in out.chunks_exact_mut(n1).enumerate() {
        let [a, b, c, e] = [0, 1, 2, 3].map(|k| &along[(i2 + k) * n1..][..n1]);
        for i in 0..n1 {
            let t = [a[i], b[i], c[i], e[i]].map(f64::from);
            row[i] = round(taps(w, t[0], t[1], t[2], t[3]));
        }
    }
}

/// The lattice value of point `p` alone, from `stored` (which covers the stored voxels
/// `p - 2 ..= p + 1`) with the weights `w` of its level: the same operations in the same order
/// as [`resample`] does for that point (along x over the 16 rows, then along y, then along z),
/// so the same bits. For a few points a box's passes would compute many more.
///
/// # Panics
/// `stored` does not cover what the point reads.
pub fn lattice_point(stored: &Field<'_>, p: [i64; 3], w: [f64; 4]) -> f32 {
    let first = p.map(|c| c - 2);
    let last = p.map(|c| c + 1);
    assert!(
        stored.contains(first) && stored.contains(last),
        "the stored voxels do not cover the lattice point"
    );
    let (sy, sz) = (stored.size[0], stored.size[0] * stored.size[1]);
    let base = stored.index(first);
    let v = stored.values;
    let mut along_y = [0f64; 4];
    for (dz, y_out) in along_y.iter_mut().enumerate() {
        let mut along_x = [0f64; 4];
        for (dy, x_out) in along_x.iter_mut().enumerate() {
            let r = &v[base + dz * sz + dy * sy..][..4];
            let t = [r[0], r[1], r[2], r[3]].map(f64::from);
            *x_out = taps(w, t[0], t[1], t[2], t[3]);
        }
        *y_out = taps(w, along_x[0], along_x[1], along_x[2], along_x[3]);
    }
    round(taps(w, along_y[0], along_y[1], along_y[2], along_y[3]))
}

/// The one value the stored voxels of the box `(lo, hi)` hold, if they hold one (same bits).
fn one_value(stored: &Field<'_>, (lo, hi): GridBox) -> Option<f32> {
    let first = stored.values[stored.index(lo)];
    let k = first.to_bits();
    let width = (hi[0] - lo[0] + 1) as usize;
    let same = (lo[2]..=hi[2]).all(|z| {
        (lo[1]..=hi[1]).all(|y| {
            let at = stored.index([lo[0], y, z]);
            let row = &stored.values[at..at + width];
            // Any differing bit, over the whole row at once (this loop vectorizes).
            row.iter().fold(0, |d, v| d | (v.to_bits() ^ k)) == 0
        })
    });
    same.then_some(first)
}

/// The lattice values of `[lo, hi]` from `stored` (which covers what they read) into `out`,
/// pass by pass over whole rows, so that the loops vectorize; every buffer is written once
/// (no clearing pass). The passes along x and y run in f32 where that is exact
/// (`exact` of them, [`exact_passes`]), else in f64; along z always in f64.
fn resample(
    stored: &Field<'_>,
    (lo, hi): GridBox,
    w: [f64; 4],
    exact: usize,
    scratch: &mut LatticeScratch,
    out: &mut Vec<f32>,
) {
    let size = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
    let (along_x, along_y, along_x_f32, along_y_f32) = scratch.passes();
    match exact {
        0 => {
            along_x_pass(stored, (lo, hi), w, along_x);
            along_y_pass(along_x, size, w, along_y);
            along_z_pass(along_y, size, w, out);
        }
        1 => {
            along_x_pass(stored, (lo, hi), w, along_x_f32);
            along_y_pass(along_x_f32, size, w, along_y);
            along_z_pass(along_y, size, w, out);
        }
        _ => {
            along_x_pass(stored, (lo, hi), w, along_x_f32);
            along_y_pass(along_x_f32, size, w, along_y_f32);
            along_z_pass(along_y_f32, size, w, out);
        }
    }
}

/// Along x: every stored row the points `[lo, hi]` read, `m` outputs each.
fn along_x_pass<T: Lane>(stored: &Field<'_>, (lo, hi): GridBox, w: [f64; 4], out: &mut Vec<T>) {
    let w = T::weights(w);
    let (slo, shi) = (lo.map(|c| c - 2), hi.map(|c| c + 1));
    let sn = [0, 1, 2].map(|a| (shi[a] - slo[a] + 1) as usize);
    let m = (hi[0] - lo[0] + 1) as usize;
    let v = stored.values;
    out.resize(m * sn[1] * sn[2], w[0]);
    let mut rows = out.chunks_exact_mut(m);
    for z in slo[2]..=shi[2] {
        for y in slo[1]..=shi[1] {
            let Some(dst) = rows.next() else { return };
            let src = &v[stored.index([slo[0], y, z])..][..m + 3];
            let (a, b, c, e) = (&src[..m], &src[1..m + 1], &src[2..m + 2], &src[3..m + 3]);
            for i in 0..m {
                let t = [a[i], b[i], c[i], e[i]].map(T::from);
                dst[i] = taps_in(w, t[0], t[1], t[2], t[3]);
            }
        }
    }
}

/// Along y: for each stored z, `size[1]` rows of `size[0]` from four rows each of `ax`.
fn along_y_pass<S: Copy, T: Lane + From<S>>(
    ax: &[S],
    size: [usize; 3],
    w: [f64; 4],
    out: &mut Vec<T>,
) {
    let w = T::weights(w);
    let m = size[0];
    let sn1 = size[1] + 3;
    out.resize(m * size[1] * (size[2] + 3), w[0]);
    let mut rows = out.chunks_exact_mut(m);
    for z in 0..size[2] + 3 {
        for y in 0..size[1] {
            let Some(dst) = rows.next() else { return };
            let first = z * sn1 + y;
            let [a, b, c, e] = [0, 1, 2, 3].map(|d| &ax[(first + d) * m..][..m]);
            for i in 0..m {
                let t = [a[i], b[i], c[i], e[i]].map(T::from);
                dst[i] = taps_in(w, t[0], t[1], t[2], t[3]);
            }
        }
    }
}

/// Along z, in f64, rounded half up: the lattice values.
fn along_z_pass<S: Copy>(ay: &[S], size: [usize; 3], w: [f64; 4], out: &mut Vec<f32>)
where
    f64: From<S>,
{
    let plane = size[0] * size[1];
    out.resize(plane * size[2], 0.0);
    for (z, dst) in out.chunks_exact_mut(plane).enumerate() {
        let [a, b, c, e] = [0, 1, 2, 3].map(|d| &ay[(z + d) * plane..][..plane]);
        for i in 0..plane {
            let t = [a[i], b[i], c[i], e[i]].map(f64::from);
            dst[i] = round(taps(w, t[0], t[1], t[2], t[3]));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_by_hand() {
        // Level 1: stored voxel i at level-0 position 2i + 0.5, lattice j at 2j: s = 3/4 of the
        // way from voxel j - 1 to voxel j. Catmull-Rom at s = 3/4 (s^2 = 9/16, s^3 = 27/64):
        // (-s^3 + 2s^2 - s)/2 = -3/128, (3s^3 - 5s^2 + 2)/2 = 29/128,
        // (-3s^3 + 4s^2 + s)/2 = 111/128, (s^3 - s^2)/2 = -9/128.
        assert_eq!(
            weights(1),
            [-3.0 / 128.0, 29.0 / 128.0, 111.0 / 128.0, -9.0 / 128.0]
        );
        // Level 2: voxel i at 4i + 1.5, lattice j at 4j: s = 5/8.
        assert_eq!(weights(2)[3], (125.0 / 512.0 - 25.0 / 64.0) / 2.0);
    }

    fn one_point(values: &[f32], level: u8) -> f32 {
        let stored = Field {
            origin: [-2; 3],
            size: [4; 3],
            values,
        };
        let mut out = Vec::new();
        let points = ([0; 3], [0; 3]);
        let f = lattice_field(
            &stored,
            points,
            level,
            VoxelType::U8,
            &mut LatticeScratch::default(),
            &mut out,
        );
        assert_eq!((f.origin, f.size), ([0; 3], [1; 3]));
        f.values[0]
    }

    #[test]
    fn level_one_lattice_value_by_hand() {
        // Lattice point 0 reads stored voxels -2..=1 on each axis; one voxel of 128 at stored
        // (0, 0, 0) has weight (111/128)^3: 128 * 111^3 / 128^3 = 1367631 / 16384 = 83.47,
        // rounded to 83.
        let mut values = vec![0f32; 64];
        values[(2 * 4 + 2) * 4 + 2] = 128.0;
        assert_eq!(one_point(&values, 1), 83.0);
        // A constant stays itself; level 0 copies.
        assert_eq!(one_point(&[200.0; 64], 3), 200.0);
        assert_eq!(one_point(&values, 0), 128.0);
    }

    #[test]
    fn value_ranges_bound_every_lattice_value() {
        // Level 1 by hand: the negative weights sum to 12/128 per axis, the positive ones to
        // 140/128; three axes overshoot by 3 (140/128)^2 (12/128) + (12/128)^3 = 0.337280 of
        // the width, plus a half for rounding.
        let (lo, hi) = value_range(1, 0.0, 100.0);
        assert!(
            (lo + 34.228).abs() < 1e-3 && (hi - 134.228).abs() < 1e-3,
            "{lo} {hi}"
        );
        assert_eq!(value_range(0, 3.0, 9.0), (3.0, 9.0));
        assert_eq!(value_range(2, 7.0, 7.0), (6.5, 7.5));
        // The worst pattern for one lattice point reaches the bound (0 where a product of
        // weights is negative, 100 where it is positive).
        let w = weights(1);
        let values: Vec<f32> = (0..64)
            .map(|i| {
                let p = w[i % 4] * w[i / 4 % 4] * w[i / 16];
                if p > 0.0 {
                    100.0
                } else {
                    0.0
                }
            })
            .collect();
        let v = one_point(&values, 1);
        assert_eq!(v, 134.0);
        assert!(v <= hi);
    }

    #[test]
    fn linear_fields_are_kept() {
        // A linear ramp along x stays exact: stored level-1 voxel i at level-0 position
        // 2i + 0.5 with value 8 (2i + 0.5) gives lattice j the value 16 j.
        let size = [7usize, 4, 4];
        let values: Vec<f32> = (0..7 * 16)
            .map(|i| 8.0 * (2.0 * (i % 7) as f32 + 0.5))
            .collect();
        let stored = Field {
            origin: [0; 3],
            size,
            values: &values,
        };
        let mut out = Vec::new();
        let points = ([2; 3], [5, 2, 2]);
        let f = lattice_field(
            &stored,
            points,
            1,
            VoxelType::U8,
            &mut LatticeScratch::default(),
            &mut out,
        );
        assert_eq!((f.origin, f.size), ([2; 3], [4, 1, 1]));
        for j in 2..6 {
            assert_eq!(f.value([j, 2, 2]), 16.0 * j as f32, "lattice {j}");
        }
    }

    /// The next number of a linear congruential sequence (Knuth's MMIX constants).
    fn next(state: &mut u64) -> u64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *state
    }

    #[test]
    fn a_point_gets_one_value_whatever_box_it_is_computed_in() {
        // Stored voxels of a 12^3 field with a surface-like ramp and noise; the lattice values of
        // the whole box they cover and of sub-boxes (a tile's plane, a thin slab, one point)
        // must be the same bits, at every level the weights differ.
        let n = 12usize;
        let mut x = 7u64;
        let values: Vec<f32> = (0..n * n * n)
            .map(|i| {
                let ramp = (i % n + 2 * (i / n % n)) as f32 * 9.0;
                (ramp + (next(&mut x) >> 59) as f32).min(255.0)
            })
            .collect();
        let stored = Field {
            origin: [-3, 0, 5],
            size: [n; 3],
            values: &values,
        };
        let whole = ([-1, 2, 7], [6, 9, 14]);
        for level in 1..4 {
            let mut all = Vec::new();
            let mut s = LatticeScratch::default();
            let reference = lattice_field(&stored, whole, level, VoxelType::U8, &mut s, &mut all);
            for part in [
                ([0, 3, 8], [4, 3, 12]),
                ([-1, 2, 10], [6, 9, 12]),
                ([6, 9, 14], [6, 9, 14]),
            ] {
                let mut out = Vec::new();
                let f = lattice_field(&stored, part, level, VoxelType::U8, &mut s, &mut out);
                for z in part.0[2]..=part.1[2] {
                    for y in part.0[1]..=part.1[1] {
                        for x in part.0[0]..=part.1[0] {
                            let p = [x, y, z];
                            assert_eq!(
                                f.value(p).to_bits(),
                                reference.value(p).to_bits(),
                                "level {level}, {p:?} in {part:?}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// Lattice value `p` of `level` by its definition, point by point: along x over each of the
    /// 16 rows it reads, then along y, then along z, rounded half up.
    fn by_definition(stored: &Field<'_>, p: [i64; 3], level: u8) -> f32 {
        let w = weights(level);
        let v = |x: i64, y: i64, z: i64| f64::from(stored.value([x, y, z]));
        let along_x = |y: i64, z: i64| {
            let [x0, x1, x2, x3] = [-2, -1, 0, 1].map(|d| v(p[0] + d, y, z));
            w[0] * x0 + w[1] * x1 + w[2] * x2 + w[3] * x3
        };
        let along_y = |z: i64| {
            let [y0, y1, y2, y3] = [-2, -1, 0, 1].map(|d| along_x(p[1] + d, z));
            w[0] * y0 + w[1] * y1 + w[2] * y2 + w[3] * y3
        };
        let [z0, z1, z2, z3] = [-2, -1, 0, 1].map(|d| along_y(p[2] + d));
        ((w[0] * z0 + w[1] * z1 + w[2] * z2 + w[3] * z3) + 0.5).floor() as f32
    }

    #[test]
    fn regions_of_one_value_and_the_rest_match_the_definition() {
        // A 40^3 block of stored voxels: 0 below a tilted plane, 255 above it, a band of
        // values between (most chunks hold one value, those along the band do not), and
        // blocks of noise (no chunk holds one value: the whole-box path), u8 and u16; and the
        // patterns that take lattice values furthest from the voxels' range (the voxel's
        // weight positive: H, else 0), which decide whether a pass is exact in f32.
        let n = 40usize;
        let plane: Vec<f32> = (0..n * n * n)
            .map(|i| {
                let (x, y, z) = (i % n, i / n % n, i / (n * n));
                let d = x as i64 + 2 * y as i64 - z as i64 - 30;
                (128 - 120 * d).clamp(0, 255) as f32
            })
            .collect();
        let mut r = 3u64;
        let noise: Vec<f32> = (0..n * n * n)
            .map(|_| (next(&mut r) >> 56) as f32)
            .collect();
        let wide: Vec<f32> = (0..n * n * n)
            .map(|_| (next(&mut r) >> 48) as f32)
            .collect();
        // Stored voxels j - 2 ..= j + 1 weigh -, +, +, - on each axis: for points j = 2 mod 4
        // the voxels at 1 and 2 mod 4 weigh positive.
        let extreme = |high: f32| -> Vec<f32> {
            (0..n * n * n)
                .map(|i| {
                    let sign = |c: usize| if matches!(c % 4, 1 | 2) { 1 } else { -1 };
                    let s = sign(i % n) * sign(i / n % n) * sign(i / (n * n));
                    if s > 0 {
                        high
                    } else {
                        0.0
                    }
                })
                .collect()
        };
        let (extreme_u8, extreme_u16) = (extreme(255.0), extreme(65535.0));
        let blocks = [
            (&plane, VoxelType::U8),
            (&noise, VoxelType::U8),
            (&wide, VoxelType::U16),
            (&extreme_u8, VoxelType::U8),
            (&extreme_u16, VoxelType::U16),
        ];
        for (values, voxels) in blocks {
            let stored = Field {
                origin: [0; 3],
                size: [n; 3],
                values,
            };
            for level in 1..4 {
                let points = ([2; 3], [37, 30, 35]);
                let mut out = Vec::new();
                let scratch = &mut LatticeScratch::default();
                let f = lattice_field(&stored, points, level, voxels, scratch, &mut out);
                for z in (2..=35).step_by(3) {
                    for y in 2..=30 {
                        for x in 2..=37 {
                            let p = [x, y, z];
                            let expected = by_definition(&stored, p, level);
                            assert_eq!(f.value(p).to_bits(), expected.to_bits(), "{p:?}");
                            let alone = lattice_point(&stored, p, weights(level));
                            assert_eq!(alone.to_bits(), expected.to_bits(), "{p:?} alone");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn planes_match_the_definition() {
        // Planes across each axis, at levels where the passes are reordered (1, 2; 3 for u8)
        // and where they are not (3 for u16), from noise and from the patterns furthest from
        // the voxels' range (see the test above), u8 and u16.
        let n = 24usize;
        let mut r = 11u64;
        let mut blocks = Vec::new();
        for (voxels, shift, high) in [(VoxelType::U8, 56, 255.0), (VoxelType::U16, 48, 65535.0)] {
            let noise: Vec<f32> = (0..n * n * n)
                .map(|_| (next(&mut r) >> shift) as f32)
                .collect();
            let sign = |c: usize| if matches!(c % 4, 1 | 2) { 1 } else { -1 };
            let extreme: Vec<f32> = (0..n * n * n)
                .map(|i| {
                    let s = sign(i % n) * sign(i / n % n) * sign(i / (n * n));
                    if s > 0 {
                        high
                    } else {
                        0.0
                    }
                })
                .collect();
            blocks.push((noise, voxels));
            blocks.push((extreme, voxels));
        }
        for (values, voxels) in &blocks {
            let stored = Field {
                origin: [0; 3],
                size: [n; 3],
                values,
            };
            for level in 1..4 {
                for normal in 0..3 {
                    for at in [2, 10, 21] {
                        let (mut lo, mut hi) = ([3, 2, 4], [21, 20, 19]);
                        lo[normal] = at;
                        hi[normal] = at;
                        let mut out = Vec::new();
                        let scratch = &mut LatticeScratch::default();
                        let f = lattice_plane(
                            &stored,
                            (lo, hi),
                            normal,
                            level,
                            *voxels,
                            scratch,
                            &mut out,
                        );
                        let size = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
                        assert_eq!((f.origin, f.size), (lo, size));
                        for z in lo[2]..=hi[2] {
                            for y in lo[1]..=hi[1] {
                                for x in lo[0]..=hi[0] {
                                    let p = [x, y, z];
                                    let expected = by_definition(&stored, p, level);
                                    assert_eq!(
                                        f.value(p).to_bits(),
                                        expected.to_bits(),
                                        "level {level}, {voxels:?}, {p:?}"
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn passes_exact_in_f32_by_hand() {
        // Level 1: weights -3, 29, 111, -9 over 128, N = 152. u8: 255 * 152 = 38,760 and
        // 255 * 152^2 = 5,891,520 are within 2^24 = 16,777,216, 255 * 152^3 is not; u16:
        // 65,535 * 152 = 9,961,320 is, 65,535 * 152^2 is not.
        assert_eq!(exact_passes(1, 255.0, 24), 2);
        assert_eq!(exact_passes(1, 65535.0, 24), 1);
        // Level 2: -45, 399, 745, -75 over 1024, N = 1264: 255 * 1264 = 322,320, but
        // 255 * 1264^2 = 407,412,480; 65,535 * 1264 = 82,836,240 already is not.
        assert_eq!(exact_passes(2, 255.0, 24), 1);
        assert_eq!(exact_passes(2, 65535.0, 24), 0);
        // Level 3: -441, 3899, 5301, -567 over 8192, N = 10,208: 255 * 10,208 = 2,603,040.
        assert_eq!(exact_passes(3, 255.0, 24), 1);
        // In f64 (2^53 = 9.007e15): level 2 u16, 65,535 * 1264^3 = 1.32e14, is exact; level 3
        // u8, 255 * 10,208^3 = 2.71e14, too, but not u16 (6.97e16).
        assert_eq!(exact_passes(2, 65535.0, 53), 3);
        assert_eq!(exact_passes(3, 255.0, 53), 3);
        assert_eq!(exact_passes(3, 65535.0, 53), 2);
    }

    /// The vectors of [`value_range`] for the web viewer's port (`web/src/tile.ts`
    /// `valueRange`, checked by `web/test/tile.test.ts`), which decides without a request which
    /// tiles and strips no surface crosses: levels 0..16 over voxel ranges of u8 and u16 volumes
    /// (equal voxels, the full ranges, narrow ones at either end, random ones). As the vectors of
    /// `proto/tests/lod_vectors.rs`, the test fails when the committed file differs;
    /// `ISOVOX_WRITE_VECTORS=1 cargo test -p isovox-server --lib lattice` rewrites it.
    #[test]
    fn web_value_range_vectors_are_current() {
        let mut pairs: Vec<(f32, f32)> = vec![
            (0.0, 0.0),
            (7.0, 7.0),
            (0.0, 1.0),
            (3.0, 9.0),
            (0.0, 100.0),
            (0.0, 255.0),
            (254.0, 255.0),
            (0.0, 65535.0),
            (65534.0, 65535.0),
            (1.0, 65534.0),
            // Level 4 reaches 65083.5 exactly in f32, where an f64 bound falls short by 0.002.
            (64825.0, 65000.0),
        ];
        let mut state = 0x7a1u64;
        for _ in 0..6 {
            let a = (next(&mut state) >> 48) as f32;
            let b = (next(&mut state) >> 48) as f32;
            pairs.push((a.min(b), a.max(b)));
            let c = (next(&mut state) >> 56) as f32;
            let d = (next(&mut state) >> 56) as f32;
            pairs.push((c.min(d), c.max(d)));
        }
        // serde_json writes an f32 with the shortest digits that read back as the same f32.
        let num = |v: f32| serde_json::to_string(&v).unwrap_or_else(|e| panic!("{v}: {e}"));
        let mut cases = Vec::new();
        for level in 0..16u8 {
            for &(min, max) in &pairs {
                let (lo, hi) = value_range(level, min, max);
                cases.push(format!(
                    "[{level},{},{},{},{}]",
                    num(min),
                    num(max),
                    num(lo),
                    num(hi)
                ));
            }
        }
        let fresh = format!(
            "{{\"generated_by\":\"server/src/mesh/lattice.rs\",\n\"columns\":[\"level\",\"min\",\"max\",\"low\",\"high\"],\n\"cases\":[\n{}\n]}}\n",
            cases.join(",\n")
        );
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../web/test-vectors/value_range.json");
        if std::env::var_os("ISOVOX_WRITE_VECTORS").is_some() {
            std::fs::write(&path, &fresh).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            return;
        }
        let committed = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            committed == fresh,
            "{} is stale: value_range changed. Rewrite it with ISOVOX_WRITE_VECTORS=1 cargo \
             test -p isovox-server --lib lattice, then make web/src pass `npm test` in web/ again",
            path.display()
        );
    }
}
