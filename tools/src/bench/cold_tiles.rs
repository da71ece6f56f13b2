//! `isovox-bench cold-tiles`: random cold mesh tiles from many connections at once, the load
//! under which an unbounded server grew to gigabytes and hundreds of threads.
//!
//! Each run starts a fresh `isovox serve` (its own process: its memory is its own) on a
//! generated world and asks every mesh tile of every level at most once, in a random order, from
//! `--connections` clients at once, each on one keep-alive connection, one request at a time; a
//! client told 503 waits the `Retry-After` it was given and asks again. Reported per run: tiles
//! answered, 503s, p50 and p99 latency (of the answers, of every attempt, and of each tile with
//! its waits), the server's peak resident memory (`VmHWM`) and most threads (`Threads`, sampled
//! every 50 ms), what its caches held at the end, and the bound `docs/limits.md` states for its
//! configuration.

use super::percentile;
use super::process::{proc_status, ServeProcess};
use anyhow::Context;
use isovox_proto::{VolumeLayout, VoxelType};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

#[derive(Debug, clap::Args)]
pub struct ColdTilesBenchArgs {
    /// Working directory (the world is generated once).
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// Edge of the cubic world.
    #[arg(long, default_value_t = 1024)]
    pub size: u32,
    /// Brick (and mesh tile) edge.
    #[arg(long, default_value_t = 32)]
    pub brick: u32,
    /// Client connections of each run, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [64usize, 1000])]
    pub connections: Vec<usize>,
    /// Tiles answered per run (each a different one).
    #[arg(long, default_value_t = 10_000)]
    pub tiles: usize,
    /// The server's mesh cache, MiB (its default).
    #[arg(long, default_value_t = 256)]
    pub mesh_cache_mb: u64,
    /// The server's brick cache, MiB (its default).
    #[arg(long, default_value_t = 64)]
    pub brick_cache_mb: u64,
    /// The server's response memory, MiB (its default).
    #[arg(long, default_value_t = 256)]
    pub response_memory_mb: u64,
    /// The server's CPU queue (default: the server's own, eight per core).
    #[arg(long)]
    pub cpu_queue: Option<usize>,
    /// Another `isovox` build to measure (an older one, say), instead of the one beside this
    /// binary. It is configured through `ISOVOX_*` variables, which older builds ignore.
    #[arg(long)]
    pub isovox: Option<PathBuf>,
}

/// The allowance per CPU thread and per connection of `docs/limits.md`'s bound.
const PER_THREAD_MIB: u64 = 48;
const PER_CONNECTION_KIB: u64 = 64;

/// One run's figures.
struct Run {
    connections: usize,
    answered: usize,
    refused: u64,
    failed: u64,
    seconds: f64,
    /// Latencies of the 200s, of every attempt, and of each tile from its first attempt to its
    /// answer (Retry-After waits included), ms.
    answers_ms: Vec<f64>,
    attempts_ms: Vec<f64>,
    tiles_ms: Vec<f64>,
    start_kib: u64,
    peak_kib: u64,
    end_kib: u64,
    threads: u64,
    caches_mib: f64,
    bound_mib: u64,
}

pub fn run_bench(a: ColdTilesBenchArgs) -> anyhow::Result<()> {
    let data = a.dir.join(format!("cold-tiles-{}", a.size));
    std::fs::create_dir_all(&data)?;
    let layout = VolumeLayout::new([a.size; 3], a.brick, VoxelType::U8)?;
    super::generated_world(&data.join("world.vod"), &layout, 1)?;
    let exe = match &a.isovox {
        Some(exe) => exe.clone(),
        None => super::isovox_exe()?,
    };
    // A thousand connections need a thousand descriptors here too.
    if let Err(e) = isovox_server::http::connections::raise_fd_limit() {
        eprintln!("cannot raise the file-descriptor limit: {e}");
    }
    let tiles = Arc::new(super::shuffled_nodes(&layout));
    let mut runs = Vec::new();
    let mut limits = String::new();
    for (i, &connections) in a.connections.iter().enumerate() {
        // Each run its own tiles (the page cache stays warm; the server's caches start empty).
        let first = (i * a.tiles) % tiles.len();
        let (run, line) = run_once(&a, &exe, &data, &layout, &tiles, first, connections)?;
        limits = line;
        runs.push(run);
    }

    let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
    println!(
        "### Random cold mesh tiles of a {0}^3 world (brick {1}), {2} tiles per run, {cores} cores shared with the load\n",
        a.size, a.brick, a.tiles
    );
    println!(
        "{limits}; caches {} + {} MiB.\n",
        a.mesh_cache_mb, a.brick_cache_mb
    );
    println!("| connections | tiles | 503s | failed | tiles/s | p50 ms | p99 ms | p99 ms, 503s included | p99 ms per tile, waits included | RSS at start MiB | peak RSS (VmHWM) MiB | RSS after MiB | most threads | caches held MiB | bound MiB |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in runs {
        println!(
            "| {} | {} | {} | {} | {:.0} | {} | {} | {} | {} | {} | **{}** | {} | {} | {:.0} | {} |",
            r.connections,
            r.answered,
            r.refused,
            r.failed,
            r.answered as f64 / r.seconds,
            ms(&r.answers_ms, 0.5),
            ms(&r.answers_ms, 0.99),
            ms(&r.attempts_ms, 0.99),
            ms(&r.tiles_ms, 0.99),
            r.start_kib >> 10,
            r.peak_kib >> 10,
            r.end_kib >> 10,
            r.threads,
            r.caches_mib,
            r.bound_mib,
        );
    }
    println!(
        "\nBound: RSS at start + caches + response memory + {PER_THREAD_MIB} MiB per CPU thread ({cores}) + {PER_CONNECTION_KIB} KiB per connection."
    );
    Ok(())
}

/// One fresh server, `connections` clients, `a.tiles` tiles from `tiles[first..]`; the figures
/// and the server's `limits:` line.
fn run_once(
    a: &ColdTilesBenchArgs,
    exe: &std::path::Path,
    data: &std::path::Path,
    layout: &VolumeLayout,
    tiles: &Arc<Vec<u64>>,
    first: usize,
    connections: usize,
) -> anyhow::Result<(Run, String)> {
    let mut envs = vec![
        ("ISOVOX_MESH_CACHE_MB", a.mesh_cache_mb.to_string()),
        ("ISOVOX_BRICK_CACHE_MB", a.brick_cache_mb.to_string()),
        (
            "ISOVOX_RESPONSE_MEMORY_MB",
            a.response_memory_mb.to_string(),
        ),
        ("ISOVOX_LOG", "warn".to_string()),
    ];
    if let Some(q) = a.cpu_queue {
        envs.push(("ISOVOX_CPU_QUEUE", q.to_string()));
    }
    let server = ServeProcess::start(exe, data, &envs)?;
    let (base, pid) = (server.base.clone(), server.pid());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(300))
        .build()?;
    // One request first, so that the memory at start is that of a server ready to answer.
    runtime.block_on(async {
        client
            .get(format!("{base}/v1/volumes/world"))
            .send()
            .await?
            .error_for_status()
    })?;
    let start_kib = proc_status(pid, "VmRSS").context("cannot read the server's memory")?;

    let most_threads = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicBool::new(false));
    let sampler = {
        let (most_threads, done) = (most_threads.clone(), done.clone());
        std::thread::spawn(move || {
            while !done.load(Ordering::Acquire) {
                if let Some(t) = proc_status(pid, "Threads") {
                    most_threads.fetch_max(t, Ordering::Relaxed);
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        })
    };

    let next = Arc::new(AtomicUsize::new(0));
    let answered = Arc::new(AtomicUsize::new(0));
    let refused = Arc::new(AtomicU64::new(0));
    let failed = Arc::new(AtomicU64::new(0));
    let answers_ms = Arc::new(Mutex::new(Vec::new()));
    let attempts_ms = Arc::new(Mutex::new(Vec::new()));
    let tiles_ms = Arc::new(Mutex::new(Vec::new()));
    let bar = crate::progress::bar(&format!("{connections} connections"));
    bar.set_length(a.tiles as u64);
    let begun = Instant::now();
    runtime.block_on(async {
        let mut clients = tokio::task::JoinSet::new();
        for _ in 0..connections {
            let (client, base, layout, tiles) =
                (client.clone(), base.clone(), layout.clone(), tiles.clone());
            let (next, answered, refused, failed) = (
                next.clone(),
                answered.clone(),
                refused.clone(),
                failed.clone(),
            );
            let (answers_ms, attempts_ms, tiles_ms, bar) = (
                answers_ms.clone(),
                attempts_ms.clone(),
                tiles_ms.clone(),
                bar.clone(),
            );
            let total = a.tiles;
            clients.spawn(async move {
                while answered.load(Ordering::Relaxed) < total {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let node = tiles[(first + i) % tiles.len()];
                    let Ok(k) = layout.key_of(node) else { break };
                    let url = format!(
                        "{base}/v1/volumes/world/meshes/{}/{}/{}/{}",
                        k.level, k.x, k.y, k.z
                    );
                    // The same tile until it is answered.
                    let first_asked = Instant::now();
                    loop {
                        let asked = Instant::now();
                        let response = client.get(&url).send().await;
                        let (status, wait) = match response {
                            Ok(r) => {
                                let wait = r
                                    .headers()
                                    .get("retry-after")
                                    .and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
                                let status = r.status().as_u16();
                                let complete = r.bytes().await.is_ok();
                                (if complete { status } else { 0 }, wait)
                            }
                            Err(_) => (0, None),
                        };
                        let ms = asked.elapsed().as_secs_f64() * 1e3;
                        lock(&attempts_ms).push(ms);
                        match status {
                            200 => {
                                lock(&answers_ms).push(ms);
                                lock(&tiles_ms).push(first_asked.elapsed().as_secs_f64() * 1e3);
                                answered.fetch_add(1, Ordering::Relaxed);
                                bar.inc(1);
                                break;
                            }
                            503 => {
                                refused.fetch_add(1, Ordering::Relaxed);
                                let secs = wait.unwrap_or(1);
                                tokio::time::sleep(Duration::from_secs(secs)).await;
                            }
                            // A failure ends this client: the server may be gone.
                            _ => {
                                failed.fetch_add(1, Ordering::Relaxed);
                                return;
                            }
                        }
                    }
                }
            });
        }
        while clients.join_next().await.is_some() {}
    });
    let seconds = begun.elapsed().as_secs_f64();
    bar.finish_and_clear();
    done.store(true, Ordering::Release);
    let _ = sampler.join();
    let caches = runtime.block_on(async {
        let text = client
            .get(format!("{base}/metrics"))
            .send()
            .await?
            .text()
            .await?;
        let sample = |name: &str| -> f64 {
            text.lines()
                .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
                .unwrap_or(0.0)
        };
        anyhow::Ok(
            sample("isovox_mesh_cache_bytes")
                + sample("isovox_mesh_answers_kept_bytes")
                + sample("isovox_brick_cache_bytes"),
        )
    })?;
    let peak_kib = proc_status(pid, "VmHWM").context("cannot read the server's memory")?;
    let end_kib = proc_status(pid, "VmRSS").context("cannot read the server's memory")?;
    let threads = most_threads.load(Ordering::Relaxed);
    let limits = server
        .log_line("limits:")
        .unwrap_or_else(|| "(the server did not print its limits)".into());
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get()) as u64;
    let bound_mib = (start_kib >> 10)
        + a.mesh_cache_mb
        + a.brick_cache_mb
        + a.response_memory_mb
        + cores * PER_THREAD_MIB
        + ((connections as u64 * PER_CONNECTION_KIB) >> 10);
    drop(server);
    let take = |v: &Arc<Mutex<Vec<f64>>>| std::mem::take(&mut *lock(v));
    Ok((
        Run {
            connections,
            answered: answered.load(Ordering::Relaxed),
            refused: refused.load(Ordering::Relaxed),
            failed: failed.load(Ordering::Relaxed),
            seconds,
            answers_ms: take(&answers_ms),
            attempts_ms: take(&attempts_ms),
            tiles_ms: take(&tiles_ms),
            start_kib,
            peak_kib,
            end_kib,
            threads,
            caches_mib: caches / f64::from(1 << 20),
            bound_mib,
        },
        limits,
    ))
}

/// The `p` quantile of `v` in milliseconds, or a dash when there is none.
fn ms(v: &[f64], p: f64) -> String {
    if v.is_empty() {
        return "-".into();
    }
    format!("{:.1}", percentile(v.to_vec(), p))
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}
