//! Following the heads of object-store volumes: each is polled with a conditional GET at a
//! short interval, and what other writers committed is served and announced on the change feed.
//!
//! Each volume is followed on its own schedule: the interval is jittered (replicas started
//! together drift apart instead of polling in lockstep), and while following fails the waits
//! grow exponentially with jitter, up to [`MAX_FAILING_WAIT`], then return to the interval at
//! the first success.

use super::LiveVolume;
use crate::store::remote::backoff::{jittered, Backoff};
use std::sync::Arc;
use std::time::Duration;

/// The longest wait between two tries while following a volume keeps failing.
pub const MAX_FAILING_WAIT: Duration = Duration::from_secs(30);

/// Polls each volume kept in an object store about every `every`, for as long as the task runs
/// (local volumes are left out: their writer is this process). A poll gives up store calls
/// after `limit` (the server's edit timeout: see [`LiveVolume::follow_blocking`]).
pub async fn follow(volumes: Vec<Arc<LiveVolume>>, every: Duration, limit: Duration) {
    let followers: Vec<_> = volumes
        .into_iter()
        .filter(|v| v.remote().is_some())
        .map(|volume| tokio::spawn(follow_one(volume, every, limit)))
        .collect();
    for follower in followers {
        if let Err(e) = follower.await {
            tracing::error!(error = %e, "a follower failed");
        }
    }
}

/// Follows one volume: the next poll after a jittered `every`, or, while polls fail, after the
/// next wait of a backoff starting from `every`.
async fn follow_one(volume: Arc<LiveVolume>, every: Duration, limit: Duration) {
    let mut failures = Backoff::new(every, MAX_FAILING_WAIT);
    let mut wait = jittered(every);
    loop {
        tokio::time::sleep(wait).await;
        let following = volume.clone();
        let failure =
            match tokio::task::spawn_blocking(move || following.follow_blocking(limit)).await {
                Ok(Ok(())) => None,
                Ok(Err(e)) => Some(crate::store::error_chain(&e)),
                Err(e) => Some(format!("the follower failed: {e}")),
            };
        match failure {
            None => {
                failures.reset();
                wait = jittered(every);
            }
            Some(error) => {
                wait = failures.next_wait();
                tracing::warn!(
                    volume = %volume.name(),
                    %error,
                    retry_in_ms = wait.as_millis() as u64,
                    "cannot follow the head; serving the last one seen"
                );
            }
        }
    }
}
