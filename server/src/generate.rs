//! Synthetic data sets like the thesis's (its Table 2): an ellipsoid filling the volume, and a
//! terrain from a fractal Perlin-noise height map. Both are [`BrickSource`]s, so any size streams
//! into a VOD 2 file without holding the volume in memory.

use crate::icvg::primitives::{constant_over, Box3, Ellipsoid, Primitive};
use crate::store::BrickSource;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use noise::{Fbm, MultiFractal, NoiseFn, Perlin};
use rayon::prelude::*;

/// Writes `value` at voxel `(x, y, z)` of a brick buffer.
fn put(out: &mut [u8], index: usize, value: u16, voxel_type: VoxelType) {
    match voxel_type {
        VoxelType::U8 => out[index] = value as u8,
        VoxelType::U16 => out[2 * index..2 * index + 2].copy_from_slice(&value.to_le_bytes()),
    }
}

/// The brick's voxel box at level 0, clipped to the volume: `(lo, hi)` inclusive, and whether
/// the brick lies wholly inside the volume.
fn brick_box(layout: &VolumeLayout, key: BrickKey) -> ([i64; 3], [i64; 3], bool) {
    let b = layout.brick() as i64;
    let dims = layout.dims();
    let lo = [key.x, key.y, key.z].map(|c| c as i64 * b);
    let hi = [0, 1, 2].map(|a| (lo[a] + b - 1).min(dims[a] as i64 - 1));
    let whole = (0..3).all(|a| lo[a] + b <= dims[a] as i64);
    (lo, hi, whole)
}

/// The ICVG ellipsoid filling the volume: radii `(dims - 1) / 2` (at least 1), centred so that
/// its extension space `2R + 1` starts at voxel 0.
#[derive(Debug, Clone)]
pub struct EllipsoidSource {
    pub layout: VolumeLayout,
    pub ellipsoid: Ellipsoid,
}

impl EllipsoidSource {
    pub fn new(layout: VolumeLayout) -> Self {
        let radii = layout.dims().map(|d| ((d.saturating_sub(1)) / 2).max(1));
        EllipsoidSource {
            ellipsoid: Ellipsoid {
                center: radii.map(|r| r as i64),
                radii,
            },
            layout,
        }
    }
}

impl BrickSource for EllipsoidSource {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        let (lo, hi, _) = brick_box(&self.layout, key);
        let b = self.layout.brick() as usize;
        let t = self.layout.voxel_type();
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let i = (((z - lo[2]) as usize * b + (y - lo[1]) as usize) * b)
                        + (x - lo[0]) as usize;
                    put(out, i, self.ellipsoid.sample([x, y, z], t), t);
                }
            }
        }
    }

    fn constant(&self, key: BrickKey) -> Option<u16> {
        let (lo, hi, whole) = brick_box(&self.layout, key);
        let t = self.layout.voxel_type();
        match constant_over(&self.ellipsoid, &Box3::new(lo, hi.map(|c| c + 1)), t) {
            // A partial brick is padded with L: constant only if the inside is L too.
            Some(v) if whole || v == t.low() => Some(v),
            _ => None,
        }
    }
}

/// Terrain from a fractal Perlin-noise height map over x and z (y is up): below the height the
/// ground is H, above it L, with a one-voxel band between, `floor(H * (h - y + 0.5))` clamped,
/// so marching cubes finds a smooth surface at S.
#[derive(Debug, Clone)]
pub struct WorldSource {
    pub layout: VolumeLayout,
    /// Height of the ground at each (x, z) column, x fastest, in voxels.
    heights: Vec<f32>,
    /// For each brick column (bx, bz): the lowest and highest height inside it.
    column_range: Vec<(f32, f32)>,
}

impl WorldSource {
    /// A world whose hills vary between about 15% and 85% of the height, four hills across.
    pub fn new(layout: VolumeLayout, seed: u32) -> Self {
        let [dx, dy, dz] = layout.dims();
        let fbm = Fbm::<Perlin>::new(seed)
            .set_octaves(6)
            .set_frequency(4.0 / dx.max(dz) as f64)
            .set_persistence(0.5);
        let heights: Vec<f32> = (0..dz)
            .into_par_iter()
            .flat_map_iter(|z| {
                let fbm = &fbm;
                (0..dx).map(move |x| {
                    let n = fbm.get([x as f64 + 0.5, z as f64 + 0.5]);
                    let h = dy as f64 * (0.5 + 0.45 * n.clamp(-1.0, 1.0));
                    h.clamp(1.0, (dy as f64 - 2.0).max(1.0)) as f32
                })
            })
            .collect();
        let b = layout.brick();
        let g = layout.grid(0);
        let mut column_range = vec![(f32::INFINITY, f32::NEG_INFINITY); (g[0] * g[2]) as usize];
        for z in 0..dz {
            for x in 0..dx {
                let h = heights[(z * dx + x) as usize];
                let c = &mut column_range[((z / b) * g[0] + x / b) as usize];
                c.0 = c.0.min(h);
                c.1 = c.1.max(h);
            }
        }
        WorldSource {
            layout,
            heights,
            column_range,
        }
    }

    /// The ground's height at column (x, z), in voxels.
    pub fn height(&self, x: u32, z: u32) -> f32 {
        let dx = self.layout.dims()[0];
        self.heights[(z.min(self.layout.dims()[2] - 1) * dx + x.min(dx - 1)) as usize]
    }

    fn value(h: f32, y: i64, high: u16) -> u16 {
        let v = (high as f64 * (h as f64 - y as f64 + 0.5)).floor();
        v.clamp(0.0, high as f64) as u16
    }
}

impl BrickSource for WorldSource {
    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        let (lo, hi, _) = brick_box(&self.layout, key);
        let b = self.layout.brick() as usize;
        let t = self.layout.voxel_type();
        let dx = self.layout.dims()[0] as usize;
        for z in lo[2]..=hi[2] {
            for x in lo[0]..=hi[0] {
                let h = self.heights[z as usize * dx + x as usize];
                for y in lo[1]..=hi[1] {
                    let i = (((z - lo[2]) as usize * b + (y - lo[1]) as usize) * b)
                        + (x - lo[0]) as usize;
                    put(out, i, Self::value(h, y, t.high()), t);
                }
            }
        }
    }

    fn constant(&self, key: BrickKey) -> Option<u16> {
        let (lo, hi, whole) = brick_box(&self.layout, key);
        let (hmin, hmax) = self.column_range[(key.z * self.layout.grid(0)[0] + key.x) as usize];
        let high = self.layout.voxel_type().high();
        // value(h, y) is L when h - y + 0.5 <= 0 and H when h - y + 0.5 >= 1.
        if lo[1] as f32 >= hmax + 0.5 {
            return Some(0);
        }
        if whole && (hi[1] as f32) <= hmin - 0.5 {
            return Some(high);
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_constant_shortcut(source: &dyn BrickSource, layout: &VolumeLayout) -> usize {
        let g = layout.grid(0);
        let mut decided = 0;
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    let key = BrickKey { level: 0, x, y, z };
                    if let Some(v) = source.constant(key) {
                        decided += 1;
                        let mut out = vec![0u8; layout.brick_bytes()];
                        source.fill(key, &mut out);
                        let mut expect = vec![0u8; layout.brick_bytes()];
                        crate::store::codec::fill_constant(&mut expect, v, layout.voxel_type());
                        assert_eq!(out, expect, "brick {key} is not the constant {v}");
                    }
                }
            }
        }
        decided
    }

    #[test]
    fn world_shortcut_is_exact() {
        let layout = VolumeLayout::new([70, 60, 50], 8, VoxelType::U8).unwrap();
        let w = WorldSource::new(layout.clone(), 7);
        assert!(check_constant_shortcut(&w, &layout) > 100);
    }

    #[test]
    fn ellipsoid_shortcut_is_exact() {
        let layout = VolumeLayout::new([61, 50, 43], 8, VoxelType::U16).unwrap();
        let e = EllipsoidSource::new(layout.clone());
        assert!(check_constant_shortcut(&e, &layout) > 20);
    }

    #[test]
    fn world_band_values() {
        // h = 10.25: y = 10 -> floor(255 * 0.75) = 191; y = 11 -> floor(255 * -0.25) -> 0;
        // y = 9 -> 255 * 1.75 clamps to 255.
        assert_eq!(WorldSource::value(10.25, 10, 255), 191);
        assert_eq!(WorldSource::value(10.25, 11, 255), 0);
        assert_eq!(WorldSource::value(10.25, 9, 255), 255);
    }
}
