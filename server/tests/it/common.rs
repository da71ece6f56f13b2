//! Test helpers shared by the storage-engine integration tests: deterministic noise, volumes as
//! plain arrays, and an independent, straightforward level-of-detail downsampling to compare the
//! engine against. Nothing here calls the code under test.
#![allow(dead_code)]

use isovox_proto::VoxelType;

/// Marsaglia's xorshift64: the tests' one seeded generator. Deterministic noise that no codec
/// can shrink; the seed must not be 0 (xorshift stays at 0 forever).
#[derive(Debug, Clone)]
pub(crate) struct XorShift(pub u64);

impl XorShift {
    pub(crate) fn next(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        x
    }

    /// Uniform-enough value in `0..n`.
    pub(crate) fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    /// A value in `lo..=hi`.
    pub(crate) fn between(&mut self, lo: i64, hi: i64) -> i64 {
        lo + (self.next() % (hi - lo + 1) as u64) as i64
    }

    /// Uniform in [0, 1), from the top 53 bits.
    pub(crate) fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [lo, hi).
    pub(crate) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }
}

/// A whole level as a plain array of values, x fastest, then y, then z.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Grid {
    pub dims: [usize; 3],
    pub values: Vec<u16>,
}

impl Grid {
    pub(crate) fn at(&self, x: usize, y: usize, z: usize) -> u16 {
        self.values[(z * self.dims[1] + y) * self.dims[0] + x]
    }

    /// Voxel value, 0 (L) outside the grid.
    pub(crate) fn at_or_zero(&self, x: usize, y: usize, z: usize) -> u16 {
        if x < self.dims[0] && y < self.dims[1] && z < self.dims[2] {
            self.at(x, y, z)
        } else {
            0
        }
    }

    pub(crate) fn dims_u32(&self) -> [u32; 3] {
        self.dims.map(|d| d as u32)
    }

    pub(crate) fn to_bytes(&self, voxel_type: VoxelType) -> Vec<u8> {
        to_bytes(&self.values, voxel_type)
    }

    /// The next coarser level: ceil(dims / 2) voxels, each (sum of its 2x2x2 voxels + 4) / 8,
    /// voxels outside this level counting as 0.
    pub(crate) fn downsample(&self) -> Grid {
        let dims = self.dims.map(|d| d.div_ceil(2));
        let mut values = Vec::with_capacity(dims.iter().product());
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let mut sum = 0u32;
                    for dz in 0..2 {
                        for dy in 0..2 {
                            for dx in 0..2 {
                                sum += self.at_or_zero(2 * x + dx, 2 * y + dy, 2 * z + dz) as u32;
                            }
                        }
                    }
                    values.push(((sum + 4) / 8) as u16);
                }
            }
        }
        Grid { dims, values }
    }

    /// The voxels of the box `[min, max)` as RAW bytes.
    pub(crate) fn slice(&self, min: [usize; 3], max: [usize; 3], voxel_type: VoxelType) -> Vec<u8> {
        let mut v = Vec::new();
        for z in min[2]..max[2] {
            for y in min[1]..max[1] {
                for x in min[0]..max[0] {
                    v.push(self.at(x, y, z));
                }
            }
        }
        to_bytes(&v, voxel_type)
    }

    /// The brick at brick position `pos` of this level: b^3 voxels from `pos * b`, x fastest,
    /// 0 beyond the grid.
    pub(crate) fn brick(&self, pos: [usize; 3], b: usize, voxel_type: VoxelType) -> Vec<u8> {
        let mut v = Vec::with_capacity(b * b * b);
        for z in 0..b {
            for y in 0..b {
                for x in 0..b {
                    v.push(self.at_or_zero(pos[0] * b + x, pos[1] * b + y, pos[2] * b + z));
                }
            }
        }
        to_bytes(&v, voxel_type)
    }
}

pub(crate) fn to_bytes(values: &[u16], voxel_type: VoxelType) -> Vec<u8> {
    match voxel_type {
        VoxelType::U8 => values
            .iter()
            .map(|&v| u8::try_from(v).expect("u8 voxel above 255"))
            .collect(),
        _ => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

/// A volume with three kinds of content across x: a constant third (L in the lower half of z,
/// H in the upper), a third of flat steps (compressible, never 0), and a third of xorshift noise
/// (incompressible).
pub(crate) fn mixed_volume(dims: [u32; 3], voxel_type: VoxelType, seed: u64) -> Grid {
    let d = dims.map(|v| v as usize);
    let high = voxel_type.high();
    let mut rng = XorShift(seed);
    let mut values = Vec::with_capacity(d.iter().product());
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let third = ((x * 3 + 1) / d[0]).min(2);
                let v = match third {
                    0 if z * 2 < d[2] => 0,
                    0 => high,
                    1 => ((x / 4 + y / 4 + z / 4 + 1) % 4) as u16 * (high / 4) + 7,
                    _ => (rng.next() & high as u64) as u16,
                };
                values.push(v);
            }
        }
    }
    Grid { dims: d, values }
}

/// Number of levels, computed by hand: level 0 plus one per halving of the largest brick grid
/// side until a single brick covers the volume.
pub(crate) fn level_count(dims: [u32; 3], brick: u32) -> usize {
    let largest = dims.iter().map(|&d| d.div_ceil(brick)).max().unwrap_or(1);
    let mut levels = 1;
    while (1u64 << (levels - 1)) < largest as u64 {
        levels += 1;
    }
    levels
}

/// Total bricks over all levels, computed by hand from the grids ceil(dims / (brick * 2^k)).
pub(crate) fn brick_count(dims: [u32; 3], brick: u32) -> u64 {
    (0..level_count(dims, brick))
        .map(|k| {
            dims.iter()
                .map(|&d| (d as u64).div_ceil((brick as u64) << k))
                .product::<u64>()
        })
        .sum()
}

/// Every level, computed independently: level 0 is the volume, each next one downsampled.
pub(crate) fn pyramid(level0: &Grid, brick: u32) -> Vec<Grid> {
    let levels = level_count(level0.dims_u32(), brick);
    let mut out = vec![level0.clone()];
    while out.len() < levels {
        let next = out[out.len() - 1].downsample();
        out.push(next);
    }
    out
}

/// A finished command's standard output then its standard error, as text, printed too (a
/// failing test shows it).
pub(crate) fn printed_output(out: &std::process::Output) -> String {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    println!("{text}");
    text
}
