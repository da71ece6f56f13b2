//! Prometheus metrics: requests by route and status, latency histograms by route, bytes sent,
//! mesh cache hits and misses, CPU queue depth. Recorded by a tower layer, rendered as text.

use super::AppState;
use axum::extract::{MatchedPath, State};
use axum::http::{header, Request};
use axum::response::{IntoResponse, Response};
use std::collections::BTreeMap;
use std::fmt::Write;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;

/// Upper bounds of the latency buckets, seconds.
const BUCKETS: [f64; 14] = [
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// One route's counters, lock-free: requests by status code, and a latency histogram.
#[derive(Debug)]
struct RouteMetrics {
    by_status: Vec<AtomicU64>,
    buckets: [AtomicU64; BUCKETS.len()],
    count: AtomicU64,
    sum_micros: AtomicU64,
}

impl Default for RouteMetrics {
    fn default() -> Self {
        RouteMetrics {
            by_status: (0..600).map(|_| AtomicU64::new(0)).collect(),
            buckets: std::array::from_fn(|_| AtomicU64::new(0)),
            count: AtomicU64::new(0),
            sum_micros: AtomicU64::new(0),
        }
    }
}

/// The server's counters. Routes are registered once (the router's templates); recording a
/// request touches only atomics, so it costs no lock and no allocation.
#[derive(Debug, Default)]
pub struct Metrics {
    routes: BTreeMap<&'static str, RouteMetrics>,
    bytes_sent: AtomicU64,
}

impl Metrics {
    /// Counters for these route templates (others are counted as "unmatched").
    pub fn new(routes: &[&'static str]) -> Self {
        let mut map = BTreeMap::new();
        for r in routes.iter().copied().chain(["unmatched"]) {
            map.insert(r, RouteMetrics::default());
        }
        Metrics {
            routes: map,
            bytes_sent: AtomicU64::new(0),
        }
    }

    fn record(&self, route: &str, status: u16, seconds: f64, bytes: u64) {
        let Some(m) = self.routes.get(route) else {
            return;
        };
        if let Some(c) = m.by_status.get(status as usize) {
            c.fetch_add(1, Ordering::Relaxed);
        }
        // One bucket per request (cumulated when rendered): every atomic shared between cores
        // costs on the hottest routes.
        if let Some(i) = BUCKETS.iter().position(|b| seconds <= *b) {
            m.buckets[i].fetch_add(1, Ordering::Relaxed);
        }
        m.count.fetch_add(1, Ordering::Relaxed);
        m.sum_micros
            .fetch_add((seconds * 1e6) as u64, Ordering::Relaxed);
        self.bytes_sent.fetch_add(bytes, Ordering::Relaxed);
    }
}

/// Times every request and counts it under its route template. A plain tower layer (not
/// `middleware::from_fn`, which boxes a future per request): on the brick routes every
/// allocation shows in the throughput.
#[derive(Debug, Clone)]
pub struct MetricsLayer {
    metrics: Arc<Metrics>,
}

impl MetricsLayer {
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
        let route = request
            .extensions()
            .get::<MatchedPath>()
            .and_then(|p| self.metrics.routes.get_key_value(p.as_str()))
            .map_or("unmatched", |(k, _)| *k);
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
        route: &'static str,
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
            this.metrics.record(
                this.route,
                response.status().as_u16(),
                this.start.elapsed().as_secs_f64(),
                bytes,
            );
        }
        Poll::Ready(result)
    }
}

/// `GET /metrics` in the Prometheus text format.
pub async fn metrics(State(state): State<AppState>) -> Response {
    let mut out = String::new();
    let m = &state.metrics;
    let _ = writeln!(out, "# HELP isovox_requests_total HTTP requests by route and status.\n# TYPE isovox_requests_total counter");
    for (route, r) in &m.routes {
        for (status, n) in r.by_status.iter().enumerate() {
            let n = n.load(Ordering::Relaxed);
            if n > 0 {
                let _ = writeln!(
                    out,
                    "isovox_requests_total{{route=\"{route}\",status=\"{status}\"}} {n}"
                );
            }
        }
    }
    let _ = writeln!(out, "# HELP isovox_request_seconds Request latency by route.\n# TYPE isovox_request_seconds histogram");
    for (route, r) in &m.routes {
        let count = r.count.load(Ordering::Relaxed);
        if count == 0 {
            continue;
        }
        let mut cumulative = 0;
        for (i, b) in BUCKETS.iter().enumerate() {
            cumulative += r.buckets[i].load(Ordering::Relaxed);
            let _ = writeln!(
                out,
                "isovox_request_seconds_bucket{{route=\"{route}\",le=\"{b}\"}} {cumulative}"
            );
        }
        let _ = writeln!(
            out,
            "isovox_request_seconds_bucket{{route=\"{route}\",le=\"+Inf\"}} {count}"
        );
        let _ = writeln!(
            out,
            "isovox_request_seconds_sum{{route=\"{route}\"}} {}",
            r.sum_micros.load(Ordering::Relaxed) as f64 / 1e6
        );
        let _ = writeln!(
            out,
            "isovox_request_seconds_count{{route=\"{route}\"}} {count}"
        );
    }
    let (mut edit_queue, mut subscribers) = (0, 0);
    for (_, v) in state.catalog.iter() {
        edit_queue += v.queue_depth() as u64;
        subscribers += v.subscribers() as u64;
    }
    let gauges: [(&str, &str, &str, u64); 11] = [
        (
            "isovox_response_bytes_total",
            "counter",
            "Response body bytes sent (known lengths).",
            m.bytes_sent.load(Ordering::Relaxed),
        ),
        (
            "isovox_mesh_cache_hits_total",
            "counter",
            "Mesh tiles served from the cache.",
            state.meshes.hits.load(Ordering::Relaxed),
        ),
        (
            "isovox_mesh_cache_misses_total",
            "counter",
            "Mesh tiles meshed on request.",
            state.meshes.misses.load(Ordering::Relaxed),
        ),
        (
            "isovox_mesh_cache_bytes",
            "gauge",
            "Bytes held by the mesh and decoded-brick caches.",
            state.meshes.bytes() as u64,
        ),
        (
            "isovox_cpu_queue_depth",
            "gauge",
            "CPU jobs (meshing, batches, levels) running or queued.",
            (state.cpu_permits - state.cpu.available_permits()) as u64,
        ),
        (
            "isovox_brick_cache_hits_total",
            "counter",
            "Brick bodies (decoded voxels, lz4 blocks) served from the cache.",
            state.bodies.hits.load(Ordering::Relaxed),
        ),
        (
            "isovox_brick_cache_misses_total",
            "counter",
            "Brick bodies decoded or transcoded on request.",
            state.bodies.misses.load(Ordering::Relaxed),
        ),
        (
            "isovox_brick_cache_bytes",
            "gauge",
            "Bytes held by the brick body cache.",
            state.bodies.bytes() as u64,
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
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}
