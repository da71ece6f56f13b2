//! The load tester behind `isovox-load`: simulated viewers and editors against one server.
//!
//! A run starts `viewers + editors` users. Every user is a [`Streamer`] whose camera flies a
//! [`CameraPath`] (an orbit, a seeded random walk, or a recorded path), moved at
//! `camera_hz`; its event channel is drained and counted. Editors also send edits (carves and
//! additions of small ellipsoids at seeded random places) at `edit_rate` per second each. A
//! few dedicated change-feed subscribers time every acknowledged edit's version from the
//! editor's acknowledgement to its arrival on the feed. Editors and subscribers run on a runtime
//! thread of their own, so that the streamers' work does not delay their clocks.
//!
//! Every HTTP exchange of every client goes through one [`Recorder`] (an [`Observer`]): the
//! report's per-route requests, bytes, throughput and latency (time to the response's
//! headers, per attempt, so a retried call counts each attempt) come from it, with every
//! sample kept. A status other than 2xx and 304, or a transport failure, is an error.
//!
//! Users start at once, or spread over `ramp_up`. The run stops after `duration`, once
//! `max_requests` exchanges were made, or when the caller's stop future resolves
//! ([`run_until`]); editors then stop, and subscribers and streamers get up to `drain` to reach
//! the last acknowledged version (streamers also load what their still camera needs) before
//! they shut down.

use isovox_client::client::{Client, ClientError, FeedEvent, Observer};
use isovox_client::streamer::{StreamEvent, Streamer, StreamerConfig, StreamerStats, TileKind};
use isovox_proto::api::VolumeInfo;
use isovox_proto::icvg::{EditRequest, Term};
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, oneshot, watch};

/// What to stream.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tiles {
    /// Bricks (voxels).
    Bricks,
    /// Marching-cubes mesh tiles at `iso` (the server's default when `None`).
    Meshes { iso: Option<f32> },
}

/// How the cameras move (world units: voxels times the volume's voxel scale; y is up).
#[derive(Debug, Clone)]
pub enum PathSpec {
    /// A circle around the volume's vertical centre line. `radius` defaults to 35% of the
    /// smaller horizontal extent, `height` to 95% of the volume's height (above the demo
    /// terrain's hills); one turn takes `period_s`. Each viewer starts at its own angle, turns
    /// its own way, and varies the radius by up to 20%.
    Orbit {
        radius: Option<f32>,
        height: Option<f32>,
        period_s: f32,
    },
    /// A seeded random walk at `speed` units per second (default 5% of the larger horizontal
    /// extent), turning gradually, between `low` and `high` (default 60% and 100% of the
    /// height), bouncing off the volume's sides.
    RandomWalk {
        speed: Option<f32>,
        low: Option<f32>,
        high: Option<f32>,
    },
    /// A recorded path, played in a loop, each viewer from its own (seeded) point in it.
    Recorded(Arc<RecordedPath>),
}

impl PathSpec {
    fn name(&self) -> &'static str {
        match self {
            PathSpec::Orbit { .. } => "orbit",
            PathSpec::RandomWalk { .. } => "random-walk",
            PathSpec::Recorded(_) => "recorded",
        }
    }
}

/// A camera path from a file: one `t x y z` per line (seconds, world units), `t`
/// non-decreasing; blank lines and `#` comments are skipped. Positions between two lines are
/// interpolated linearly.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedPath {
    points: Vec<(f32, [f32; 3])>,
}

impl RecordedPath {
    /// Parses the text of a path file.
    ///
    /// # Errors
    /// A line that is not four numbers, a time before the previous one, or no point at all;
    /// the message names the line.
    pub fn parse(text: &str) -> Result<RecordedPath, String> {
        let mut points: Vec<(f32, [f32; 3])> = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let v: Vec<f32> = line
                .split_whitespace()
                .map(str::parse::<f32>)
                .collect::<Result<_, _>>()
                .map_err(|e| format!("line {}: {e}", i + 1))?;
            let [t, x, y, z] = v[..] else {
                return Err(format!(
                    "line {}: expected `t x y z`, found {} numbers",
                    i + 1,
                    v.len()
                ));
            };
            if v.iter().any(|f| !f.is_finite()) {
                return Err(format!("line {}: not a finite number", i + 1));
            }
            if points.last().is_some_and(|(last, _)| t < *last) {
                return Err(format!("line {}: time {t} before the previous one", i + 1));
            }
            points.push((t, [x, y, z]));
        }
        if points.is_empty() {
            return Err("no point in the path".into());
        }
        Ok(RecordedPath { points })
    }

    /// Seconds from the first point to the last.
    pub fn span(&self) -> f32 {
        match (self.points.first(), self.points.last()) {
            (Some(a), Some(b)) => b.0 - a.0,
            _ => 0.0,
        }
    }

    /// The position `t` seconds after the first point, looping at the end.
    pub fn at(&self, t: f32) -> [f32; 3] {
        let (first, span) = (self.points[0].0, self.span());
        if span <= 0.0 || self.points.len() == 1 {
            return self.points[0].1;
        }
        let t = first + t.rem_euclid(span);
        let i = self.points.partition_point(|(pt, _)| *pt <= t);
        if i == 0 {
            return self.points[0].1;
        }
        if i >= self.points.len() {
            return self.points[self.points.len() - 1].1;
        }
        let ((t0, a), (t1, b)) = (self.points[i - 1], self.points[i]);
        let f = if t1 > t0 { (t - t0) / (t1 - t0) } else { 0.0 };
        [0, 1, 2].map(|k| a[k] + (b[k] - a[k]) * f)
    }
}

/// A small seeded generator (SplitMix64): viewers and editors draw their own streams.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        let mut r = Rng(seed ^ 0x6a09_e667_f3bc_c909);
        r.next_u64();
        r
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
}

/// The volume's size in world units.
fn extent(info: &VolumeInfo) -> [f32; 3] {
    [0, 1, 2].map(|a| info.dims[a] as f32 * info.voxel_scale[a])
}

/// One camera's flight, sampled by time since its start.
#[derive(Debug, Clone)]
pub struct CameraPath(PathState);

#[derive(Debug, Clone)]
enum PathState {
    Orbit {
        centre: [f32; 2],
        radius: f32,
        height: f32,
        phase: f32,
        omega: f32,
    },
    Walk {
        pos: [f32; 3],
        heading: f32,
        climb: f32,
        speed: f32,
        min: [f32; 3],
        max: [f32; 3],
        last_t: f32,
        rng: Rng,
    },
    Recorded {
        path: Arc<RecordedPath>,
        offset: f32,
    },
}

impl CameraPath {
    /// The path `spec` over `info`'s volume for the viewer seeded `seed`.
    pub fn new(spec: &PathSpec, info: &VolumeInfo, seed: u64) -> CameraPath {
        let e = extent(info);
        let mut rng = Rng::new(seed);
        CameraPath(match spec {
            PathSpec::Orbit {
                radius,
                height,
                period_s,
            } => {
                let r = radius.unwrap_or(0.35 * e[0].min(e[2]));
                let dir = if rng.unit() < 0.5 { -1.0 } else { 1.0 };
                PathState::Orbit {
                    centre: [e[0] / 2.0, e[2] / 2.0],
                    radius: r * rng.range(0.8, 1.2),
                    height: height.unwrap_or(0.95 * e[1]),
                    phase: rng.range(0.0, std::f32::consts::TAU),
                    omega: dir * std::f32::consts::TAU / period_s.max(0.1),
                }
            }
            PathSpec::RandomWalk { speed, low, high } => {
                let lo = low.unwrap_or(0.6 * e[1]);
                let hi = high.unwrap_or(e[1]).max(lo);
                let min = [0.0, lo, 0.0];
                let max = [e[0], hi, e[2]];
                PathState::Walk {
                    pos: [0, 1, 2].map(|a| rng.range(min[a], max[a])),
                    heading: rng.range(0.0, std::f32::consts::TAU),
                    climb: 0.0,
                    speed: speed.unwrap_or(0.05 * e[0].max(e[2])),
                    min,
                    max,
                    last_t: 0.0,
                    rng,
                }
            }
            PathSpec::Recorded(path) => PathState::Recorded {
                offset: rng.range(0.0, path.span().max(0.0)),
                path: path.clone(),
            },
        })
    }

    /// The camera position `t` seconds after the start (a random walk moves forward only:
    /// earlier times return the current position).
    pub fn at(&mut self, t: f32) -> [f32; 3] {
        match &mut self.0 {
            PathState::Orbit {
                centre,
                radius,
                height,
                phase,
                omega,
            } => {
                let a = *phase + *omega * t;
                [
                    centre[0] + *radius * a.cos(),
                    *height,
                    centre[1] + *radius * a.sin(),
                ]
            }
            PathState::Walk {
                pos,
                heading,
                climb,
                speed,
                min,
                max,
                last_t,
                rng,
            } => {
                while *last_t < t {
                    let dt = (t - *last_t).min(0.05);
                    *last_t += dt;
                    // The heading and the climb rate wander; the speed stays.
                    *heading += rng.range(-4.0, 4.0) * dt;
                    *climb = (*climb + rng.range(-1.0, 1.0) * dt).clamp(-0.3, 0.3);
                    let v = [heading.cos(), *climb, heading.sin()];
                    for a in 0..3 {
                        pos[a] += v[a] * *speed * dt;
                        if pos[a] < min[a] || pos[a] > max[a] {
                            // Bounce: mirror the position and turn back.
                            pos[a] = pos[a].clamp(min[a], max[a]);
                            match a {
                                0 => *heading = std::f32::consts::PI - *heading,
                                1 => *climb = -*climb,
                                _ => *heading = -*heading,
                            }
                        }
                    }
                }
                *pos
            }
            PathState::Recorded { path, offset } => path.at(t + *offset),
        }
    }
}

/// A load run.
#[derive(Debug, Clone)]
pub struct LoadConfig {
    /// The server, e.g. `http://127.0.0.1:7070`.
    pub url: String,
    pub volume: String,
    /// Users who only view.
    pub viewers: usize,
    /// Users who view and edit.
    pub editors: usize,
    /// How long the run lasts (unless `max_requests` stops it first).
    pub duration: Duration,
    /// Stop once this many HTTP exchanges were made (checked every 50 ms).
    pub max_requests: Option<u64>,
    /// The write token editors send.
    pub token: Option<String>,
    pub tiles: Tiles,
    pub path: PathSpec,
    /// Camera updates per second.
    pub camera_hz: f64,
    /// Users start evenly spread over this time (all at once when zero); it counts in
    /// `duration`.
    pub ramp_up: Duration,
    /// Streamer detail radii (world units); when `None`, derived from `max_error_px`.
    pub radii: Option<Vec<f32>>,
    /// The screen-space error the radii are derived for (60 degree field of view, 1080-pixel
    /// viewport: [`StreamerConfig::radii_for_screen_error`]). 16 by default: the streamer's own
    /// default (1 pixel) asks for level 0 within about 1,900 units, all of the demo world, so
    /// that after the first load a moving camera would need nothing new.
    pub max_error_px: f32,
    /// Requests each streamer keeps in flight; the streamer's default when `None`.
    pub max_in_flight: Option<usize>,
    /// Each streamer's cache. 16 MiB by default (a streamer's own default is 256 MiB, and a run
    /// holds a hundred of them in one process).
    pub cache_bytes: usize,
    /// Edits per second per editor.
    pub edit_rate: f64,
    /// Radii of the edited ellipsoids, voxels (each axis drawn in `min..=max`).
    pub edit_radius: (u32, u32),
    /// The share of edits that carve (difference); the others add (union).
    pub carve_fraction: f64,
    /// Change-feed subscribers timing edit notifications; `min(viewers, 8)` (at least 1) when
    /// `None` and there are editors.
    pub subscribers: Option<usize>,
    pub seed: u64,
    /// How long, after the end, subscribers wait for the last notifications and streamers
    /// for their requests in flight.
    pub drain: Duration,
    /// Draw a progress bar on stderr (only when it is a terminal).
    pub progress: bool,
}

impl LoadConfig {
    /// A run with the defaults of `isovox-load`: 10 viewers, no editor, 30 s, bricks, orbits.
    pub fn new(url: &str, volume: &str) -> LoadConfig {
        LoadConfig {
            url: url.to_string(),
            volume: volume.to_string(),
            viewers: 10,
            editors: 0,
            duration: Duration::from_secs(30),
            max_requests: None,
            token: None,
            tiles: Tiles::Bricks,
            path: PathSpec::Orbit {
                radius: None,
                height: None,
                period_s: 60.0,
            },
            camera_hz: 30.0,
            ramp_up: Duration::ZERO,
            radii: None,
            max_error_px: 16.0,
            max_in_flight: None,
            cache_bytes: 16 << 20,
            edit_rate: 1.0,
            edit_radius: (4, 12),
            carve_fraction: 0.5,
            subscribers: None,
            seed: 1,
            drain: Duration::from_secs(10),
            progress: false,
        }
    }

    /// The streamers' configuration for `info`'s volume.
    pub fn streamer_config(&self, info: &VolumeInfo) -> StreamerConfig {
        let d = StreamerConfig::default();
        StreamerConfig {
            kind: match self.tiles {
                Tiles::Bricks => TileKind::Bricks,
                Tiles::Meshes { iso } => TileKind::Meshes { iso },
            },
            radii: self.radii.clone().unwrap_or_else(|| {
                StreamerConfig::radii_for_screen_error(
                    info,
                    60f32.to_radians(),
                    1080.0,
                    self.max_error_px,
                )
            }),
            max_in_flight: self.max_in_flight.unwrap_or(d.max_in_flight),
            cache_bytes: self.cache_bytes,
            follow_edits: true,
        }
    }

    fn subscriber_count(&self) -> usize {
        if self.editors == 0 {
            return 0;
        }
        self.subscribers.unwrap_or(self.viewers.clamp(1, 8))
    }
}

/// Why a run could not start.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{0}")]
    Config(String),
    #[error("cannot read the volume: {0}")]
    Client(#[from] ClientError),
}

/// Collects every HTTP exchange of every client of a run: per route, the outcomes, bytes and
/// every latency sample, and when each kind of failure was first and last seen.
#[derive(Debug)]
pub struct Recorder {
    start: Instant,
    routes: Mutex<BTreeMap<&'static str, RouteAcc>>,
    requests: AtomicU64,
    errors: AtomicU64,
}

impl Default for Recorder {
    fn default() -> Self {
        Recorder {
            start: Instant::now(),
            routes: Mutex::default(),
            requests: AtomicU64::new(0),
            errors: AtomicU64::new(0),
        }
    }
}

#[derive(Debug, Default)]
struct RouteAcc {
    bytes: u64,
    /// Microseconds, one per exchange.
    latencies: Vec<u32>,
    outcomes: BTreeMap<String, u64>,
    errors: u64,
    /// Seconds since the start when each failure kind was first and last seen.
    error_times: BTreeMap<String, (f64, f64)>,
}

impl Recorder {
    /// Exchanges so far.
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }

    /// Failed exchanges so far.
    pub fn errors(&self) -> u64 {
        self.errors.load(Ordering::Relaxed)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<&'static str, RouteAcc>> {
        self.routes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// Whether an exchange's outcome counts as a success: 2xx, and 304 (a revalidated brick).
fn is_success(outcome: Result<u16, &str>) -> bool {
    matches!(outcome, Ok(s) if (200..300).contains(&s) || s == 304)
}

impl Observer for Recorder {
    fn exchange(
        &self,
        route: &'static str,
        outcome: Result<u16, &str>,
        latency: Duration,
        bytes: u64,
    ) {
        let ok = is_success(outcome);
        let name = match outcome {
            Ok(s) => s.to_string(),
            Err(kind) => kind.to_string(),
        };
        {
            let mut routes = self.lock();
            let r = routes.entry(route).or_default();
            r.bytes += bytes;
            r.latencies
                .push(latency.as_micros().min(u128::from(u32::MAX)) as u32);
            if !ok {
                r.errors += 1;
                let t = self.start.elapsed().as_secs_f64();
                let span = r.error_times.entry(name.clone()).or_insert((t, t));
                span.1 = t;
            }
            *r.outcomes.entry(name).or_default() += 1;
        }
        self.requests.fetch_add(1, Ordering::Relaxed);
        if !ok {
            self.errors.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Latency percentiles (nearest rank), milliseconds.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Latency {
    pub samples: u64,
    pub p50: f64,
    pub p90: f64,
    pub p99: f64,
    pub max: f64,
    pub mean: f64,
}

impl Latency {
    /// From samples in microseconds (sorted in place).
    pub fn from_micros(samples: &mut [u32]) -> Latency {
        if samples.is_empty() {
            return Latency::default();
        }
        samples.sort_unstable();
        let n = samples.len();
        let rank = |p: f64| {
            let i = ((p / 100.0 * n as f64).ceil() as usize).clamp(1, n) - 1;
            f64::from(samples[i]) / 1000.0
        };
        let sum: u64 = samples.iter().map(|&s| u64::from(s)).sum();
        Latency {
            samples: n as u64,
            p50: rank(50.0),
            p90: rank(90.0),
            p99: rank(99.0),
            max: f64::from(samples[n - 1]) / 1000.0,
            mean: sum as f64 / n as f64 / 1000.0,
        }
    }

    fn from_durations(samples: &[Duration]) -> Latency {
        let mut us: Vec<u32> = samples
            .iter()
            .map(|d| d.as_micros().min(u128::from(u32::MAX)) as u32)
            .collect();
        Latency::from_micros(&mut us)
    }
}

/// One route's figures (`route` is the client's name for it: `brick`, `mesh`, `edit`, ...;
/// `all` for the sum).
#[derive(Debug, Clone, Serialize)]
pub struct RouteReport {
    pub route: String,
    /// Exchanges (every attempt of a retried call).
    pub requests: u64,
    /// 2xx answers.
    pub ok: u64,
    /// 304 answers (revalidated bricks).
    pub not_modified: u64,
    /// Other statuses and transport failures.
    pub errors: u64,
    /// Response body bytes (as announced by Content-Length; 0 for streams).
    pub bytes: u64,
    pub requests_per_s: f64,
    pub mib_per_s: f64,
    /// Time to the response's headers.
    pub latency_ms: Latency,
    /// Exchanges by status code or transport failure kind.
    pub outcomes: BTreeMap<String, u64>,
}

/// Errors of one kind from one source.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ErrorCount {
    /// A route (HTTP exchanges), or `streamer`, `feed`, `notification`, `edit`.
    pub source: String,
    /// A status code or transport failure kind, or what went wrong.
    pub kind: String,
    pub count: u64,
    /// Seconds after the run's start of the first and the last one (HTTP exchanges and
    /// streamer error events).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_s: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_s: Option<f64>,
}

/// What the editors did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct EditReport {
    pub editors: usize,
    /// Edits per second per editor asked for.
    pub rate_per_editor: f64,
    pub attempted: u64,
    pub acknowledged: u64,
    pub failed: u64,
    pub carves: u64,
    pub additions: u64,
    pub acknowledged_per_s: f64,
    /// From sending an edit to its acknowledgement (the whole call, retries included).
    pub latency_ms: Latency,
}

/// Edit-to-notification: from an edit's acknowledgement (as its editor received it) to the
/// arrival of its version on each dedicated change-feed subscriber.
#[derive(Debug, Clone, Default, Serialize)]
pub struct NotificationReport {
    pub subscribers: usize,
    /// Acknowledged edits times subscribers.
    pub expected: u64,
    pub seen: u64,
    pub missing: u64,
    /// Notifications that arrived before the editor had its acknowledgement (counted as 0).
    pub before_ack: u64,
    /// `resync` events (a subscriber fell behind; the gap was fetched from `changes`).
    pub resyncs: u64,
    /// Times a subscription broke and was resumed.
    pub reconnects: u64,
    /// From the acknowledgement to the arrival.
    pub latency_ms: Latency,
    /// From sending the edit to the arrival (the edit's own latency included).
    pub from_send_ms: Latency,
}

/// The streamers' side, summed over every user.
#[derive(Debug, Clone, Default, Serialize)]
pub struct StreamerReport {
    pub streamers: usize,
    /// Streamers that failed to start.
    pub failed_to_start: u64,
    /// Users the ramp-up had not reached when the run ended.
    pub never_started: u64,
    /// `Ready` events (tiles delivered), all levels.
    pub tiles_ready: u64,
    /// `Ready` tiles by level (level 0 first).
    pub ready_by_level: Vec<u64>,
    /// Bytes of the delivered tiles (decoded voxels, or mesh positions, normals and indices).
    pub ready_bytes: u64,
    pub dropped: u64,
    /// `Stale` events: tiles an edit changed.
    pub stale: u64,
    pub version_events: u64,
    pub error_events: u64,
    /// The first few error messages.
    pub error_samples: Vec<String>,
    /// The streamers' own counts ([`StreamerStats`]).
    pub requests: u64,
    pub bytes: u64,
    pub cache_hits: u64,
    pub cache_misses: u64,
    /// `cache_hits / (cache_hits + cache_misses)`.
    pub cache_hit_rate: f64,
    pub stale_refetches: u64,
    pub resident_at_end: u64,
    pub in_flight_at_end: u64,
    /// The streamers' limits on requests in flight at the end, summed: `max_in_flight` each,
    /// less where the server answered 503 and the limit has not grown back yet.
    pub in_flight_limit_at_end: u64,
    /// The newest version any streamer had reached at the end.
    pub max_version: u64,
    /// The oldest version a streamer had reached at the end.
    pub min_version: u64,
}

/// Everything a run measured.
#[derive(Debug, Clone, Serialize)]
pub struct LoadReport {
    pub url: String,
    pub volume: String,
    pub viewers: usize,
    pub editors: usize,
    pub tiles: String,
    pub path: String,
    /// The streamers' detail radii, world units (level k within `radii[k]`).
    pub radii: Vec<f32>,
    /// Requests each streamer keeps in flight.
    pub max_in_flight: usize,
    /// Each streamer's content cache, bytes.
    pub cache_bytes: usize,
    /// The configured duration.
    pub duration_s: f64,
    /// From the first request to the end of the drain; rates are per this.
    pub elapsed_s: f64,
    pub version_start: u64,
    pub version_end: u64,
    pub total: RouteReport,
    pub routes: Vec<RouteReport>,
    pub errors: Vec<ErrorCount>,
    /// The sum of `errors`; `isovox-load` exits non-zero when it is not 0.
    pub errors_total: u64,
    pub edits: EditReport,
    pub notifications: NotificationReport,
    pub streamers: StreamerReport,
}

/// One viewer's counts.
#[derive(Debug, Default)]
struct ViewerResult {
    started: bool,
    /// The run ended before the ramp-up reached this user.
    not_started: bool,
    radii: Vec<f32>,
    ready: u64,
    ready_by_level: Vec<u64>,
    ready_bytes: u64,
    dropped: u64,
    stale: u64,
    versions: u64,
    errors: u64,
    error_samples: Vec<String>,
    /// When the first and the last error event arrived.
    error_span: Option<(Instant, Instant)>,
    closed_early: bool,
    stats: Option<StreamerStats>,
}

impl ViewerResult {
    fn record(&mut self, event: StreamEvent) {
        match event {
            StreamEvent::Ready { key, data, .. } => {
                self.ready += 1;
                let l = usize::from(key.level);
                if self.ready_by_level.len() <= l {
                    self.ready_by_level.resize(l + 1, 0);
                }
                self.ready_by_level[l] += 1;
                self.ready_bytes += data.bytes();
            }
            StreamEvent::Dropped { .. } => self.dropped += 1,
            StreamEvent::Stale { .. } => self.stale += 1,
            StreamEvent::Version { .. } => self.versions += 1,
            StreamEvent::Error { key, error } => {
                self.errors += 1;
                let now = Instant::now();
                let span = self.error_span.get_or_insert((now, now));
                span.1 = now;
                if self.error_samples.len() < 5 {
                    self.error_samples.push(match key {
                        Some(k) => format!("{k}: {error}"),
                        None => error,
                    });
                }
            }
        }
    }
}

/// Runs `fut` while counting `rx`'s events.
async fn draining<F: Future>(
    rx: &mut mpsc::Receiver<StreamEvent>,
    result: &mut ViewerResult,
    fut: F,
) -> F::Output {
    tokio::pin!(fut);
    loop {
        tokio::select! {
            out = &mut fut => return out,
            event = rx.recv() => match event {
                Some(e) => result.record(e),
                None => return fut.await,
            },
        }
    }
}

/// One user's streamer: starts it, flies the camera until `stop`, lets it finish what it has
/// in flight, shuts it down.
async fn viewer(
    client: Client,
    config: Arc<LoadConfig>,
    streamer_config: StreamerConfig,
    mut path: CameraPath,
    delay: Duration,
    mut stop: watch::Receiver<bool>,
    mut until: watch::Receiver<Option<u64>>,
) -> ViewerResult {
    let mut result = ViewerResult::default();
    tokio::select! {
        () = tokio::time::sleep(delay) => {}
        _ = stop.wait_for(|s| *s) => {
            result.not_started = true;
            return result;
        }
    }
    let (streamer, mut rx) = match Streamer::start(client, &config.volume, streamer_config).await {
        Ok(s) => s,
        Err(e) => {
            result.errors += 1;
            result.error_samples.push(format!("streamer start: {e}"));
            return result;
        }
    };
    result.started = true;
    result.radii = streamer.radii().to_vec();
    let start = Instant::now();
    streamer.set_camera(path.at(0.0));
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / config.camera_hz.max(0.1)));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut open = true;
    while !*stop.borrow() {
        tokio::select! {
            changed = stop.changed() => if changed.is_err() { break },
            _ = tick.tick() => streamer.set_camera(path.at(start.elapsed().as_secs_f32())),
            event = rx.recv(), if open => match event {
                Some(e) => result.record(e),
                None => { open = false; result.closed_early = true; }
            },
        }
    }
    // The camera stops; once the editors are done, the streamer catches up with the last
    // acknowledged version and loads what the camera needs (or the drain time runs out).
    let catch_up = async {
        let last = match until.wait_for(Option::is_some).await {
            Ok(v) => v.unwrap_or(0),
            Err(_) => 0,
        };
        streamer.wait_version(last).await;
    };
    let _ = draining(
        &mut rx,
        &mut result,
        tokio::time::timeout(config.drain, catch_up),
    )
    .await;
    result.stats = Some(streamer.stats());
    draining(&mut rx, &mut result, streamer.shutdown()).await;
    result
}

/// One editor's counts.
#[derive(Debug, Default)]
struct EditorResult {
    attempted: u64,
    carves: u64,
    additions: u64,
    /// (version, sent at, acknowledged at).
    acks: Vec<(u64, Instant, Instant)>,
    failures: BTreeMap<String, u64>,
}

/// An ellipsoid carve or addition at a random place: x and z anywhere, y in the band the demo
/// terrain's surface lies in (15% to 85% of the height).
fn random_edit(rng: &mut Rng, info: &VolumeInfo, config: &LoadConfig) -> (bool, EditRequest) {
    let carve = f64::from(rng.unit()) < config.carve_fraction;
    let d = info.dims.map(|v| v as f32);
    let center = [
        rng.range(0.0, d[0]),
        rng.range(0.15 * d[1], 0.85 * d[1]),
        rng.range(0.0, d[2]),
    ]
    .map(|v| v as i64);
    let (lo, hi) = (
        config.edit_radius.0.max(1),
        config.edit_radius.1.max(config.edit_radius.0.max(1)),
    );
    let radii = [0; 3].map(|_| (lo + (rng.next_u64() % u64::from(hi - lo + 1)) as u32).max(1));
    let op = if carve { "difference" } else { "union" };
    (
        carve,
        EditRequest {
            op: op.into(),
            term: Some(Term::Ellipsoid { center, radii }),
            s_l: None,
            k: None,
            region: None,
        },
    )
}

async fn editor(
    client: Client,
    config: Arc<LoadConfig>,
    info: Arc<VolumeInfo>,
    seed: u64,
    delay: Duration,
    mut stop: watch::Receiver<bool>,
) -> EditorResult {
    let mut result = EditorResult::default();
    let mut rng = Rng::new(seed);
    let period = Duration::from_secs_f64(1.0 / config.edit_rate.max(0.001));
    // Editors start at different points of their period, so they do not edit in step.
    let first = tokio::time::Instant::now() + delay + period.mul_f32(rng.unit());
    let mut tick = tokio::time::interval_at(first, period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            changed = stop.changed() => if changed.is_err() || *stop.borrow() { break } else { continue },
            _ = tick.tick() => {}
        }
        if *stop.borrow() {
            break;
        }
        let (carve, request) = random_edit(&mut rng, &info, &config);
        result.attempted += 1;
        if carve {
            result.carves += 1;
        } else {
            result.additions += 1;
        }
        let sent = Instant::now();
        match client.edit(&config.volume, &request, None).await {
            Ok(r) => {
                result.acks.push((r.version, sent, Instant::now()));
            }
            Err(e) => *result.failures.entry(e.kind()).or_default() += 1,
        }
    }
    result
}

/// One dedicated change-feed subscriber's observations.
#[derive(Debug, Default)]
struct SubscriberResult {
    /// Arrival of each version.
    seen: HashMap<u64, Instant>,
    resyncs: u64,
    reconnects: u64,
    errors: BTreeMap<String, u64>,
}

/// Follows the change feed until `until` names a version it has seen (or the drain time after
/// it was set runs out). Sends the hello version on `ready` once subscribed.
async fn subscriber(
    client: Client,
    volume: String,
    drain: Duration,
    ready: oneshot::Sender<Result<u64, ClientError>>,
    mut until: watch::Receiver<Option<u64>>,
) -> SubscriberResult {
    let mut result = SubscriberResult::default();
    let mut feed = match client.events(&volume, None).await {
        Ok(f) => f,
        Err(e) => {
            let _ = ready.send(Err(e));
            return result;
        }
    };
    let mut last = match feed.next().await {
        Ok(Some(FeedEvent::Hello { version })) => version,
        Ok(other) => {
            let _ = ready.send(Err(ClientError::Decode(format!(
                "the feed began with {other:?}, not hello"
            ))));
            return result;
        }
        Err(e) => {
            let _ = ready.send(Err(e));
            return result;
        }
    };
    let _ = ready.send(Ok(last));
    let mut deadline: Option<tokio::time::Instant> = None;
    let mut until_open = true;
    loop {
        let target = *until.borrow();
        if target.is_some_and(|t| last >= t) {
            break;
        }
        let sleep = async {
            match deadline {
                Some(d) => tokio::time::sleep_until(d).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            changed = until.changed(), if until_open => {
                if changed.is_err() {
                    until_open = false;
                }
                if until.borrow().is_some() && deadline.is_none() {
                    deadline = Some(tokio::time::Instant::now() + drain);
                }
            }
            () = sleep => break,
            event = feed.next() => match event {
                Ok(Some(FeedEvent::Commit(c))) => {
                    result.seen.entry(c.version).or_insert_with(Instant::now);
                    last = last.max(c.version);
                }
                Ok(Some(FeedEvent::Hello { .. })) => {}
                Ok(Some(FeedEvent::Resync { since, version })) => {
                    result.resyncs += 1;
                    let mut from = since;
                    while from < version {
                        match client.changes(&volume, from, None).await {
                            Ok(list) => {
                                let now = Instant::now();
                                for c in &list.changes {
                                    result.seen.entry(c.version).or_insert(now);
                                    from = from.max(c.version);
                                }
                                if !list.more || list.changes.is_empty() {
                                    break;
                                }
                            }
                            Err(e) => {
                                *result.errors.entry(format!("changes {}", e.kind())).or_default() += 1;
                                break;
                            }
                        }
                    }
                    last = last.max(version);
                }
                Ok(None) | Err(_) => {
                    // The subscription broke: resume after the last version seen.
                    result.reconnects += 1;
                    *result.errors.entry("disconnected".into()).or_default() += 1;
                    loop {
                        match client.events(&volume, Some(last)).await {
                            Ok(f) => {
                                feed = f;
                                break;
                            }
                            Err(_) if deadline.is_some_and(|d| tokio::time::Instant::now() >= d) => {
                                return result;
                            }
                            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                        }
                    }
                }
            },
        }
    }
    result
}

/// The progress bar (hidden unless asked for and stderr is a terminal).
fn progress_bar(config: &LoadConfig) -> indicatif::ProgressBar {
    use std::io::IsTerminal;
    if !config.progress || !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(config.duration.as_secs().max(1));
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} s  {msg}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar
}

/// Runs the load test and reports what it measured.
///
/// # Errors
/// The volume cannot be read, the configuration is unusable (editors without a token), or a
/// change-feed subscriber could not subscribe. Failures during the run are counted in the
/// report, not returned.
pub async fn run(config: LoadConfig) -> Result<LoadReport, LoadError> {
    run_until(config, std::future::pending()).await
}

/// Aborts the tasks it holds when dropped: a run that fails to start leaves nothing behind.
#[derive(Debug, Default)]
struct Tasks(Vec<tokio::task::AbortHandle>);

impl Drop for Tasks {
    fn drop(&mut self) {
        for t in &self.0 {
            t.abort();
        }
    }
}

/// A runtime that may be dropped from async code (it shuts down in the background).
#[derive(Debug)]
struct SideRuntime(Option<tokio::runtime::Runtime>);

impl SideRuntime {
    fn handle(&self) -> tokio::runtime::Handle {
        match &self.0 {
            Some(r) => r.handle().clone(),
            None => tokio::runtime::Handle::current(),
        }
    }
}

impl Drop for SideRuntime {
    fn drop(&mut self) {
        if let Some(r) = self.0.take() {
            r.shutdown_background();
        }
    }
}

/// [`run`], ending early (with a report) when `stop` resolves, e.g. on Ctrl-C.
///
/// # Errors
/// As [`run`].
pub async fn run_until(
    config: LoadConfig,
    stop: impl Future<Output = ()>,
) -> Result<LoadReport, LoadError> {
    if config.editors > 0 && config.token.is_none() {
        return Err(LoadError::Config("editors need a write token".into()));
    }
    if config.viewers + config.editors == 0 {
        return Err(LoadError::Config("nobody to simulate".into()));
    }
    let started = Instant::now();
    let recorder = Arc::new(Recorder::default());
    let config = Arc::new(config);
    // Linked with the server library, reqwest's rustls needs ring installed as its provider.
    isovox_server::client_tls::install_provider();
    let make_client = || -> Result<Client, ClientError> {
        let c = Client::new(&config.url)?.with_observer(recorder.clone());
        Ok(match &config.token {
            Some(t) => c.with_token(t.clone()),
            None => c,
        })
    };
    let probe = make_client()?;
    let info = Arc::new(probe.volume(&config.volume).await?);
    let version_start = info.version;
    let streamer_config = config.streamer_config(&info);
    let (stop_tx, stop_rx) = watch::channel(false);
    // After the end: the last acknowledged version, for subscribers and streamers to reach.
    let (until_tx, until_rx) = watch::channel(None::<u64>);
    let seed_of = |role: u64, i: usize| {
        Rng::new(config.seed ^ (role << 56) ^ (i as u64).wrapping_mul(0x9e37_79b9)).next_u64()
    };

    // Editors and subscribers time edits: they run on a runtime of their own, so that a
    // hundred streamers busy on the main one do not stand between an event and its clock.
    let side_runtime = SideRuntime(Some(
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("isovox-load-edits")
            .enable_all()
            .build()
            .map_err(|e| LoadError::Config(format!("cannot start a runtime: {e}")))?,
    ));
    let side = side_runtime.handle();

    // Subscribers first, so that every acknowledged edit comes after their hello.
    let mut tasks = Tasks::default();
    let mut subscribers = Vec::new();
    let mut hellos = Vec::new();
    for _ in 0..config.subscriber_count() {
        let (tx, rx) = oneshot::channel();
        let task = side.spawn(subscriber(
            make_client()?,
            config.volume.clone(),
            config.drain,
            tx,
            until_rx.clone(),
        ));
        tasks.0.push(task.abort_handle());
        subscribers.push(task);
        hellos.push(rx);
    }
    for h in hellos {
        match h.await {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => return Err(LoadError::Client(e)),
            Err(_) => return Err(LoadError::Config("a subscriber stopped".into())),
        }
    }

    let users = config.viewers + config.editors;
    // User i starts at i/users of the ramp-up (editors are the last users).
    let ramp = |i: usize| config.ramp_up.mul_f64(i as f64 / users as f64);
    let mut viewers = Vec::with_capacity(users);
    for i in 0..users {
        let task = tokio::spawn(viewer(
            make_client()?,
            config.clone(),
            streamer_config.clone(),
            CameraPath::new(&config.path, &info, seed_of(1, i)),
            ramp(i),
            stop_rx.clone(),
            until_rx.clone(),
        ));
        tasks.0.push(task.abort_handle());
        viewers.push(task);
    }
    let mut editors = Vec::with_capacity(config.editors);
    for i in 0..config.editors {
        let task = side.spawn(editor(
            make_client()?,
            config.clone(),
            info.clone(),
            seed_of(2, i),
            ramp(config.viewers + i),
            stop_rx.clone(),
        ));
        tasks.0.push(task.abort_handle());
        editors.push(task);
    }

    // Run until the time is up or enough requests were made.
    let bar = progress_bar(&config);
    let run_start = Instant::now();
    let mut window: std::collections::VecDeque<(Instant, u64)> = Default::default();
    let mut tick = tokio::time::interval(Duration::from_millis(50));
    tokio::pin!(stop);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = &mut stop => break,
        }
        let now = Instant::now();
        let requests = recorder.requests();
        if now - run_start >= config.duration || config.max_requests.is_some_and(|n| requests >= n)
        {
            break;
        }
        window.push_back((now, requests));
        while window
            .front()
            .is_some_and(|(t, _)| now - *t > Duration::from_secs(1))
        {
            window.pop_front();
        }
        if let Some((t0, r0)) = window.front() {
            let dt = (now - *t0).as_secs_f64();
            let rate = if dt > 0.0 {
                (requests - r0) as f64 / dt
            } else {
                0.0
            };
            bar.set_position((now - run_start).as_secs());
            bar.set_message(format!(
                "{rate:.0} req/s, {requests} requests, {} errors",
                recorder.errors()
            ));
        }
    }
    bar.set_message("draining");
    let _ = stop_tx.send(true);

    let mut editor_results = Vec::new();
    for e in editors {
        if let Ok(r) = e.await {
            editor_results.push(r);
        }
    }
    let last_version = editor_results
        .iter()
        .flat_map(|e| e.acks.iter().map(|a| a.0))
        .max()
        .unwrap_or(version_start);
    let _ = until_tx.send(Some(last_version));
    let mut subscriber_results = Vec::with_capacity(subscribers.len());
    for s in subscribers {
        if let Ok(r) = s.await {
            subscriber_results.push(r);
        }
    }
    let mut viewer_results = Vec::new();
    for v in viewers {
        if let Ok(r) = v.await {
            viewer_results.push(r);
        }
    }
    bar.finish_and_clear();
    let elapsed = started.elapsed();
    let version_end = probe
        .volume(&config.volume)
        .await
        .map_or(last_version, |i| i.version);

    Ok(report(
        &config,
        &recorder,
        elapsed,
        (version_start, version_end),
        &editor_results,
        &subscriber_results,
        &viewer_results,
    ))
}

fn report(
    config: &LoadConfig,
    recorder: &Recorder,
    elapsed: Duration,
    (version_start, version_end): (u64, u64),
    editors: &[EditorResult],
    subscribers: &[SubscriberResult],
    viewers: &[ViewerResult],
) -> LoadReport {
    let secs = elapsed.as_secs_f64().max(1e-9);
    let mut errors = Vec::new();

    // Routes.
    let mut routes = Vec::new();
    let mut all_latencies = Vec::new();
    let mut all_outcomes: BTreeMap<String, u64> = BTreeMap::new();
    let (mut all_bytes, mut all_errors) = (0, 0);
    {
        let mut accs = recorder.lock();
        for (route, acc) in accs.iter_mut() {
            all_latencies.extend_from_slice(&acc.latencies);
            for (k, v) in &acc.outcomes {
                *all_outcomes.entry(k.clone()).or_default() += v;
                let ok = k.parse::<u16>().is_ok_and(|s| is_success(Ok(s)));
                if !ok {
                    let times = acc.error_times.get(k);
                    errors.push(ErrorCount {
                        source: (*route).to_string(),
                        kind: k.clone(),
                        count: *v,
                        first_s: times.map(|t| t.0),
                        last_s: times.map(|t| t.1),
                    });
                }
            }
            all_bytes += acc.bytes;
            all_errors += acc.errors;
            routes.push(route_report(
                route,
                acc.bytes,
                acc.errors,
                &mut acc.latencies,
                &acc.outcomes,
                secs,
            ));
        }
    }
    let total = route_report(
        "all",
        all_bytes,
        all_errors,
        &mut all_latencies,
        &all_outcomes,
        secs,
    );

    // Edits.
    let mut edit_latencies = Vec::new();
    let mut acks: HashMap<u64, (Instant, Instant)> = HashMap::new();
    let mut edits = EditReport {
        editors: config.editors,
        rate_per_editor: config.edit_rate,
        ..EditReport::default()
    };
    let mut edit_failures: BTreeMap<String, u64> = BTreeMap::new();
    for e in editors {
        edits.attempted += e.attempted;
        edits.carves += e.carves;
        edits.additions += e.additions;
        edits.acknowledged += e.acks.len() as u64;
        for (version, sent, acked) in &e.acks {
            acks.insert(*version, (*sent, *acked));
            edit_latencies.push(acked.saturating_duration_since(*sent));
        }
        for (k, v) in &e.failures {
            edits.failed += v;
            *edit_failures.entry(k.clone()).or_default() += v;
        }
    }
    edits.acknowledged_per_s = edits.acknowledged as f64 / secs;
    edits.latency_ms = Latency::from_durations(&edit_latencies);
    // HTTP failures of edits are counted with the route; the others (an answer that did not
    // decode) only here.
    for (kind, count) in edit_failures {
        if kind == "decode" {
            errors.push(ErrorCount {
                source: "edit".into(),
                kind,
                count,
                first_s: None,
                last_s: None,
            });
        }
    }

    // Notifications.
    let mut notifications = NotificationReport {
        subscribers: subscribers.len(),
        ..NotificationReport::default()
    };
    let (mut note_latencies, mut from_send) = (Vec::new(), Vec::new());
    for s in subscribers {
        notifications.resyncs += s.resyncs;
        notifications.reconnects += s.reconnects;
        for (version, (sent, acked)) in &acks {
            notifications.expected += 1;
            match s.seen.get(version) {
                Some(arrived) => {
                    notifications.seen += 1;
                    if arrived < acked {
                        notifications.before_ack += 1;
                    }
                    note_latencies.push(arrived.saturating_duration_since(*acked));
                    from_send.push(arrived.saturating_duration_since(*sent));
                }
                None => notifications.missing += 1,
            }
        }
        for (kind, count) in &s.errors {
            errors.push(ErrorCount {
                source: "feed".into(),
                kind: kind.clone(),
                count: *count,
                first_s: None,
                last_s: None,
            });
        }
    }
    notifications.latency_ms = Latency::from_durations(&note_latencies);
    notifications.from_send_ms = Latency::from_durations(&from_send);
    if notifications.missing > 0 {
        errors.push(ErrorCount {
            source: "notification".into(),
            kind: "missing".into(),
            count: notifications.missing,
            first_s: None,
            last_s: None,
        });
    }

    // Streamers.
    let mut st = StreamerReport {
        streamers: viewers.len(),
        min_version: u64::MAX,
        ..StreamerReport::default()
    };
    let mut closed_early = 0;
    let mut error_span: Option<(Instant, Instant)> = None;
    for v in viewers {
        if v.not_started {
            st.never_started += 1;
        } else if !v.started {
            st.failed_to_start += 1;
        }
        st.tiles_ready += v.ready;
        if st.ready_by_level.len() < v.ready_by_level.len() {
            st.ready_by_level.resize(v.ready_by_level.len(), 0);
        }
        for (l, n) in v.ready_by_level.iter().enumerate() {
            st.ready_by_level[l] += n;
        }
        st.ready_bytes += v.ready_bytes;
        st.dropped += v.dropped;
        st.stale += v.stale;
        st.version_events += v.versions;
        st.error_events += v.errors;
        for m in &v.error_samples {
            if st.error_samples.len() < 10 {
                st.error_samples.push(m.clone());
            }
        }
        if v.closed_early {
            closed_early += 1;
        }
        if let Some((a, b)) = v.error_span {
            let span = error_span.get_or_insert((a, b));
            *span = (span.0.min(a), span.1.max(b));
        }
        if let Some(s) = &v.stats {
            st.requests += s.requests;
            st.bytes += s.bytes;
            st.cache_hits += s.cache_hits;
            st.cache_misses += s.cache_misses;
            st.stale_refetches += s.stale_refetches;
            st.resident_at_end += s.resident as u64;
            st.in_flight_at_end += s.in_flight as u64;
            st.in_flight_limit_at_end += s.in_flight_limit as u64;
            st.max_version = st.max_version.max(s.version);
            st.min_version = st.min_version.min(s.version);
        }
    }
    if st.min_version == u64::MAX {
        st.min_version = 0;
    }
    let lookups = st.cache_hits + st.cache_misses;
    st.cache_hit_rate = if lookups > 0 {
        st.cache_hits as f64 / lookups as f64
    } else {
        0.0
    };
    let since_start = |t: Instant| t.saturating_duration_since(recorder.start).as_secs_f64();
    for (kind, count, span) in [
        ("error event", st.error_events, error_span),
        ("closed early", closed_early, None),
    ] {
        if count > 0 {
            errors.push(ErrorCount {
                source: "streamer".into(),
                kind: kind.into(),
                count,
                first_s: span.map(|s| since_start(s.0)),
                last_s: span.map(|s| since_start(s.1)),
            });
        }
    }
    let errors_total = errors.iter().map(|e| e.count).sum();

    LoadReport {
        url: config.url.clone(),
        volume: config.volume.clone(),
        viewers: config.viewers,
        editors: config.editors,
        tiles: match config.tiles {
            Tiles::Bricks => "bricks".into(),
            Tiles::Meshes { .. } => "meshes".into(),
        },
        path: config.path.name().into(),
        radii: viewers
            .iter()
            .find(|v| v.started)
            .map(|v| v.radii.clone())
            .unwrap_or_default(),
        max_in_flight: config
            .max_in_flight
            .unwrap_or(StreamerConfig::default().max_in_flight),
        cache_bytes: config.cache_bytes,
        duration_s: config.duration.as_secs_f64(),
        elapsed_s: secs,
        version_start,
        version_end,
        total,
        routes,
        errors,
        errors_total,
        edits,
        notifications,
        streamers: st,
    }
}

fn route_report(
    route: &str,
    bytes: u64,
    errors: u64,
    latencies: &mut [u32],
    outcomes: &BTreeMap<String, u64>,
    secs: f64,
) -> RouteReport {
    let requests = latencies.len() as u64;
    let count = |f: &dyn Fn(u16) -> bool| {
        outcomes
            .iter()
            .filter(|(k, _)| k.parse::<u16>().is_ok_and(f))
            .map(|(_, v)| v)
            .sum()
    };
    RouteReport {
        route: route.to_string(),
        requests,
        ok: count(&|s| (200..300).contains(&s)),
        not_modified: count(&|s| s == 304),
        errors,
        bytes,
        requests_per_s: requests as f64 / secs,
        mib_per_s: bytes as f64 / secs / f64::from(1u32 << 20),
        latency_ms: Latency::from_micros(latencies),
        outcomes: outcomes.clone(),
    }
}

fn plural(n: usize) -> &'static str {
    if n == 1 {
        ""
    } else {
        "s"
    }
}

impl LoadReport {
    /// The report as Markdown tables.
    pub fn to_markdown(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "## isovox-load: {} viewer{} + {} editor{}, {} along {} paths over `{}`, {:.1} s (asked {} s)\n",
            self.viewers,
            plural(self.viewers),
            self.editors,
            plural(self.editors),
            self.tiles,
            self.path,
            self.volume,
            self.elapsed_s,
            self.duration_s
        );
        let radii: Vec<String> = self.radii.iter().map(|r| format!("{r:.0}")).collect();
        let _ = writeln!(
            s,
            "Server {}, versions {} -> {}. Streamers: radii {}, at most {} requests in flight (halved \
             on a 503; {} in all at the end), {} MiB cache each. Latency: time to the response's \
             headers, every attempt.\n",
            self.url,
            self.version_start,
            self.version_end,
            radii.join(", "),
            self.max_in_flight,
            self.streamers.in_flight_limit_at_end,
            self.cache_bytes >> 20
        );
        let _ = writeln!(
            s,
            "| route | requests | 2xx | 304 | errors | MiB | req/s | MiB/s | p50 ms | p90 ms | p99 ms | max ms |"
        );
        let _ = writeln!(
            s,
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        );
        for r in self.routes.iter().chain(std::iter::once(&self.total)) {
            let l = &r.latency_ms;
            let name = if r.route == "all" {
                "**all**".to_string()
            } else {
                format!("`{}`", r.route)
            };
            let _ = writeln!(
                s,
                "| {name} | {} | {} | {} | {} | {:.2} | {:.0} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} |",
                r.requests,
                r.ok,
                r.not_modified,
                r.errors,
                r.bytes as f64 / f64::from(1u32 << 20),
                r.requests_per_s,
                r.mib_per_s,
                l.p50,
                l.p90,
                l.p99,
                l.max
            );
        }
        let _ = writeln!(s);
        if self.errors.is_empty() {
            let _ = writeln!(s, "Errors: **0**.\n");
        } else {
            let _ = writeln!(s, "Errors: **{}**.\n", self.errors_total);
            let _ = writeln!(
                s,
                "| source | kind | count | first at | last at |\n|---|---|---:|---:|---:|"
            );
            let at = |t: Option<f64>| t.map_or(String::new(), |t| format!("{t:.1} s"));
            for e in &self.errors {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {} |",
                    e.source,
                    e.kind,
                    e.count,
                    at(e.first_s),
                    at(e.last_s)
                );
            }
            let _ = writeln!(s);
        }
        let e = &self.edits;
        if e.editors > 0 {
            let l = &e.latency_ms;
            let _ = writeln!(
                s,
                "| edits | attempted | acknowledged | failed | carves | additions | per s | p50 ms | p90 ms | p99 ms | max ms |"
            );
            let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
            let _ = writeln!(
                s,
                "| {} editor{} at {}/s | {} | {} | {} | {} | {} | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} |\n",
                e.editors,
                plural(e.editors),
                e.rate_per_editor,
                e.attempted,
                e.acknowledged,
                e.failed,
                e.carves,
                e.additions,
                e.acknowledged_per_s,
                l.p50,
                l.p90,
                l.p99,
                l.max
            );
            let n = &self.notifications;
            let l = &n.latency_ms;
            let _ = writeln!(
                s,
                "| edit to notification | expected | seen | missing | before ack | resyncs | reconnects | p50 ms | p90 ms | p99 ms | max ms |"
            );
            let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
            let _ = writeln!(
                s,
                "| {} subscriber{}, from the ack | {} | {} | {} | {} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} |",
                n.subscribers,
                plural(n.subscribers),
                n.expected,
                n.seen,
                n.missing,
                n.before_ack,
                n.resyncs,
                n.reconnects,
                l.p50,
                l.p90,
                l.p99,
                l.max
            );
            let l = &n.from_send_ms;
            let _ = writeln!(
                s,
                "| from sending the edit | | | | | | | {:.2} | {:.2} | {:.2} | {:.2} |\n",
                l.p50, l.p90, l.p99, l.max
            );
        }
        let t = &self.streamers;
        let _ = writeln!(
            s,
            "| streamers | tiles ready | MiB ready | dropped | stale | stale refetches | cache hits | cache misses | hit rate | resident at end | versions at end |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|");
        let _ = writeln!(
            s,
            "| {} | {} | {:.2} | {} | {} | {} | {} | {} | {:.1}% | {} | {}..{} |\n",
            t.streamers,
            t.tiles_ready,
            t.ready_bytes as f64 / f64::from(1u32 << 20),
            t.dropped,
            t.stale,
            t.stale_refetches,
            t.cache_hits,
            t.cache_misses,
            t.cache_hit_rate * 100.0,
            t.resident_at_end,
            t.min_version,
            t.max_version
        );
        let levels: Vec<String> = t
            .ready_by_level
            .iter()
            .enumerate()
            .map(|(l, n)| format!("L{l} {n}"))
            .collect();
        let _ = writeln!(s, "Tiles ready by level: {}.", levels.join(", "));
        if t.failed_to_start > 0 || t.never_started > 0 {
            let _ = writeln!(
                s,
                "\n{} streamers failed to start; the ramp-up never reached {} users.",
                t.failed_to_start, t.never_started
            );
        }
        if !t.error_samples.is_empty() {
            let _ = writeln!(s, "\nStreamer errors (first {}):", t.error_samples.len());
            for m in &t.error_samples {
                let _ = writeln!(s, "- {m}");
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recorded_paths_parse_and_interpolate() {
        let p =
            RecordedPath::parse("# t x y z\n0 0 0 0\n\n2 10 20 30  # two seconds\n4 10 20 50\n")
                .unwrap();
        assert_eq!(p.span(), 4.0);
        assert_eq!(p.at(0.0), [0.0, 0.0, 0.0]);
        assert_eq!(p.at(1.0), [5.0, 10.0, 15.0]);
        assert_eq!(p.at(3.0), [10.0, 20.0, 40.0]);
        // It loops.
        assert_eq!(p.at(5.0), [5.0, 10.0, 15.0]);
        assert!(RecordedPath::parse("0 1 2").unwrap_err().contains("line 1"));
        assert!(RecordedPath::parse("1 0 0 0\n0 0 0 0")
            .unwrap_err()
            .contains("line 2"));
        assert!(RecordedPath::parse("# nothing\n").is_err());
        assert_eq!(
            RecordedPath::parse("3 1 2 3").unwrap().at(7.0),
            [1.0, 2.0, 3.0]
        );
    }

    #[test]
    fn percentiles_by_nearest_rank() {
        let mut v: Vec<u32> = (1..=1000).rev().map(|i| i * 1000).collect();
        let l = Latency::from_micros(&mut v);
        assert_eq!(l.samples, 1000);
        assert_eq!((l.p50, l.p90, l.p99, l.max), (500.0, 900.0, 990.0, 1000.0));
        assert_eq!(l.mean, 500.5);
        assert_eq!(Latency::from_micros(&mut []), Latency::default());
    }

    fn info() -> VolumeInfo {
        let layout =
            isovox_proto::VolumeLayout::new([512, 256, 512], 32, isovox_proto::VoxelType::U8)
                .unwrap();
        VolumeInfo::new("demo", &layout, [1.0; 3], 1)
    }

    #[test]
    fn paths_stay_in_their_bounds_and_differ_by_seed() {
        let info = info();
        let orbit = PathSpec::Orbit {
            radius: None,
            height: None,
            period_s: 10.0,
        };
        let (mut a, mut b) = (
            CameraPath::new(&orbit, &info, 1),
            CameraPath::new(&orbit, &info, 2),
        );
        assert_ne!(a.at(0.0), b.at(0.0));
        for i in 0..100 {
            let p = a.at(i as f32 * 0.1);
            let r = ((p[0] - 256.0).powi(2) + (p[2] - 256.0).powi(2)).sqrt();
            assert!(
                (0.8 * 179.2 - 0.01..=1.2 * 179.2 + 0.01).contains(&r),
                "{r}"
            );
            assert_eq!(p[1], 0.95 * 256.0);
        }
        let walk = PathSpec::RandomWalk {
            speed: Some(100.0),
            low: None,
            high: None,
        };
        let (mut a, mut b) = (
            CameraPath::new(&walk, &info, 1),
            CameraPath::new(&walk, &info, 1),
        );
        let mut moved = 0.0f32;
        let mut last = a.at(0.0);
        for i in 0..600 {
            let t = i as f32 / 30.0;
            let p = a.at(t);
            assert_eq!(p, b.at(t), "the same seed walks the same way");
            assert!((0.0..=512.0).contains(&p[0]) && (0.0..=512.0).contains(&p[2]));
            assert!((0.6 * 256.0..=256.0).contains(&p[1]), "{p:?}");
            moved += (0..3).map(|k| (p[k] - last[k]).powi(2)).sum::<f32>().sqrt();
            last = p;
        }
        // 100 units/s for 20 s, less what the bounces clip, more what the climbing adds.
        assert!((1500.0..=2100.0).contains(&moved), "{moved}");
    }

    #[test]
    fn edits_land_inside_the_volume() {
        let info = info();
        let config = LoadConfig::new("http://x", "demo");
        let mut rng = Rng::new(5);
        let (mut carves, mut adds) = (0, 0);
        for _ in 0..1000 {
            let (carve, e) = random_edit(&mut rng, &info, &config);
            if carve {
                carves += 1;
                assert_eq!(e.op, "difference");
            } else {
                adds += 1;
                assert_eq!(e.op, "union");
            }
            let Some(Term::Ellipsoid { center, radii }) = e.term else {
                panic!("{e:?}")
            };
            assert!(center[0] >= 0 && center[0] < 512 && center[2] >= 0 && center[2] < 512);
            assert!(center[1] >= 38 && center[1] < 218);
            assert!(radii.iter().all(|r| (4..=12).contains(r)));
        }
        assert!(carves > 400 && adds > 400);
    }
}
