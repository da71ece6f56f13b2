//! `isovox-load`: simulated viewers and editors against an Isovox server.
//!
//! ```sh
//! isovox-load --url http://127.0.0.1:7070 --volume demo --viewers 100 --editors 10 \
//!     --duration 60 --token "$(awk '/^demo/ {print $2}' data/tokens)" --json load.json
//! ```
//!
//! Prints the report as Markdown tables on stdout (and as JSON with `--json`); draws a progress
//! bar on a terminal. Ctrl-C ends the run early, with the report of what ran. Exits with 1 when anything failed during the run (an HTTP status other
//! than 2xx/304, a transport failure, a streamer error, a missing edit notification), with 2
//! when the run could not start.

use clap::{Parser, ValueEnum};
use isovox_tools::load::{run_until, LoadConfig, PathSpec, RecordedPath, Tiles};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

// Fifty streamers in one process allocate small plans and answers from every worker thread:
// under glibc's malloc about a fifth of the load tester's time went to the allocator and its
// locks (docs/benchmarks.md, "Many viewers on a large world").
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Debug, Clone, Copy, ValueEnum)]
enum TilesArg {
    Bricks,
    Meshes,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PathArg {
    Orbit,
    RandomWalk,
}

/// Simulated users against an Isovox server: viewers stream a volume along camera paths,
/// editors also carve and add; prints requests, bytes, throughput, latency per route, errors,
/// edit-to-notification latency and cache hit rate.
#[derive(Debug, Parser)]
#[command(name = "isovox-load", version)]
struct Args {
    /// The server.
    #[arg(long, env = "ISOVOX_URL")]
    url: String,
    /// The volume to stream and edit.
    #[arg(long)]
    volume: String,
    /// Users who view (each one streamer).
    #[arg(long, default_value_t = 10)]
    viewers: usize,
    /// Users who view and edit.
    #[arg(long, default_value_t = 0)]
    editors: usize,
    /// Seconds to run.
    #[arg(long, default_value_t = 30.0)]
    duration: f64,
    /// Stop earlier, once this many HTTP requests were made.
    #[arg(long)]
    requests: Option<u64>,
    /// Write token for the editors.
    #[arg(long, env = "ISOVOX_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Also write the report as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Stream bricks or mesh tiles.
    #[arg(long, value_enum, default_value_t = TilesArg::Bricks)]
    tiles: TilesArg,
    /// Iso value of the mesh tiles (default: the server's).
    #[arg(long)]
    iso: Option<f32>,
    /// Camera path: a circle above the volume or a seeded random walk.
    #[arg(long, value_enum, default_value_t = PathArg::Orbit)]
    path: PathArg,
    /// A recorded camera path instead: lines `t x y z` (seconds, world units), looped.
    #[arg(long, conflicts_with = "path")]
    path_file: Option<PathBuf>,
    /// Orbit radius, world units (default: 35% of the smaller horizontal extent).
    #[arg(long)]
    orbit_radius: Option<f32>,
    /// Orbit height, world units (default: 95% of the volume's height).
    #[arg(long)]
    orbit_height: Option<f32>,
    /// Seconds per turn of the orbit.
    #[arg(long, default_value_t = 60.0)]
    orbit_period: f32,
    /// Random-walk speed, world units per second (default: 5% of the larger horizontal extent).
    #[arg(long)]
    walk_speed: Option<f32>,
    /// Camera updates per second.
    #[arg(long, default_value_t = 30.0)]
    camera_hz: f64,
    /// Seconds over which the users start, evenly spread (counted in --duration).
    #[arg(long, default_value_t = 0.0)]
    ramp_up: f64,
    /// Detail radii of the streamers, world units, comma-separated: level k within the k-th
    /// (default: derived from --max-error-px).
    #[arg(long, value_delimiter = ',')]
    radii: Option<Vec<f32>>,
    /// Screen-space error, in pixels of a 1080-pixel viewport with a 60 degree field of view,
    /// that the detail radii are derived for.
    #[arg(long, default_value_t = 16.0)]
    max_error_px: f32,
    /// Requests each streamer keeps in flight (default: the streamer's).
    #[arg(long)]
    max_in_flight: Option<usize>,
    /// Each streamer's content cache, MiB.
    #[arg(long, default_value_t = 16)]
    cache_mb: usize,
    /// Streamers do without the octree descent (which skips the tiles that cannot hold the
    /// surface, deciding from coarser bricks' ranges; see `StreamerConfig::descent`): they ask
    /// for the grid regions of every tile they want.
    #[arg(long)]
    no_descent: bool,
    /// Mesh streamers ask for every desired tile, even those their bricks' value ranges show
    /// to be empty (see `StreamerConfig::skip_empty`).
    #[arg(long)]
    fetch_empty_tiles: bool,
    /// Edits per second per editor.
    #[arg(long, default_value_t = 1.0)]
    edit_rate: f64,
    /// Radii of the edited ellipsoids, voxels: MIN,MAX.
    #[arg(long, value_delimiter = ',', num_args = 2, default_values_t = [4u32, 12])]
    edit_radius: Vec<u32>,
    /// Share of the edits that carve (the others add).
    #[arg(long, default_value_t = 0.5)]
    carve_fraction: f64,
    /// Share of the edits after which the editor undoes one of its own edits (0 to 1).
    #[arg(long, default_value_t = 0.0)]
    undo_fraction: f64,
    /// Presence messages per second per viewer (0: none); they need a token.
    #[arg(long, default_value_t = 0.0)]
    presence_hz: f64,
    /// A token file (`NAME TOKEN ...` per line, the server's format): viewers say where they
    /// are as these users, in turn (default: all as the --token's user).
    #[arg(long)]
    presence_tokens: Option<std::path::PathBuf>,
    /// Change-feed subscribers timing edit notifications (default: min(viewers, 8)).
    #[arg(long)]
    subscribers: Option<usize>,
    /// Seed of the camera paths and edits.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Seconds to wait, at the end, for requests in flight and the last notifications.
    #[arg(long, default_value_t = 10.0)]
    drain: f64,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

fn seconds(name: &str, v: f64) -> Result<Duration, String> {
    Duration::try_from_secs_f64(v).map_err(|_| format!("--{name} {v}: not a duration"))
}

fn config(a: Args) -> Result<(LoadConfig, Option<PathBuf>), String> {
    let path = match &a.path_file {
        Some(f) => {
            let text = std::fs::read_to_string(f)
                .map_err(|e| format!("cannot read {}: {e}", f.display()))?;
            PathSpec::Recorded(std::sync::Arc::new(
                RecordedPath::parse(&text).map_err(|e| format!("{}: {e}", f.display()))?,
            ))
        }
        None => match a.path {
            PathArg::Orbit => PathSpec::Orbit {
                radius: a.orbit_radius,
                height: a.orbit_height,
                period_s: a.orbit_period,
            },
            PathArg::RandomWalk => PathSpec::RandomWalk {
                speed: a.walk_speed,
                low: None,
                high: None,
            },
        },
    };
    if a.editors > 0 && a.token.is_none() {
        return Err("--editors needs a write token: --token T or ISOVOX_TOKEN".into());
    }
    if !(0.0..=1.0).contains(&a.undo_fraction) {
        return Err("--undo-fraction is a share between 0 and 1".into());
    }
    if !(0.0..=1.0).contains(&a.carve_fraction) {
        return Err("--carve-fraction is a share between 0 and 1".into());
    }
    if a.edit_rate <= 0.0 || a.camera_hz <= 0.0 {
        return Err("--edit-rate and --camera-hz must be positive".into());
    }
    let mut c = LoadConfig::new(&a.url, &a.volume);
    c.viewers = a.viewers;
    c.editors = a.editors;
    c.duration = seconds("duration", a.duration)?;
    c.max_requests = a.requests;
    c.token = a.token;
    c.tiles = match a.tiles {
        TilesArg::Bricks => Tiles::Bricks,
        TilesArg::Meshes => Tiles::Meshes { iso: a.iso },
    };
    c.path = path;
    c.camera_hz = a.camera_hz;
    c.ramp_up = seconds("ramp-up", a.ramp_up)?;
    c.radii = a.radii;
    c.max_in_flight = a.max_in_flight;
    c.max_error_px = a.max_error_px;
    c.cache_bytes = a.cache_mb << 20;
    c.descent = !a.no_descent;
    c.skip_empty = !a.fetch_empty_tiles;
    c.edit_rate = a.edit_rate;
    c.edit_radius = (a.edit_radius[0], a.edit_radius[1]);
    c.carve_fraction = a.carve_fraction;
    c.undo_fraction = a.undo_fraction;
    if !(0.0..=100.0).contains(&a.presence_hz) {
        return Err(format!("--presence-hz {} is not in 0..=100", a.presence_hz));
    }
    c.presence_hz = a.presence_hz;
    if let Some(file) = &a.presence_tokens {
        let text = std::fs::read_to_string(file)
            .map_err(|e| format!("cannot read {}: {e}", file.display()))?;
        c.presence_tokens = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .filter_map(|l| l.split_whitespace().nth(1).map(str::to_string))
            .collect();
        if c.presence_tokens.is_empty() {
            return Err(format!("{} holds no token", file.display()));
        }
    }
    c.subscribers = a.subscribers;
    c.seed = a.seed;
    c.drain = seconds("drain", a.drain)?;
    c.progress = !a.quiet;
    Ok((c, a.json))
}

fn main() -> ExitCode {
    let (config, json) = match config(Args::parse()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("isovox-load: {e}");
            return ExitCode::from(2);
        }
    };
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("isovox-load: cannot start the async runtime: {e}");
            return ExitCode::from(2);
        }
    };
    // Ctrl-C ends the run early; the report covers what ran.
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    let report = match runtime.block_on(run_until(config, ctrl_c)) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("isovox-load: {e}");
            return ExitCode::from(2);
        }
    };
    print!("{}", report.to_markdown());
    if let Some(path) = json {
        let written = serde_json::to_vec_pretty(&report)
            .map_err(|e| e.to_string())
            .and_then(|b| std::fs::write(&path, b).map_err(|e| e.to_string()));
        if let Err(e) = written {
            eprintln!("isovox-load: cannot write {}: {e}", path.display());
            return ExitCode::from(2);
        }
    }
    if report.errors_total > 0 {
        eprintln!("isovox-load: {} errors", report.errors_total);
        return ExitCode::from(1);
    }
    ExitCode::SUCCESS
}
