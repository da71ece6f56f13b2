//! `isovox-bench memory`: the server's resident memory while a client walks every brick of a
//! large volume once, in random order.
//!
//! The server runs as a child process (this binary's `serve`), so its memory is its own.
//! Reported from `/proc/PID/status`: `RssAnon` (heap, caches, stacks: what the server itself
//! holds) and `RssFile` (mapped file pages: the page cache, which the kernel reclaims at will),
//! sampled every 200 ms.

use super::process::{proc_status, ServeProcess};
use anyhow::Context;
use isovox_proto::{VolumeLayout, VoxelType};
use std::path::PathBuf;
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

/// `RssAnon` and `RssFile` of a process, in KiB.
fn rss(pid: u32) -> Option<(u64, u64)> {
    Some((proc_status(pid, "RssAnon")?, proc_status(pid, "RssFile")?))
}

pub fn run_bench(a: MemoryBenchArgs) -> anyhow::Result<()> {
    let data = a.dir.join("memory");
    std::fs::create_dir_all(&data)?;
    let layout = VolumeLayout::new([a.size; 3], a.brick, VoxelType::U8)?;
    let file = data.join("world.vod");
    super::generated_world(&file, &layout, 3)?;
    let server = ServeProcess::start(&super::isovox_exe()?, &data, &[])?;
    let (base, pid) = (server.base.clone(), server.pid());
    let (anon_start, file_start) = rss(pid).context("cannot read the server's memory")?;

    // Every brick of every level once, in a random order.
    let nodes = Arc::new(super::shuffled_nodes(&layout));
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
