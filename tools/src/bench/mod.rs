//! `isovox-bench ...`: benchmarks that print Markdown tables next to the papers' figures and
//! the peers' (`store` here; the others in their own modules).
//!
//! Timings are wall-clock on this machine with a warm page cache (the data was just written);
//! each figure is the median of several runs where a run is short.

pub mod channels;
pub mod checkpoint;
pub mod cold_tiles;
pub mod edits;
pub mod http;
pub mod icvg;
pub mod memory;
pub mod mesh;
pub mod process;
pub mod voxelize;

use crate::args::parse_dims;
use anyhow::Context;
use clap::Subcommand;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::generate::{EllipsoidSource, WorldSource};
use isovox_server::geometry::Box3;
use isovox_server::progress::Silent;
use isovox_server::store::codec::{Compression, DEFAULT_ZSTD_LEVEL};
use isovox_server::store::raw::{export_raw, RawInput};
use isovox_server::store::{
    build_vod2, stream_pyramid, BrickSource, BuildOptions, DenseGrid, MemorySink, Vod2,
};
use rayon::prelude::*;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// The thesis's Tables 3-5 on generated data of the same sizes (brick 16): RAW and VOD sizes
    /// with and without compression, load times; plus import throughput and open time.
    Store(StoreArgs),
    /// ICVG: primitive sampling in ns/voxel (the paper's 72^3 shapes) and edit latency (carving
    /// radius-16 ellipsoids into a world, evaluate + dedup + LOD + durable commit).
    Icvg(icvg::IcvgArgs),
    /// Marching cubes: throughput next to VTK Flying Edges and scikit-image (--peers), by
    /// thread count and level, and the adaptive LOD's triangle savings.
    Mesh(mesh::MeshBenchArgs),
    /// HTTP: brick requests per second with wrk against isovox serve, nginx on the same bytes,
    /// and a bare axum handler (needs wrk and nginx; scripts/bench-http.sh installs them).
    Http(http::HttpBenchArgs),
    /// Shared editing over HTTP: edit throughput and latency under concurrent editors, change
    /// propagation to many subscribers, and read throughput while edits run (needs wrk).
    Edits(edits::EditsBenchArgs),
    /// The server's resident memory (RssAnon, beyond the page cache) while a client walks
    /// every brick of a 2048^3 world once in random order.
    Memory(memory::MemoryBenchArgs),
    /// Random cold mesh tiles of a 1024^3 world from 64, then 1,000 connections: the
    /// server's peak resident memory and threads against its stated bound, p99, 503s.
    ColdTiles(cold_tiles::ColdTilesBenchArgs),
    /// Solid voxelization of a ~300k-triangle closed model into 512^3 and 1024^3, next to the
    /// paper's GPU figures.
    Voxelize(voxelize::VoxelizeBenchArgs),
    /// An index checkpoint of a large volume after small edits: copying the untouched chunks
    /// of the previous checkpoint against encoding every chunk.
    Checkpoint(checkpoint::CheckpointBenchArgs),
    /// Attribute channels: mode downsampling next to tinybrain, label storage next to
    /// compressed_segmentation + gzip, edits/s with a material channel against density alone.
    Channels(channels::ChannelsBenchArgs),
}

#[derive(Debug, clap::Args)]
pub struct StoreArgs {
    /// Working directory for the generated files.
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// A real scan as RAW (e.g. the MNI152 T1 template; scripts/bench-store.sh fetches it).
    #[arg(long)]
    pub mri: Option<PathBuf>,
    /// Dimensions of the --mri RAW.
    #[arg(long, value_parser = parse_dims, default_value = "197,233,189")]
    pub mri_dims: [u32; 3],
    /// Voxel type of the --mri RAW (u8 or u16).
    #[arg(long, default_value = "u8")]
    pub mri_type: VoxelType,
    /// Edge of the large world used for the open-time comparison (0 skips it).
    #[arg(long, default_value_t = 2048)]
    pub large: u32,
    /// Brick edge (the thesis's storage experiments used 16).
    #[arg(long, default_value_t = 16)]
    pub brick: u32,
}

pub fn run(cmd: BenchCommand) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Store(a) => bench_store(a),
        BenchCommand::Icvg(a) => icvg::run(a),
        BenchCommand::Mesh(a) => mesh::run(a),
        BenchCommand::Http(a) => http::run_bench(a),
        BenchCommand::Edits(a) => edits::run_bench(a),
        BenchCommand::Memory(a) => memory::run_bench(a),
        BenchCommand::Voxelize(a) => voxelize::run_bench(a),
        BenchCommand::Channels(a) => channels::run_bench(a),
        BenchCommand::Checkpoint(a) => checkpoint::run_bench(a),
        BenchCommand::ColdTiles(a) => cold_tiles::run_bench(a),
    }
}

/// The thesis's figures (Tables 3, 4, 5): uncompressed VOD ratio, compressed (FastLZ)
/// ratio, RAW load ms, uncompressed VOD load ms, compressed VOD load ms.
struct Thesis {
    ratio_plain: f64,
    ratio_compressed: f64,
    load_raw_ms: u64,
    load_vod_ms: u64,
    load_vod_compressed_ms: u64,
}

fn thesis(name: &str) -> Option<Thesis> {
    let t =
        |ratio_plain, ratio_compressed, load_raw_ms, load_vod_ms, load_vod_compressed_ms| Thesis {
            ratio_plain,
            ratio_compressed,
            load_raw_ms,
            load_vod_ms,
            load_vod_compressed_ms,
        };
    match name {
        "MRI" => Some(t(1.62, 2.59, 854, 103, 171)),
        "Small Ellipsoid" => Some(t(2.31, 18.39, 871, 90, 185)),
        "Large Ellipsoid" => Some(t(6.69, 52.18, 12837, 252, 441)),
        "Small World" => Some(t(2.37, 15.62, 963, 56, 63)),
        "Large World" => Some(t(5.25, 32.63, 14701, 320, 428)),
        _ => None,
    }
}

struct Row {
    name: String,
    dims: [u32; 3],
    raw_bytes: u64,
    sizes: [u64; 3], // none, lz4, zstd
    import_secs: f64,
    load_raw_ms: f64,
    load_vod_ms: f64,
}

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn percentile(mut v: Vec<f64>, p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn time<T>(f: impl FnOnce() -> anyhow::Result<T>) -> anyhow::Result<(T, Duration)> {
    let start = Instant::now();
    let out = f()?;
    Ok((out, start.elapsed()))
}

/// Writes a generated data set as RAW by building it and exporting level 0.
fn write_raw(
    dir: &Path,
    name: &str,
    layout: &VolumeLayout,
    source: &dyn BrickSource,
) -> anyhow::Result<PathBuf> {
    let vod = dir.join(format!("{name}.source.vod"));
    build_vod2(&vod, layout, [1.0; 3], source, &BuildOptions::default())?;
    let raw = dir.join(format!("{name}.raw"));
    write_level0_raw(&Vod2::open(&vod)?, &raw)?;
    std::fs::remove_file(&vod).ok();
    Ok(raw)
}

/// Writes a volume's level 0 as a RAW file (what the peers and the RAW timings read).
pub fn write_level0_raw(vod: &Vod2, raw: &Path) -> anyhow::Result<()> {
    let mut out = BufWriter::with_capacity(1 << 20, File::create(raw)?);
    let region = Box3::new([0; 3], vod.layout().dims().map(i64::from));
    export_raw(&vod.head(), 0, region, &mut out, &Silent)?;
    out.flush()?;
    Ok(())
}

/// Reads every brick of every level once (decoded and hash-checked), in parallel.
fn read_every_brick(vod: &Vod2) -> anyhow::Result<()> {
    let snap = vod.head();
    let layout = snap.layout();
    (0..layout.node_count()).into_par_iter().try_for_each_init(
        || vec![0u8; layout.brick_bytes()],
        |buf, node| -> anyhow::Result<()> {
            let key: BrickKey = layout.key_of(node)?;
            snap.read_into(key, buf)?;
            Ok(())
        },
    )
}

fn measure(
    dir: &Path,
    name: &str,
    raw: &Path,
    dims: [u32; 3],
    voxel_type: VoxelType,
    brick: u32,
) -> anyhow::Result<Row> {
    let layout = VolumeLayout::new(dims, brick, voxel_type)?;
    let raw_bytes = std::fs::metadata(raw)?.len();
    let mut sizes = [0u64; 3];
    let mut import_secs = 0.0;
    let compressions = [
        Compression::None,
        Compression::Lz4,
        Compression::Zstd(DEFAULT_ZSTD_LEVEL),
    ];
    for (i, compression) in compressions.into_iter().enumerate() {
        let out = dir.join(format!("{name}.{i}.vod"));
        let mut runs = Vec::new();
        for _ in 0..3 {
            let ((), d) = time(|| {
                let input = RawInput::open(raw, false, Some(dims), Some(voxel_type))?;
                let grid = DenseGrid::new(dims, voxel_type, brick, input.voxels());
                build_vod2(
                    &out,
                    &layout,
                    [1.0; 3],
                    &grid,
                    &BuildOptions {
                        compression,
                        progress: std::sync::Arc::new(Silent),
                    },
                )?;
                Ok(())
            })?;
            runs.push(d.as_secs_f64());
        }
        sizes[i] = std::fs::metadata(&out)?.len();
        if i == 2 {
            import_secs = median(runs);
        }
    }
    // Table 5: RAW read + building the octree in memory, versus opening the VOD and reading
    // every brick once.
    let mut raw_runs = Vec::new();
    let mut vod_runs = Vec::new();
    for _ in 0..3 {
        let (_, d) = time(|| {
            let bytes = std::fs::read(raw)?;
            let grid = DenseGrid::new(dims, voxel_type, brick, &bytes);
            let mut sink = MemorySink::default();
            stream_pyramid(&layout, &grid, &mut sink, &Silent)?;
            Ok(sink.bricks.len())
        })?;
        raw_runs.push(d.as_secs_f64() * 1e3);
        let (_, d) = time(|| {
            let vod = Vod2::open(&dir.join(format!("{name}.2.vod")))?;
            read_every_brick(&vod)
        })?;
        vod_runs.push(d.as_secs_f64() * 1e3);
    }
    for i in 0..2 {
        std::fs::remove_file(dir.join(format!("{name}.{i}.vod"))).ok();
    }
    Ok(Row {
        name: name.to_string(),
        dims,
        raw_bytes,
        sizes,
        import_secs,
        load_raw_ms: median(raw_runs),
        load_vod_ms: median(vod_runs),
    })
}

/// Median and p99 of opening a file in-process, in microseconds.
fn open_times(path: &Path, runs: usize) -> anyhow::Result<(f64, f64)> {
    let mut t = Vec::with_capacity(runs);
    for _ in 0..runs {
        let start = Instant::now();
        let vod = Vod2::open(path)?;
        let e = start.elapsed();
        std::hint::black_box(&vod);
        t.push(e.as_secs_f64() * 1e6);
    }
    Ok((median(t.clone()), percentile(t, 0.99)))
}

/// The `isovox` binary the benchmarks run as a process of its own: the one built beside this
/// binary (`cargo build --release -p isovox-server -p isovox-tools` builds both).
///
/// # Errors
/// It is not there.
pub fn isovox_exe() -> anyhow::Result<PathBuf> {
    let me = std::env::current_exe()?;
    let exe = me.with_file_name("isovox");
    anyhow::ensure!(
        exe.is_file(),
        "{} is missing: build it with cargo build --release -p isovox-server",
        exe.display()
    );
    Ok(exe)
}

/// Generates the terrain world of `layout` (seed `seed`) at `path`, unless it is there from an
/// earlier run.
pub(crate) fn generated_world(path: &Path, layout: &VolumeLayout, seed: u32) -> anyhow::Result<()> {
    if !path.exists() {
        eprintln!("generating {} (once)", path.display());
        build_vod2(
            path,
            layout,
            [1.0; 3],
            &WorldSource::new(layout.clone(), seed),
            &BuildOptions::default(),
        )?;
    }
    Ok(())
}

/// Every node (brick, or mesh tile) of every level of `layout` once, in a random order
/// (Fisher-Yates, the same order every run).
pub(crate) fn shuffled_nodes(layout: &VolumeLayout) -> Vec<u64> {
    let mut nodes: Vec<u64> = (0..layout.node_count()).collect();
    let mut rng = icvg::Rng(0x2545_f491_4f6c_dd1d);
    for i in (1..nodes.len()).rev() {
        nodes.swap(i, (rng.next() % (i as u64 + 1)) as usize);
    }
    nodes
}

/// Median whole-process time of `isovox get FILE 0 x y z` in milliseconds.
fn get_process_ms(path: &Path, runs: usize) -> anyhow::Result<f64> {
    let exe = isovox_exe()?;
    let mut t = Vec::new();
    for _ in 0..runs {
        let start = Instant::now();
        let out = Command::new(&exe)
            .args([
                "get",
                &path.to_string_lossy(),
                "0",
                "1",
                "1",
                "1",
                "-o",
                "/dev/null",
            ])
            .output()
            .context("cannot run isovox get")?;
        if !out.status.success() {
            anyhow::bail!(
                "isovox get failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        t.push(start.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median(t))
}

fn kb(b: u64) -> String {
    format!("{:.0}", b as f64 / 1024.0)
}

fn bench_store(a: StoreArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&a.dir)
        .with_context(|| format!("cannot create {}", a.dir.display()))?;
    let b = a.brick;
    let mut rows = Vec::new();
    let small = [200, 160, 160];
    let large = [512, 512, 512];
    if let Some(mri) = &a.mri {
        eprintln!("bench store: MRI {}", mri.display());
        rows.push(measure(&a.dir, "MRI", mri, a.mri_dims, a.mri_type, b)?);
    }
    for (name, dims, world) in [
        ("Small Ellipsoid", small, false),
        ("Large Ellipsoid", large, false),
        ("Small World", small, true),
        ("Large World", large, true),
    ] {
        eprintln!("bench store: {name}");
        let layout = VolumeLayout::new(dims, b, VoxelType::U8)?;
        let source: Box<dyn BrickSource> = if world {
            Box::new(WorldSource::new(layout.clone(), 1))
        } else {
            Box::new(EllipsoidSource::new(layout.clone()))
        };
        let file = name.to_lowercase().replace(' ', "-");
        let raw = write_raw(&a.dir, &file, &layout, source.as_ref())?;
        let mut row = measure(&a.dir, &file, &raw, dims, VoxelType::U8, b)?;
        row.name = name.to_string();
        rows.push(row);
        std::fs::remove_file(&raw).ok();
    }

    println!("### Sizes (thesis Tables 3 and 4), brick {b}^3, whole file counted\n");
    println!("| data set | voxels | RAW KB | VOD 2 no compression KB | ratio | VOD 2 lz4 KB | ratio | VOD 2 zstd-{DEFAULT_ZSTD_LEVEL} KB | ratio | thesis VOD ratio | thesis FastLZ ratio |");
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &rows {
        let t = thesis(&r.name);
        let ratio = |s: u64| r.raw_bytes as f64 / s as f64;
        println!(
            "| {} | {}x{}x{} | {} | {} | {:.2}:1 | {} | {:.2}:1 | {} | {:.2}:1 | {} | {} |",
            r.name,
            r.dims[0],
            r.dims[1],
            r.dims[2],
            kb(r.raw_bytes),
            kb(r.sizes[0]),
            ratio(r.sizes[0]),
            kb(r.sizes[1]),
            ratio(r.sizes[1]),
            kb(r.sizes[2]),
            ratio(r.sizes[2]),
            t.as_ref()
                .map_or("-".into(), |t| format!("{:.2}:1", t.ratio_plain)),
            t.as_ref()
                .map_or("-".into(), |t| format!("{:.2}:1", t.ratio_compressed)),
        );
    }
    println!("\nThe thesis's MRI is a 200x160x160 scan; ours is the MNI152 T1 template (197x233x189, u8).");

    println!("\n### Load time (thesis Table 5): RAW read + octree build vs. VOD open + every brick read once\n");
    println!("| data set | RAW + build ms | VOD 2 (zstd) open + read all ms | speed-up | thesis RAW ms | thesis VOD ms (plain / FastLZ) | thesis speed-up |");
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for r in &rows {
        let t = thesis(&r.name);
        println!(
            "| {} | {:.1} | {:.1} | {:.1}x | {} | {} | {} |",
            r.name,
            r.load_raw_ms,
            r.load_vod_ms,
            r.load_raw_ms / r.load_vod_ms,
            t.as_ref().map_or("-".into(), |t| t.load_raw_ms.to_string()),
            t.as_ref().map_or("-".into(), |t| format!(
                "{} / {}",
                t.load_vod_ms, t.load_vod_compressed_ms
            )),
            t.as_ref().map_or("-".into(), |t| format!(
                "{:.1}x",
                t.load_raw_ms as f64 / t.load_vod_compressed_ms as f64
            )),
        );
    }

    println!("\n### Import throughput (RAW in page cache -> VOD 2 zstd-{DEFAULT_ZSTD_LEVEL}, {} threads)\n", rayon::current_num_threads());
    println!("| data set | RAW MB | import s | MB/s of RAW |");
    println!("|---|---:|---:|---:|");
    for r in &rows {
        let mb = r.raw_bytes as f64 / 1e6;
        println!(
            "| {} | {:.1} | {:.3} | {:.0} |",
            r.name,
            mb,
            r.import_secs,
            mb / r.import_secs
        );
    }

    println!("\n### Open time (header, slots, head commit, index directory; no brick data)\n");
    println!("| file | dims | file MB | open median us | open p99 us | `isovox get` whole process median ms |");
    println!("|---|---|---:|---:|---:|---:|");
    let mut opens = vec![
        (
            "Large Ellipsoid",
            a.dir.join("large-ellipsoid.2.vod"),
            large,
        ),
        ("Large World", a.dir.join("large-world.2.vod"), large),
    ];
    if a.large > 0 {
        let dims = [a.large; 3];
        let path = a.dir.join(format!("world-{}.vod", a.large));
        eprintln!("bench store: generating the {0}^3 world", a.large);
        let layout = VolumeLayout::new(dims, b, VoxelType::U8)?;
        build_vod2(
            &path,
            &layout,
            [1.0; 3],
            &WorldSource::new(layout.clone(), 1),
            &BuildOptions::default(),
        )?;
        opens.push(("Huge World", path, dims));
    }
    for (name, path, dims) in &opens {
        let (med, p99) = open_times(path, 300)?;
        let get = get_process_ms(path, 30)?;
        println!(
            "| {name} | {}^3 | {:.1} | {med:.1} | {p99:.1} | {get:.2} |",
            dims[0],
            std::fs::metadata(path)?.len() as f64 / 1e6
        );
    }
    Ok(())
}
