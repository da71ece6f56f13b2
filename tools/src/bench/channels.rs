//! `isovox-bench channels`: the costs of attribute channels (`docs/channels.md`), each next to
//! a peer on the same data in the same run.
//!
//! 1. Mode downsampling of a segmentation, one level, one thread, against `tinybrain`'s
//!    `downsample_segmentation` (the field's fast mode pooling, PyPI) on the same array.
//! 2. Label storage: the bytes of a segmentation's level-0 bricks as a VOD 2 channel against
//!    Neuroglancer's `compressed_segmentation` encoding of the same chunks plus gzip (the
//!    `compressed-segmentation` package, PyPI), what a precomputed server stores and sends.
//! 3. Edits per second carving and building with materials into a world with a material
//!    channel, against the same edits into the same world without one (in process, durable
//!    commits, runs alternating).
//!
//! The Python peers run from `--python` (scripts/bench-channels.sh makes a venv with them).

use super::icvg::Rng;
use super::median;
use isovox_proto::channel::ChannelInfo;
use isovox_proto::icvg::EditRequest;
use isovox_proto::vod2::{FileHeader, NodeEntry};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::cancel::CancelToken;
use isovox_server::generate::{world_header, WorldMaterials, WorldSource};
use isovox_server::icvg::edit::{apply_edit, Edit};
use isovox_server::icvg::term::{NoVolumes, TermLimits};
use isovox_server::store::codec::Compression;
use isovox_server::store::pyramid::{downsample, Downsampling};
use isovox_server::store::{
    build_streams, build_vod2, BrickSource, BrickVoxels, BuildOptions, CheckpointPolicy, DenseGrid,
    StoredBrick, Vod2, Vod2Writer,
};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct ChannelsBenchArgs {
    /// Working directory.
    #[arg(long, default_value = "bench-out/channels")]
    pub dir: PathBuf,
    /// Edge of the cubic segmentation (parts 1 and 2).
    #[arg(long, default_value_t = 256)]
    pub size: u32,
    /// Brick edge of the channel, and chunk edge of the compressed_segmentation peer.
    #[arg(long, default_value_t = 64)]
    pub brick: u32,
    /// Edge of the cubic world of the edit runs (part 3).
    #[arg(long, default_value_t = 512)]
    pub world: u32,
    /// Edits per run (part 3; 0 skips it).
    #[arg(long, default_value_t = 100)]
    pub edits: usize,
    /// Runs of each side, alternating; the tables show medians.
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// A Python with numpy, tinybrain and compressed_segmentation.
    #[arg(long, default_value = "python3")]
    pub python: PathBuf,
    /// Only part 3, the edit runs (no Python peers needed): for profiling them.
    #[arg(long)]
    pub edits_only: bool,
    /// The segmentation's id type (parts 1 and 2): u16 (ids below 60,000), u32 (ids spread
    /// over 31 bits) or u64 (ids spread over 48 bits, as connectomics numbers its segments).
    #[arg(long, default_value = "u16")]
    pub label_type: VoxelType,
}

/// The id of cell hash `h` (24 bits) in a segmentation of `t`: never 0; in u32 and u64 one id
/// per hash, spread over 31 and 48 bits.
fn cell_id(h: u64, t: VoxelType) -> u64 {
    match t {
        VoxelType::U8 => 1 + h % 250,
        VoxelType::U16 => 1 + h % 60_000,
        VoxelType::U32 => 1 + (h << 7),
        VoxelType::U64 => 1 + (h << 24 | h),
    }
}

/// A synthetic segmentation: cells about 24 voxels across with wavy walls, one id each
/// ([`cell_id`]), a seventh of them background (0). Deterministic.
fn segmentation(n: u32, t: VoxelType) -> Vec<u64> {
    let n = n as usize;
    let mut out = vec![0u64; n * n * n];
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let (fx, fy, fz) = (x as f64, y as f64, z as f64);
                let wx = fx + 5.0 * (fy / 9.0).sin() + 3.0 * (fz / 13.0).cos();
                let wy = fy + 5.0 * (fz / 11.0).sin() + 3.0 * (fx / 7.0).cos();
                let wz = fz + 5.0 * (fx / 10.0).sin() + 3.0 * (fy / 12.0).cos();
                let cell = [wx, wy, wz].map(|c| (c / 24.0).floor() as i64);
                let h = (cell[0].wrapping_mul(73_856_093)
                    ^ cell[1].wrapping_mul(19_349_663)
                    ^ cell[2].wrapping_mul(83_492_791)) as u64;
                let h = h.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40;
                out[(z * n + y) * n + x] = if h.is_multiple_of(7) {
                    0
                } else {
                    cell_id(h, t)
                };
            }
        }
    }
    out
}

pub fn run_bench(a: ChannelsBenchArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&a.dir)?;
    if a.edits_only {
        return edits_per_second(&a);
    }
    let (n, b, t) = (a.size, a.brick, a.label_type);
    eprintln!("making a {n}^3 {t} segmentation");
    let labels = segmentation(n, t);
    let width = t.bytes();
    let bytes: Vec<u8> = labels
        .iter()
        .flat_map(|v| v.to_le_bytes()[..width].to_vec())
        .collect();
    drop(labels);
    let raw = a.dir.join(format!("labels.{t}"));
    std::fs::write(&raw, &bytes)?;
    // The array's NumPy type, as the peers read it.
    let np_type = format!("<u{width}");
    // compressed_segmentation takes uint32 or uint64.
    let cseg_type = if t == VoxelType::U64 {
        "uint64"
    } else {
        "uint32"
    };

    // 1. Mode downsampling, one level, one thread.
    let layout = VolumeLayout::new([n; 3], b, VoxelType::U8)?.with_voxel_type(t);
    let grid = DenseGrid::new([n; 3], t, b, &bytes);
    let g = layout.grid(0);
    let bricks: Vec<BrickVoxels> = (0..g[0] * g[1] * g[2])
        .map(|i| {
            let key = BrickKey {
                level: 0,
                x: i % g[0],
                y: i / g[0] % g[1],
                z: i / (g[0] * g[1]),
            };
            let mut out = vec![0u8; layout.brick_bytes()];
            grid.fill(key, &mut out);
            BrickVoxels::Data(out)
        })
        .collect();
    let at = |x: u32, y: u32, z: u32| -> Option<&BrickVoxels> {
        (x < g[0] && y < g[1] && z < g[2]).then(|| &bricks[((z * g[1] + y) * g[0] + x) as usize])
    };
    let parents = layout.grid(1);
    let mut ours = Vec::new();
    let mut level1 = Vec::new();
    for _ in 0..a.runs {
        let start = Instant::now();
        level1.clear();
        for pz in 0..parents[2] {
            for py in 0..parents[1] {
                for px in 0..parents[0] {
                    let kids: [Option<&BrickVoxels>; 8] = std::array::from_fn(|o| {
                        at(
                            2 * px + (o & 1) as u32,
                            2 * py + (o >> 1 & 1) as u32,
                            2 * pz + (o >> 2) as u32,
                        )
                    });
                    let mut out = vec![0u8; layout.brick_bytes()];
                    let how = Downsampling::Mode { sparse: false };
                    downsample(&kids, b, t, how, &mut out);
                    level1.push(out);
                }
            }
        }
        ours.push(start.elapsed().as_secs_f64());
    }
    let peer = python(
        &a.python,
        &format!(
            r#"
import numpy as np, time, tinybrain
a = np.fromfile({raw:?}, dtype={np_type:?}).reshape(({n},{n},{n})).transpose(2, 1, 0)
best = []
for _ in range({runs}):
    t = time.perf_counter()
    out = tinybrain.downsample_segmentation(a, factor=(2, 2, 2), num_mips=1, sparse=False)[0]
    best.append(time.perf_counter() - t)
best.sort()
print(best[len(best) // 2])
np.ascontiguousarray(out.transpose(2, 1, 0)).astype({np_type:?}).tofile({raw:?} + '.tinybrain')
"#,
            raw = raw.to_string_lossy(),
            runs = a.runs
        ),
    )?;
    let peer_s: f64 = peer.trim().parse()?;
    let ours_s = median(ours);
    // How often the two agree (tie rules differ: ours is documented, tinybrain's is its own).
    let theirs = std::fs::read(a.dir.join(format!("labels.{t}.tinybrain")))?;
    let h = (n / 2) as usize;
    let (mut same, mut total) = (0usize, 0usize);
    let hb = b as usize;
    for z in 0..h {
        for y in 0..h {
            for x in 0..h {
                let brick = &level1
                    [((z / hb * parents[1] as usize + y / hb) * parents[0] as usize) + x / hb];
                let i = ((z % hb * hb + y % hb) * hb + x % hb) * width;
                let j = ((z * h + y) * h + x) * width;
                same += usize::from(brick[i..i + width] == theirs[j..j + width]);
                total += 1;
            }
        }
    }
    println!("### Mode downsampling: a {n}^3 {t} segmentation to level 1, one thread (median of {} runs)\n", a.runs);
    println!("| | seconds | Mvoxels/s (input) |\n|---|---:|---:|");
    let mv = |s: f64| (n as f64).powi(3) / s / 1e6;
    println!("| isovox (brick {b}) | {ours_s:.3} | {:.0} |", mv(ours_s));
    println!(
        "| tinybrain {} | {peer_s:.3} | {:.0} |",
        version(&a.python, "tinybrain")?,
        mv(peer_s)
    );
    println!(
        "\nisovox / tinybrain time: **{:.2}x** (below 1: faster); the two agree on {:.2}% of the level's voxels (ties are broken differently).\n",
        ours_s / peer_s,
        100.0 * same as f64 / total as f64
    );

    // 2. Storage of level 0.
    let path = a.dir.join("labels.vod");
    let density_layout = VolumeLayout::new([n; 3], b, VoxelType::U8)?;
    let empty = vec![0u8; (n as usize).pow(3)];
    let density = DenseGrid::new([n; 3], VoxelType::U8, b, &empty);
    let header = FileHeader::with_channels(
        density_layout,
        [1.0; 3],
        vec![ChannelInfo {
            sparse: true,
            ..ChannelInfo::new("label", t)
        }],
    )?;
    build_streams(&path, header, &[&density, &grid], &BuildOptions::default())?;
    let ours_bytes = level0_bytes(&path, "label")?;
    let peer_bytes: u64 = python(
        &a.python,
        &format!(
            r#"
import numpy as np, gzip, compressed_segmentation as cseg
a = np.fromfile({raw:?}, dtype={np_type:?}).reshape(({n},{n},{n})).transpose(2, 1, 0).astype({cseg_type:?})
total = 0
for z in range(0, {n}, {b}):
    for y in range(0, {n}, {b}):
        for x in range(0, {n}, {b}):
            chunk = np.asfortranarray(a[x:x+{b}, y:y+{b}, z:z+{b}])
            total += len(gzip.compress(cseg.compress(chunk, block_size=(8, 8, 8), order='F'), 6))
print(total)
"#,
            raw = raw.to_string_lossy()
        ),
    )?
    .trim()
    .parse()?;
    println!("### Label storage: the same {n}^3 segmentation's level 0 in chunks of {b}^3\n");
    println!("| | bytes | bits per voxel |\n|---|---:|---:|");
    let bpv = |bytes: u64| bytes as f64 * 8.0 / (n as f64).powi(3);
    println!(
        "| isovox channel (zstd level {}, constant bricks free) | {ours_bytes} | {:.3} |",
        isovox_server::store::codec::CHANNEL_ZSTD_LEVEL,
        bpv(ours_bytes)
    );
    println!(
        "| compressed_segmentation {} (8^3 blocks, {cseg_type}) + gzip 6 | {peer_bytes} | {:.3} |",
        version(&a.python, "compressed_segmentation")?,
        bpv(peer_bytes)
    );
    println!(
        "\nisovox / peer size: **{:.2}x** (below 1: smaller).\n",
        ours_bytes as f64 / peer_bytes as f64
    );

    // 3. Edits per second with and without a material channel.
    if a.edits == 0 {
        return Ok(());
    }
    edits_per_second(&a)
}

/// Payload bytes of the level-0 bricks of `channel` (each distinct record once; constants are
/// free).
fn level0_bytes(path: &Path, channel: &str) -> anyhow::Result<u64> {
    let vod = Vod2::open(path)?;
    let head = vod.head();
    let view = head
        .channel(channel)
        .ok_or_else(|| anyhow::anyhow!("no channel {channel}"))?;
    let (start, count) = view.layout().level_range(0);
    let mut seen = std::collections::HashSet::new();
    let mut bytes = 0;
    for node in start..start + count {
        if let NodeEntry::Stored(offset) = view.entry_at(node)? {
            if seen.insert(offset) {
                if let StoredBrick::Record { header, .. } =
                    view.stored_entry(NodeEntry::Stored(offset))?
                {
                    bytes += u64::from(header.stored_len);
                }
            }
        }
    }
    Ok(bytes)
}

fn python(python: &Path, script: &str) -> anyhow::Result<String> {
    let out = Command::new(python).arg("-c").arg(script).output()?;
    if !out.status.success() {
        anyhow::bail!(
            "the Python peer failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8(out.stdout)?)
}

fn version(interpreter: &Path, module: &str) -> anyhow::Result<String> {
    let dist = module.replace('_', "-");
    Ok(python(
        interpreter,
        &format!("import importlib.metadata as m; print(m.version({dist:?}))"),
    )?
    .trim()
    .to_string())
}

/// Runs of `--edits` unions of marble towers and carves, half each, into a world with and
/// without a material channel, alternating; prints edits/s.
fn edits_per_second(a: &ChannelsBenchArgs) -> anyhow::Result<()> {
    let layout = VolumeLayout::new([a.world; 3], 32, VoxelType::U8)?;
    let world = WorldSource::new(layout.clone(), 7);
    let plain = a.dir.join(format!("world-{}.vod", a.world));
    let with = a.dir.join(format!("world-{}-materials.vod", a.world));
    if !plain.exists() {
        eprintln!("generating {}", plain.display());
        build_vod2(&plain, &layout, [1.0; 3], &world, &BuildOptions::default())?;
    }
    if !with.exists() {
        eprintln!("generating {}", with.display());
        let materials = WorldMaterials::new(world.clone());
        build_streams(
            &with,
            world_header(&layout)?,
            &[&world, &materials],
            &BuildOptions::default(),
        )?;
    }
    let mut rates: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
    for run in 0..a.runs {
        for (side, source) in [&plain, &with].into_iter().enumerate() {
            let copy = a.dir.join("edited.vod");
            std::fs::copy(source, &copy)?;
            let rate = edit_run(&copy, &world, a.edits, run as u64)?;
            eprintln!(
                "run {}: {} {rate:.1} edits/s",
                run + 1,
                ["density only", "with materials"][side]
            );
            rates[side].push(rate);
        }
    }
    let [plain_rate, with_rate] = [median(rates[0].clone()), median(rates[1].clone())];
    println!(
        "### Edits with a material channel: {} edits a run into a {}^3 world (brick 32), half unions of radius-8 marble spheres on the ground, half radius-8 carves; in process, durable commits (median of {} runs, alternating)\n",
        a.edits, a.world, a.runs
    );
    println!("| world | edits/s |\n|---|---:|");
    println!("| density only | {plain_rate:.1} |");
    println!("| density + material channel | {with_rate:.1} |");
    println!(
        "\nWith the channel: **{:.1}%** {} edits/s.",
        (1.0 - with_rate / plain_rate).abs() * 100.0,
        if with_rate < plain_rate {
            "fewer"
        } else {
            "more"
        }
    );
    Ok(())
}

fn edit_run(path: &Path, world: &WorldSource, edits: usize, seed: u64) -> anyhow::Result<f64> {
    let size = world.layout.dims()[0];
    let mut rng = Rng(0x5eed_0000_0000_0001 ^ seed);
    let mut writer = Vod2Writer::open_append(path, Compression::for_edits())?;
    let mut vod = Vod2::open(path)?;
    let mut snap = vod.head();
    let start = Instant::now();
    for i in 0..edits {
        let (x, z) = (16 + rng.below(size - 32), 16 + rng.below(size - 32));
        let y = world.height(x, z) as i64;
        let (op, material) = if i % 2 == 0 {
            ("union", r#", "material": 6"#)
        } else {
            ("difference", "")
        };
        let json = format!(
            r#"{{"op": "{op}", "term": {{"ellipsoid": {{"center": [{x}, {y}, {z}], "radii": [8, 8, 8]{material}}}}}}}"#
        );
        let req: EditRequest = serde_json::from_str(&json)?;
        let mut edit = Edit::for_volume(
            &req,
            snap.header(),
            &TermLimits::default(),
            &NoVolumes,
            None,
            &CancelToken::never(),
        )?;
        apply_edit(
            &mut writer,
            &snap,
            &mut edit,
            CheckpointPolicy::default(),
            &CancelToken::never(),
        )?;
        // The next version as the server sees it after a commit: the file advanced to the
        // writer's new head (the new index entries read), not opened again.
        let slot = writer
            .tip()
            .ok_or_else(|| anyhow::anyhow!("the edit left the writer without a version"))?;
        vod = vod.advance(slot)?;
        snap = vod.head();
    }
    Ok(edits as f64 / start.elapsed().as_secs_f64())
}
