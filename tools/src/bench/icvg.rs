//! `isovox-bench icvg`: primitive sampling speed and edit latency.

use super::{median, percentile};
use clap::Args;
use isovox_proto::icvg::Term;
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::cancel::CancelToken;
use isovox_server::generate::WorldSource;
use isovox_server::geometry::Box3;
use isovox_server::icvg::edit::{apply_edit, Edit, EditKind};
use isovox_server::icvg::ops::BinaryOp;
use isovox_server::icvg::term::{CompiledTerm, NoVolumes, Node, TermLimits};
use isovox_server::store::codec::Compression;
use isovox_server::store::CheckpointPolicy;
use isovox_server::store::{build_vod2, BuildOptions, Vod2, Vod2Writer};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct IcvgArgs {
    /// Working directory for the generated worlds.
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// Edits per world.
    #[arg(long, default_value_t = 1000)]
    pub edits: usize,
    /// Brick edge of the worlds.
    #[arg(long, default_value_t = 32)]
    pub brick: u32,
    /// Edges of the cubic worlds to carve.
    #[arg(long, value_delimiter = ',', default_value = "256,1024")]
    pub sizes: Vec<u32>,
}

/// xorshift64*: deterministic positions without a dependency (shared by the benches).
pub(super) struct Rng(pub(super) u64);

impl Rng {
    pub(super) fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    pub(super) fn below(&mut self, n: u32) -> u32 {
        (self.next() % n as u64) as u32
    }
}

fn shapes() -> Vec<(&'static str, Term)> {
    // Each fills a 72^3 extension space (the ICVG paper's timing case).
    vec![
        (
            "cuboid",
            Term::Cuboid {
                origin: [0; 3],
                size: [72; 3],
            },
        ),
        (
            "ellipsoid",
            Term::Ellipsoid {
                center: [36; 3],
                radii: [35, 35, 35],
            },
        ),
        (
            "cylinder",
            Term::Cylinder {
                base: [36, 0, 36],
                radii: [35, 35],
                height: 72,
            },
        ),
        (
            "cone",
            Term::Cone {
                base: [36, 0, 36],
                radii: [35, 35],
                height: 72,
            },
        ),
        (
            "torus",
            Term::Torus {
                center: [36, 36, 36],
                major: 24,
                minor: 11,
            },
        ),
        (
            "capsule",
            Term::Capsule {
                center: [36, 36, 36],
                radius: 20,
                length: 30,
            },
        ),
        (
            "prism",
            Term::Prism {
                origin: [0; 3],
                size: [72; 3],
            },
        ),
        (
            "pyramid",
            Term::Pyramid {
                origin: [0; 3],
                size: [72; 3],
            },
        ),
    ]
}

pub fn run(a: IcvgArgs) -> anyhow::Result<()> {
    println!("### Primitive sampling, one thread, 72^3 extension space (the ICVG paper: under 40 ms, about 107 ns/voxel, 2012 CPU)\n");
    println!("| primitive | voxels | every voxel sampled: ms | ns/voxel | evaluation (boxes of certain value filled): ms | ns/voxel | speed-up vs paper |");
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for (name, term) in shapes() {
        let t = CompiledTerm::compile(&term, VoxelType::U8, &TermLimits::default(), &NoVolumes)?;
        let bb = t.bbox.unwrap_or(Box3::new([0; 3], [72; 3]));
        let n = bb.voxels() as usize;
        let mut out = vec![0u16; n];
        let mut naive = Vec::new();
        let mut fast = Vec::new();
        for _ in 0..5 {
            // Every voxel through the sampling function, row by row, no classification.
            let Node::Primitive(p) = &t.node else {
                anyhow::bail!("{name} is not a primitive")
            };
            let width = (bb.max[0] - bb.min[0]) as usize;
            let start = Instant::now();
            for (row, (y, z)) in (bb.min[2]..bb.max[2])
                .flat_map(|z| (bb.min[1]..bb.max[1]).map(move |y| (y, z)))
                .enumerate()
            {
                p.sample_row(
                    bb.min[0],
                    y,
                    z,
                    VoxelType::U8,
                    &mut out[row * width..(row + 1) * width],
                );
            }
            naive.push(start.elapsed().as_secs_f64());
            std::hint::black_box(&out);
            // The edit path: 16^3 boxes, each filled without sampling when its value is certain.
            let start = Instant::now();
            let mut scratch = vec![0u16; 16 * 16 * 16];
            let mut z = bb.min[2];
            while z < bb.max[2] {
                let mut y = bb.min[1];
                while y < bb.max[1] {
                    let mut x = bb.min[0];
                    while x < bb.max[0] {
                        let b = Box3::new([x, y, z], [x + 16, y + 16, z + 16]).intersect(&bb);
                        let len = b.voxels() as usize;
                        t.eval(&b, &mut scratch[..len])?;
                        x += 16;
                    }
                    y += 16;
                }
                z += 16;
            }
            fast.push(start.elapsed().as_secs_f64());
            std::hint::black_box(&scratch);
        }
        let (naive, fast) = (median(naive), median(fast));
        println!(
            "| {name} | {n} | {:.2} | {:.1} | {:.2} | {:.1} | {:.0}x |",
            naive * 1e3,
            naive * 1e9 / n as f64,
            fast * 1e3,
            fast * 1e9 / n as f64,
            107.0 / (fast * 1e9 / n as f64)
        );
    }

    println!("\n### Edit latency: carve a radius-16 ellipsoid at a random place on the terrain (evaluate + dedup + LOD + durable commit, 2 threads)\n");
    println!("| world | brick | edits | median ms | p90 ms | p99 ms | max ms | bricks changed per edit (median, all levels) | reopen after commit median ms |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    std::fs::create_dir_all(&a.dir)?;
    for &size in &a.sizes {
        let dims = [size; 3];
        let layout = VolumeLayout::new(dims, a.brick, VoxelType::U8)?;
        let world = WorldSource::new(layout.clone(), 7);
        let path = a.dir.join(format!("edit-world-{size}.vod"));
        build_vod2(&path, &layout, [1.0; 3], &world, &BuildOptions::default())?;
        let mut writer = Vod2Writer::open_append(&path, Compression::for_edits())?;
        let mut snap = Vod2::open(&path)?.head();
        let mut rng = Rng(0x1234_5678_9abc_def1 ^ size as u64);
        let (mut latency, mut reopen, mut changed) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..a.edits {
            let (x, z) = (16 + rng.below(size - 32), 16 + rng.below(size - 32));
            let y = world.height(x, z) as i64;
            let term = Term::Ellipsoid {
                center: [x as i64, y, z as i64],
                radii: [16; 3],
            };
            let mut edit = Edit {
                kind: EditKind::Binary(
                    BinaryOp::Difference,
                    CompiledTerm::compile(
                        &term,
                        VoxelType::U8,
                        &TermLimits::default(),
                        &NoVolumes,
                    )?,
                ),
                region: None,
                sampled: 0,
                note: Default::default(),
            };
            let start = Instant::now();
            let outcome = apply_edit(
                &mut writer,
                &snap,
                &mut edit,
                CheckpointPolicy::default(),
                &CancelToken::never(),
            )?;
            latency.push(start.elapsed().as_secs_f64() * 1e3);
            changed.push(outcome.changed.iter().map(Vec::len).sum::<usize>() as f64);
            let start = Instant::now();
            snap = Vod2::open(&path)?.head();
            reopen.push(start.elapsed().as_secs_f64() * 1e3);
        }
        println!(
            "| {}x{}x{} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.0} | {:.2} |",
            dims[0],
            dims[1],
            dims[2],
            a.brick,
            a.edits,
            median(latency.clone()),
            percentile(latency.clone(), 0.9),
            percentile(latency.clone(), 0.99),
            percentile(latency, 1.0),
            median(changed),
            median(reopen),
        );
    }
    Ok(())
}
