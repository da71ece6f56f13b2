//! `isovox-bench edits`: shared editing over HTTP on a generated world.
//!
//! One server (in this process, on an ephemeral port) serves a copy of a world; `--editors`
//! clients carve small ellipsoids at random places on its terrain as fast as they are answered,
//! while `--subscribers` clients follow the change feed; then one editor edits alone. Reported:
//! edit throughput and latency, the delay from each edit's acknowledgement (at its editor) to
//! its arrival at every subscriber, one editor's latency, and brick-read throughput (wrk) with
//! and without paced edits running.
//!
//! The strategies of `--groups` (how many edits the server makes durable with one sync; 1 is
//! one sync per edit) run in turn, `--runs` times each, in this one process, so
//! their ratio comes from the same conditions: this machine's speed drifts by 20-30% from one
//! invocation to the next, and other builds share its cores.
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
use isovox_server::http::{spawn, AppState, ServerConfig, Spawned};
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
    /// Length of the single-editor phase of each run.
    #[arg(long, default_value_t = 5)]
    pub single_seconds: u64,
    /// Runs of each strategy (alternating); the tables show the medians.
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// The strategies compared: edits made durable together at most (`--edit-group`); 1 is
    /// one sync per edit, what the server did before group commit.
    #[arg(long, value_delimiter = ',', default_values_t = [1, isovox_server::volume::group::DEFAULT_MAX_GROUP])]
    pub groups: Vec<usize>,
    /// Radius of the carved ellipsoids.
    #[arg(long, default_value_t = 8)]
    pub radius: u32,
    /// Edits per second per editor while reads are measured.
    #[arg(long, default_value_t = 2.0)]
    pub paced_rate: f64,
    /// wrk connections for the read phases.
    #[arg(long, default_value_t = 64)]
    pub connections: u32,
    /// Editors of the undo phase that undo each of their edits once it is acknowledged (the
    /// others only edit).
    #[arg(long, default_value_t = 2)]
    pub undoers: usize,
    /// Run only the undo phase.
    #[arg(long)]
    pub only_undo: bool,
}

/// What the editors saw: per acknowledged version, when its answer arrived and how long the
/// request took.
#[derive(Default)]
struct Acks {
    at: HashMap<u64, Instant>,
    latency_ms: Vec<f64>,
    errors: usize,
    /// Undos (of the editor's own edit, just acknowledged): their latency and how many edits
    /// the server applied again under each.
    undo_latency_ms: Vec<f64>,
    replayed: Vec<u64>,
    undo_errors: usize,
}

/// Arrival times of versions at one subscriber.
type Arrivals = Arc<Mutex<Vec<(u64, Instant)>>>;

/// One run of editors flat out with the subscribers listening.
#[derive(Debug, Clone, Copy)]
struct Figures {
    edits: usize,
    per_second: f64,
    p50_ms: f64,
    p99_ms: f64,
    errors: usize,
    deliveries: usize,
    missing: usize,
    out_of_order: usize,
    early_percent: f64,
    propagation_p50_ms: f64,
    propagation_p99_ms: f64,
    propagation_max_ms: f64,
    /// One editor alone: its median and p99 latency.
    single_p50_ms: f64,
    single_p99_ms: f64,
}

impl Figures {
    /// The medians of `runs`; the counts (errors, deliveries, missing, out of order) summed.
    fn summary(runs: &[Figures]) -> Figures {
        let m = |f: fn(&Figures) -> f64| median(runs.iter().map(f).collect());
        let sum = |f: fn(&Figures) -> usize| runs.iter().map(f).sum::<usize>();
        Figures {
            edits: m(|f| f.edits as f64).round() as usize,
            per_second: m(|f| f.per_second),
            p50_ms: m(|f| f.p50_ms),
            p99_ms: m(|f| f.p99_ms),
            errors: sum(|f| f.errors),
            deliveries: sum(|f| f.deliveries),
            missing: sum(|f| f.missing),
            out_of_order: sum(|f| f.out_of_order),
            early_percent: m(|f| f.early_percent),
            propagation_p50_ms: m(|f| f.propagation_p50_ms),
            propagation_p99_ms: m(|f| f.propagation_p99_ms),
            propagation_max_ms: m(|f| f.propagation_max_ms),
            single_p50_ms: m(|f| f.single_p50_ms),
            single_p99_ms: m(|f| f.single_p99_ms),
        }
    }

    /// One row of the table.
    fn row(&self, label: &str) -> String {
        let f = self;
        format!(
            "| {label} | {} | {:.0} | {:.2} | {:.2} | {} | {} | {} | {} | {:.0}% | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} |",
            f.edits, f.per_second, f.p50_ms, f.p99_ms, f.errors, f.deliveries, f.missing,
            f.out_of_order, f.early_percent, f.propagation_p50_ms, f.propagation_p99_ms,
            f.propagation_max_ms, f.single_p50_ms, f.single_p99_ms,
        )
    }
}

/// The world and what every run shares.
struct Bench {
    a: EditsBenchArgs,
    layout: VolumeLayout,
    world: Arc<WorldSource>,
    source: PathBuf,
    secret: String,
    runtime: tokio::runtime::Runtime,
    client: reqwest::Client,
}

pub fn run_bench(a: EditsBenchArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&a.dir)?;
    if a.groups.is_empty() || a.groups.contains(&0) || a.runs == 0 {
        anyhow::bail!("--groups takes sizes of at least 1, --runs at least 1");
    }
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
    let bench = Bench {
        layout,
        world,
        source,
        secret: random_secret()?,
        runtime: tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?,
        client: reqwest::Client::builder()
            .pool_max_idle_per_host(64)
            .build()?,
        a,
    };
    let a = &bench.a;
    if a.only_undo {
        return bench.undo_run();
    }

    // Phase 1: each strategy in turn, `runs` times, on a fresh copy of the world each time.
    let mut figures: Vec<Vec<Figures>> = vec![Vec::new(); a.groups.len()];
    for run in 0..a.runs {
        for (i, &group) in a.groups.iter().enumerate() {
            eprintln!("run {}/{}: edit group {group}", run + 1, a.runs);
            figures[i].push(bench.edit_run(group)?);
        }
    }
    println!(
        "### Shared editing: {} editors carving radius-{} ellipsoids into a {}^3 world (brick {}), {} change-feed subscribers, {} s; then one editor alone for {} s\n",
        a.editors, a.radius, a.size, a.brick, a.subscribers, a.seconds, a.single_seconds
    );
    println!("Strategies alternate run by run, each on a fresh copy of the world; medians of {} runs (errors, deliveries, missing and out of order: their sums), every run below.\n", a.runs);
    println!("| edit group | edits | edits/s | edit p50 ms | edit p99 ms | errors | deliveries | missing | out of order | before the ack | propagation p50 ms | propagation p99 ms | max ms | one editor p50 ms | one editor p99 ms |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (group, runs) in a.groups.iter().zip(&figures) {
        println!(
            "{}",
            Figures::summary(runs).row(&format!("**{group}** (median)"))
        );
        for f in runs {
            println!("{}", f.row(&group.to_string()));
        }
    }
    if let (Some(first), Some(last)) = (figures.first(), figures.last()) {
        if a.groups.len() > 1 {
            let ratio = |f: fn(&Figures) -> f64| {
                median(first.iter().zip(last).map(|(x, y)| f(y) / f(x)).collect())
            };
            println!(
                "\nEdit group {} against {} (median of the run-by-run ratios): edits/s {:.2}x, edit p99 {:.2}x, one editor's p50 {:.2}x and p99 {:.2}x (below 1: faster).",
                a.groups[a.groups.len() - 1],
                a.groups[0],
                ratio(|f| f.per_second),
                ratio(|f| f.p99_ms),
                ratio(|f| f.single_p50_ms),
                ratio(|f| f.single_p99_ms),
            );
        }
    }
    bench.read_runs()?;
    bench.undo_run()
}

impl Bench {
    /// A fresh copy of the world served in this process with edits grouped by `group`.
    fn serve(&self, group: usize) -> anyhow::Result<Spawned> {
        let data = self.a.dir.join("edits");
        let _ = std::fs::remove_dir_all(&data);
        std::fs::create_dir_all(&data)?;
        std::fs::copy(&self.source, data.join("world.vod"))?;
        let mut tokens = Tokens::default();
        tokens
            .add("bench", &self.secret, Scope::Write)
            .map_err(anyhow::Error::msg)?;
        let config = ServerConfig {
            tokens,
            edit_rate: 1e9,
            edit_queue: 4096,
            edit_group: group,
            ..ServerConfig::default()
        };
        let catalog = Catalog::open_dir(&data)?;
        let state = AppState::with_config(catalog, config);
        Ok(self
            .runtime
            .block_on(async { spawn("127.0.0.1:0", state).await })?)
    }

    /// Editors flat out while the subscribers listen, then one editor alone.
    fn edit_run(&self, group: usize) -> anyhow::Result<Figures> {
        let a = &self.a;
        let server = self.serve(group)?;
        let base = server.base();
        let arrivals: Vec<Arrivals> = (0..a.subscribers).map(|_| Arrivals::default()).collect();
        let (acks, elapsed, single) = self.runtime.block_on(async {
            let ready = Arc::new(AtomicUsize::new(0));
            let subscribers: Vec<_> = arrivals
                .iter()
                .map(|sink| {
                    tokio::spawn(subscribe(
                        self.client.clone(),
                        format!("{base}/v1/volumes/world/events"),
                        sink.clone(),
                        ready.clone(),
                    ))
                })
                .collect();
            while ready.load(Ordering::Acquire) < a.subscribers {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            let start = Instant::now();
            let acks = self.edit_for(&base, a.editors, a.seconds, None).await;
            let elapsed = start.elapsed();
            // Let the last events arrive.
            tokio::time::sleep(Duration::from_millis(500)).await;
            for s in subscribers {
                s.abort();
            }
            let single = self.edit_for(&base, 1, a.single_seconds, None).await;
            (acks, elapsed, single)
        });
        drop(server);
        let edits = acks.latency_ms.len();
        if edits == 0 || single.latency_ms.is_empty() {
            anyhow::bail!(
                "no edit was acknowledged ({} errors)",
                acks.errors + single.errors
            );
        }
        let mut delays = Vec::new();
        let (mut missing, mut early, mut out_of_order) = (0, 0, 0);
        for sink in &arrivals {
            let got = sink.lock().map(|g| g.clone()).unwrap_or_default();
            if got.windows(2).any(|w| w[1].0 <= w[0].0) {
                out_of_order += 1;
            }
            let by_version: HashMap<u64, Instant> = got.into_iter().collect();
            for (v, acked) in &acks.at {
                match by_version.get(v) {
                    // The event is sent right after the commit, before the editor's answer is
                    // written: it often arrives first, which counts as no delay (and is
                    // reported).
                    Some(arrived) => {
                        early += usize::from(arrived < acked);
                        delays.push(arrived.saturating_duration_since(*acked).as_secs_f64() * 1e3)
                    }
                    None => missing += 1,
                }
            }
        }
        if delays.is_empty() {
            anyhow::bail!("no subscriber received an acknowledged version");
        }
        Ok(Figures {
            edits,
            per_second: edits as f64 / elapsed.as_secs_f64(),
            p50_ms: median(acks.latency_ms.clone()),
            p99_ms: percentile(acks.latency_ms, 0.99),
            errors: acks.errors,
            deliveries: delays.len(),
            missing,
            out_of_order,
            early_percent: 100.0 * early as f64 / delays.len() as f64,
            propagation_p50_ms: median(delays.clone()),
            propagation_p99_ms: percentile(delays.clone(), 0.99),
            propagation_max_ms: percentile(delays, 1.0),
            single_p50_ms: median(single.latency_ms.clone()),
            single_p99_ms: percentile(single.latency_ms, 0.99),
        })
    }

    /// Phase 2: brick reads with wrk, alone and with paced edits (the last strategy).
    fn read_runs(&self) -> anyhow::Result<()> {
        let a = &self.a;
        let group = a.groups[a.groups.len() - 1];
        let server = self.serve(group)?;
        let base = server.base();
        let wrk_dir = a.dir.join("wrk");
        std::fs::create_dir_all(&wrk_dir)?;
        let script = wrk_script(
            &wrk_dir,
            "edits-read",
            "/v1/volumes/world/bricks/0",
            self.layout.grid(0),
            None,
        )?;
        let seconds = a.seconds as u32;
        let alone = wrk(&base, &script, seconds, a.connections)?;
        let (with_edits, paced) = self.runtime.block_on(async {
            let (script, base2, connections) = (script.clone(), base.clone(), a.connections);
            let reads =
                tokio::task::spawn_blocking(move || wrk(&base2, &script, seconds, connections));
            let acks = self
                .edit_for(&base, a.editors, a.seconds, Some(a.paced_rate))
                .await;
            let reads = reads.await.context("wrk task failed")?;
            anyhow::Ok((reads?, acks))
        })?;
        drop(server);
        println!("\n### Brick reads (wrk, 2 threads, {} connections, {} s, random level-0 bricks) with and without {} editors at {} edits/s each (edit group {group})\n", a.connections, a.seconds, a.editors, a.paced_rate);
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

    /// Phase 3: `editors` editors flat out, `undoers` of whom undo each of their edits once it
    /// is acknowledged (the last strategy): edits/s, and an undo's latency beside the edit's.
    fn undo_run(&self) -> anyhow::Result<()> {
        let a = &self.a;
        let group = a.groups[a.groups.len() - 1];
        let undoers = a.undoers.min(a.editors);
        let mut rows = Vec::new();
        for undoing in [0, undoers] {
            let server = self.serve(group)?;
            let base = server.base();
            let start = Instant::now();
            let acks = self
                .runtime
                .block_on(self.edit_undo_for(&base, a.editors, a.seconds, None, undoing));
            let secs = start.elapsed().as_secs_f64();
            drop(server);
            rows.push((undoing, acks, secs));
        }
        println!("\n### Undo: {} editors carving radius-{} ellipsoids into the {}^3 world for {} s, of whom 0 or {undoers} undo each of their edits once it is acknowledged (edit group {group})\n", a.editors, a.radius, a.size, a.seconds);
        println!("| editors undoing | edits/s | edit p50 ms | edit p99 ms | undos/s | undo p50 ms | undo p99 ms | edits applied again per undo | errors |");
        println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        for (undoing, acks, secs) in &rows {
            let q = |v: &Vec<f64>, p: f64| {
                if v.is_empty() {
                    f64::NAN
                } else {
                    percentile(v.clone(), p)
                }
            };
            let replayed = if acks.replayed.is_empty() {
                f64::NAN
            } else {
                acks.replayed.iter().sum::<u64>() as f64 / acks.replayed.len() as f64
            };
            println!(
                "| {undoing} | {:.0} | {:.2} | {:.2} | {:.0} | {:.2} | {:.2} | {:.2} | {} |",
                acks.latency_ms.len() as f64 / secs,
                q(&acks.latency_ms, 0.5),
                q(&acks.latency_ms, 0.99),
                acks.undo_latency_ms.len() as f64 / secs,
                q(&acks.undo_latency_ms, 0.5),
                q(&acks.undo_latency_ms, 0.99),
                replayed,
                acks.errors + acks.undo_errors,
            );
        }
        Ok(())
    }

    /// Runs `editors` editors for `seconds`, each as fast as it is answered or at `rate`
    /// edits/s.
    async fn edit_for(&self, base: &str, editors: usize, seconds: u64, rate: Option<f64>) -> Acks {
        self.edit_undo_for(base, editors, seconds, rate, 0).await
    }

    /// [`Bench::edit_for`] where the first `undoers` editors undo each of their edits once it
    /// is acknowledged.
    async fn edit_undo_for(
        &self,
        base: &str,
        editors: usize,
        seconds: u64,
        rate: Option<f64>,
        undoers: usize,
    ) -> Acks {
        let deadline = Instant::now() + Duration::from_secs(seconds);
        let acks = Arc::new(Mutex::new(Acks::default()));
        let mut tasks = Vec::new();
        for e in 0..editors {
            let (client, acks, world) = (self.client.clone(), acks.clone(), self.world.clone());
            let url = format!("{base}/v1/volumes/world/edits");
            let undo_url = format!("{base}/v1/volumes/world/undo");
            let undoes = e < undoers;
            let auth = format!("Bearer {}", self.secret);
            let (size, radius) = (self.a.size, self.a.radius);
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
                        message: None,
                        channel: None,
                        overwrite: None,
                    };
                    let body = serde_json::to_vec(&request).unwrap_or_default();
                    let start = Instant::now();
                    let ok = post_for_answer(&client, &url, &auth, body).await;
                    let now = Instant::now();
                    let version = ok.as_ref().map(|r| r.version);
                    if let Ok(mut acks) = acks.lock() {
                        match ok {
                            Some(r) => {
                                acks.at.insert(r.version, now);
                                acks.latency_ms.push((now - start).as_secs_f64() * 1e3);
                            }
                            None => acks.errors += 1,
                        }
                    }
                    let Some(version) = version.filter(|_| undoes) else {
                        continue;
                    };
                    let start = Instant::now();
                    let body = format!("{{\"version\":{version}}}").into_bytes();
                    let undone = post_for_answer(&client, &undo_url, &auth, body).await;
                    let now = Instant::now();
                    if let Ok(mut acks) = acks.lock() {
                        match undone {
                            Some(r) => {
                                acks.undo_latency_ms.push((now - start).as_secs_f64() * 1e3);
                                acks.replayed.push(r.replayed.unwrap_or(0));
                            }
                            None => acks.undo_errors += 1,
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
}

/// Posts the JSON `body` to `url` with `auth`: the answer of a commit (edit, undo), or `None`
/// for a failure of any kind.
async fn post_for_answer(
    client: &reqwest::Client,
    url: &str,
    auth: &str,
    body: Vec<u8>,
) -> Option<EditResponse> {
    let answer = client
        .post(url)
        .header("content-type", "application/json")
        .header("authorization", auth)
        .body(body)
        .send()
        .await;
    match answer {
        Ok(r) if r.status().is_success() => r
            .bytes()
            .await
            .ok()
            .and_then(|b| serde_json::from_slice::<EditResponse>(&b).ok()),
        _ => None,
    }
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
        // Lines are looked at where they lie, without a copy each: 100 subscribers read about
        // half a million lines a second, on the cores the server under test runs on.
        let mut start = 0;
        while let Some(len) = buffer[start..].iter().position(|&b| b == b'\n') {
            let line = &buffer[start..start + len];
            start += len + 1;
            if !greeted && line.starts_with(b"event: hello") {
                greeted = true;
                ready.fetch_add(1, Ordering::AcqRel);
            }
            if let Some(v) = line
                .strip_prefix(b"id: ")
                .and_then(|v| std::str::from_utf8(v).ok())
                .and_then(|v| v.trim().parse::<u64>().ok())
            {
                if let Ok(mut s) = sink.lock() {
                    s.push((v, now));
                }
            }
        }
        buffer.drain(..start);
    }
}
