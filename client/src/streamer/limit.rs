//! How many requests the streamer keeps in flight: adapted to the server's 503s.

use crate::client::Observer;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::time::Instant;

/// The number of requests a streamer keeps in flight, additive increase, multiplicative decrease
/// (AIMD, as TCP paces its congestion window).
///
/// Why: the server answers 503 with `Retry-After` rather than queue CPU work (mesh tiles, grid
/// regions) without bound, and its queue is small (8 places per core). A fixed number of requests
/// per streamer overflows it as soon as a few viewers share a server (three streamers at 16 each
/// exceed a two-core server's 16 places), and every refused request comes back after its pause.
/// Halving the limit on a 503 lets the streamers share the queue; growing it by one after a
/// window of successes (as many as the limit) finds the room again when the load goes away.
///
/// The limit starts at the configured maximum (a streamer alone on a server runs as before),
/// never exceeds it and never falls below one. One overload halves it once: a 503 to a request
/// started before the last cut was caused by the load that cut already answered, so it does not
/// cut again (otherwise the 16 refusals of one burst would take 16 down to 1 at once).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct InFlightLimit {
    max: usize,
    limit: usize,
    /// Successes since the limit last changed.
    successes: usize,
    /// When the limit was last cut.
    cut_at: Option<Instant>,
}

impl InFlightLimit {
    /// A limit of `max` (at least 1).
    pub(super) fn new(max: usize) -> InFlightLimit {
        let max = max.max(1);
        InFlightLimit {
            max,
            limit: max,
            successes: 0,
            cut_at: None,
        }
    }

    /// Requests that may run at once now.
    pub(super) fn get(&self) -> usize {
        self.limit
    }

    /// The server answered a request started at `started` with 503 (or 429) at `now`: halve the
    /// limit, unless the request started before the last cut.
    pub(super) fn overloaded(&mut self, started: Instant, now: Instant) {
        if self.cut_at.is_some_and(|cut| started <= cut) {
            return;
        }
        self.limit = (self.limit / 2).max(1);
        self.successes = 0;
        self.cut_at = Some(now);
    }

    /// The server answered a request: after as many successes as the limit, grow it by one.
    pub(super) fn succeeded(&mut self) {
        if self.limit >= self.max {
            return;
        }
        self.successes += 1;
        if self.successes >= self.limit {
            self.limit += 1;
            self.successes = 0;
        }
    }
}

/// The [`InFlightLimit`] shared by the streamer's task and its requests.
pub(super) type SharedLimit = Arc<Mutex<InFlightLimit>>;

pub(super) fn lock_limit(limit: &SharedLimit) -> std::sync::MutexGuard<'_, InFlightLimit> {
    // Nothing panics while holding the lock; a poisoned lock still holds whole values.
    limit.lock().unwrap_or_else(|p| p.into_inner())
}

/// Watches one request's exchanges (each attempt of its retries) for the [`InFlightLimit`], and
/// passes them on to the observer the streamer's client already had.
#[derive(Debug)]
pub(super) struct Pacer {
    pub(super) started: Instant,
    pub(super) limit: SharedLimit,
    pub(super) next: Option<Arc<dyn Observer>>,
}

impl Observer for Pacer {
    fn exchange(
        &self,
        route: &'static str,
        outcome: Result<u16, &str>,
        latency: Duration,
        bytes: u64,
        retried: bool,
    ) {
        match outcome {
            Ok(503 | 429) => lock_limit(&self.limit).overloaded(self.started, Instant::now()),
            Ok(200..=299 | 304) => lock_limit(&self.limit).succeeded(),
            _ => {}
        }
        if let Some(next) = &self.next {
            next.exchange(route, outcome, latency, bytes, retried);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn halves_once_per_overload_and_grows_by_one_per_window() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let mut l = InFlightLimit::new(16);
        assert_eq!(l.get(), 16);
        // At the maximum, successes change nothing.
        l.succeeded();
        assert_eq!(l.get(), 16);

        // A 503 at 10 ms to a request started at 5: 16 / 2 = 8.
        l.overloaded(at(5), at(10));
        assert_eq!(l.get(), 8);
        // More 503s to requests started before the cut (at 10 ms): still 8.
        l.overloaded(at(1), at(11));
        l.overloaded(at(10), at(12));
        assert_eq!(l.get(), 8);
        // A 503 to a request started after it: 8 / 2 = 4.
        l.overloaded(at(13), at(20));
        assert_eq!(l.get(), 4);

        // 4 successes make 5, 5 more make 6.
        for _ in 0..3 {
            l.succeeded();
        }
        assert_eq!(l.get(), 4);
        l.succeeded();
        assert_eq!(l.get(), 5);
        for _ in 0..4 {
            l.succeeded();
        }
        assert_eq!(l.get(), 5);
        l.succeeded();
        assert_eq!(l.get(), 6);

        // A cut drops the successes counted so far: 6 / 2 = 3, then 3 successes to 4.
        l.succeeded();
        l.succeeded();
        l.overloaded(at(21), at(30));
        assert_eq!(l.get(), 3);
        l.succeeded();
        l.succeeded();
        assert_eq!(l.get(), 3);
        l.succeeded();
        assert_eq!(l.get(), 4);

        // Down to 4 / 2 = 2, 2 / 2 = 1, and 1 / 2 stays 1.
        l.overloaded(at(31), at(40));
        l.overloaded(at(41), at(50));
        assert_eq!(l.get(), 1);
        l.overloaded(at(51), at(60));
        assert_eq!(l.get(), 1);
    }

    #[test]
    fn grows_back_to_the_maximum_and_no_further() {
        let t0 = Instant::now();
        let mut l = InFlightLimit::new(3);
        l.overloaded(t0, t0); // 3 / 2 = 1
        assert_eq!(l.get(), 1);
        l.succeeded(); // a window of 1: 2
        assert_eq!(l.get(), 2);
        l.succeeded();
        l.succeeded(); // a window of 2: 3
        assert_eq!(l.get(), 3);
        for _ in 0..10 {
            l.succeeded();
        }
        assert_eq!(l.get(), 3);
    }

    #[test]
    fn a_maximum_of_zero_is_one() {
        let mut l = InFlightLimit::new(0);
        assert_eq!(l.get(), 1);
        l.succeeded();
        assert_eq!(l.get(), 1);
    }
}
