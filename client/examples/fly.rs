//! Flies a camera over the demo world with a [`Streamer`] and prints, once a second, what it
//! streams: tiles ready and dropped (by level), requests and bytes, the requests it may have in
//! flight now (fewer after the server answered 503), tiles resident, cache hits.
//!
//! Start a server (it generates the demo world on first start), then fly:
//!
//! ```sh
//! cargo run --release -p isovox-server --bin isovox -- serve
//! cargo run --release -p isovox-client --example fly
//! cargo run --release -p isovox-client --example fly -- --meshes --seconds 20
//! ```
//!
//! Flags: `--url URL` (default `$ISOVOX_URL` or `http://127.0.0.1:7070`), `--volume NAME`
//! (default `$ISOVOX_VOLUME` or `demo`), `--seconds S` (default 15), `--meshes` (mesh tiles
//! instead of bricks), `--max-error-px E` (default 16: the detail radii for that screen-space
//! error on a 1080-pixel viewport with a 60 degree field of view; the streamer's own default,
//! one pixel, puts all of the demo world at level 0). The camera crosses the world diagonally
//! at 90% of its height, sinking to 60% half way, and comes back.

use isovox_client::{Client, StreamEvent, Streamer, StreamerConfig, TileKind};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

struct Args {
    url: String,
    volume: String,
    seconds: f32,
    meshes: bool,
    max_error_px: f32,
}

fn args() -> Result<Args, String> {
    let mut a = Args {
        url: std::env::var("ISOVOX_URL").unwrap_or_else(|_| "http://127.0.0.1:7070".into()),
        volume: std::env::var("ISOVOX_VOLUME").unwrap_or_else(|_| "demo".into()),
        seconds: 15.0,
        meshes: false,
        max_error_px: 16.0,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--url" => a.url = value()?,
            "--volume" => a.volume = value()?,
            "--seconds" => {
                a.seconds = value()?.parse().map_err(|e| format!("--seconds: {e}"))?;
            }
            "--meshes" => a.meshes = true,
            "--max-error-px" => {
                a.max_error_px = value()?
                    .parse()
                    .map_err(|e| format!("--max-error-px: {e}"))?;
            }
            _ => {
                return Err(format!(
                    "unknown argument {flag} (flags: --url URL --volume NAME --seconds S --meshes \
                     --max-error-px E)"
                ))
            }
        }
    }
    Ok(a)
}

/// Counts of one second.
#[derive(Default)]
struct Second {
    ready: BTreeMap<u8, u64>,
    dropped: BTreeMap<u8, u64>,
    stale: u64,
    bytes: u64,
    errors: Vec<String>,
}

fn by_level(m: &BTreeMap<u8, u64>) -> String {
    if m.is_empty() {
        return "-".into();
    }
    m.iter()
        .map(|(l, n)| format!("L{l}:{n}"))
        .collect::<Vec<_>>()
        .join(" ")
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let a = args()?;
    // Examples build with the dev-dependencies, the server among them: reqwest then has rustls
    // without a built-in crypto provider (isovox_server::client_tls), and needs one installed.
    isovox_server::client_tls::install_provider();
    let client = Client::new(&a.url)?;
    let info = client.volume(&a.volume).await?;
    let config = StreamerConfig {
        radii: StreamerConfig::radii_for_screen_error(
            &info,
            60f32.to_radians(),
            1080.0,
            a.max_error_px,
        ),
        kind: if a.meshes {
            TileKind::Meshes { iso: None }
        } else {
            TileKind::Bricks
        },
        ..StreamerConfig::default()
    };
    let (streamer, mut events) = Streamer::start(client, &a.volume, config).await?;
    let info = streamer.info().clone();
    let e = [0, 1, 2].map(|k| info.dims[k] as f32 * info.voxel_scale[k]);
    println!(
        "flying over {} ({}x{}x{} voxels, brick {}, {} levels, version {}) at {}; radii {:?}",
        info.name,
        info.dims[0],
        info.dims[1],
        info.dims[2],
        info.brick,
        info.levels.len(),
        info.version,
        a.url,
        streamer.radii()
    );
    // Corner to corner and back, dipping half way.
    let camera = |t: f32| {
        let u = (t / a.seconds * std::f32::consts::TAU).cos() * -0.5 + 0.5; // 0 -> 1 -> 0
        let dip = (u * std::f32::consts::PI).sin();
        [
            e[0] * (0.05 + 0.9 * u),
            e[1] * (0.9 - 0.3 * dip),
            e[2] * (0.05 + 0.9 * u),
        ]
    };
    println!(
        "{:>4}  {:>22}  {:>26}  {:>20}  {:>5}  {:>9}  {:>8}  {:>5}  {:>8}  {:>5}",
        "s", "camera", "ready", "dropped", "stale", "MiB", "requests", "limit", "resident", "hits"
    );
    let start = Instant::now();
    let mut tick = tokio::time::interval(Duration::from_millis(33));
    let mut second = Second::default();
    let mut next_print = 1.0f32;
    let (mut last_requests, mut last_hits, mut last_lookups) = (0, 0, 0);
    let (mut total_ready, mut total_bytes) = (0u64, 0u64);
    loop {
        tokio::select! {
            _ = tick.tick() => {
                let t = start.elapsed().as_secs_f32();
                if t >= a.seconds {
                    break;
                }
                streamer.set_camera(camera(t));
                if t >= next_print {
                    next_print += 1.0;
                    let s = streamer.stats();
                    let lookups = s.cache_hits + s.cache_misses;
                    let hits = if lookups > last_lookups {
                        format!("{:.0}%", 100.0 * (s.cache_hits - last_hits) as f64 / (lookups - last_lookups) as f64)
                    } else {
                        "-".into()
                    };
                    let c = camera(t);
                    println!(
                        "{:>4.0}  {:>22}  {:>26}  {:>20}  {:>5}  {:>9.1}  {:>8}  {:>5}  {:>8}  {:>5}",
                        t,
                        format!("{:.0},{:.0},{:.0}", c[0], c[1], c[2]),
                        by_level(&second.ready),
                        by_level(&second.dropped),
                        second.stale,
                        second.bytes as f64 / f64::from(1u32 << 20),
                        s.requests - last_requests,
                        s.in_flight_limit,
                        s.resident,
                        hits,
                    );
                    for err in second.errors.drain(..) {
                        println!("      error: {err}");
                    }
                    (last_requests, last_hits, last_lookups) = (s.requests, s.cache_hits, lookups);
                    second = Second::default();
                }
            }
            event = events.recv() => match event {
                Some(StreamEvent::Ready { key, data, .. }) => {
                    *second.ready.entry(key.level).or_default() += 1;
                    let n = data.bytes();
                    second.bytes += n;
                    total_ready += 1;
                    total_bytes += n;
                }
                Some(StreamEvent::Dropped { key }) => *second.dropped.entry(key.level).or_default() += 1,
                Some(StreamEvent::Stale { .. }) => second.stale += 1,
                Some(StreamEvent::Version { version }) => println!("      version {version}"),
                Some(StreamEvent::Error { key, error }) => {
                    second.errors.push(key.map_or(error.clone(), |k| format!("{k}: {error}")));
                }
                None => break,
            },
        }
    }
    let s = streamer.stats();
    println!(
        "done: {total_ready} tiles ready ({:.1} MiB), {} requests, {:.1} MiB on the wire, {} resident, cache hits {}/{}",
        total_bytes as f64 / f64::from(1u32 << 20),
        s.requests,
        s.bytes as f64 / f64::from(1u32 << 20),
        s.resident,
        s.cache_hits,
        s.cache_hits + s.cache_misses
    );
    // Keep draining while the streamer shuts down.
    let shutdown = streamer.shutdown();
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            () = &mut shutdown => break,
            e = events.recv() => if e.is_none() { shutdown.await; break },
        }
    }
    Ok(())
}
