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

/// Reusable memory for [`lattice_field`]: the passes along x and along y, one chunk's values,
/// and each chunk's one value (when its stored voxels hold one).
#[derive(Debug, Default)]
pub struct LatticeScratch {
    along_x: Vec<f64>,
    along_y: Vec<f64>,
    chunk: Vec<f32>,
    constants: Vec<Option<f32>>,
}

/// One Catmull-Rom tap sum, in the one order every lattice value is computed in.
#[inline(always)]
fn taps([w0, w1, w2, w3]: [f64; 4], a: f64, b: f64, c: f64, e: f64) -> f64 {
    w0 * a + w1 * b + w2 * c + w3 * e
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
/// larger. Level 0 copies the voxels of `[lo, hi]`.
///
/// Separable: along x, then y, then z, each output from its four inputs in one fixed order, so
/// a lattice point gets the same value whatever box it is computed in (tiles of neighbouring
/// levels compute the same points from differently placed boxes). The box is taken in chunks
/// of up to 8^3 points: a chunk whose stored voxels all hold one value gets the value those
/// operations give for it, computed once. When fewer than a third of the chunks are like that,
/// the box is computed whole (chunks read their neighbours' voxels again).
///
/// # Panics
/// `level > 30`, or `stored` does not cover what the points read.
pub fn lattice_field<'o>(
    stored: &Field<'_>,
    (lo, hi): GridBox,
    level: u8,
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
        resample(stored, (lo, hi), w, scratch, out);
        return Field {
            origin: lo,
            size,
            values: out,
        };
    }
    out.resize(size[0] * size[1] * size[2], 0.0);
    let whole = Field {
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
                resample(stored, (clo, chi), w, scratch, &mut values);
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
/// (no clearing pass).
fn resample(
    stored: &Field<'_>,
    (lo, hi): GridBox,
    w: [f64; 4],
    scratch: &mut LatticeScratch,
    out: &mut Vec<f32>,
) {
    let (slo, shi) = (lo.map(|c| c - 2), hi.map(|c| c + 1));
    let size = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
    let sn = [0, 1, 2].map(|a| (shi[a] - slo[a] + 1) as usize);
    let m = size[0];
    let v = stored.values;
    // Along x: every stored row read, m outputs each.
    let ax = &mut scratch.along_x;
    ax.resize(m * sn[1] * sn[2], 0.0);
    for (r, dst) in ax.chunks_exact_mut(m).enumerate() {
        let at = stored.index([
            slo[0],
            slo[1] + (r % sn[1]) as i64,
            slo[2] + (r / sn[1]) as i64,
        ]);
        let src = &v[at..][..m + 3];
        let (a, b, c, e) = (&src[..m], &src[1..m + 1], &src[2..m + 2], &src[3..m + 3]);
        for i in 0..m {
            let t = [a[i], b[i], c[i], e[i]].map(f64::from);
            dst[i] = taps(w, t[0], t[1], t[2], t[3]);
        }
    }
    // Along y: for each z, size[1] rows from four rows each.
    let ay = &mut scratch.along_y;
    ay.resize(m * size[1] * sn[2], 0.0);
    for (r, dst) in ay.chunks_exact_mut(m).enumerate() {
        let first = (r / size[1]) * sn[1] + r % size[1];
        let [a, b, c, e] = [0, 1, 2, 3].map(|d| &ax[(first + d) * m..][..m]);
        for i in 0..m {
            dst[i] = taps(w, a[i], b[i], c[i], e[i]);
        }
    }
    // Along z, rounded half up.
    let plane = m * size[1];
    out.resize(plane * size[2], 0.0);
    for (z, dst) in out.chunks_exact_mut(plane).enumerate() {
        let [a, b, c, e] = [0, 1, 2, 3].map(|d| &ay[(z + d) * plane..][..plane]);
        for i in 0..plane {
            dst[i] = round(taps(w, a[i], b[i], c[i], e[i]));
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
        let f = lattice_field(&stored, points, 1, &mut LatticeScratch::default(), &mut out);
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
            let reference = lattice_field(&stored, whole, level, &mut s, &mut all);
            for part in [
                ([0, 3, 8], [4, 3, 12]),
                ([-1, 2, 10], [6, 9, 12]),
                ([6, 9, 14], [6, 9, 14]),
            ] {
                let mut out = Vec::new();
                let f = lattice_field(&stored, part, level, &mut s, &mut out);
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
        // values between (most chunks hold one value, those along the band do not), and a
        // second block of noise (no chunk holds one value: the whole-box path).
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
        for values in [&plane, &noise] {
            let stored = Field {
                origin: [0; 3],
                size: [n; 3],
                values,
            };
            for level in 1..4 {
                let points = ([2; 3], [37, 30, 35]);
                let mut out = Vec::new();
                let scratch = &mut LatticeScratch::default();
                let f = lattice_field(&stored, points, level, scratch, &mut out);
                for z in (2..=35).step_by(3) {
                    for y in 2..=30 {
                        for x in 2..=37 {
                            let p = [x, y, z];
                            let expected = by_definition(&stored, p, level);
                            assert_eq!(f.value(p).to_bits(), expected.to_bits(), "{p:?}");
                        }
                    }
                }
            }
        }
    }
}
