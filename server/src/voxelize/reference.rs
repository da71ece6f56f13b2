//! The voxelizer's passes as they were before triangle binning and the cache-aware box filter,
//! kept as the oracle of the current ones (the tests compare them voxel for voxel on random
//! closed meshes) and as the baseline `isovox-bench voxelize` times next to them.
//!
//! - The parity pass, [`voxelize_solid_reference`]: the same sampling rules (module docs of
//!   [`super::solid`]), the straightforward way: each band of 16 rows scans every triangle,
//!   then each of its rows scans the band's list again, and each covered column's edge
//!   functions are computed from scratch.
//! - The 2x2x2 box filter: one task per slab of 32 output planes, each output column's values
//!   written a plane apart.

use super::solid::{
    edge, owns, project, sample_range, BitGrid, GridVertex, Projected, TriMesh, BAND, HALF, ONE,
};
use super::{box_fields, voxelize_with, Options, Passes, VoxelizeError, Voxelized};
use isovox_proto::VoxelType;
use rayon::prelude::*;

/// [`super::voxelize`] with the previous passes: the same voxels, slower.
///
/// # Errors
/// Those of [`super::voxelize`].
pub fn voxelize_reference(mesh: &TriMesh, options: &Options) -> Result<Voxelized, VoxelizeError> {
    voxelize_with(mesh, options, Passes::Previous)
}

/// [`super::solid::voxelize_solid`], the straightforward way: the same voxels, slower.
pub fn voxelize_solid_reference(
    mesh: &TriMesh,
    dims: [usize; 3],
    to_grid: impl Fn([f32; 3]) -> [f64; 3] + Sync,
) -> BitGrid {
    // Zeroed by one thread, as it was.
    let words = dims[2].div_ceil(64);
    let mut grid = BitGrid {
        dims,
        words,
        bits: vec![0; dims[0] * dims[1] * words],
    };
    let projected: Vec<Projected> = mesh
        .triangles
        .par_iter()
        .filter_map(|t| {
            project(
                t.map(|v| GridVertex::new(to_grid(mesh.positions[v as usize]))),
                dims,
            )
        })
        .collect();
    // The sample rows each triangle covers.
    let rows_of = |t: &Projected| {
        let ymin = t.y.iter().copied().min().unwrap_or(0);
        let ymax = t.y.iter().copied().max().unwrap_or(0);
        sample_range(ymin, ymax, dims[1])
    };
    let (nx, nz, words) = (dims[0], dims[2], grid.words);
    let row_words = (nx * words).max(1);
    grid.bits
        .par_chunks_mut(row_words * BAND)
        .enumerate()
        .for_each(|(band, rows)| {
            let first = band * BAND;
            let last = first + rows.len() / row_words - 1;
            let mut mine = Vec::new();
            for (i, t) in projected.iter().enumerate() {
                if let Some((lo, hi)) = rows_of(t) {
                    if lo <= last && hi >= first {
                        mine.push(i as u32);
                    }
                }
            }
            for (r, row) in rows.chunks_mut(row_words).enumerate() {
                let y = first + r;
                let py = y as i64 * ONE + HALF;
                for &i in &mine {
                    let t = &projected[i as usize];
                    if !rows_of(t).is_some_and(|(lo, hi)| lo <= y && y <= hi) {
                        continue;
                    }
                    toggle_below(t, py, nx, nz, words, row);
                }
            }
        });
    grid
}

/// Toggles, in one row of columns (sample y `py`, fixed point), the voxels below triangle `t`
/// in every column whose centre its projection covers.
fn toggle_below(t: &Projected, py: i64, nx: usize, nz: usize, words: usize, row: &mut [u64]) {
    let xmin = t.x.iter().copied().min().unwrap_or(0);
    let xmax = t.x.iter().copied().max().unwrap_or(0);
    let Some((x0, x1)) = sample_range(xmin, xmax, nx) else {
        return;
    };
    for x in x0..=x1 {
        let px = x as i64 * ONE + HALF;
        let mut w = [0i128; 3];
        let mut inside = true;
        for (e, we) in w.iter_mut().enumerate() {
            let (a, b) = ((e + 1) % 3, (e + 2) % 3);
            *we = edge(t.x[a], t.y[a], t.x[b], t.y[b], px, py);
            if *we < 0 || (*we == 0 && !owns(t.x[b] - t.x[a], t.y[b] - t.y[a])) {
                inside = false;
                break;
            }
        }
        if !inside {
            continue;
        }
        let z =
            (w[0] as f64 * t.z[0] + w[1] as f64 * t.z[1] + w[2] as f64 * t.z[2]) / t.area2 as f64;
        // Centres k + 0.5 strictly below z: k < z - 0.5.
        let below = ((z - 0.5).ceil().max(0.0) as usize).min(nz);
        let col = &mut row[x * words..(x + 1) * words];
        for word in col.iter_mut().take(below / 64) {
            *word = !*word;
        }
        if !below.is_multiple_of(64) {
            col[below / 64] ^= (1u64 << (below % 64)) - 1;
        }
    }
}

/// The previous 2x2x2 box filter (see `fill_density_2` in the parent module for the fields).
pub(super) fn fill_density_2(
    grid: &BitGrid,
    dims: [u32; 3],
    table: &[u16],
    t: VoxelType,
    out: &mut [u8],
) {
    let [nx, ny, nz] = dims.map(|d| d as usize);
    let bpv = t.bytes();
    let plane = nx * ny * bpv;
    // One fine word holds 32 output voxels along z: slabs of 32 planes are independent.
    out.par_chunks_mut(32 * plane)
        .enumerate()
        .for_each(|(w, slab)| {
            let planes = (nz - 32 * w).min(32);
            for y in 0..ny {
                for x in 0..nx {
                    let (even, odd) = box_fields(
                        [(0, 0), (1, 0), (0, 1), (1, 1)]
                            .map(|(dx, dy)| grid.column_words(2 * x + dx, 2 * y + dy)[w]),
                    );
                    let at = (y * nx + x) * bpv;
                    for z in 0..planes {
                        let field = if z % 2 == 0 { even } else { odd };
                        let v = table[((field >> (4 * (z / 2))) & 0xf) as usize];
                        let i = z * plane + at;
                        match t {
                            VoxelType::U8 => slab[i] = v as u8,
                            _ => slab[i..i + 2].copy_from_slice(&v.to_le_bytes()),
                        }
                    }
                }
            }
        });
}
