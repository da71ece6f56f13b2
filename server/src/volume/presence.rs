//! Who is looking at a volume now: each user's last position, sent to the others on the change
//! feed as `presence` events and never stored. A user silent for [`PRESENCE_TIMEOUT`] is
//! announced gone.
//!
//! Presence has a broadcast channel of its own, not the commits': a subscriber that falls
//! behind on cursors loses cursors (the next one replaces them), never a commit.

use isovox_proto::history::{Presence, PresenceRequest};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::sync::broadcast;

/// A user silent this long is gone.
pub const PRESENCE_TIMEOUT: Duration = Duration::from_secs(10);

/// Longest presence label, in characters.
pub const MAX_LABEL_CHARS: usize = 64;

/// Presence events a subscriber may fall behind by (older ones are dropped for it).
const PRESENCE_CAPACITY: usize = 256;

/// How often silent users are looked for.
pub(super) const SWEEP_INTERVAL: Duration = Duration::from_secs(1);

#[derive(Debug)]
struct Present {
    presence: Presence,
    heard: Instant,
}

/// The users present on one volume.
#[derive(Debug)]
pub struct Presences {
    users: Mutex<BTreeMap<String, Present>>,
    feed: broadcast::Sender<Arc<String>>,
    /// Whether a task looks for silent users (one per volume while anyone is present).
    sweeping: AtomicBool,
}

impl Default for Presences {
    fn default() -> Self {
        Presences {
            users: Mutex::default(),
            feed: broadcast::channel(PRESENCE_CAPACITY).0,
            sweeping: AtomicBool::new(false),
        }
    }
}

/// Checks a presence request: finite coordinates, a label of at most
/// [`MAX_LABEL_CHARS`].
///
/// # Errors
/// What is wrong with it, for a 400.
pub fn check(request: &PresenceRequest) -> Result<(), String> {
    let finite = |p: &[f64; 3]| p.iter().all(|c| c.is_finite() && c.abs() < 1e15);
    if !finite(&request.position) || !request.looking.as_ref().is_none_or(finite) {
        return Err("position and looking must be finite coordinates".into());
    }
    if let Some(label) = &request.label {
        if label.chars().count() > MAX_LABEL_CHARS {
            return Err(format!("a label is at most {MAX_LABEL_CHARS} characters"));
        }
    }
    Ok(())
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

impl Presences {
    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Present>> {
        // Every update is one insert or removal: a poisoned lock is still sound.
        self.users.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records where `user` is and tells the others. Returns whether a task must now look for
    /// silent users (none does).
    pub fn update(&self, user: &str, request: PresenceRequest) -> bool {
        let presence = Presence {
            user: user.to_string(),
            position: request.position,
            looking: request.looking,
            label: request.label,
            at_ms: now_ms(),
            gone: false,
        };
        self.send(&presence);
        self.lock().insert(
            user.to_string(),
            Present {
                presence,
                heard: Instant::now(),
            },
        );
        !self.sweeping.swap(true, Ordering::AcqRel)
    }

    fn send(&self, presence: &Presence) {
        let json = serde_json::to_string(presence).unwrap_or_default();
        // No subscriber is not an error.
        let _ = self.feed.send(Arc::new(json));
    }

    /// Who is present now, by name.
    pub fn list(&self) -> Vec<Presence> {
        let now = Instant::now();
        self.lock()
            .values()
            .filter(|p| now.duration_since(p.heard) < PRESENCE_TIMEOUT)
            .map(|p| p.presence.clone())
            .collect()
    }

    /// Announces and forgets the users silent for [`PRESENCE_TIMEOUT`]; returns whether
    /// anyone is left.
    pub(super) fn sweep(&self) -> bool {
        let now = Instant::now();
        let gone: Vec<Presence> = {
            let mut users = self.lock();
            let silent: Vec<String> = users
                .iter()
                .filter(|(_, p)| now.duration_since(p.heard) >= PRESENCE_TIMEOUT)
                .map(|(u, _)| u.clone())
                .collect();
            silent
                .iter()
                .filter_map(|u| users.remove(u))
                .map(|p| Presence {
                    gone: true,
                    at_ms: now_ms(),
                    ..p.presence
                })
                .collect()
        };
        for p in &gone {
            self.send(p);
        }
        let left = !self.lock().is_empty();
        if !left {
            self.sweeping.store(false, Ordering::Release);
            // Someone may have arrived between the check and the store: sweep on for them.
            if !self.lock().is_empty() && !self.sweeping.swap(true, Ordering::AcqRel) {
                return true;
            }
        }
        left
    }

    /// Every presence event from now on (JSON).
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<String>> {
        self.feed.subscribe()
    }
}

impl super::LiveVolume {
    /// Records where `user` is on this volume and tells the other subscribers; a task on
    /// `runtime` announces the users who fall silent.
    pub fn present(
        self: &Arc<Self>,
        user: &str,
        request: PresenceRequest,
        runtime: &tokio::runtime::Handle,
    ) {
        if self.presence.update(user, request) {
            let vol = self.clone();
            runtime.spawn(async move {
                loop {
                    tokio::time::sleep(SWEEP_INTERVAL).await;
                    if !vol.presence.sweep() {
                        return;
                    }
                }
            });
        }
    }

    /// Who is present now.
    pub fn presences(&self) -> Vec<Presence> {
        self.presence.list()
    }

    /// Every presence event from now on (JSON).
    pub fn subscribe_presence(&self) -> broadcast::Receiver<Arc<String>> {
        self.presence.subscribe()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn at(x: f64) -> PresenceRequest {
        PresenceRequest {
            position: [x, 0.0, 0.0],
            looking: None,
            label: None,
        }
    }

    #[test]
    fn bad_requests_are_refused() {
        assert!(check(&at(f64::NAN)).is_err());
        assert!(check(&at(1e300)).is_err());
        let mut long = at(1.0);
        long.label = Some("x".repeat(65));
        assert!(check(&long).is_err());
        long.label = Some("é".repeat(64));
        assert!(check(&long).is_ok());
    }

    #[test]
    fn the_others_hear_of_each_update_and_the_list_has_the_last() {
        let p = Presences::default();
        let mut rx = p.subscribe();
        assert!(
            p.update("alice", at(1.0)),
            "the first update starts a sweeper"
        );
        assert!(!p.update("alice", at(2.0)), "one sweeper is enough");
        let first: Presence = serde_json::from_str(&rx.try_recv().unwrap()).unwrap();
        assert_eq!(first.position[0], 1.0);
        let list = p.list();
        assert_eq!(list.len(), 1);
        assert_eq!(list[0].position[0], 2.0);
    }
}
