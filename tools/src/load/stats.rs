//! The [`Recorder`] every HTTP exchange of a run goes through (per route: outcomes, bytes,
//! every latency sample, when each failure was seen), and latency percentiles.

use isovox_client::client::Observer;
use serde::Serialize;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Collects every HTTP exchange of every client of a run: per route, the outcomes, bytes and
/// every latency sample, and when each kind of failure was first and last seen.
#[derive(Debug)]
pub struct Recorder {
    pub(super) start: Instant,
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
pub(super) struct RouteAcc {
    pub(super) bytes: u64,
    /// Microseconds, one per exchange.
    pub(super) latencies: Vec<u32>,
    /// Every exchange, by status code or transport failure kind.
    pub(super) outcomes: BTreeMap<String, u64>,
    /// The exchanges that failed their call (the client did not try again), by kind.
    pub(super) failures: BTreeMap<String, u64>,
    /// Unsuccessful exchanges the client tried again after (503, 429, a transport failure it
    /// may repeat): not errors, unless the last attempt failed too.
    pub(super) retried: u64,
    /// Seconds since the start when each failure kind was first and last seen.
    pub(super) error_times: BTreeMap<String, (f64, f64)>,
}

impl Recorder {
    /// Exchanges so far.
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }

    /// Exchanges that failed their call so far (not those the client tried again after).
    pub fn errors(&self) -> u64 {
        self.errors.load(Ordering::Relaxed)
    }

    pub(super) fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<&'static str, RouteAcc>> {
        self.routes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// Whether an exchange's outcome counts as a success: 2xx, and 304 (a revalidated brick).
pub(super) fn is_success(outcome: Result<u16, &str>) -> bool {
    matches!(outcome, Ok(s) if (200..300).contains(&s) || s == 304)
}

impl Observer for Recorder {
    fn exchange(
        &self,
        route: &'static str,
        outcome: Result<u16, &str>,
        latency: Duration,
        bytes: u64,
        retried: bool,
    ) {
        let ok = is_success(outcome);
        let failed = !ok && !retried;
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
            if !ok && retried {
                r.retried += 1;
            }
            if failed {
                *r.failures.entry(name.clone()).or_default() += 1;
                let t = self.start.elapsed().as_secs_f64();
                let span = r.error_times.entry(name.clone()).or_insert((t, t));
                span.1 = t;
            }
            *r.outcomes.entry(name).or_default() += 1;
        }
        self.requests.fetch_add(1, Ordering::Relaxed);
        if failed {
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

    pub(super) fn from_durations(samples: &[Duration]) -> Latency {
        let mut us: Vec<u32> = samples
            .iter()
            .map(|d| d.as_micros().min(u128::from(u32::MAX)) as u32)
            .collect();
        Latency::from_micros(&mut us)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_answer_the_client_tried_again_after_is_not_an_error() {
        let r = Recorder::default();
        let ms = Duration::from_millis(1);
        // A brick shed twice then sent; a mesh shed on its last attempt.
        r.exchange("brick", Ok(503), ms, 0, true);
        r.exchange("brick", Err("connect"), ms, 0, true);
        r.exchange("brick", Ok(200), ms, 10, false);
        r.exchange("mesh", Ok(503), ms, 0, true);
        r.exchange("mesh", Ok(503), ms, 0, false);
        assert_eq!((r.requests(), r.errors()), (5, 1));
        let routes = r.lock();
        let brick = &routes["brick"];
        assert_eq!(brick.retried, 2);
        assert!(brick.failures.is_empty());
        assert_eq!(brick.outcomes.len(), 3, "{:?}", brick.outcomes);
        let mesh = &routes["mesh"];
        assert_eq!(mesh.retried, 1);
        assert_eq!(mesh.failures, BTreeMap::from([("503".to_string(), 1)]));
        assert_eq!(mesh.outcomes, BTreeMap::from([("503".to_string(), 2)]));
        assert!(mesh.error_times.contains_key("503"));
    }
}
