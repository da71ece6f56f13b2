//! Presence under load: viewers say where their camera is, the change-feed subscribers time
//! each message from its sending to its arrival.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// What the viewers sent and the subscribers received, shared by both.
#[derive(Debug, Default)]
pub(super) struct PresenceLog {
    inner: Mutex<Inner>,
}

#[derive(Debug, Default)]
struct Inner {
    /// When each message (by its label, unique in a run) was sent.
    sent_at: HashMap<String, Instant>,
    /// Answered 2xx, 429, anything else.
    accepted: u64,
    limited: u64,
    failed: u64,
    /// Arrivals of sent messages at subscribers, and their delays.
    delays: Vec<Duration>,
}

/// The presence part of a run's report.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct PresenceReport {
    pub sent: u64,
    pub accepted: u64,
    /// Refused for the per-user rate (429).
    pub limited: u64,
    pub failed: u64,
    /// Arrivals at the change-feed subscribers (each subscriber counts each message once).
    pub delivered: u64,
    /// Arrivals per accepted message: the subscribers' count when every one reached every one.
    pub fan_out: f64,
    pub delay_p50_ms: f64,
    pub delay_p99_ms: f64,
}

impl PresenceLog {
    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A message labelled `label` is being sent now.
    pub(super) fn sending(&self, label: &str) {
        self.lock()
            .sent_at
            .insert(label.to_string(), Instant::now());
    }

    /// Its answer: accepted, 429, or another failure.
    pub(super) fn answered(&self, status: Result<(), Option<u16>>) {
        let mut inner = self.lock();
        match status {
            Ok(()) => inner.accepted += 1,
            Err(Some(429)) => inner.limited += 1,
            Err(_) => inner.failed += 1,
        }
    }

    /// A subscriber received the message labelled `label` now.
    pub(super) fn arrived(&self, label: &str) {
        let now = Instant::now();
        let mut inner = self.lock();
        if let Some(&at) = inner.sent_at.get(label) {
            inner.delays.push(now.saturating_duration_since(at));
        }
    }

    pub(super) fn report(&self) -> PresenceReport {
        let inner = self.lock();
        let mut ms: Vec<f64> = inner.delays.iter().map(|d| d.as_secs_f64() * 1e3).collect();
        ms.sort_by(f64::total_cmp);
        let at = |p: f64| {
            if ms.is_empty() {
                0.0
            } else {
                ms[((ms.len() - 1) as f64 * p).round() as usize]
            }
        };
        PresenceReport {
            sent: inner.sent_at.len() as u64,
            accepted: inner.accepted,
            limited: inner.limited,
            failed: inner.failed,
            delivered: ms.len() as u64,
            fan_out: ms.len() as f64 / inner.accepted.max(1) as f64,
            delay_p50_ms: at(0.5),
            delay_p99_ms: at(0.99),
        }
    }
}
