//! `isovox-bench mesh`: marching-cubes throughput next to VTK's Flying Edges and scikit-image,
//! the thesis's Tables 6-8 (speed-up by threads, by level, triangles per level, adaptive LOD),
//! and what crack-free stitching costs: tiles with their moves against without, the transition
//! strips a view needs, the whole view (meshing time, triangles, bytes), and the adaptive LOD's
//! savings once stitched.

use super::median;
use anyhow::Context;
use clap::Args;
use isovox_proto::mesh::{encode_compact, encode_tile, Mesh as ProtoMesh, TileMesh};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::generate::{EllipsoidSource, WorldSource};
use isovox_server::mesh::check::{crossing_triangles, open_edges};
use isovox_server::mesh::level::{
    adaptive_tiles, balanced_tiles, each_in_parallel, level_tiles, mesh_stitchable_parts,
    mesh_stitched, mesh_strips, mesh_tile_parts, mesh_tiles, mesh_tiles_with_moves, weld,
};
use isovox_server::mesh::mc::{Kernel, Mesh};
use isovox_server::mesh::tile::{
    default_iso, mesh_strip_world, mesh_tile, mesh_tile_with_moves, TileScratch,
};
use isovox_server::progress::Silent;
use isovox_server::store::decoded::DecodedBricks;
use isovox_server::store::raw::RawInput;
use isovox_server::store::{
    build_vod2, BrickSource, BuildOptions, DenseGrid, Snapshot, StoreError, Vod2,
};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct MeshBenchArgs {
    /// Working directory.
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// A real scan as RAW (scripts/bench-store.sh fetches the MNI152 T1 template).
    #[arg(long)]
    pub mri: Option<PathBuf>,
    #[arg(long, value_delimiter = ',', default_value = "197,233,189")]
    pub mri_dims: Vec<u32>,
    /// Voxel type of the --mri RAW (u8 or u16).
    #[arg(long, default_value = "u8")]
    pub mri_type: VoxelType,
    /// Run the peers (python3 scripts/bench_mesh_peers.py: VTK and scikit-image must be
    /// installed; scripts/bench-mesh.sh installs them).
    #[arg(long)]
    pub peers: bool,
    /// Brick (tile) edge.
    #[arg(long, default_value_t = 32)]
    pub brick: u32,
    /// Only the transition-data comparison (for measuring a change to the strips).
    #[arg(long)]
    pub transitions_only: bool,
    /// Alternating runs of each side in the transition-data comparison.
    #[arg(long, default_value_t = 5)]
    pub transition_runs: usize,
    /// Print a digest of every tile with its moves and of every transition strip at every level
    /// (their content, and their compact bytes) instead of timing: equal digests before and
    /// after a change to the meshing code show that it changed no tile and no strip.
    #[arg(long)]
    pub digest: bool,
    /// Only the marching-cubes table (the kernels and the peers), not the levels, the
    /// transition data and the adaptive LOD.
    #[arg(long)]
    pub kernels_only: bool,
}

/// A benchmark input: name, RAW path (for the peers), the volume, its dims and voxel type.
type DataSet = (String, PathBuf, Arc<Snapshot>, [u32; 3], VoxelType);

/// Runs of each kernel (and thread count) in the marching-cubes table; the peers script runs
/// each peer three times.
const KERNEL_RUNS: usize = 5;

/// Memory for decoded bricks during one pass, as `mesh_tile_parts` gives it.
const BRICK_CACHE_BYTES: usize = 256 << 20;

struct Run {
    seconds: f64,
    triangles: usize,
}

/// Every tile of `tiles` meshed with `kernel` on the current thread pool exactly as
/// `mesh_tile_parts` does it (one scratch per thread, one cache of decoded bricks per pass,
/// one mesh per tile, all kept), with the kernel chosen.
fn mesh_pass(
    snap: &Snapshot,
    tiles: &[BrickKey],
    iso: f32,
    kernel: Kernel,
) -> anyhow::Result<Vec<Mesh>> {
    mesh_each(tiles, kernel, |key, mesh: &mut Mesh, scratch| {
        mesh_tile(snap, key, iso, mesh, scratch)
    })
}

/// Each of `tiles` meshed into a fresh `T` by `mesh`, in parallel on the current rayon pool,
/// marching with `kernel`: one scratch per thread, all sharing one cache of decoded bricks (as
/// `mesh_tile_parts` gives them).
fn mesh_each<I: Copy + Sync, T: Default + Send, S>(
    tiles: &[I],
    kernel: Kernel,
    mesh: impl Fn(I, &mut T, &mut TileScratch) -> Result<S, StoreError> + Sync,
) -> anyhow::Result<Vec<T>> {
    let bricks = Arc::new(DecodedBricks::new(BRICK_CACHE_BYTES));
    let parts = each_in_parallel(
        tiles,
        || TileScratch::with_bricks(bricks.clone()).with_kernel(kernel),
        |scratch, key| {
            let mut out = T::default();
            mesh(key, &mut out, scratch).map(|_| out)
        },
    )?;
    Ok(parts)
}

/// The tiles of `level` meshed with each of `kernels` on `threads` threads: one warm-up pass of
/// each (page cache, allocator), then `runs` rounds in which they take turns, so that a machine
/// whose load changes slows all alike; each kernel's median, in the order of `kernels`.
fn kernels_in_turn(
    snap: &Snapshot,
    level: u8,
    threads: usize,
    kernels: &[Kernel],
    runs: usize,
) -> anyhow::Result<Vec<Run>> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let tiles = level_tiles(snap, level);
    let iso = default_iso(snap.layout().voxel_type());
    let mut times = vec![Vec::new(); kernels.len()];
    let mut triangles = vec![0; kernels.len()];
    for &kernel in kernels {
        pool.install(|| mesh_pass(snap, &tiles, iso, kernel))?;
    }
    for _ in 0..runs {
        for (k, &kernel) in kernels.iter().enumerate() {
            let start = Instant::now();
            let parts = pool.install(|| mesh_pass(snap, &tiles, iso, kernel))?;
            times[k].push(start.elapsed().as_secs_f64());
            triangles[k] = parts.iter().map(Mesh::triangles).sum();
        }
    }
    if triangles.iter().any(|&t| t != triangles[0]) {
        anyhow::bail!("the kernels made different meshes: {triangles:?} triangles");
    }
    Ok(times
        .into_iter()
        .zip(triangles)
        .map(|(t, triangles)| Run {
            seconds: median(t),
            triangles,
        })
        .collect())
}

/// Two sides timed in alternating runs: medians, in seconds.
struct Alternating {
    /// With the transition data.
    with: f64,
    /// Without.
    without: f64,
    /// What the transition data adds: the median of each pair's difference.
    added: f64,
}

/// `without` and `with` on one thread: one warm-up of each, then they alternate `runs` times so
/// that a machine whose load changes slows both alike. Returns the medians and the last
/// result of `with`.
fn alternate<T: Send>(
    runs: usize,
    without: impl Fn() -> anyhow::Result<()> + Sync,
    with: impl Fn() -> anyhow::Result<T> + Sync,
) -> anyhow::Result<(Alternating, T)> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    pool.install(&without)?;
    let mut last = pool.install(&with)?;
    let (mut w, mut wo, mut added) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        let start = Instant::now();
        pool.install(&without)?;
        let plain = start.elapsed().as_secs_f64();
        let start = Instant::now();
        last = pool.install(&with)?;
        let stitchable = start.elapsed().as_secs_f64();
        wo.push(plain);
        w.push(stitchable);
        added.push(stitchable - plain);
    }
    let times = Alternating {
        with: median(w),
        without: median(wo),
        added: median(added),
    };
    Ok((times, last))
}

/// Every face of every tile of `tiles` that can touch a coarser tile.
fn all_faces(snap: &Snapshot, tiles: &[BrickKey]) -> Vec<(BrickKey, usize)> {
    let layout = snap.layout();
    tiles
        .iter()
        .flat_map(|&k| (0..6).map(move |f| (k, f)))
        .filter(|&(k, f)| isovox_proto::tile::has_strip(layout, k, f))
        .collect()
}

/// The digests of one level's tiles ([`tile_digests`]).
struct LevelDigests {
    level: u8,
    tiles: usize,
    content: u64,
    order_free: u64,
    bytes: u64,
    strips: u64,
}

/// Digests of every tile of every level of `snap` meshed with its moves: of its content
/// (regular mesh and moves: independent of the encoding), of the same content free of order
/// ([`order_free_digest`]) and of its compact bytes; and of every strip of every face that can
/// touch a coarser tile (order-free, with its face).
fn tile_digests(snap: &Snapshot, kernel: Kernel) -> anyhow::Result<Vec<LevelDigests>> {
    use std::hash::{DefaultHasher, Hash, Hasher};
    let iso = default_iso(snap.layout().voxel_type());
    let mut out = Vec::new();
    for level in 0..snap.layout().levels() {
        let tiles = level_tiles(snap, level);
        let parts = mesh_each(&tiles, kernel, |key, tile: &mut TileMesh, scratch| {
            mesh_tile_with_moves(snap, key, iso, tile, scratch)
        })?;
        let (mut content, mut bytes) = (DefaultHasher::new(), DefaultHasher::new());
        let mut order_free = DefaultHasher::new();
        for tile in &parts {
            order_free_digest(tile).hash(&mut order_free);
            let m = &tile.mesh;
            let bits = |v: &[[f32; 3]]| v.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>();
            bits(&m.positions).hash(&mut content);
            bits(&m.normals).hash(&mut content);
            m.indices.hash(&mut content);
            for mv in &tile.moves {
                (mv.vertex, mv.face, mv.distance.to_bits()).hash(&mut content);
            }
            encode_tile(tile).hash(&mut bytes);
        }
        let faces = all_faces(snap, &tiles);
        let strips = mesh_each(
            &faces,
            kernel,
            |(key, face), strip: &mut ProtoMesh, scratch| {
                mesh_strip_world(snap, key, face, iso, strip, scratch)
            },
        )?;
        let mut strip_digest = DefaultHasher::new();
        for ((_, face), strip) in faces.iter().zip(&strips) {
            face.hash(&mut strip_digest);
            let tile = TileMesh {
                mesh: strip.clone(),
                moves: Vec::new(),
            };
            order_free_digest(&tile).hash(&mut strip_digest);
        }
        out.push(LevelDigests {
            level,
            tiles: tiles.len(),
            content: content.finish(),
            order_free: order_free.finish(),
            bytes: bytes.finish(),
            strips: strip_digest.finish(),
        });
    }
    Ok(out)
}

/// A digest of a tile's content that does not depend on the order of its vertices, triangles
/// or moves: every index is replaced by its vertex (position and normal bits), every triangle
/// is rotated to start at its least vertex (its winding kept) and the lists are sorted. Two
/// meshing kernels that number vertices differently give equal digests exactly when they make
/// the same surface and moves.
fn order_free_digest(tile: &TileMesh) -> u64 {
    use std::hash::{DefaultHasher, Hash, Hasher};
    type Vertex = [u32; 6];
    let m = &tile.mesh;
    let vertex = |(p, n): (&[f32; 3], &[f32; 3])| -> Vertex {
        let [a, b, c] = p.map(f32::to_bits);
        let [d, e, f] = n.map(f32::to_bits);
        [a, b, c, d, e, f]
    };
    let vertices: Vec<Vertex> = m.positions.iter().zip(&m.normals).map(vertex).collect();
    let mut triangles: Vec<[Vertex; 3]> = m
        .indices
        .chunks_exact(3)
        .map(|tri| {
            let mut v = [0, 1, 2].map(|k| vertices[tri[k] as usize]);
            let least = (0..3).min_by_key(|&k| v[k]).unwrap_or(0);
            v.rotate_left(least);
            v
        })
        .collect();
    triangles.sort_unstable();
    let mut moves: Vec<(Vertex, u8, u32)> = tile
        .moves
        .iter()
        .map(|mv| (vertices[mv.vertex as usize], mv.face, mv.distance.to_bits()))
        .collect();
    moves.sort_unstable();
    let mut hasher = DefaultHasher::new();
    triangles.hash(&mut hasher);
    moves.hash(&mut hasher);
    hasher.finish()
}

fn peers(raw: &Path, dims: [u32; 3], t: VoxelType) -> anyhow::Result<serde_json::Value> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/bench_mesh_peers.py");
    let iso = default_iso(t);
    let out = Command::new("python3")
        .arg(&script)
        .arg(raw)
        .args(dims.map(|d| d.to_string()))
        .arg(t.name())
        .arg(iso.to_string())
        .output()
        .context("cannot run python3 scripts/bench_mesh_peers.py")?;
    if !out.status.success() {
        anyhow::bail!(
            "the peers script failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(serde_json::from_slice(&out.stdout)?)
}

pub fn run(a: MeshBenchArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&a.dir)?;
    let mut sets: Vec<DataSet> = Vec::new();
    let mut keep = Vec::new();
    for (name, world) in [("Large Ellipsoid", false), ("Large World", true)] {
        let layout = VolumeLayout::new([512; 3], a.brick, VoxelType::U8)?;
        let source: Box<dyn BrickSource> = if world {
            Box::new(WorldSource::new(layout.clone(), 1))
        } else {
            Box::new(EllipsoidSource::new(layout.clone()))
        };
        let file = a.dir.join(format!(
            "mesh-{}.vod",
            name.to_lowercase().replace(' ', "-")
        ));
        build_vod2(
            &file,
            &layout,
            [1.0; 3],
            source.as_ref(),
            &BuildOptions::default(),
        )?;
        let vod = Vod2::open(&file)?;
        let raw = file.with_extension("raw");
        if a.peers {
            super::write_level0_raw(&vod, &raw)?;
        }
        sets.push((
            name.to_string(),
            raw,
            vod.head(),
            layout.dims(),
            VoxelType::U8,
        ));
        keep.push(vod);
    }
    if let Some(mri) = &a.mri {
        let dims = [a.mri_dims[0], a.mri_dims[1], a.mri_dims[2]];
        let t = a.mri_type;
        let input = RawInput::open(mri, false, Some(dims), Some(t))?;
        let layout = VolumeLayout::new(dims, a.brick, t)?;
        let file = a.dir.join("mesh-mri.vod");
        build_vod2(
            &file,
            &layout,
            [1.0; 3],
            &DenseGrid::new(dims, t, a.brick, input.voxels()),
            &BuildOptions::default(),
        )?;
        let vod = Vod2::open(&file)?;
        sets.push(("MRI (MNI152 T1)".into(), mri.clone(), vod.head(), dims, t));
        keep.push(vod);
    }

    if a.digest {
        println!("| data set | kernel | level | tiles | content digest | order-free digest | bytes digest | strips digest |");
        println!("|---|---|---:|---:|---|---|---|---|");
        for (name, _, snap, _, _) in &sets {
            for kernel in [Kernel::Rows, Kernel::Reference] {
                for d in tile_digests(snap, kernel)? {
                    println!(
                        "| {name} | {kernel:?} | {} | {} | {:016x} | {:016x} | {:016x} | {:016x} |",
                        d.level, d.tiles, d.content, d.order_free, d.bytes, d.strips
                    );
                }
            }
        }
        return Ok(());
    }
    if a.transitions_only {
        return transition_table(&sets, a.transition_runs);
    }

    println!("### Marching cubes, level 0, iso = S - 0.5 (Isovox: every tile's mesh, tiles of {0}^3, including reading and decoding the bricks, the current kernel and the previous one taking turns, median of {KERNEL_RUNS} each; the peers: one mesh from an array in memory, median of 3)\n", a.brick);
    println!("| data set | voxels | triangles | Isovox 1 thread | previous kernel 1 thread | Isovox 2 threads | previous 2 threads | 2-thread speed-up (previous) | VTK FlyingEdges3D 1 thread | VTK 2 threads | scikit-image | Isovox / VTK, 1 thread | previous / VTK, 1 thread | Isovox / VTK, 2 threads | Isovox / previous, 1 thread |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut goals = Vec::new();
    for (name, raw, snap, dims, t) in &sets {
        eprintln!("bench mesh: {name}");
        let voxels = dims.iter().map(|&d| d as f64).product::<f64>();
        let kernels = [Kernel::Rows, Kernel::Reference];
        let one = kernels_in_turn(snap, 0, 1, &kernels, KERNEL_RUNS)?;
        let two = kernels_in_turn(snap, 0, 2, &kernels, KERNEL_RUNS)?;
        let mv = |s: f64| voxels / s / 1e6;
        let (mut vtk1, mut vtk2, mut sk) = ("-".to_string(), "-".to_string(), "-".to_string());
        let (mut r1, mut r1_previous, mut r2) = ("-".to_string(), "-".to_string(), "-".to_string());
        let mut vtk_ratio = None;
        if a.peers {
            let p = peers(raw, *dims, *t)?;
            let get = |k: &str| {
                p.get(k)
                    .and_then(|v| v.get("seconds"))
                    .and_then(serde_json::Value::as_f64)
            };
            let tris = |k: &str| {
                p.get(k)
                    .and_then(|v| v.get("triangles"))
                    .and_then(serde_json::Value::as_u64)
                    .unwrap_or(0)
            };
            if let (Some(v1), Some(v2)) = (get("vtk_1"), get("vtk_2")) {
                vtk1 = format!("{:.0} Mvoxel/s ({} tri)", mv(v1), tris("vtk_1"));
                vtk2 = format!("{:.0} Mvoxel/s", mv(v2));
                r1 = format!("**{:.2}x**", v1 / one[0].seconds);
                r1_previous = format!("{:.2}x", v1 / one[1].seconds);
                r2 = format!("{:.2}x", v2 / two[0].seconds);
                vtk_ratio = Some(v1 / one[0].seconds);
            }
            if let Some(s) = get("skimage") {
                sk = format!("{:.0} Mvoxel/s ({} tri)", mv(s), tris("skimage"));
            }
        }
        let speed_up = one[0].seconds / two[0].seconds;
        println!(
            "| {name} | {} | {} | {:.0} Mvoxel/s | {:.0} Mvoxel/s | {:.0} Mvoxel/s | {:.0} Mvoxel/s | {speed_up:.2}x ({:.2}x) | {vtk1} | {vtk2} | {sk} | {r1} | {r1_previous} | {r2} | {:.2}x |",
            voxels as u64,
            one[0].triangles,
            mv(one[0].seconds),
            mv(one[1].seconds),
            mv(two[0].seconds),
            mv(two[1].seconds),
            one[1].seconds / two[1].seconds,
            one[1].seconds / one[0].seconds,
        );
        // The goals of the faster kernel: 2x VTK on one thread (1.5x on the scan), and two
        // threads 1.8x one.
        let want = if name.starts_with("MRI") { 1.5 } else { 2.0 };
        let verdict = |ok: bool| if ok { "met" } else { "not met" };
        goals.push(format!(
            "- {name}: Isovox / VTK on one thread {} (goal {want:.1}x: {}); two threads / one {speed_up:.2}x (goal 1.8x: {})",
            vtk_ratio.map_or("-".into(), |r| format!("{r:.2}x")),
            vtk_ratio.map_or("no peer", |r| verdict(r >= want)),
            verdict(speed_up >= 1.8),
        ));
    }
    println!("\n{}", goals.join("\n"));
    if a.kernels_only {
        return Ok(());
    }

    println!("\n### By level (thesis Tables 7 and 8), 2 threads\n");
    println!("| data set | level | voxels | tiles | triangles | ms | speed-up vs level 0 |");
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for (name, _, snap, _, _) in &sets {
        let layout = snap.layout();
        let mut base = None;
        for level in 0..layout.levels().min(4) {
            let run = kernels_in_turn(snap, level, 2, &[Kernel::Rows], KERNEL_RUNS)?.remove(0);
            let base_s = *base.get_or_insert(run.seconds);
            let d = layout.level_dims(level);
            println!(
                "| {name} | {level} | {} | {} | {} | {:.1} | {:.1}x |",
                d.iter().map(|&v| v as u64).product::<u64>(),
                level_tiles(snap, level).len(),
                run.triangles,
                run.seconds * 1e3,
                base_s / run.seconds
            );
        }
    }

    transition_table(&sets, a.transition_runs)?;

    println!(
        "\n### Adaptive LOD (thesis Table 8): camera at a corner, level k within radius r_k\n"
    );
    println!(
        "| data set | radii (voxels) | tiles | triangles | level-0 triangles | fewer triangles |"
    );
    println!("|---|---|---:|---:|---:|---:|");
    let mut stitched_rows = Vec::new();
    for (name, _, snap, dims, _) in &sets {
        let max = *dims.iter().max().unwrap_or(&1) as f32;
        let radii = [max / 4.0, max / 2.0, max];
        let camera = [0.0, dims[1] as f32, 0.0];
        let tiles = adaptive_tiles(snap, camera, &radii);
        let iso = default_iso(snap.layout().voxel_type());
        let adaptive = mesh_tiles(snap, &tiles, iso, &Silent)?.triangles();
        let full = weld(&mesh_tiles(snap, &level_tiles(snap, 0), iso, &Silent)?);
        println!(
            "| {name} | {:.0}, {:.0}, {:.0} | {} | {adaptive} | {} | {:.0}% |",
            radii[0],
            radii[1],
            radii[2],
            tiles.len(),
            full.triangles(),
            100.0 * (1.0 - adaptive as f64 / full.triangles() as f64)
        );
        // The same view stitched: the selection balanced (neighbours one level apart at most),
        // each tile drawn with its face mask, welded.
        let balanced = balanced_tiles(snap, camera, &radii);
        let start = Instant::now();
        let stitched = weld(&mesh_stitched(snap, &balanced, iso, &Silent)?);
        let seconds = start.elapsed().as_secs_f64();
        let all = vec![true; stitched.triangles()];
        stitched_rows.push(format!(
            "| {name} | {} | {} | {} | {:.0}% | {} | {} | {:.0} |",
            balanced.len(),
            stitched.triangles(),
            full.triangles(),
            100.0 * (1.0 - stitched.triangles() as f64 / full.triangles() as f64),
            open_edges(&stitched),
            crossing_triangles(&stitched, &all),
            seconds * 1e3
        ));
    }
    println!("\nThe same views stitched across levels: the selection balanced so that neighbouring tiles differ by at most one level, each tile drawn with its face mask, welded; open edges (every edge in exactly two triangles, once each way) and pairs of crossing triangles counted over the whole mesh.\n");
    println!("| data set | tiles | triangles | level-0 triangles | fewer triangles | open edges | crossing pairs | ms (2 threads) |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for row in stitched_rows {
        println!("{row}");
    }
    Ok(())
}

/// The corner view of the adaptive-LOD figures: camera at (0, dims y, 0), level k within
/// radius max/4, max/2, max.
fn corner_view(dims: [u32; 3]) -> ([f32; 3], [f32; 3]) {
    let max = *dims.iter().max().unwrap_or(&1) as f32;
    ([0.0, dims[1] as f32, 0.0], [max / 4.0, max / 2.0, max])
}

/// `tiles` meshed plain (regular meshes alone), the baseline of the transition table.
fn plain_pass(snap: &Snapshot, tiles: &[BrickKey], iso: f32) -> anyhow::Result<()> {
    mesh_tile_parts(snap, tiles, iso, &Silent)?;
    Ok(())
}

/// What crack-free stitching costs: (a) every level-0 tile with its moves against plain, (b) the
/// strips alone, (c) a corner view's tiles with moves and the strips their masks need against
/// the same tiles plain, (d) bytes.
fn transition_table(sets: &[DataSet], runs: usize) -> anyhow::Result<()> {
    println!("\n### Transition data (crack-free LOD), 1 thread\n");
    println!("(a) Every level-0 tile meshed as served, its regular mesh and the moves (secondary positions) of its boundary vertices (docs/lod-meshes.md), against the regular mesh alone, in alternating runs (median of {runs} each; the moves' part is the median of each pair's difference). Bytes in the compact encoding (version 3 against version 1), over the tiles with a surface.\n");
    println!("| data set | plain: ms | with moves: ms | moves' part: ms | with / plain (goal < 1.15x) | tiles with a surface | regular triangles | moves | bytes plain | bytes with moves | bytes more |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut strip_rows = Vec::new();
    let mut view_rows = Vec::new();
    for (name, _, snap, dims, _) in sets {
        eprintln!("bench mesh: transitions, {name}");
        let tiles = level_tiles(snap, 0);
        let iso = default_iso(snap.layout().voxel_type());
        let (times, parts) = alternate(
            runs,
            || plain_pass(snap, &tiles, iso),
            || mesh_tiles_with_moves(snap, &tiles, iso, &Silent).map_err(Into::into),
        )?;
        let surfaced: Vec<&TileMesh> = parts.iter().filter(|t| !t.mesh.is_empty()).collect();
        let regular: usize = surfaced.iter().map(|t| t.mesh.triangles()).sum();
        let moves: usize = surfaced.iter().map(|t| t.moves.len()).sum();
        let bytes_without: usize = surfaced.iter().map(|t| encode_compact(&t.mesh).len()).sum();
        let bytes_with: usize = surfaced.iter().map(|t| encode_tile(t).len()).sum();
        println!(
            "| {name} | {:.1} | {:.1} | {:.1} | **{:.3}x** | {} | {regular} | {moves} | {bytes_without} | {bytes_with} | {:.1}% |",
            times.without * 1e3,
            times.with * 1e3,
            times.added * 1e3,
            times.with / times.without,
            surfaced.len(),
            100.0 * (bytes_with as f64 / bytes_without as f64 - 1.0)
        );
        // (b) Every strip of every level-0 face that can touch a coarser tile, one thread.
        let faces = all_faces(snap, &tiles);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
        pool.install(|| mesh_strips(snap, &faces, iso, &Silent))?;
        let mut seconds = Vec::new();
        let mut strips = Vec::new();
        for _ in 0..runs.max(1) {
            let start = Instant::now();
            strips = pool.install(|| mesh_strips(snap, &faces, iso, &Silent))?;
            seconds.push(start.elapsed().as_secs_f64());
        }
        let all_s = median(seconds);
        let drawn: Vec<&ProtoMesh> = strips.iter().filter(|s| !s.is_empty()).collect();
        let strip_triangles: usize = drawn.iter().map(|s| s.triangles()).sum();
        let strip_bytes: usize = drawn.iter().map(|s| encode_compact(s).len()).sum();
        // (c) The corner view: its balanced tiles with moves and the strips their masks need,
        // against the same tiles plain.
        let (camera, radii) = corner_view(*dims);
        let view = balanced_tiles(snap, camera, &radii);
        let (view_times, parts) = alternate(
            runs,
            || plain_pass(snap, &view, iso),
            || mesh_stitchable_parts(snap, &view, iso, &Silent).map_err(Into::into),
        )?;
        let view_tiles = &parts.tiles;
        let view_strips: Vec<&ProtoMesh> = parts.strips.iter().flatten().flatten().collect();
        let masked = parts.masks.iter().filter(|&&m| m != 0).count();
        let view_strip_bytes: usize = view_strips.iter().map(|s| encode_compact(s).len()).sum();
        let view_tile_bytes: usize = view_tiles.iter().map(|t| encode_tile(t).len()).sum();
        let view_plain_bytes: usize = view_tiles
            .iter()
            .map(|t| encode_compact(&t.mesh).len())
            .sum();
        strip_rows.push(format!(
            "| {name} | {} | {:.1} | {:.1} | {} | {strip_triangles} | {strip_bytes} | {:.0} |",
            faces.len(),
            all_s * 1e3,
            all_s * 1e6 / faces.len().max(1) as f64,
            drawn.len(),
            strip_bytes as f64 / drawn.len().max(1) as f64,
        ));
        view_rows.push(format!(
            "| {name} | {:.0}, {:.0}, {:.0} | {} | {masked} | {} | {} | {:.1} | {:.1} | **{:.3}x** | {view_plain_bytes} | {view_tile_bytes} | {view_strip_bytes} | {:.1}% |",
            radii[0],
            radii[1],
            radii[2],
            view.len(),
            parts.strip_count(),
            view_strips.iter().filter(|s| !s.is_empty()).count(),
            view_times.without * 1e3,
            view_times.with * 1e3,
            view_times.with / view_times.without,
            100.0 * ((view_tile_bytes + view_strip_bytes) as f64 / view_plain_bytes as f64 - 1.0),
        ));
    }
    println!("\n(b) The transition strips alone: every face of a level-0 tile that can touch a coarser tile, each strip meshed as served (the layer of the tile's cells along the face, the coarser level's plane, the strip), one thread, median of {runs}; bytes of the non-empty strips in the compact encoding (version 1).\n");
    println!("| data set | strips | ms (all) | us per strip | non-empty | strip triangles | strip bytes | bytes per non-empty strip |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for row in strip_rows {
        println!("{row}");
    }
    println!("\n(c) A view: the balanced selection for the camera at a corner (as in the adaptive-LOD figures), its tiles meshed with their moves plus the strips their face masks need (one cache of decoded bricks for both passes, as the server's requests share one), against the same tiles plain, one thread, alternating runs (median of {runs} each); bytes in the compact encoding: the tiles plain (version 1), with moves (version 3), the strips (version 1), and what moves and strips add.\n");
    println!("| data set | radii | tiles | tiles with a coarser face | strips needed | non-empty | plain: ms | with moves and strips: ms | ratio | bytes plain | bytes with moves | strip bytes | bytes more |");
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for row in view_rows {
        println!("{row}");
    }
    Ok(())
}
