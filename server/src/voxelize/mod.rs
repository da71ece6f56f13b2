//! Meshes into volumes: solid voxelization by parity, the paper's 2x2x2 box-filter density,
//! and conservative variants (Eisemann and Decoret, "Single-Pass GPU Solid Voxelization for
//! Real-Time Applications", 2008), on the CPU.
//!
//! Layout:
//! - [`load`]: STL, OBJ, PLY and glTF/GLB readers.
//! - [`store`]: uploaded meshes by content hash, for mesh leaves of ICVG terms.
//! - [`solid`]: bit-packed columns, XOR parity per triangle with exact centre sampling
//!   (triangles binned by band of rows in parallel), the conservative surface, the
//!   watertightness check.
//! - [`reference`]: the previous parity pass and box filter, the tests' oracle and the
//!   benchmark's baseline.
//!
//! Placement: the model's longest bounding-box side spans `size` voxels; `padding` voxels of L
//! surround it, so the surface is closed inside the volume. With `supersample` s the solid is
//! sampled on a grid s times finer per axis and each output voxel's value is the fraction of its
//! s^3 samples inside (for s = 2 exactly the paper's density 0..8), mapped linearly to [L, H]
//! and rounded half up: half the samples inside gives a value >= S, so the inside test (`>= S`)
//! and the mesher's default iso (S - 0.5) put the surface where the density is one half.

pub mod load;
pub mod reference;
pub mod solid;
pub mod store;

use crate::cancel::{CancelToken, Stopped};
use isovox_proto::VoxelType;
use rayon::prelude::*;
use solid::{odd_edges, voxelize_solid, voxelize_solid_until, voxelize_surface, BitGrid, TriMesh};
use std::time::{Duration, Instant};

/// Most samples one voxelization may take (16 GiB of bits).
const MAX_SAMPLES: u128 = 1 << 37;

/// What a voxel's value says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fill {
    /// Fraction of the supersampled centres inside, as a density in [L, H] (the default).
    Density,
    /// H where the voxel's centre is inside, else L.
    Center,
    /// H where the whole voxel is inside (conservative under-estimate).
    Inside,
    /// H where any part of the voxel is inside (conservative over-estimate).
    Touched,
}

/// How to voxelize.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Voxels along the model's longest side.
    pub size: u32,
    /// Samples per voxel per axis for `Fill::Density`.
    pub supersample: u32,
    /// Voxels of L around the model.
    pub padding: u32,
    /// How voxel values are decided.
    pub fill: Fill,
    /// The voxel type.
    pub voxel_type: VoxelType,
    /// Voxelize even when some edges are used by an odd number of triangles.
    pub allow_open: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            size: 256,
            supersample: 2,
            padding: 2,
            fill: Fill::Density,
            voxel_type: VoxelType::U8,
            allow_open: false,
        }
    }
}

/// Why a model could not be voxelized.
#[derive(Debug, thiserror::Error)]
pub enum VoxelizeError {
    /// The model has no triangle.
    #[error("the model has no triangles")]
    Empty,
    /// Some edges are used by an odd number of triangles: the inside is not defined.
    #[error("the model is not watertight: {odd} of its {edges} edges are used by an odd number of triangles (holes, or inner walls meeting the hull), so its inside is not defined; fix the model, or voxelize it anyway with --allow-open (parity then decides)")]
    NotWatertight {
        /// Edges used by an odd number of triangles.
        odd: usize,
        /// Edges in all.
        edges: usize,
    },
    /// Every edge pairs up, but the triangles enclose no volume (all of zero area, or folded
    /// flat onto each other): there is no inside to fill.
    #[error("the model is not watertight: its {triangles} triangles enclose no volume (they have zero area or lie flat on each other), so it has no inside")]
    Flat {
        /// The model's triangles.
        triangles: usize,
    },
    /// An option out of range.
    #[error("{0}")]
    Invalid(String),
}

/// Checks that a mesh bounds a solid: it has triangles, every edge is used by an even number
/// of them (the paper's watertight), and they enclose some volume. The last catches what edge
/// counting cannot: triangles of zero area (three points on a line) pair up their edges as
/// well as a real surface does.
///
/// # Errors
/// [`VoxelizeError::Empty`], [`VoxelizeError::NotWatertight`], [`VoxelizeError::Flat`].
pub fn check_closed(mesh: &TriMesh) -> Result<(), VoxelizeError> {
    if mesh.triangles.is_empty() {
        return Err(VoxelizeError::Empty);
    }
    let (odd, edges) = odd_edges(mesh);
    if odd > 0 {
        return Err(VoxelizeError::NotWatertight { odd, edges });
    }
    let (volume, magnitude) = enclosed_volume(mesh);
    // The signed volume is a sum of tetrahedra that cancel for a flat surface; what is left
    // then is rounding, far below a billionth of the terms' magnitude. A real solid keeps a
    // share of it about as large as its thickness over its length.
    if volume.abs() <= magnitude * 1e-9 {
        return Err(VoxelizeError::Flat {
            triangles: mesh.triangles.len(),
        });
    }
    Ok(())
}

/// The signed volume a closed mesh encloses (the divergence theorem: tetrahedra from the
/// bounds' centre to each triangle) and the sum of those tetrahedra's absolute volumes.
fn enclosed_volume(mesh: &TriMesh) -> (f64, f64) {
    let Some((lo, hi)) = mesh.bounds() else {
        return (0.0, 0.0);
    };
    let centre: [f64; 3] = std::array::from_fn(|a| (lo[a] as f64 + hi[a] as f64) / 2.0);
    let at = |i: u32| -> [f64; 3] {
        let p = mesh.positions[i as usize];
        std::array::from_fn(|a| p[a] as f64 - centre[a])
    };
    let (mut volume, mut magnitude) = (0.0, 0.0);
    for t in &mesh.triangles {
        let v = crate::geometry::tetra_volume(at(t[0]), at(t[1]), at(t[2]));
        volume += v;
        magnitude += v.abs();
    }
    (volume, magnitude)
}

/// A voxelized model.
#[derive(Debug)]
pub struct Voxelized {
    /// Size in voxels.
    pub dims: [u32; 3],
    /// Voxels, x fastest, u16 little endian for u16.
    pub bytes: Vec<u8>,
    /// Model units per voxel.
    pub voxel_size: f64,
    /// Where model point `p` lands in voxel coordinates: `(p - origin) / voxel_size`.
    pub origin: [f64; 3],
    /// What it did and cost.
    pub report: Report,
}

/// What the voxelization did and cost.
#[derive(Debug, Clone, Copy, Default)]
pub struct Report {
    /// The model's triangles.
    pub triangles: usize,
    /// Samples of the solid (voxels of the fine grid).
    pub samples: u64,
    /// Of them inside the model.
    pub samples_inside: u64,
    /// Bytes of bit grids held at once during voxelization.
    pub bit_bytes: usize,
    /// Time of the solid pass.
    pub solid_time: Duration,
    /// Time of the fill.
    pub fill_time: Duration,
}

/// Voxelizes `mesh` as `options` says.
///
/// # Errors
/// No triangles, a size out of range, or (unless `allow_open`) a mesh that does not bound a
/// solid (see [`check_closed`]).
pub fn voxelize(mesh: &TriMesh, options: &Options) -> Result<Voxelized, VoxelizeError> {
    voxelize_with(mesh, options, Passes::Current)
}

/// Which implementation of the parity pass and the box filter runs: the current ones, or the
/// previous ones, kept in [`reference`] as the tests' oracle and the benchmark's baseline.
#[derive(Debug, Clone, Copy)]
enum Passes {
    Current,
    Previous,
}

fn voxelize_with(
    mesh: &TriMesh,
    options: &Options,
    passes: Passes,
) -> Result<Voxelized, VoxelizeError> {
    let (lo, hi) = mesh.bounds().ok_or(VoxelizeError::Empty)?;
    if !(1..=4096).contains(&options.size)
        || !(1..=4).contains(&options.supersample)
        || options.padding > 1024
    {
        return Err(VoxelizeError::Invalid(format!(
            "size must be in 1..=4096, supersample in 1..=4 and padding at most 1024 (got {}, {} and {})",
            options.size, options.supersample, options.padding
        )));
    }
    let extent: [f64; 3] = std::array::from_fn(|a| (hi[a] - lo[a]) as f64);
    let longest = extent.iter().copied().fold(0.0, f64::max);
    if longest <= 0.0 || !longest.is_finite() {
        return Err(VoxelizeError::Invalid(
            "the model is flat or a point".into(),
        ));
    }
    if !options.allow_open {
        check_closed(mesh)?;
    }
    let voxel_size = longest / options.size as f64;
    let pad = options.padding as f64;
    let dims: [u32; 3] = std::array::from_fn(|a| {
        ((extent[a] / voxel_size).ceil() as u32).max(1) + 2 * options.padding
    });
    let origin: [f64; 3] = std::array::from_fn(|a| lo[a] as f64 - pad * voxel_size);
    let s = match options.fill {
        Fill::Density => options.supersample as usize,
        _ => 1,
    };
    let fine = dims.map(|d| d as usize * s);
    // One bit per sample: refuse grids whose bits alone would not fit in memory.
    let samples: u128 = fine.iter().map(|&d| d as u128).product();
    if samples > MAX_SAMPLES {
        return Err(VoxelizeError::Invalid(format!(
            "{}x{}x{} samples would need {} GiB of bits; the limit is {} GiB (lower --size or --supersample)",
            fine[0],
            fine[1],
            fine[2],
            (samples / 8) >> 30,
            (MAX_SAMPLES / 8) >> 30
        )));
    }
    let to_fine = |p: [f32; 3]| -> [f64; 3] {
        std::array::from_fn(|a| (p[a] as f64 - origin[a]) / voxel_size * s as f64)
    };
    let start = Instant::now();
    let mut grid = match passes {
        Passes::Current => voxelize_solid(mesh, fine, to_fine),
        Passes::Previous => reference::voxelize_solid_reference(mesh, fine, to_fine),
    };
    let mut bit_bytes = grid.bytes();
    let samples_inside = grid.count();
    match options.fill {
        Fill::Touched => {
            let surface = voxelize_surface(mesh, fine, to_fine);
            bit_bytes += surface.bytes();
            grid.or_with(&surface);
        }
        Fill::Inside => {
            let surface = voxelize_surface(mesh, fine, to_fine);
            bit_bytes += surface.bytes();
            grid.and_not(&surface);
        }
        Fill::Density | Fill::Center => {}
    }
    let solid_time = start.elapsed();
    let start = Instant::now();
    let bytes = fill_values(&grid, dims, s, options.voxel_type, passes);
    Ok(Voxelized {
        dims,
        bytes,
        voxel_size,
        origin,
        report: Report {
            triangles: mesh.triangles.len(),
            samples: fine.iter().map(|&d| d as u64).product(),
            samples_inside,
            bit_bytes,
            solid_time,
            fill_time: start.elapsed(),
        },
    })
}

/// The value of a voxel whose `inside` of `total` samples are inside: linear in [L, H],
/// rounded half up.
pub fn density_value(inside: u32, total: u32, t: VoxelType) -> u16 {
    let h = t.high() as u64;
    ((2 * h * inside as u64 + total as u64) / (2 * total as u64)) as u16
}

/// Output voxels from a grid `s` times finer: the count of set samples in each s^3 block.
fn fill_values(grid: &BitGrid, dims: [u32; 3], s: usize, t: VoxelType, passes: Passes) -> Vec<u8> {
    let [nx, ny, _] = dims.map(|d| d as usize);
    let total = (s * s * s) as u32;
    let table: Vec<u16> = (0..=total).map(|c| density_value(c, total, t)).collect();
    let bpv = t.bytes();
    let len = dims.iter().map(|&d| d as usize).product::<usize>() * bpv;
    let mut out = match passes {
        Passes::Current => solid::zeroed(len),
        // Zeroed by one thread, as it was.
        Passes::Previous => vec![0u8; len],
    };
    if s == 2 {
        match passes {
            Passes::Current => fill_density_2(grid, dims, &table, t, &mut out),
            Passes::Previous => reference::fill_density_2(grid, dims, &table, t, &mut out),
        }
        return out;
    }
    out.par_chunks_mut(nx * ny * bpv)
        .enumerate()
        .for_each(|(z, slice)| {
            for y in 0..ny {
                for x in 0..nx {
                    let mut count = 0;
                    for j in 0..s {
                        for i in 0..s {
                            count += grid.bits_at(x * s + i, y * s + j, z * s, s).count_ones();
                        }
                    }
                    let v = table[count as usize];
                    let at = (y * nx + x) * bpv;
                    match t {
                        VoxelType::U8 => slice[at] = v as u8,
                        _ => slice[at..at + 2].copy_from_slice(&v.to_le_bytes()),
                    }
                }
            }
        });
    out
}

/// The sample counts of 32 output voxels along z from the same word of their four fine columns:
/// 4-bit fields, those of the even output voxels in the first value, the odd in the second
/// (field `j` of each is voxel `2j` or `2j + 1`).
fn box_fields(words: [u64; 4]) -> (u64, u64) {
    const PAIRS: u64 = 0x5555_5555_5555_5555;
    const NIBBLES: u64 = 0x3333_3333_3333_3333;
    let (mut even, mut odd) = (0u64, 0u64);
    for word in words {
        let pairs = (word & PAIRS) + ((word >> 1) & PAIRS);
        even += pairs & NIBBLES;
        odd += (pairs >> 2) & NIBBLES;
    }
    (even, odd)
}

/// The paper's 2x2x2 box filter, word-parallel: per output column, the four fine columns'
/// words are summed pairwise along z into 2-bit fields, split into even and odd output voxels
/// (4-bit fields, room for 0..8), and added up; then each field is one output value.
///
/// One fine word holds 32 output planes along z, so slabs of 32 planes are independent. A task
/// takes up to 8 words of each fine column (a cache line, 256 planes); it sums the fields of
/// 64 output columns of a row at a time, then writes them plane by plane, so the bits are read
/// once and every plane gets a run of 64 consecutive values (not bytes a plane apart, which
/// would all fall in the same cache sets).
fn fill_density_2(grid: &BitGrid, dims: [u32; 3], table: &[u16], t: VoxelType, out: &mut [u8]) {
    const RUN: usize = 64;
    let [nx, ny, nz] = dims.map(|d| d as usize);
    let bpv = t.bytes();
    let plane = nx * ny * bpv;
    // Fewer words per task when there are too few slabs to keep every thread busy.
    let per_task = nz
        .div_ceil(32)
        .div_ceil(2 * rayon::current_num_threads())
        .clamp(1, 8);
    out.par_chunks_mut(32 * per_task * plane)
        .enumerate()
        .for_each(|(task, slab)| {
            let planes = slab.len() / plane;
            let first = task * per_task;
            // (even, odd) fields of word k of output column x0 + i, at k * RUN + i.
            let mut fields = vec![(0u64, 0u64); per_task * RUN];
            for y in 0..ny {
                for x0 in (0..nx).step_by(RUN) {
                    let run = RUN.min(nx - x0);
                    for i in 0..run {
                        let x = x0 + i;
                        for k in 0..planes.div_ceil(32) {
                            fields[k * RUN + i] =
                                box_fields([(0, 0), (1, 0), (0, 1), (1, 1)].map(|(dx, dy)| {
                                    grid.column_words(2 * x + dx, 2 * y + dy)[first + k]
                                }));
                        }
                    }
                    for z in 0..planes {
                        let (k, shift) = (z / 32, 4 * (z % 32 / 2));
                        let at = z * plane + (y * nx + x0) * bpv;
                        let values = fields[k * RUN..k * RUN + run].iter().map(|&(even, odd)| {
                            let field = if z % 2 == 0 { even } else { odd };
                            table[(field >> shift & 0xf) as usize]
                        });
                        let dest = &mut slab[at..at + run * bpv];
                        match t {
                            VoxelType::U8 => {
                                dest.iter_mut().zip(values).for_each(|(d, v)| *d = v as u8)
                            }
                            _ => dest
                                .chunks_exact_mut(2)
                                .zip(values)
                                .for_each(|(d, v)| d.copy_from_slice(&v.to_le_bytes())),
                        }
                    }
                }
            }
        });
}

/// The density of `mesh` placed by `to_voxel` (model point -> voxel coordinates) over the box
/// of `dims` voxels starting at voxel `min`, one value per voxel (x fastest), sampled `s`^3
/// times per voxel: for ICVG mesh leaves. The model may reach far beyond the box: parity along
/// each column counts the surfaces above the box too, so the values are those of the whole
/// model's voxelization, cut to the box.
///
/// # Errors
/// [`Stopped`] when `cancel` stops the work.
pub fn density_box(
    mesh: &TriMesh,
    min: [i64; 3],
    dims: [usize; 3],
    s: usize,
    t: VoxelType,
    to_voxel: impl Fn([f32; 3]) -> [f64; 3] + Sync,
    cancel: &CancelToken,
) -> Result<Vec<u16>, Stopped> {
    let fine = dims.map(|d| d * s);
    let grid = voxelize_solid_until(
        mesh,
        fine,
        |p| {
            let v = to_voxel(p);
            std::array::from_fn(|a| (v[a] - min[a] as f64) * s as f64)
        },
        cancel,
    )?;
    cancel.check()?;
    let bytes = fill_values(&grid, dims.map(|d| d as u32), s, t, Passes::Current);
    Ok(match t {
        VoxelType::U8 => bytes.into_iter().map(u16::from).collect(),
        _ => bytes
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, failure_persistence: None, ..ProptestConfig::default() })]

        /// The box filter gives the previous one's values for any bits and thread count (which
        /// sets how many words a task takes), with rows cut into runs of 64 anywhere.
        #[test]
        fn box_filter_matches_the_previous_one(
            dims in (1u32..150, 1u32..4, 1u32..300),
            seed in any::<u64>(),
            threads in 1usize..4,
            wide in any::<bool>(),
        ) {
            let dims = [dims.0, dims.1, dims.2];
            let t = if wide { VoxelType::U16 } else { VoxelType::U8 };
            let mut grid = BitGrid::new(dims.map(|d| 2 * d as usize));
            let mut state = seed;
            for w in &mut grid.bits {
                // Knuth's MMIX LCG, high half.
                state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
                *w = state.rotate_left(32);
            }
            let table: Vec<u16> = (0..=8).map(|c| density_value(c, 8, t)).collect();
            let n = dims.iter().map(|&d| d as usize).product::<usize>() * t.bytes();
            let (mut got, mut want) = (vec![0u8; n], vec![0u8; n]);
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .map_err(|e| TestCaseError::fail(e.to_string()))?;
            pool.install(|| {
                fill_density_2(&grid, dims, &table, t, &mut got);
                reference::fill_density_2(&grid, dims, &table, t, &mut want);
            });
            let differ = got.iter().zip(&want).filter(|(a, b)| a != b).count();
            prop_assert!(got == want, "{differ} of {n} bytes differ");
        }
    }
}
