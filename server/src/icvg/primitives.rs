//! Virtual volume sampling functions (`spec/icvg.md`, "Virtual volume sampling functions").
//!
//! Bodies, unit vectors and quotients are computed in f64, then floored and clamped, so that
//! independent implementations agree voxel for voxel.

use isovox_proto::VoxelType;

/// The ellipsoid primitive, placed with its local centre C = R on `center` (world voxel
/// coordinates): its extension space is `2R + 1` voxels per axis starting at `center - R`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ellipsoid {
    pub center: [i64; 3],
    pub radii: [u32; 3],
}

fn body(p: [f64; 3], r: [f64; 3]) -> f64 {
    (p[0] * p[0]) / (r[0] * r[0]) + (p[1] * p[1]) / (r[1] * r[1]) + (p[2] * p[2]) / (r[2] * r[2])
}

impl Ellipsoid {
    fn radii_f64(&self) -> [f64; 3] {
        self.radii.map(|r| r as f64)
    }

    /// The value at world voxel `v`.
    pub fn sample(&self, v: [i64; 3], voxel_type: VoxelType) -> u16 {
        let r = self.radii_f64();
        let outside = (0..3).any(|a| {
            let local = v[a] - (self.center[a] - self.radii[a] as i64);
            local < 0 || local > 2 * self.radii[a] as i64
        });
        if outside {
            return voxel_type.low();
        }
        let t = [0, 1, 2].map(|a| (v[a] - self.center[a]) as f64);
        let len = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
        let unit = if len == 0.0 {
            [0.0; 3]
        } else {
            t.map(|c| c / len)
        };
        let (h, s) = (voxel_type.high(), voxel_type.surface());
        if body([t[0] + unit[0], t[1] + unit[1], t[2] + unit[2]], r) < 1.0 {
            return h;
        }
        if body([t[0] - unit[0], t[1] - unit[1], t[2] - unit[2]], r) > 1.0 {
            return voxel_type.low();
        }
        (s as f64 / body(t, r)).floor().min(h as f64) as u16
    }

    /// The one value every voxel of the box `lo..=hi` takes, when that is certain without
    /// sampling them: the ellipsoidal norm is convex, so its maximum over a box is at a corner,
    /// and `|unit|_E <= 1 / min(R)` bounds how far one unit step moves it.
    pub fn constant_over(&self, lo: [i64; 3], hi: [i64; 3], voxel_type: VoxelType) -> Option<u16> {
        let r = self.radii_f64();
        let step = 1.0 / r.iter().cloned().fold(f64::INFINITY, f64::min);
        let margin = 1e-9;
        let mut max_sq = 0.0f64;
        let mut min_sq = 0.0f64;
        for a in 0..3 {
            let (l, h) = (
                (lo[a] - self.center[a]) as f64,
                (hi[a] - self.center[a]) as f64,
            );
            let far = l.abs().max(h.abs());
            max_sq += far * far / (r[a] * r[a]);
            let near = if l <= 0.0 && h >= 0.0 {
                0.0
            } else {
                l.abs().min(h.abs())
            };
            min_sq += near * near / (r[a] * r[a]);
        }
        if max_sq.sqrt() + step < 1.0 - margin {
            return Some(voxel_type.high());
        }
        if min_sq.sqrt() - step > 1.0 + margin {
            return Some(voxel_type.low());
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ellipsoid_golden_values() {
        // Sphere of radius 4 centred at (4,4,4), u8: S = 127.
        let e = Ellipsoid {
            center: [4, 4, 4],
            radii: [4, 4, 4],
        };
        let t = VoxelType::U8;
        // Centre: T = 0, T^ = 0, body(0) = 0 < 1 -> H.
        assert_eq!(e.sample([4, 4, 4], t), 255);
        // (7,4,4): T = (3,0,0), body(T+T^) = 16/16 = 1, not < 1; body(T-T^) = 4/16 <= 1;
        // band: floor(127 / (9/16)) = floor(225.77) = 225.
        assert_eq!(e.sample([7, 4, 4], t), 225);
        // (8,4,4): T = (4,0,0): body(T-T^) = 9/16 <= 1 -> band: floor(127 / 1) = 127 = S.
        assert_eq!(e.sample([8, 4, 4], t), 127);
        // (6,4,4): T = (2,0,0): body(T+T^) = 9/16 < 1 -> H.
        assert_eq!(e.sample([6, 4, 4], t), 255);
        // (8,8,4): T = (4,4,0), |T| = 5.657, T - T^ = (3.293, 3.293, 0): body = 1.355 > 1 -> L.
        assert_eq!(e.sample([8, 8, 4], t), 0);
        // Outside the extension space [0, 8]: L.
        assert_eq!(e.sample([9, 4, 4], t), 0);
        assert_eq!(e.sample([-1, 4, 4], t), 0);
        // u16: (8,4,4) is floor(32767 / 1) = 32767; (7,4,4) floor(32767 * 16 / 9) = 58252.
        assert_eq!(e.sample([8, 4, 4], VoxelType::U16), 32767);
        assert_eq!(e.sample([7, 4, 4], VoxelType::U16), 58252);
    }

    #[test]
    fn constant_over_agrees_with_sampling() {
        let e = Ellipsoid {
            center: [40, 30, 35],
            radii: [33, 25, 29],
        };
        let t = VoxelType::U8;
        let mut decided = 0;
        for bz in 0..9i64 {
            for by in 0..8i64 {
                for bx in 0..10i64 {
                    let lo = [bx * 8, by * 8, bz * 8];
                    let hi = lo.map(|c| c + 7);
                    if let Some(v) = e.constant_over(lo, hi, t) {
                        decided += 1;
                        for z in lo[2]..=hi[2] {
                            for y in lo[1]..=hi[1] {
                                for x in lo[0]..=hi[0] {
                                    assert_eq!(
                                        e.sample([x, y, z], t),
                                        v,
                                        "box {lo:?} voxel {x},{y},{z}"
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(
            decided > 300,
            "the shortcut should decide most boxes, decided {decided}"
        );
    }
}
