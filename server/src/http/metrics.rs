//! Prometheus metrics: requests by route and status, latency histograms by route, bytes sent,
//! mesh cache hits and misses, CPU queue depth. Recorded by a tower layer, rendered as text.

use super::AppState;
use axum::extract::State;
use axum::http::{header, Request};
use axum::response::{IntoResponse, Response};
use std::fmt::Write;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;

/// Upper bounds of the latency buckets, seconds.
const BUCKETS: [f64; 14] = [
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// Status codes are counted in a table indexed by the code (codes outside it are not counted).
const STATUSES: usize = 600;

/// One route's counters, lock-free: requests by status code, and a latency histogram.
#[derive(Debug)]
struct RouteMetrics {
    by_status: Box<[AtomicU64]>,
    buckets: [AtomicU64; BUCKETS.len()],
    count: AtomicU64,
    sum_micros: AtomicU64,
}

impl Default for RouteMetrics {
    fn default() -> Self {
        RouteMetrics {
            by_status: (0..STATUSES).map(|_| AtomicU64::new(0)).collect(),
            buckets: std::array::from_fn(|_| AtomicU64::new(0)),
            count: AtomicU64::new(0),
            sum_micros: AtomicU64::new(0),
        }
    }
}

/// One shard of every counter. Each thread records into its own shard, so the counters of a
/// request touch no cache line another core is writing (shared counters cost the brick routes
/// measurable throughput); `/metrics` sums the shards.
#[derive(Debug)]
#[repr(align(128))]
struct Shard {
    routes: Box<[RouteMetrics]>,
    bytes_sent: AtomicU64,
}

thread_local! {
    /// This thread's number, given out in turn at its first request; it picks the thread's
    /// shard (threads beyond the shard count share shards: still correct, only slower).
    static THREAD: usize = {
        static NEXT: AtomicUsize = AtomicUsize::new(0);
        NEXT.fetch_add(1, Ordering::Relaxed)
    };
}

/// The server's counters, by route template (the router's, see [`super::ROUTES`]; requests
/// matching none are counted as "unmatched"). Recording a request costs no lock and no
/// allocation.
#[derive(Debug)]
pub struct Metrics {
    /// Route templates, `unmatched` last.
    names: Vec<&'static str>,
    /// Path to index in `names`, matched by the same rules as axum's router (both use matchit).
    matcher: matchit::Router<usize>,
    shards: Box<[Shard]>,
}

impl Metrics {
    /// Counters for these route templates.
    ///
    /// # Panics
    /// A template is not valid route syntax, or two conflict (a programming error: the router
    /// would refuse them too).
    pub fn new(routes: &[&'static str]) -> Self {
        let mut matcher = matchit::Router::new();
        for (i, r) in routes.iter().enumerate() {
            #[allow(clippy::expect_used)]
            matcher
                .insert(*r, i)
                .expect("route templates are valid and distinct");
        }
        let names: Vec<_> = routes.iter().copied().chain(["unmatched"]).collect();
        // One shard per core: the async workers, which record the requests, are as many.
        let cores = std::thread::available_parallelism().map_or(4, usize::from);
        let shards = (0..cores)
            .map(|_| Shard {
                routes: names.iter().map(|_| RouteMetrics::default()).collect(),
                bytes_sent: AtomicU64::new(0),
            })
            .collect();
        Metrics {
            names,
            matcher,
            shards,
        }
    }

    /// The index of the route `path` takes.
    fn route_of(&self, path: &str) -> usize {
        self.matcher
            .at(path)
            .map_or(self.names.len() - 1, |m| *m.value)
    }

    /// The template of route `route` ("unmatched" for requests matching none).
    fn route_name(&self, route: usize) -> &'static str {
        self.names.get(route).copied().unwrap_or("unmatched")
    }

    fn record(&self, route: usize, status: u16, seconds: f64, bytes: u64) {
        let shard = &self.shards[THREAD.with(|t| *t) % self.shards.len()];
        let Some(m) = shard.routes.get(route) else {
            return;
        };
        if let Some(c) = m.by_status.get(status as usize) {
            c.fetch_add(1, Ordering::Relaxed);
        }
        // One bucket per request (cumulated when rendered).
        if let Some(i) = BUCKETS.iter().position(|b| seconds <= *b) {
            m.buckets[i].fetch_add(1, Ordering::Relaxed);
        }
        m.count.fetch_add(1, Ordering::Relaxed);
        m.sum_micros
            .fetch_add((seconds * 1e6) as u64, Ordering::Relaxed);
        shard.bytes_sent.fetch_add(bytes, Ordering::Relaxed);
    }

    /// A counter of route `route` summed over the shards.
    fn sum(&self, route: usize, counter: impl Fn(&RouteMetrics) -> &AtomicU64) -> u64 {
        self.shards
            .iter()
            .map(|s| counter(&s.routes[route]).load(Ordering::Relaxed))
            .sum()
    }

    fn bytes_sent(&self) -> u64 {
        self.shards
            .iter()
            .map(|s| s.bytes_sent.load(Ordering::Relaxed))
            .sum()
    }
}

/// Times every request and counts it under its route template. A plain tower layer around the
/// whole router (not `middleware::from_fn`, which boxes a future per request, nor a layer per
/// route, which boxes the route's service again): on the brick routes every allocation shows
/// in the throughput.
#[derive(Debug, Clone)]
pub struct MetricsLayer {
    metrics: Arc<Metrics>,
}

impl MetricsLayer {
    /// A layer counting into `metrics`.
    pub fn new(metrics: Arc<Metrics>) -> Self {
        MetricsLayer { metrics }
    }
}

impl<S> tower::Layer<S> for MetricsLayer {
    type Service = MetricsService<S>;

    fn layer(&self, inner: S) -> MetricsService<S> {
        MetricsService {
            inner,
            metrics: self.metrics.clone(),
        }
    }
}

/// See [`MetricsLayer`].
#[derive(Debug, Clone)]
pub struct MetricsService<S> {
    inner: S,
    metrics: Arc<Metrics>,
}

impl<S, B> tower::Service<Request<B>> for MetricsService<S>
where
    S: tower::Service<Request<B>, Response = Response>,
{
    type Response = Response;
    type Error = S::Error;
    type Future = MetricsFuture<S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<B>) -> Self::Future {
        let route = self.metrics.route_of(request.uri().path());
        MetricsFuture {
            inner: self.inner.call(request),
            metrics: self.metrics.clone(),
            route,
            start: Instant::now(),
        }
    }
}

pin_project_lite::pin_project! {
    /// The response future of [`MetricsService`]: records the request when it completes.
    pub struct MetricsFuture<F> {
        #[pin]
        inner: F,
        metrics: Arc<Metrics>,
        route: usize,
        start: Instant,
    }
}

impl<F, E> Future for MetricsFuture<F>
where
    F: Future<Output = Result<Response, E>>,
{
    type Output = Result<Response, E>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let this = self.project();
        let result = std::task::ready!(this.inner.poll(cx));
        if let Ok(response) = &result {
            // The body's exact size when known (Content-Length is added later, by the server).
            let bytes = axum::body::HttpBody::size_hint(response.body())
                .exact()
                .unwrap_or(0);
            let (status, seconds) = (
                response.status().as_u16(),
                this.start.elapsed().as_secs_f64(),
            );
            this.metrics.record(*this.route, status, seconds, bytes);
            tracing::debug!(
                route = this.metrics.route_name(*this.route),
                status,
                seconds,
                "request"
            );
        }
        Poll::Ready(result)
    }
}

/// `GET /metrics` in the Prometheus text format.
pub async fn metrics(State(state): State<AppState>) -> Response {
    let mut out = String::new();
    requests(&state.metrics, &mut out);
    gauges(&state, &mut out);
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}

/// Requests by route and status, and the latency histogram by route.
fn requests(m: &Metrics, out: &mut String) {
    let _ = writeln!(out, "# HELP isovox_requests_total HTTP requests by route and status.\n# TYPE isovox_requests_total counter");
    for (i, route) in m.names.iter().enumerate() {
        for status in 0..STATUSES {
            let n = m.sum(i, |r| &r.by_status[status]);
            if n > 0 {
                let _ = writeln!(
                    out,
                    "isovox_requests_total{{route=\"{route}\",status=\"{status}\"}} {n}"
                );
            }
        }
    }
    let _ = writeln!(out, "# HELP isovox_request_seconds Request latency by route.\n# TYPE isovox_request_seconds histogram");
    for (i, route) in m.names.iter().enumerate() {
        let count = m.sum(i, |r| &r.count);
        if count == 0 {
            continue;
        }
        let mut cumulative = 0;
        for (b, bound) in BUCKETS.iter().enumerate() {
            cumulative += m.sum(i, |r| &r.buckets[b]);
            let _ = writeln!(
                out,
                "isovox_request_seconds_bucket{{route=\"{route}\",le=\"{bound}\"}} {cumulative}"
            );
        }
        let _ = writeln!(
            out,
            "isovox_request_seconds_bucket{{route=\"{route}\",le=\"+Inf\"}} {count}"
        );
        let _ = writeln!(
            out,
            "isovox_request_seconds_sum{{route=\"{route}\"}} {}",
            m.sum(i, |r| &r.sum_micros) as f64 / 1e6
        );
        let _ = writeln!(
            out,
            "isovox_request_seconds_count{{route=\"{route}\"}} {count}"
        );
    }
}

/// The counters and gauges of the server's parts: bytes sent, caches, queues, subscribers.
fn gauges(state: &AppState, out: &mut String) {
    let m = &state.metrics;
    let (mut edit_queue, mut subscribers) = (0, 0);
    let (mut fetches, mut fetched, mut mirrored) = (0, 0, 0);
    for (_, v) in state.catalog.iter() {
        edit_queue += v.queue_depth() as u64;
        subscribers += v.subscribers() as u64;
        if let Some(remote) = v.remote() {
            use std::sync::atomic::Ordering::Relaxed;
            fetches += remote.counters().requests.load(Relaxed);
            fetched += remote.counters().bytes.load(Relaxed);
            mirrored += remote.cached_bytes();
        }
    }
    let open = &state.connections;
    let gauges: [(&str, &str, &str, u64); 21] = [
        (
            "isovox_response_bytes_total",
            "counter",
            "Response body bytes sent (known lengths).",
            m.bytes_sent(),
        ),
        (
            "isovox_mesh_cache_hits_total",
            "counter",
            "Mesh tiles served from the cache.",
            state.meshes.hits(),
        ),
        (
            "isovox_mesh_cache_misses_total",
            "counter",
            "Mesh tiles meshed on request.",
            state.meshes.misses(),
        ),
        (
            "isovox_mesh_cache_bytes",
            "gauge",
            "Bytes held by the mesh cache.",
            state.meshes.bytes() as u64,
        ),
        (
            "isovox_cpu_queue_depth",
            "gauge",
            "CPU jobs (meshing, batches, levels) running or queued.",
            state.cpu.depth() as u64,
        ),
        (
            "isovox_store_read_queue_depth",
            "gauge",
            "Reads of volumes kept in an object store running or queued.",
            state.store_reads.depth() as u64,
        ),
        (
            "isovox_response_memory_bytes",
            "gauge",
            "Bytes of response bodies built by CPU jobs and not yet sent.",
            state.cpu.memory.held() as u64,
        ),
        (
            "isovox_connections_max",
            "gauge",
            "Connections that may be open at once.",
            open.limits().max_connections as u64,
        ),
        (
            "isovox_connections_open",
            "gauge",
            "Connections open (change feeds included).",
            open.open() as u64,
        ),
        (
            "isovox_connections_refused_total",
            "counter",
            "Connections closed on arrival: the limit was reached and none was idle.",
            open.refused(),
        ),
        (
            "isovox_connections_evicted_total",
            "counter",
            "Idle connections closed to make room for new ones.",
            open.evicted(),
        ),
        (
            "isovox_connections_timed_out_total",
            "counter",
            "Connections closed by the header or the idle timeout.",
            open.timed_out(),
        ),
        (
            "isovox_brick_cache_hits_total",
            "counter",
            "Decoded bricks and lz4 blocks (for bodies and meshing) found in the cache.",
            state.bricks.hits(),
        ),
        (
            "isovox_brick_cache_misses_total",
            "counter",
            "Bricks decoded or transcoded on request (for bodies and meshing).",
            state.bricks.misses(),
        ),
        (
            "isovox_brick_cache_bytes",
            "gauge",
            "Bytes held by the cache of decoded bricks.",
            state.bricks.bytes() as u64,
        ),
        (
            "isovox_edit_queue_depth",
            "gauge",
            "Edits waiting for a volume's writer.",
            edit_queue,
        ),
        (
            "isovox_feed_subscribers",
            "gauge",
            "Change-feed subscribers connected.",
            subscribers,
        ),
        (
            "isovox_store_fetches_total",
            "counter",
            "Range requests to the object store for pages of its volumes.",
            fetches,
        ),
        (
            "isovox_store_fetched_bytes_total",
            "counter",
            "Bytes those range requests returned.",
            fetched,
        ),
        (
            "isovox_store_mirror_bytes",
            "gauge",
            "Bytes of fetched pages held in the local mirrors of the store's volumes.",
            mirrored,
        ),
        (
            "isovox_volumes",
            "gauge",
            "Volumes served.",
            state.catalog.len() as u64,
        ),
    ];
    for (name, kind, help, value) in gauges {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {value}"
        );
    }
}
