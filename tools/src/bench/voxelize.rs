//! `isovox-bench voxelize`: solid voxelization of a closed model of about 390,000 triangles
//! into 512^3 and 1024^3 grids, on 1 and 2 threads, next to the previous parity pass (kept in
//! the server as the tests' oracle) and the paper's GPU figures.
//!
//! The model is the project's own mesh of a generated world (marching cubes on a coarse level,
//! welded: closed by construction). Reported per grid and thread count: the parity pass before
//! and now (time, triangles per second; the two grids are checked to be identical), and the
//! 2x2x2 density end to end (`voxelize`: the watertightness check, the parity pass on a grid
//! twice as fine, the box filter), with its parts.

use super::median;
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::mesh::level::{level_tiles, mesh_tiles, weld};
use isovox_server::mesh::tile::default_iso;
use isovox_server::progress::Silent;
use isovox_server::store::{build_vod2, BuildOptions, Vod2};
use isovox_server::voxelize::reference::{voxelize_reference, voxelize_solid_reference};
use isovox_server::voxelize::solid::{voxelize_solid, TriMesh};
use isovox_server::voxelize::{voxelize, Fill, Options};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct VoxelizeBenchArgs {
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// Runs per figure (the median is shown).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
}

/// Thread counts measured.
const THREADS: [usize; 2] = [1, 2];

/// Grids (voxels per side) and the paper's GPU time for each (262,078 triangles, 2008).
const GRIDS: [(usize, &str); 2] = [(512, "1.6 ms"), (1024, "10.65 ms")];

pub fn run_bench(a: VoxelizeBenchArgs) -> anyhow::Result<()> {
    let model = world_model(&a.dir)?;
    let (lo, hi) = model
        .bounds()
        .ok_or_else(|| anyhow::anyhow!("empty model"))?;
    let longest = (0..3).map(|i| hi[i] - lo[i]).fold(0f32, f32::max) as f64;
    let triangles = model.triangles.len() as f64;
    let runs = a.runs.max(1);
    println!(
        "### Solid voxelization (CPU): the world's level-1 mesh, {} triangles, closed; median of {runs} runs, before and now alternating\n",
        model.triangles.len()
    );
    println!("Parity pass (one bit per voxel); before = the previous pass (every band of 16 rows scans every triangle), now = triangles binned by band in parallel:\n");
    println!("| grid | threads | before ms | before M triangles/s | now ms | now M triangles/s | now G voxels/s | speed-up | same voxels | paper GPU |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---|---:|");
    for (n, paper) in GRIDS {
        let scale = n as f64 / longest;
        let to_grid = |p: [f32; 3]| std::array::from_fn(|i| (p[i] - lo[i]) as f64 * scale);
        let dims = [n; 3];
        for threads in THREADS {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()?;
            let (before, now, same) = pool.install(|| {
                alternate(
                    runs,
                    || Ok(voxelize_solid_reference(&model, dims, to_grid)),
                    || Ok(voxelize_solid(&model, dims, to_grid)),
                )
            })?;
            println!(
                "| {n}^3 | {threads} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {:.2}x | {} | {paper} |",
                median(before.clone()) * 1e3,
                triangles / median(before.clone()) / 1e6,
                median(now.clone()) * 1e3,
                triangles / median(now.clone()) / 1e6,
                (n * n * n) as f64 / median(now.clone()) / 1e9,
                median(before) / median(now),
                if same { "yes" } else { "NO" },
            );
        }
    }
    println!("\nThe 2x2x2 density, `voxelize` end to end (the model fitted to the grid: its longest side spans it): the watertightness check, the parity pass on a grid twice as fine per axis (8 bits of samples per output voxel), the box filter (one byte per output voxel); before = the previous parity pass and box filter:\n");
    println!("| grid | threads | before ms | now ms | now: check + parity pass + box filter ms | speed-up | same values |");
    println!("|---|---:|---:|---:|---|---:|---|");
    for (n, _) in GRIDS {
        let options = Options {
            size: n as u32,
            supersample: 2,
            padding: 0,
            fill: Fill::Density,
            voxel_type: VoxelType::U8,
            allow_open: false,
        };
        for threads in THREADS {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()?;
            let (mut solid, mut fill) = (Vec::new(), Vec::new());
            let (before, now, same) = pool.install(|| {
                alternate(
                    runs,
                    || Ok(voxelize_reference(&model, &options)?.bytes),
                    || {
                        let v = voxelize(&model, &options)?;
                        solid.push(v.report.solid_time.as_secs_f64());
                        fill.push(v.report.fill_time.as_secs_f64());
                        Ok(v.bytes)
                    },
                )
            })?;
            let (before, now) = (median(before), median(now));
            let (solid, fill) = (median(solid), median(fill));
            println!(
                "| {n}^3 | {threads} | {:.0} | {:.0} | {:.0} + {:.0} + {:.0} | {:.2}x | {} |",
                before * 1e3,
                now * 1e3,
                (now - solid - fill).max(0.0) * 1e3,
                solid * 1e3,
                fill * 1e3,
                before / now,
                if same { "yes" } else { "NO" },
            );
        }
    }
    Ok(())
}

/// Times `runs` calls of `before` and of `now`, alternating (so drift hits both alike): their
/// times in seconds, and whether their results are equal (compared on the last run only, so
/// that otherwise each call finds the memory the previous one freed, as in a service).
fn alternate<T: PartialEq>(
    runs: usize,
    before: impl Fn() -> anyhow::Result<T>,
    mut now: impl FnMut() -> anyhow::Result<T>,
) -> anyhow::Result<(Vec<f64>, Vec<f64>, bool)> {
    let (mut before_times, mut now_times) = (Vec::new(), Vec::new());
    let mut same = false;
    for run in 0..runs {
        let start = Instant::now();
        let old = before()?;
        before_times.push(start.elapsed().as_secs_f64());
        let old = (run + 1 == runs).then_some(old);
        let start = Instant::now();
        let new = now()?;
        now_times.push(start.elapsed().as_secs_f64());
        same = old.is_some_and(|old| old == new);
    }
    Ok((before_times, now_times, same))
}

/// The welded level-1 mesh of a generated 384x192x384 world (built once into `dir`).
fn world_model(dir: &std::path::Path) -> anyhow::Result<TriMesh> {
    std::fs::create_dir_all(dir)?;
    let path = dir.join("voxelize-world-384.vod");
    let layout = VolumeLayout::new([384, 192, 384], 16, VoxelType::U8)?;
    if !path.exists() {
        build_vod2(
            &path,
            &layout,
            [1.0; 3],
            &WorldSource::new(layout.clone(), 11),
            &BuildOptions::default(),
        )?;
    }
    let snap = Vod2::open(&path)?.head();
    let tiles = level_tiles(&snap, 1);
    let mesh = weld(&mesh_tiles(
        &snap,
        &tiles,
        default_iso(VoxelType::U8),
        &Silent,
    )?);
    Ok(TriMesh {
        positions: mesh.positions.clone(),
        triangles: mesh
            .indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect(),
    })
}
