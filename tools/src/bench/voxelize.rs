//! `isovox-bench voxelize`: solid voxelization of a closed model of about 300,000 triangles
//! into 512^3 and 1024^3 grids, next to the paper's GPU figures.
//!
//! The model is the project's own mesh of a generated world (marching cubes on a coarse level,
//! welded: closed by construction). Reported per grid: time of the parity pass, triangles and
//! voxels per second, the bits held per voxel, and the same with the 2x2x2 density (the parity
//! pass on a grid twice as fine, then the box filter).

use super::median;
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::mesh::level::{level_tiles, mesh_tiles, weld};
use isovox_server::mesh::tile::default_iso;
use isovox_server::progress::Silent;
use isovox_server::store::{build_vod2, BuildOptions, Vod2};
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

pub fn run_bench(a: VoxelizeBenchArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&a.dir)?;
    let path = a.dir.join("voxelize-world-384.vod");
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
    let level = 1;
    let tiles = level_tiles(&snap, level);
    let mesh = weld(&mesh_tiles(
        &snap,
        &tiles,
        default_iso(VoxelType::U8),
        &Silent,
    )?);
    let model = TriMesh {
        positions: mesh.positions.clone(),
        triangles: mesh
            .indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect(),
    };
    let (lo, hi) = model
        .bounds()
        .ok_or_else(|| anyhow::anyhow!("empty model"))?;
    let longest = (0..3).map(|i| hi[i] - lo[i]).fold(0f32, f32::max) as f64;
    println!(
        "### Solid voxelization (CPU, 2 threads): the world's level-{level} mesh, {} triangles, closed\n",
        model.triangles.len()
    );
    println!("| grid | parity pass ms | M triangles/s | G voxels/s | bits per voxel | with density (2x2x2) ms | paper GPU (262,078 triangles, 2008) |");
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for (n, paper) in [(512usize, "1.6 ms"), (1024, "10.65 ms")] {
        let scale = n as f64 / longest;
        let dims = [n; 3];
        let mut times = Vec::new();
        let mut bytes = 0;
        for _ in 0..a.runs.max(1) {
            let start = Instant::now();
            let grid = voxelize_solid(&model, dims, |p| {
                std::array::from_fn(|i| (p[i] - lo[i]) as f64 * scale)
            });
            times.push(start.elapsed().as_secs_f64());
            bytes = grid.bytes();
        }
        let t = median(times);
        let mut density = Vec::new();
        for _ in 0..a.runs.max(1) {
            let start = Instant::now();
            let v = voxelize(
                &model,
                &Options {
                    size: n as u32,
                    supersample: 2,
                    padding: 0,
                    fill: Fill::Density,
                    voxel_type: VoxelType::U8,
                    allow_open: false,
                },
            )?;
            density.push(start.elapsed().as_secs_f64());
            drop(v);
        }
        let voxels = (n * n * n) as f64;
        println!(
            "| {n}^3 | {:.1} | {:.1} | {:.2} | {:.2} | {:.0} | {paper} |",
            t * 1e3,
            model.triangles.len() as f64 / t / 1e6,
            voxels / t / 1e9,
            bytes as f64 * 8.0 / voxels,
            median(density) * 1e3,
        );
    }
    println!("\nThe parity pass holds one bit per voxel (columns of u64 words); the density pass samples a grid 2x finer per axis (8 bits of samples per output voxel) and writes one byte per output voxel.");
    Ok(())
}
