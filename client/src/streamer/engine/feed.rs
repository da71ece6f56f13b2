//! The change-feed follower: a task of its own that forwards commits to the engine in order,
//! reconnecting (or asking for a reload) when the stream ends.

use crate::client::{Client, Feed, FeedEvent};
use crate::streamer::{FEED_RETRY_MAX, FEED_RETRY_MIN};
use isovox_proto::api::{ChangeEvent, VolumeInfo};
use tokio::sync::mpsc;

/// What the change-feed follower forwards to the task.
#[derive(Debug)]
pub(in crate::streamer) enum FeedMsg {
    /// Commits in version order, applied together: one live commit, or every version the
    /// server replayed after a (re)subscription.
    Commits(Vec<ChangeEvent>),
    /// The history the streamer followed is gone: start over from this metadata.
    Reload(VolumeInfo),
    Error(String),
}

/// Follows the change feed from `feed` (subscribed after version `last`), forwarding commits in
/// order; reconnects after `last` when the stream ends.
///
/// After a subscription the server first replays the versions after `last` up to the head its
/// `hello` names. Those are forwarded as one message, so the task applies them together and
/// fetches the newest content of what they changed, never the content of a version it already
/// knows is superseded (after a long disconnect, one grid region and one blob per changed brick
/// instead of one per missed version).
pub(in crate::streamer) async fn follow(
    client: Client,
    name: String,
    feed: Feed,
    mut last: u64,
    tx: mpsc::Sender<FeedMsg>,
) {
    let mut feed = Some(feed);
    let mut delay = FEED_RETRY_MIN;
    loop {
        let mut f = match feed.take() {
            Some(f) => f,
            None => match client.events(&name, Some(last)).await {
                Ok(f) => f,
                Err(e) if matches!(e.status().map(|s| s.as_u16()), Some(409 | 410)) => {
                    // 410: versions after `last` were compacted away; 409: the volume is behind
                    // `last` (replaced). Either way what the streamer holds cannot be updated.
                    match client.volume(&name).await {
                        Ok(info) => {
                            last = info.version;
                            if tx.send(FeedMsg::Reload(info)).await.is_err() {
                                return;
                            }
                        }
                        Err(e) => {
                            let msg = format!("change feed: reloading the metadata: {e}");
                            if tx.send(FeedMsg::Error(msg)).await.is_err() {
                                return;
                            }
                            tokio::time::sleep(delay).await;
                            delay = (delay * 2).min(FEED_RETRY_MAX);
                        }
                    }
                    continue;
                }
                Err(e) => {
                    let msg = format!("change feed: cannot subscribe after version {last}: {e}");
                    if tx.send(FeedMsg::Error(msg)).await.is_err() {
                        return;
                    }
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(FEED_RETRY_MAX);
                    continue;
                }
            },
        };
        // Commits read but not forwarded yet: the replay, until it reaches `replayed_to`.
        let mut replay = Vec::new();
        let mut replayed_to = 0;
        let pause = loop {
            match f.next().await {
                Ok(Some(FeedEvent::Hello { version })) => {
                    delay = FEED_RETRY_MIN;
                    replayed_to = version;
                }
                Ok(Some(FeedEvent::Commit(ev))) => {
                    if ev.version > last {
                        last = ev.version;
                        replay.push(*ev);
                        if last >= replayed_to
                            && tx
                                .send(FeedMsg::Commits(std::mem::take(&mut replay)))
                                .await
                                .is_err()
                        {
                            return;
                        }
                    }
                }
                // Fell behind: subscribing again after `last` replays the gap from the file.
                Ok(Some(FeedEvent::Resync { .. })) => break false,
                // Where others are is not the streamer's business.
                Ok(Some(FeedEvent::Presence(_))) => {}
                Ok(None) => {
                    let msg = format!("change feed closed after version {last}; reconnecting");
                    if tx.send(FeedMsg::Error(msg)).await.is_err() {
                        return;
                    }
                    break true;
                }
                Err(e) => {
                    let msg = format!("change feed failed after version {last}: {e}");
                    if tx.send(FeedMsg::Error(msg)).await.is_err() {
                        return;
                    }
                    break true;
                }
            }
        };
        // A stream that broke during the replay: what arrived of it is still history to apply.
        if !replay.is_empty() && tx.send(FeedMsg::Commits(replay)).await.is_err() {
            return;
        }
        if pause {
            tokio::time::sleep(delay).await;
            delay = (delay * 2).min(FEED_RETRY_MAX);
        }
    }
}
