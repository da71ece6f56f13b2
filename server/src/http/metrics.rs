//! Prometheus metrics: requests by route and status, latency histograms by route, bytes sent,
//! mesh cache hits and misses, CPU queue depth. Recorded by a tower layer into
//! `prometheus-client`'s metrics, which also writes the text format.

use super::AppState;
use axum::extract::State;
use axum::http::{header, Request};
use axum::response::{IntoResponse, Response};
use prometheus_client::encoding::{prometheus_text, EncodeLabelSet};
use prometheus_client::metrics::counter::{ConstCounter, Counter};
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::Registry;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, OnceLock};
use std::task::{Context, Poll};
use std::time::Instant;

/// Upper bounds of the latency buckets, seconds.
const BUCKETS: [f64; 14] = [
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// Status codes are counted in a table indexed by the code (codes outside it are not counted).
const STATUSES: usize = 600;

/// The labels of `isovox_requests_total`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, EncodeLabelSet)]
struct RouteStatus {
    route: &'static str,
    status: u16,
}

/// The label of `isovox_request_seconds`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, EncodeLabelSet)]
struct RouteLabel {
    route: &'static str,
}

fn latency_histogram() -> Histogram {
    Histogram::new(BUCKETS)
}

/// One route's handles into the families, taken from them at the route's first request (and
/// the first of each status), so that recording a request neither hashes its labels nor takes
/// the family's lock. A series appears when its first request is recorded, as it did when the
/// text was written by hand: routes and statuses never seen are not in the exposition.
#[derive(Debug)]
struct RouteHandles {
    by_status: Box<[OnceLock<Counter>]>,
    latency: OnceLock<Histogram>,
}

/// The server's counters, by route template (the router's, see [`super::ROUTES`]; requests
/// matching none are counted as "unmatched").
#[derive(Debug)]
pub struct Metrics {
    /// Route templates, `unmatched` last.
    names: Vec<&'static str>,
    /// Path to index in `names`, matched by the same rules as axum's router (both use matchit).
    matcher: matchit::Router<usize>,
    requests: Family<RouteStatus, Counter>,
    latency: Family<RouteLabel, Histogram, fn() -> Histogram>,
    bytes_sent: Counter,
    /// By index in `names`.
    handles: Box<[RouteHandles]>,
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
        let handles = names
            .iter()
            .map(|_| RouteHandles {
                by_status: (0..STATUSES).map(|_| OnceLock::new()).collect(),
                latency: OnceLock::new(),
            })
            .collect();
        Metrics {
            names,
            matcher,
            requests: Family::default(),
            latency: Family::new_with_constructor(latency_histogram),
            bytes_sent: Counter::default(),
            handles,
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
        let Some(h) = self.handles.get(route) else {
            return;
        };
        let name = self.route_name(route);
        if let Some(counter) = h.by_status.get(usize::from(status)) {
            counter
                .get_or_init(|| {
                    let labels = RouteStatus {
                        route: name,
                        status,
                    };
                    self.requests.get_or_create(&labels).clone()
                })
                .inc();
        }
        h.latency
            .get_or_init(|| {
                self.latency
                    .get_or_create(&RouteLabel { route: name })
                    .clone()
            })
            .observe(seconds);
        self.bytes_sent.inc_by(bytes);
    }

    /// Adds the request metrics to `registry` (the families are shared, not copied).
    fn register(&self, registry: &mut Registry) {
        registry.register(
            "isovox_requests",
            "HTTP requests by route and status",
            self.requests.clone(),
        );
        registry.register(
            "isovox_request_seconds",
            "Request latency by route",
            self.latency.clone(),
        );
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

/// `GET /metrics` in the Prometheus text format (0.0.4).
pub async fn metrics(State(state): State<AppState>) -> Response {
    let mut registry = Registry::default();
    state.metrics.register(&mut registry);
    gauges(&state, &mut registry);
    let mut out = String::new();
    // Writing into a String cannot fail.
    let _ = prometheus_text::encode(&mut out, &registry);
    ([(header::CONTENT_TYPE, prometheus_text::CONTENT_TYPE)], out).into_response()
}

/// The counters and gauges of the server's parts, read at the scrape: bytes sent, caches,
/// queues, subscribers. Counter names get their `_total` from the encoder.
fn gauges(state: &AppState, registry: &mut Registry) {
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
    let mut counter = |name: &str, help: &str, value: u64| {
        registry.register(name, help, ConstCounter::new(value));
    };
    counter(
        "isovox_response_bytes",
        "Response body bytes sent (known lengths)",
        state.metrics.bytes_sent.get(),
    );
    counter(
        "isovox_mesh_cache_hits",
        "Mesh tiles served from the cache",
        state.meshes.hits(),
    );
    counter(
        "isovox_mesh_cache_misses",
        "Mesh tiles meshed on request",
        state.meshes.misses(),
    );
    counter(
        "isovox_mesh_answers_kept_hits",
        "Mesh tiles and strips sent as an earlier request's answer, with no CPU job",
        state.mesh_answers.hits(),
    );
    counter(
        "isovox_mesh_answers_joined",
        "Mesh tiles and strips asked for while another request was making the same answer, sent when it was made",
        state.mesh_answers.joined(),
    );
    counter(
        "isovox_connections_refused",
        "Connections closed on arrival: the limit was reached and none was idle",
        open.refused(),
    );
    counter(
        "isovox_connections_evicted",
        "Idle connections closed to make room for new ones",
        open.evicted(),
    );
    counter(
        "isovox_connections_timed_out",
        "Connections closed by the header or the idle timeout",
        open.timed_out(),
    );
    counter(
        "isovox_brick_cache_hits",
        "Decoded bricks and lz4 blocks (for bodies and meshing) found in the cache",
        state.bricks.hits(),
    );
    counter(
        "isovox_brick_cache_misses",
        "Bricks decoded or transcoded on request (for bodies and meshing)",
        state.bricks.misses(),
    );
    counter(
        "isovox_store_fetches",
        "Range requests to the object store for pages of its volumes",
        fetches,
    );
    counter(
        "isovox_store_fetched_bytes",
        "Bytes those range requests returned",
        fetched,
    );
    let gauges: [(&str, &str, u64); 12] = [
        (
            "isovox_mesh_cache_bytes",
            "Bytes held by the mesh cache",
            state.meshes.bytes() as u64,
        ),
        (
            "isovox_mesh_answers_kept_bytes",
            "Bytes of mesh answers kept as sent",
            state.mesh_answers.bytes() as u64,
        ),
        (
            "isovox_cpu_queue_depth",
            "CPU jobs (meshing, batches, levels) running or queued",
            state.cpu.depth() as u64,
        ),
        (
            "isovox_store_read_queue_depth",
            "Reads of volumes kept in an object store running or queued",
            state.store_reads.depth() as u64,
        ),
        (
            "isovox_response_memory_bytes",
            "Bytes of response bodies built by CPU jobs and not yet sent",
            state.cpu.memory.held() as u64,
        ),
        (
            "isovox_connections_max",
            "Connections that may be open at once",
            open.limits().max_connections as u64,
        ),
        (
            "isovox_connections_open",
            "Connections open (change feeds included)",
            open.open() as u64,
        ),
        (
            "isovox_brick_cache_bytes",
            "Bytes held by the cache of decoded bricks",
            state.bricks.bytes() as u64,
        ),
        (
            "isovox_edit_queue_depth",
            "Edits waiting for a volume's writer",
            edit_queue,
        ),
        (
            "isovox_feed_subscribers",
            "Change-feed subscribers connected",
            subscribers,
        ),
        (
            "isovox_store_mirror_bytes",
            "Bytes of fetched pages held in the local mirrors of the store's volumes",
            mirrored,
        ),
        (
            "isovox_volumes",
            "Volumes served",
            state.catalog.len() as u64,
        ),
    ];
    for (name, help, value) in gauges {
        registry.register(name, help, ConstGauge::new(value));
    }
}
