//! Following the heads of object-store volumes: each is polled with a conditional GET at a
//! short interval, and what other writers committed is served and announced on the change feed.

use super::LiveVolume;
use std::sync::Arc;
use std::time::Duration;

/// Polls each volume kept in an object store every `every`, for as long as the task runs
/// (local volumes are left out: their writer is this process).
pub async fn follow(volumes: Vec<Arc<LiveVolume>>, every: Duration) {
    let volumes: Vec<_> = volumes
        .into_iter()
        .filter(|v| v.remote().is_some())
        .collect();
    if volumes.is_empty() {
        return;
    }
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        for volume in &volumes {
            let following = volume.clone();
            match tokio::task::spawn_blocking(move || following.follow_blocking()).await {
                Ok(Ok(())) => {}
                Ok(Err(e)) => tracing::warn!(
                    volume = %volume.name(),
                    error = %crate::store::error_chain(&e),
                    "cannot follow the head; serving the last one seen"
                ),
                Err(e) => {
                    tracing::error!(volume = %volume.name(), error = %e, "the follower failed")
                }
            }
        }
    }
}
