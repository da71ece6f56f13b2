//! `isovox-bench memory`: the server's resident memory while a client walks every brick of a
//! large volume once, in random order.
//!
//! The server runs as a child process (this binary's `serve`), so its memory is its own.
//! Reported from `/proc/PID/status`: `RssAnon` (heap, caches, stacks: what the server itself
//! holds) and `RssFile` (mapped file pages: the page cache, which the kernel reclaims at will),
//! sampled every 200 ms.

use anyhow::Context;
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::store::{build_vod2, BuildOptions};
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Debug, clap::Args)]
pub struct MemoryBenchArgs {
    /// Working directory (the volume is generated once).
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// Edge of the cubic world.
    #[arg(long, default_value_t = 2048)]
    pub size: u32,
    #[arg(long, default_value_t = 16)]
    pub brick: u32,
    /// Concurrent requests.
    #[arg(long, default_value_t = 32)]
    pub concurrency: usize,
}

/// The server child, killed on drop.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `RssAnon` and `RssFile` of a process, in KiB.
fn rss(pid: u32) -> Option<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<u64>().ok())
    };
    Some((field("RssAnon:")?, field("RssFile:")?))
}

pub fn run_bench(a: MemoryBenchArgs) -> anyhow::Result<()> {
    let data = a.dir.join("memory");
    std::fs::create_dir_all(&data)?;
    let layout = VolumeLayout::new([a.size; 3], a.brick, VoxelType::U8)?;
    let file = data.join("world.vod");
    if !file.exists() {
        eprintln!("generating {} (once)", file.display());
        build_vod2(
            &file,
            &layout,
            [1.0; 3],
            &WorldSource::new(layout.clone(), 3),
            &BuildOptions::default(),
        )?;
    }
    let mut child = Command::new(super::isovox_exe()?)
        .args(["serve", "--addr", "127.0.0.1:0", "--data"])
        .arg(&data)
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .context("cannot start the server")?;
    let stderr = child.stderr.take().context("no stderr")?;
    let server = Server(child);
    let pid = server.0.id();
    let mut lines = BufReader::new(stderr).lines();
    let base = loop {
        let line = lines
            .next()
            .context("the server exited before listening")??;
        if let Some(at) = line.find("http://") {
            let rest = &line[at..];
            break rest.split("/v1").next().unwrap_or(rest).trim().to_string();
        }
    };
    // Keep draining the server's log.
    std::thread::spawn(move || for _ in lines {});
    let (anon_start, file_start) = rss(pid).context("cannot read the server's memory")?;

    // Every brick of every level once, in a random order (Fisher-Yates).
    let mut nodes: Vec<u64> = (0..layout.node_count()).collect();
    let mut rng = super::icvg::Rng(0x2545_f491_4f6c_dd1d);
    for i in (1..nodes.len()).rev() {
        nodes.swap(i, (rng.next() % (i as u64 + 1)) as usize);
    }
    let nodes = Arc::new(nodes);
    let next = Arc::new(AtomicUsize::new(0));
    let errors = Arc::new(AtomicU64::new(0));
    let bytes = Arc::new(AtomicU64::new(0));
    let peak = Arc::new(AtomicU64::new(anon_start));
    let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let sampler = {
        let (peak, done) = (peak.clone(), done.clone());
        std::thread::spawn(move || {
            while !done.load(Ordering::Acquire) {
                if let Some((anon, _)) = rss(pid) {
                    peak.fetch_max(anon, Ordering::Relaxed);
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        })
    };
    let bar = crate::progress::bar("walking");
    bar.set_length(nodes.len() as u64);
    let start = Instant::now();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let client = reqwest::Client::new();
        let mut tasks = Vec::new();
        for t in 0..a.concurrency {
            let (client, nodes, next, errors, bytes, layout, base, bar) = (
                client.clone(),
                nodes.clone(),
                next.clone(),
                errors.clone(),
                bytes.clone(),
                layout.clone(),
                base.clone(),
                bar.clone(),
            );
            tasks.push(tokio::spawn(async move {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&node) = nodes.get(i) else { break };
                    let Ok(k) = layout.key_of(node) else { break };
                    let url = format!(
                        "{base}/v1/volumes/world/bricks/{}/{}/{}/{}",
                        k.level, k.x, k.y, k.z
                    );
                    // Every representation: raw voxels, lz4 blocks, the stored zstd frames.
                    let request = match (i + t) % 3 {
                        0 => client.get(&url),
                        1 => client.get(&url).header("accept", "application/x-lz4"),
                        _ => client.get(&url).header("accept-encoding", "zstd"),
                    };
                    match request.send().await {
                        Ok(r) if r.status().is_success() => match r.bytes().await {
                            Ok(b) => {
                                bytes.fetch_add(b.len() as u64, Ordering::Relaxed);
                            }
                            Err(_) => {
                                errors.fetch_add(1, Ordering::Relaxed);
                            }
                        },
                        _ => {
                            errors.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    if i % 1024 == 0 {
                        bar.set_position(i as u64);
                    }
                }
            }));
        }
        for t in tasks {
            let _ = t.await;
        }
    });
    bar.finish_and_clear();
    let elapsed = start.elapsed();
    done.store(true, Ordering::Release);
    let _ = sampler.join();
    let (anon_end, file_end) = rss(pid).context("cannot read the server's memory")?;
    peak.fetch_max(anon_end, Ordering::Relaxed);
    drop(server);
    let file_mb = std::fs::metadata(&file)?.len() as f64 / 1048576.0;
    println!(
        "### Memory: a full random walk over every brick of a {0}^3 world (brick {1}, {2} bricks, file {file_mb:.1} MB), {3} concurrent requests, raw / lz4 / zstd in turn\n",
        a.size,
        a.brick,
        nodes.len(),
        a.concurrency
    );
    println!("| requests | seconds | requests/s | MB received | errors | RssAnon start MB | RssAnon peak MB | RssAnon end MB | RssFile start / end MB |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    println!(
        "| {} | {:.1} | {:.0} | {:.0} | {} | {:.1} | **{:.1}** | {:.1} | {:.1} / {:.1} |",
        nodes.len(),
        elapsed.as_secs_f64(),
        nodes.len() as f64 / elapsed.as_secs_f64(),
        bytes.load(Ordering::Relaxed) as f64 / 1048576.0,
        errors.load(Ordering::Relaxed),
        anon_start as f64 / 1024.0,
        peak.load(Ordering::Relaxed) as f64 / 1024.0,
        anon_end as f64 / 1024.0,
        file_start as f64 / 1024.0,
        file_end as f64 / 1024.0,
    );
    println!("\nGoal: under 200 MB beyond the page cache (RssAnon).");
    Ok(())
}
