//! `isovox-bench http`: brick requests per second and latency with wrk (2 threads, 64
//! connections, random keys over a 512^3 world) against `isovox serve`, nginx serving the same
//! bytes as static files, and a bare axum handler returning static bytes of the same size (the
//! ceiling on this machine). Needs `wrk` and `nginx` on the PATH (scripts/bench-http.sh
//! installs them).

use anyhow::{bail, Context};
use clap::Args;
use isovox_proto::vod2::Codec;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::{run, AppState};
use isovox_server::store::{build_vod2, BuildOptions, StoredBrick, Vod2};
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::Duration;

#[derive(Debug, Args)]
pub struct HttpBenchArgs {
    #[arg(long, default_value = "bench-out/http")]
    pub dir: PathBuf,
    /// Seconds per wrk run.
    #[arg(long, default_value_t = 10)]
    pub seconds: u32,
    #[arg(long, default_value_t = 64)]
    pub connections: u32,
    /// Rounds: the three servers are measured in turn this many times and each one's median
    /// run is reported (this machine's throughput drifts between runs).
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
    /// Edge of the cubic world.
    #[arg(long, default_value_t = 512)]
    pub size: u32,
}

/// A child process started in a process group of its own ([`spawn_group`]), stopped with its
/// whole group: nginx's workers outlive their master otherwise. The group is the child's own,
/// never this process's.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let group = format!("-{}", self.0.id());
        let _ = Command::new("kill")
            .args(["-s", "TERM", "--", &group])
            .status();
        let deadline = std::time::Instant::now() + Duration::from_secs(5);
        while std::time::Instant::now() < deadline {
            if matches!(self.0.try_wait(), Ok(Some(_))) {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        // Whatever is left of the group (a worker that ignored TERM), and the master.
        let _ = Command::new("kill")
            .args(["-s", "KILL", "--", &group])
            .stderr(std::process::Stdio::null())
            .status();
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `command` as the leader of a new process group.
fn spawn_group(command: &mut Command) -> std::io::Result<Killed> {
    use std::os::unix::process::CommandExt;
    command.process_group(0).spawn().map(Killed)
}

/// A wrk Lua script requesting random level-0 bricks under `prefix`, with `accept`.
pub(super) fn wrk_script(
    dir: &Path,
    name: &str,
    prefix: &str,
    grid: [u32; 3],
    accept: Option<&str>,
) -> anyhow::Result<PathBuf> {
    let path = dir.join(format!("{name}.lua"));
    let header = accept
        .map(|a| format!("wrk.headers[\"Accept\"] = \"{a}\"\n"))
        .unwrap_or_default();
    std::fs::write(
        &path,
        format!(
            "{header}math.randomseed(42)\nrequest = function()\n  local x, y, z = math.random(0, {}), math.random(0, {}), math.random(0, {})\n  return wrk.format(\"GET\", \"{prefix}/\" .. x .. \"/\" .. y .. \"/\" .. z)\nend\n",
            grid[0] - 1,
            grid[1] - 1,
            grid[2] - 1
        ),
    )?;
    Ok(path)
}

#[derive(Debug, Default)]
pub(super) struct WrkResult {
    pub rps: f64,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub errors: String,
}

fn parse_ms(s: &str) -> Option<f64> {
    let (num, unit) = s
        .trim()
        .split_at(s.trim().find(|c: char| c.is_alphabetic())?);
    let v: f64 = num.parse().ok()?;
    Some(match unit {
        "us" => v / 1000.0,
        "ms" => v,
        "s" => v * 1000.0,
        _ => return None,
    })
}

pub(super) fn wrk(
    url: &str,
    script: &Path,
    seconds: u32,
    connections: u32,
) -> anyhow::Result<WrkResult> {
    let out = Command::new("wrk")
        .args([
            "-t2",
            &format!("-c{connections}"),
            &format!("-d{seconds}s"),
            "--latency",
            "-s",
        ])
        .arg(script)
        .arg(url)
        .output()
        .context("cannot run wrk (install it: scripts/bench-http.sh)")?;
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    let find = |prefix: &str| {
        text.lines()
            .find(|l| l.trim_start().starts_with(prefix))
            .map(str::trim)
            .map(str::to_string)
    };
    let rps = find("Requests/sec:")
        .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse().ok()))
        .unwrap_or(0.0);
    let pct = |p: &str| {
        find(p)
            .and_then(|l| l.split_whitespace().nth(1).and_then(parse_ms))
            .unwrap_or(f64::NAN)
    };
    let errors = [find("Non-2xx"), find("Socket errors")]
        .into_iter()
        .flatten()
        .collect::<Vec<_>>()
        .join("; ");
    Ok(WrkResult {
        rps,
        p50_ms: pct("50%"),
        p99_ms: pct("99%"),
        errors,
    })
}

async fn wait_up(port: u16) -> anyhow::Result<()> {
    for _ in 0..100 {
        if tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .is_ok()
        {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    bail!("nothing listens on port {port}")
}

pub fn run_bench(a: HttpBenchArgs) -> anyhow::Result<()> {
    let data = a.dir.join("data");
    let statics = a.dir.join("static");
    std::fs::create_dir_all(&data)?;
    let layout = VolumeLayout::new([a.size; 3], 32, VoxelType::U8)?;
    let file = data.join("world.vod");
    if !file.exists() {
        eprintln!("bench http: generating the {0}^3 world", a.size);
        build_vod2(
            &file,
            &layout,
            [1.0; 3],
            &WorldSource::new(layout.clone(), 1),
            &BuildOptions {
                compression: isovox_server::store::codec::Compression::Lz4,
                ..BuildOptions::default()
            },
        )?;
    }
    // The same bytes as static files: raw voxels, and the lz4 blocks isovox serves.
    let vod = Vod2::open(&file)?;
    let snap = vod.head();
    let g = layout.grid(0);
    let mut lz4_sizes = Vec::new();
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                let key = BrickKey { level: 0, x, y, z };
                let raw = snap.read(key)?;
                let lz4 = match snap.stored(key)? {
                    StoredBrick::Record {
                        header, payload, ..
                    } if header.codec == Codec::Lz4 => payload.to_vec(),
                    _ => lz4_flex::block::compress(&raw),
                };
                lz4_sizes.push(lz4.len());
                for (tree, bytes) in [("raw", &raw), ("lz4", &lz4)] {
                    let dir = statics.join(format!("{tree}/{x}/{y}"));
                    std::fs::create_dir_all(&dir)?;
                    std::fs::write(dir.join(z.to_string()), bytes)?;
                }
            }
        }
    }
    lz4_sizes.sort_unstable();
    let lz4_median = lz4_sizes[lz4_sizes.len() / 2];
    // nginx on the static tree.
    let nginx_port = 7081u16;
    let conf = a.dir.join("nginx.conf");
    let root = std::fs::canonicalize(&statics)?;
    let logs = std::fs::canonicalize(&a.dir)?;
    std::fs::write(
        &conf,
        format!(
            "worker_processes 2;\npid {logs}/nginx.pid;\nerror_log {logs}/nginx-error.log;\nevents {{ worker_connections 1024; }}\nhttp {{\n  access_log off;\n  open_file_cache max=10000 inactive=60s;\n  open_file_cache_valid 60s;\n  sendfile on;\n  tcp_nopush on;\n  default_type application/octet-stream;\n  client_body_temp_path {logs}/tmp;\n  proxy_temp_path {logs}/tmp;\n  fastcgi_temp_path {logs}/tmp;\n  uwsgi_temp_path {logs}/tmp;\n  scgi_temp_path {logs}/tmp;\n  server {{ listen 127.0.0.1:{nginx_port}; root {root}; etag on; }}\n}}\n",
            logs = logs.display(),
            root = root.display()
        ),
    )?;
    std::fs::create_dir_all(a.dir.join("tmp"))?;
    let _nginx = spawn_group(
        Command::new("nginx")
            .args(["-c"])
            .arg(std::fs::canonicalize(&conf)?)
            .args(["-g", "daemon off;"]),
    )
    .context("cannot start nginx (install it: scripts/bench-http.sh)")?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let (isovox_port, ceiling_port) = (7082u16, 7083u16);
    let brick_bytes = layout.brick_bytes();
    runtime.block_on(async {
        let catalog = Catalog::open_dir(&data)?;
        let listener = tokio::net::TcpListener::bind(("127.0.0.1", isovox_port)).await?;
        tokio::spawn(run(
            listener,
            AppState::new(catalog, 256 << 20, 64),
            std::future::pending(),
        ));
        // The ceiling: a bare axum handler returning static bytes of a brick's size.
        let raw_body = bytes::Bytes::from(vec![7u8; brick_bytes]);
        let lz4_body = bytes::Bytes::from(vec![7u8; lz4_median]);
        let app = axum::Router::new()
            .route(
                "/raw/{x}/{y}/{z}",
                axum::routing::get(move || {
                    let b = raw_body.clone();
                    async move { b }
                }),
            )
            .route(
                "/lz4/{x}/{y}/{z}",
                axum::routing::get(move || {
                    let b = lz4_body.clone();
                    async move { b }
                }),
            );
        let listener = tokio::net::TcpListener::bind(("127.0.0.1", ceiling_port)).await?;
        tokio::spawn(async move { axum::serve(listener, app).await });
        for p in [nginx_port, isovox_port, ceiling_port] {
            wait_up(p).await?;
        }
        anyhow::Ok(())
    })?;
    let bench = a.dir.join("wrk");
    std::fs::create_dir_all(&bench)?;
    println!("### Brick requests: wrk, 2 threads, {} connections, {} s per run, {} rounds taken in turn (median run shown), random level-0 keys over a {}^3 world (brick 32^3: {} B raw, lz4 median {} B)\n", a.connections, a.seconds, a.rounds, a.size, brick_bytes, lz4_median);
    println!("| server | encoding | requests/s | p50 ms | p99 ms | errors | isovox / nginx | isovox / bare axum |");
    println!("|---|---|---:|---:|---:|---|---:|---:|");
    for (encoding, accept) in [("raw", None), ("lz4", Some("application/x-lz4"))] {
        let iso_script = wrk_script(
            &bench,
            &format!("isovox-{encoding}"),
            "/v1/volumes/world/bricks/0",
            g,
            accept,
        )?;
        let static_script = wrk_script(
            &bench,
            &format!("static-{encoding}"),
            &format!("/{encoding}"),
            g,
            None,
        )?;
        let mut runs: [Vec<WrkResult>; 3] = Default::default();
        for _ in 0..a.rounds.max(1) {
            for (i, (port, script)) in [
                (isovox_port, &iso_script),
                (nginx_port, &static_script),
                (ceiling_port, &static_script),
            ]
            .into_iter()
            .enumerate()
            {
                runs[i].push(wrk(
                    &format!("http://127.0.0.1:{port}"),
                    script,
                    a.seconds,
                    a.connections,
                )?);
            }
        }
        let [isovox, nginx, ceiling] = runs.map(|mut r| {
            r.sort_by(|x, y| x.rps.total_cmp(&y.rps));
            r.swap_remove(r.len() / 2)
        });
        for (name, r) in [
            ("isovox serve", &isovox),
            ("nginx (static files)", &nginx),
            ("bare axum (static bytes)", &ceiling),
        ] {
            let ratios = if name == "isovox serve" {
                format!(
                    "{:.2} | {:.2}",
                    isovox.rps / nginx.rps,
                    isovox.rps / ceiling.rps
                )
            } else {
                "| ".to_string()
            };
            println!(
                "| {name} | {encoding} | {:.0} | {:.2} | {:.2} | {} | {ratios} |",
                r.rps,
                r.p50_ms,
                r.p99_ms,
                if r.errors.is_empty() {
                    "none"
                } else {
                    &r.errors
                }
            );
        }
    }
    drop(_nginx);
    mesh_tiles(&runtime, isovox_port, g)?;
    Ok(())
}

/// Mesh tiles per second over every level-0 tile of the world: first cold (meshed on
/// request), then again from the mesh cache; 8 requests in flight, compact encoding.
fn mesh_tiles(runtime: &tokio::runtime::Runtime, port: u16, grid: [u32; 3]) -> anyhow::Result<()> {
    let mut urls = Vec::new();
    for z in 0..grid[2] {
        for y in 0..grid[1] {
            for x in 0..grid[0] {
                urls.push(format!(
                    "http://127.0.0.1:{port}/v1/volumes/world/meshes/0/{x}/{y}/{z}"
                ));
            }
        }
    }
    let urls = std::sync::Arc::new(urls);
    println!("\n### Mesh tiles (every level-0 tile of the world, 32^3 voxels each, compact encoding, 8 requests in flight)\n");
    println!("| pass | tiles | seconds | tiles/s | MB received | errors |");
    println!("|---|---:|---:|---:|---:|---:|");
    for pass in ["cold (meshed on request)", "cached"] {
        let start = std::time::Instant::now();
        let (bytes, errors) = runtime.block_on(async {
            let client = reqwest::Client::new();
            let next = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
            let mut tasks = Vec::new();
            for _ in 0..8 {
                let (client, urls, next) = (client.clone(), urls.clone(), next.clone());
                tasks.push(tokio::spawn(async move {
                    let (mut bytes, mut errors) = (0usize, 0usize);
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(url) = urls.get(i) else { break };
                        match client.get(url).send().await {
                            Ok(r) if r.status().is_success() => match r.bytes().await {
                                Ok(b) => bytes += b.len(),
                                Err(_) => errors += 1,
                            },
                            _ => errors += 1,
                        }
                    }
                    (bytes, errors)
                }));
            }
            let mut total = (0, 0);
            for t in tasks {
                let (b, e) = t.await.unwrap_or((0, 1));
                total = (total.0 + b, total.1 + e);
            }
            total
        });
        let seconds = start.elapsed().as_secs_f64();
        println!(
            "| {pass} | {} | {seconds:.2} | {:.0} | {:.1} | {errors} |",
            urls.len(),
            urls.len() as f64 / seconds,
            bytes as f64 / 1048576.0
        );
    }
    Ok(())
}
