//! A dedicated change-feed subscriber: the arrival time of every version, for the
//! edit-to-notification latency.

use isovox_client::client::{Client, ClientError, FeedEvent};
use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};
use tokio::sync::{oneshot, watch};

/// One dedicated change-feed subscriber's observations.
#[derive(Debug, Default)]
pub(super) struct SubscriberResult {
    /// Arrival of each version.
    pub(super) seen: HashMap<u64, Instant>,
    pub(super) resyncs: u64,
    pub(super) reconnects: u64,
    pub(super) errors: BTreeMap<String, u64>,
}

/// Follows the change feed until `until` names a version it has seen (or the drain time after
/// it was set runs out). Sends the hello version on `ready` once subscribed.
pub(super) async fn subscriber(
    client: Client,
    volume: String,
    drain: Duration,
    ready: oneshot::Sender<Result<u64, ClientError>>,
    mut until: watch::Receiver<Option<u64>>,
    presence: std::sync::Arc<super::presence::PresenceLog>,
) -> SubscriberResult {
    let mut result = SubscriberResult::default();
    let mut feed = match client.events(&volume, None).await {
        Ok(f) => f,
        Err(e) => {
            let _ = ready.send(Err(e));
            return result;
        }
    };
    let mut last = match feed.next().await {
        Ok(Some(FeedEvent::Hello { version })) => version,
        Ok(other) => {
            let _ = ready.send(Err(ClientError::Decode(format!(
                "the feed began with {other:?}, not hello"
            ))));
            return result;
        }
        Err(e) => {
            let _ = ready.send(Err(e));
            return result;
        }
    };
    let _ = ready.send(Ok(last));
    let mut deadline: Option<tokio::time::Instant> = None;
    let mut until_open = true;
    loop {
        let target = *until.borrow();
        if target.is_some_and(|t| last >= t) {
            break;
        }
        let sleep = async {
            match deadline {
                Some(d) => tokio::time::sleep_until(d).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            changed = until.changed(), if until_open => {
                if changed.is_err() {
                    until_open = false;
                }
                if until.borrow().is_some() && deadline.is_none() {
                    deadline = Some(tokio::time::Instant::now() + drain);
                }
            }
            () = sleep => break,
            event = feed.next() => match event {
                Ok(Some(FeedEvent::Commit(c))) => {
                    result.seen.entry(c.version).or_insert_with(Instant::now);
                    last = last.max(c.version);
                }
                Ok(Some(FeedEvent::Hello { .. })) => {}
                Ok(Some(FeedEvent::Presence(p))) => {
                    if let Some(label) = &p.label {
                        presence.arrived(label);
                    }
                }
                Ok(Some(FeedEvent::Resync { since, version })) => {
                    result.resyncs += 1;
                    let mut from = since;
                    while from < version {
                        match client.changes(&volume, from, None).await {
                            Ok(list) => {
                                let now = Instant::now();
                                for c in &list.changes {
                                    result.seen.entry(c.version).or_insert(now);
                                    from = from.max(c.version);
                                }
                                if !list.more || list.changes.is_empty() {
                                    break;
                                }
                            }
                            Err(e) => {
                                *result.errors.entry(format!("changes {}", e.kind())).or_default() += 1;
                                break;
                            }
                        }
                    }
                    last = last.max(version);
                }
                Ok(None) | Err(_) => {
                    // The subscription broke: resume after the last version seen.
                    result.reconnects += 1;
                    *result.errors.entry("disconnected".into()).or_default() += 1;
                    loop {
                        match client.events(&volume, Some(last)).await {
                            Ok(f) => {
                                feed = f;
                                break;
                            }
                            Err(_) if deadline.is_some_and(|d| tokio::time::Instant::now() >= d) => {
                                return result;
                            }
                            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                        }
                    }
                }
            },
        }
    }
    result
}
