//! Prometheus metrics: requests by route and status, latency histograms by route, bytes sent,
//! mesh cache hits and misses, CPU queue depth. Recorded by a middleware, rendered as text.

use super::AppState;
use axum::extract::{MatchedPath, Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// Upper bounds of the latency buckets, seconds.
const BUCKETS: [f64; 14] = [
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

#[derive(Debug, Default)]
struct Histogram {
    counts: [u64; BUCKETS.len()],
    count: u64,
    sum: f64,
}

/// The server's counters.
#[derive(Debug, Default)]
pub struct Metrics {
    requests: Mutex<BTreeMap<(String, u16), u64>>,
    latency: Mutex<BTreeMap<String, Histogram>>,
    bytes_sent: AtomicU64,
}

impl Metrics {
    fn record(&self, route: &str, status: u16, seconds: f64, bytes: u64) {
        if let Ok(mut r) = self.requests.lock() {
            *r.entry((route.to_string(), status)).or_default() += 1;
        }
        if let Ok(mut l) = self.latency.lock() {
            let h = l.entry(route.to_string()).or_default();
            for (i, b) in BUCKETS.iter().enumerate() {
                if seconds <= *b {
                    h.counts[i] += 1;
                }
            }
            h.count += 1;
            h.sum += seconds;
        }
        self.bytes_sent.fetch_add(bytes, Ordering::Relaxed);
    }
}

/// Middleware: times every request and counts it under its route template.
pub async fn track(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_string())
        .unwrap_or_else(|| "unmatched".to_string());
    let start = Instant::now();
    let response = next.run(request).await;
    let bytes = response
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    state.metrics.record(
        &route,
        response.status().as_u16(),
        start.elapsed().as_secs_f64(),
        bytes,
    );
    response
}

/// `GET /metrics` in the Prometheus text format.
pub async fn metrics(State(state): State<AppState>) -> Response {
    let mut out = String::new();
    let m = &state.metrics;
    let _ = writeln!(out, "# HELP isovox_requests_total HTTP requests by route and status.\n# TYPE isovox_requests_total counter");
    if let Ok(r) = m.requests.lock() {
        for ((route, status), n) in r.iter() {
            let _ = writeln!(
                out,
                "isovox_requests_total{{route=\"{route}\",status=\"{status}\"}} {n}"
            );
        }
    }
    let _ = writeln!(out, "# HELP isovox_request_seconds Request latency by route.\n# TYPE isovox_request_seconds histogram");
    if let Ok(l) = m.latency.lock() {
        for (route, h) in l.iter() {
            for (i, b) in BUCKETS.iter().enumerate() {
                let _ = writeln!(
                    out,
                    "isovox_request_seconds_bucket{{route=\"{route}\",le=\"{b}\"}} {}",
                    h.counts[i]
                );
            }
            let _ = writeln!(
                out,
                "isovox_request_seconds_bucket{{route=\"{route}\",le=\"+Inf\"}} {}",
                h.count
            );
            let _ = writeln!(
                out,
                "isovox_request_seconds_sum{{route=\"{route}\"}} {}",
                h.sum
            );
            let _ = writeln!(
                out,
                "isovox_request_seconds_count{{route=\"{route}\"}} {}",
                h.count
            );
        }
    }
    let gauges: [(&str, &str, &str, u64); 6] = [
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
