//! `isovox-bench edits`: shared editing over HTTP on a generated world.
//!
//! One server (in this process, on an ephemeral port) serves a copy of a world; `--editors`
//! clients carve small ellipsoids at random places on its terrain as fast as they are answered,
//! while `--subscribers` clients follow the change feed. Reported: edit throughput and latency,
//! the delay from each edit's acknowledgement (at its editor) to its arrival at every
//! subscriber, and brick-read throughput (wrk) with and without paced edits running.
//!
//! Everything shares this machine's cores: the clients' own work is in every figure.

use super::http::{wrk, wrk_script};
use super::icvg::Rng;
use super::{median, percentile};
use anyhow::Context;
use isovox_proto::api::EditResponse;
use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::auth::{random_secret, Scope, Tokens};
use isovox_server::http::{run, AppState, ServerConfig};
use isovox_server::store::{build_vod2, BuildOptions};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

#[derive(Debug, clap::Args)]
pub struct EditsBenchArgs {
    /// Working directory (the world is generated once and copied for every run).
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// Edge of the cubic world.
    #[arg(long, default_value_t = 1024)]
    pub size: u32,
    #[arg(long, default_value_t = 16)]
    pub brick: u32,
    /// Concurrent editors.
    #[arg(long, default_value_t = 8)]
    pub editors: usize,
    /// Change-feed subscribers.
    #[arg(long, default_value_t = 100)]
    pub subscribers: usize,
    /// Length of each phase.
    #[arg(long, default_value_t = 10)]
    pub seconds: u64,
    /// Radius of the carved ellipsoids.
    #[arg(long, default_value_t = 8)]
    pub radius: u32,
    /// Edits per second per editor while reads are measured.
    #[arg(long, default_value_t = 2.0)]
    pub paced_rate: f64,
    /// wrk connections for the read phases.
    #[arg(long, default_value_t = 64)]
    pub connections: u32,
}

/// What the editors saw: per acknowledged version, when its answer arrived and how long the
/// request took.
#[derive(Default)]
struct Acks {
    at: HashMap<u64, Instant>,
    latency_ms: Vec<f64>,
    errors: usize,
}

/// Arrival times of versions at one subscriber.
type Arrivals = Arc<Mutex<Vec<(u64, Instant)>>>;

pub fn run_bench(a: EditsBenchArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&a.dir)?;
    let layout = VolumeLayout::new([a.size; 3], a.brick, VoxelType::U8)?;
    let world = Arc::new(WorldSource::new(layout.clone(), 7));
    let source = a
        .dir
        .join(format!("edits-world-{}-b{}.vod", a.size, a.brick));
    if !source.exists() {
        eprintln!("generating {} (once)", source.display());
        build_vod2(
            &source,
            &layout,
            [1.0; 3],
            &*world,
            &BuildOptions::default(),
        )?;
    }
    let data = a.dir.join("edits");
    let _ = std::fs::remove_dir_all(&data);
    std::fs::create_dir_all(&data)?;
    std::fs::copy(&source, data.join("world.vod"))?;
    let secret = random_secret()?;
    let mut tokens = Tokens::default();
    tokens
        .add("bench", &secret, Scope::Write)
        .map_err(anyhow::Error::msg)?;
    let config = ServerConfig {
        tokens,
        edit_rate: 1e9,
        edit_queue: 4096,
        ..ServerConfig::default()
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let base = runtime.block_on(async {
        let catalog = Catalog::open_dir(&data)?;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        tokio::spawn(run(
            listener,
            AppState::with_config(catalog, config),
            std::future::pending(),
        ));
        anyhow::Ok(format!("http://{addr}"))
    })?;
    let client = reqwest::Client::builder()
        .pool_max_idle_per_host(64)
        .build()?;

    // Phase 1: editors flat out, subscribers listening.
    let arrivals: Vec<Arrivals> = (0..a.subscribers).map(|_| Arrivals::default()).collect();
    let (acks, elapsed) = runtime.block_on(async {
        let ready = Arc::new(AtomicUsize::new(0));
        for sink in &arrivals {
            tokio::spawn(subscribe(
                client.clone(),
                format!("{base}/v1/volumes/world/events"),
                sink.clone(),
                ready.clone(),
            ));
        }
        while ready.load(Ordering::Acquire) < a.subscribers {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let start = Instant::now();
        let acks = edit_for(&a, &client, &base, &secret, &world, None).await;
        let elapsed = start.elapsed();
        // Let the last events arrive.
        tokio::time::sleep(Duration::from_millis(500)).await;
        (acks, elapsed)
    });
    let edits = acks.latency_ms.len();
    let mut delays = Vec::new();
    let mut missing = 0usize;
    let mut early = 0usize;
    let mut out_of_order = 0usize;
    for sink in &arrivals {
        let got = sink.lock().map(|g| g.clone()).unwrap_or_default();
        if got.windows(2).any(|w| w[1].0 <= w[0].0) {
            out_of_order += 1;
        }
        let by_version: HashMap<u64, Instant> = got.into_iter().collect();
        for (v, acked) in &acks.at {
            match by_version.get(v) {
                // The event is sent right after the commit, before the editor's answer is
                // written: it often arrives first, which counts as no delay (and is reported).
                Some(arrived) => {
                    early += usize::from(arrived < acked);
                    delays.push(arrived.saturating_duration_since(*acked).as_secs_f64() * 1e3)
                }
                None => missing += 1,
            }
        }
    }
    println!(
        "### Shared editing: {} editors carving radius-{} ellipsoids into a {}^3 world (brick {}), {} change-feed subscribers, {} s\n",
        a.editors, a.radius, a.size, a.brick, a.subscribers, a.seconds
    );
    println!("| edits | edits/s | edit p50 ms | edit p99 ms | errors | deliveries | missing | out of order | before the ack | propagation p50 ms | propagation p99 ms | max ms |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    if edits == 0 || delays.is_empty() {
        anyhow::bail!("no edit was acknowledged ({} errors)", acks.errors);
    }
    println!(
        "| {edits} | {:.0} | {:.2} | {:.2} | {} | {} | {missing} | {out_of_order} | {:.0}% | {:.2} | {:.2} | {:.2} |",
        edits as f64 / elapsed.as_secs_f64(),
        median(acks.latency_ms.clone()),
        percentile(acks.latency_ms.clone(), 0.99),
        acks.errors,
        delays.len(),
        100.0 * early as f64 / delays.len() as f64,
        median(delays.clone()),
        percentile(delays.clone(), 0.99),
        percentile(delays, 1.0),
    );

    // Phase 2: brick reads with wrk, alone and with paced edits.
    let wrk_dir = a.dir.join("wrk");
    std::fs::create_dir_all(&wrk_dir)?;
    let script = wrk_script(
        &wrk_dir,
        "edits-read",
        "/v1/volumes/world/bricks/0",
        layout.grid(0),
        None,
    )?;
    let seconds = a.seconds as u32;
    let alone = wrk(&base, &script, seconds, a.connections)?;
    let (with_edits, paced) = runtime.block_on(async {
        let (script, base2, connections) = (script.clone(), base.clone(), a.connections);
        let reads = tokio::task::spawn_blocking(move || wrk(&base2, &script, seconds, connections));
        let acks = edit_for(&a, &client, &base, &secret, &world, Some(a.paced_rate)).await;
        let reads = reads.await.context("wrk task failed")?;
        anyhow::Ok((reads?, acks))
    })?;
    println!("\n### Brick reads (wrk, 2 threads, {} connections, {} s, random level-0 bricks) with and without {} editors at {} edits/s each\n", a.connections, a.seconds, a.editors, a.paced_rate);
    println!("| reads | requests/s | p50 ms | p99 ms | errors | edits during | edit p99 ms |");
    println!("|---|---:|---:|---:|---|---:|---:|");
    println!(
        "| alone | {:.0} | {:.2} | {:.2} | {} | - | - |",
        alone.rps, alone.p50_ms, alone.p99_ms, alone.errors
    );
    println!(
        "| with edits | {:.0} | {:.2} | {:.2} | {} | {} | {:.2} |",
        with_edits.rps,
        with_edits.p50_ms,
        with_edits.p99_ms,
        with_edits.errors,
        paced.latency_ms.len(),
        if paced.latency_ms.is_empty() {
            f64::NAN
        } else {
            percentile(paced.latency_ms.clone(), 0.99)
        }
    );
    println!(
        "\nRead throughput with edits: {:.1}% of alone (goal: a drop under 20%).",
        100.0 * with_edits.rps / alone.rps.max(1.0)
    );
    Ok(())
}

/// Follows the change feed, recording when each version arrives.
async fn subscribe(client: reqwest::Client, url: String, sink: Arrivals, ready: Arc<AtomicUsize>) {
    let Ok(mut response) = client.get(&url).send().await else {
        return;
    };
    let mut buffer = Vec::new();
    let mut greeted = false;
    while let Ok(Some(chunk)) = response.chunk().await {
        let now = Instant::now();
        buffer.extend_from_slice(&chunk);
        while let Some(end) = buffer.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = buffer.drain(..=end).collect();
            let line = String::from_utf8_lossy(&line);
            if !greeted && line.starts_with("event: hello") {
                greeted = true;
                ready.fetch_add(1, Ordering::AcqRel);
            }
            if let Some(v) = line
                .strip_prefix("id: ")
                .and_then(|v| v.trim().parse::<u64>().ok())
            {
                if let Ok(mut s) = sink.lock() {
                    s.push((v, now));
                }
            }
        }
    }
}

/// Runs the editors for `a.seconds`, each as fast as it is answered or at `rate` edits/s.
async fn edit_for(
    a: &EditsBenchArgs,
    client: &reqwest::Client,
    base: &str,
    secret: &str,
    world: &Arc<WorldSource>,
    rate: Option<f64>,
) -> Acks {
    let deadline = Instant::now() + Duration::from_secs(a.seconds);
    let acks = Arc::new(Mutex::new(Acks::default()));
    let mut tasks = Vec::new();
    for e in 0..a.editors {
        let (client, acks, world) = (client.clone(), acks.clone(), world.clone());
        let url = format!("{base}/v1/volumes/world/edits");
        let auth = format!("Bearer {secret}");
        let (size, radius) = (a.size, a.radius);
        tasks.push(tokio::spawn(async move {
            let mut rng = Rng(0x9e37_79b9_7f4a_7c15 ^ ((e as u64 + 1) * 0x1000_0001));
            let mut next = Instant::now();
            while Instant::now() < deadline {
                if let Some(rate) = rate {
                    tokio::time::sleep_until(next.into()).await;
                    next += Duration::from_secs_f64(1.0 / rate);
                }
                let margin = 2 * radius;
                let (x, z) = (
                    margin + rng.below(size - 2 * margin),
                    margin + rng.below(size - 2 * margin),
                );
                let y = world.height(x, z) as i64;
                let request = EditRequest {
                    op: "difference".into(),
                    term: Some(Term::Ellipsoid {
                        center: [x as i64, y, z as i64],
                        radii: [radius; 3],
                    }),
                    s_l: None,
                    k: None,
                    region: None,
                };
                let body = serde_json::to_vec(&request).unwrap_or_default();
                let start = Instant::now();
                let answer = client
                    .post(&url)
                    .header("content-type", "application/json")
                    .header("authorization", &auth)
                    .body(body)
                    .send()
                    .await;
                let ok = match answer {
                    Ok(r) if r.status().is_success() => r
                        .bytes()
                        .await
                        .ok()
                        .and_then(|b| serde_json::from_slice::<EditResponse>(&b).ok()),
                    _ => None,
                };
                let now = Instant::now();
                if let Ok(mut acks) = acks.lock() {
                    match ok {
                        Some(r) => {
                            acks.at.insert(r.version, now);
                            acks.latency_ms.push((now - start).as_secs_f64() * 1e3);
                        }
                        None => acks.errors += 1,
                    }
                }
            }
        }));
    }
    for t in tasks {
        let _ = t.await;
    }
    Arc::try_unwrap(acks)
        .ok()
        .and_then(|m| m.into_inner().ok())
        .unwrap_or_default()
}
