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

/// Reusable memory for [`lattice_field`]: the passes along x and along y.
#[derive(Debug, Default)]
pub struct LatticeScratch {
    along_x: Vec<f64>,
    along_y: Vec<f64>,
}

/// Resamples stored voxels of `level` onto the level's lattice: for a field of stored voxels
/// covering `[s, e]` (inclusive) on each axis, writes into `out` the lattice values of
/// `[s + 2, e - 1]` and returns them as a field. Level 0 copies the voxels of `[s + 2, e - 1]`.
///
/// Separable: along x, then y, then z, each output from its four inputs in one fixed order, so
/// a lattice point gets the same value whatever box it is computed in (tiles of neighbouring
/// levels compute the same points from differently placed boxes). The loops run over whole rows
/// so that they vectorize.
///
/// # Panics
/// `level > 30`, or the stored field is less than 4 voxels wide on an axis.
pub fn lattice_field<'o>(
    stored: &Field<'_>,
    level: u8,
    scratch: &mut LatticeScratch,
    out: &'o mut Vec<f32>,
) -> Field<'o> {
    assert!(level <= 30, "level {level} out of range");
    assert!(
        stored.size.iter().all(|&s| s >= 4),
        "a lattice value needs four stored voxels per axis"
    );
    let n = stored.size;
    let size = n.map(|s| s - 3);
    let origin = stored.origin.map(|o| o + 2);
    out.clear();
    let v = stored.values;
    assert_eq!(v.len(), n[0] * n[1] * n[2]);
    if level == 0 {
        out.reserve(size[0] * size[1] * size[2]);
        for z in 0..size[2] {
            for y in 0..size[1] {
                let row = ((z + 2) * n[1] + y + 2) * n[0] + 2;
                out.extend_from_slice(&v[row..row + size[0]]);
            }
        }
    } else {
        let [w0, w1, w2, w3] = weights(level);
        // Along x: every stored row, size[0] outputs each.
        let ax = &mut scratch.along_x;
        ax.clear();
        ax.resize(size[0] * n[1] * n[2], 0.0);
        for (dst, src) in ax.chunks_exact_mut(size[0]).zip(v.chunks_exact(n[0])) {
            let taps = src
                .iter()
                .zip(&src[1..])
                .zip(src[2..].iter().zip(&src[3..]));
            for (d, ((a, b), (c, e))) in dst.iter_mut().zip(taps) {
                *d = w0 * f64::from(*a)
                    + w1 * f64::from(*b)
                    + w2 * f64::from(*c)
                    + w3 * f64::from(*e);
            }
        }
        // Along y: for each z, size[1] rows from four rows each.
        let ay = &mut scratch.along_y;
        ay.clear();
        ay.resize(size[0] * size[1] * n[2], 0.0);
        let row = size[0];
        for z in 0..n[2] {
            for y in 0..size[1] {
                let at = |dy: usize| &ax[((z * n[1]) + y + dy) * row..][..row];
                let (a, b, c, e) = (at(0), at(1), at(2), at(3));
                let dst = &mut ay[(z * size[1] + y) * row..][..row];
                for (i, d) in dst.iter_mut().enumerate() {
                    *d = w0 * a[i] + w1 * b[i] + w2 * c[i] + w3 * e[i];
                }
            }
        }
        // Along z, rounded half up.
        out.resize(size[0] * size[1] * size[2], 0.0);
        let plane = size[0] * size[1];
        for z in 0..size[2] {
            let at = |dz: usize| &ay[(z + dz) * plane..][..plane];
            let (a, b, c, e) = (at(0), at(1), at(2), at(3));
            let dst = &mut out[z * plane..][..plane];
            for (i, d) in dst.iter_mut().enumerate() {
                let value = w0 * a[i] + w1 * b[i] + w2 * c[i] + w3 * e[i] + 0.5;
                // floor, without the libm call: truncate, then one down where that rounded up
                // (negative values).
                let t = value as i64 as f64;
                *d = (if t > value { t - 1.0 } else { t }) as f32;
            }
        }
    }
    Field {
        origin,
        size,
        values: out,
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
        let f = lattice_field(&stored, level, &mut LatticeScratch::default(), &mut out);
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
        let f = lattice_field(&stored, 1, &mut LatticeScratch::default(), &mut out);
        assert_eq!((f.origin, f.size), ([2; 3], [4, 1, 1]));
        for j in 2..6 {
            assert_eq!(f.value([j, 2, 2]), 16.0 * j as f32, "lattice {j}");
        }
    }
}
