//! The change feed (`GET .../events`, server-sent events) and its catch-up list
//! (`GET .../changes?since=N`), both read from the file's commit records (`docs/editing.md`).

use super::compression::{accepts_zstd, Body};
use super::cpu::Admission;
use super::extract::{Path, Query};
use super::{ApiError, AppState};
use crate::volume::{FeedItem, LiveVolume, VolumeError, DEFAULT_CHANGES};
use axum::extract::State;
use axum::http::HeaderMap;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use std::collections::VecDeque;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::broadcast::error::RecvError;

/// `?since=N&limit=K`.
#[derive(Debug, Deserialize)]
pub struct ChangesQuery {
    /// The version to list after; everything the file holds when absent.
    pub since: Option<u64>,
    /// Versions listed at most (1000 by default, at most 10,000).
    pub limit: Option<usize>,
}

/// `GET /v1/volumes/{name}/changes?since=N&limit=K`, read from the file (and compressed) on the
/// CPU threads, with a place in their queue.
pub async fn changes(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(query): Query<ChangesQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let vol = state.catalog.get(&name)?.clone();
    let zstd = accepts_zstd(&headers);
    let body = state
        .cpu
        .answer(0, move || {
            let list = vol.change_list(query.since, query.limit)?;
            Ok::<_, VolumeError>(Body::json(&list, zstd))
        })
        .await?;
    Ok(body.respond("application/json", HeaderMap::new()))
}

/// `GET /v1/volumes/{name}/events`: server-sent events, `hello` then one `commit` per version
/// (after `?since=N` or `Last-Event-ID: N` first the versions since then, from the file), and
/// `presence` events as users move or leave.
pub async fn events(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(query): Query<ChangesQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let since = query.since.or(last_event_id(&headers)?);
    let closing = state.closing.closed();
    // Starting reads nothing from the file or the store (the head and the history are in
    // memory; the backlog after `since` is read later, on the CPU queue): a subscription is
    // taken even while a replica's store reads are all busy, as a new viewer's first request.
    let vol = state.catalog.get(&name)?;
    let feed = Feed::start(vol, since, closing, state.clone())?;
    let stream = futures_util::stream::unfold(feed, |mut feed| async move {
        feed.next()
            .await
            .map(|e| (Ok::<_, std::convert::Infallible>(e), feed))
    });
    Ok(Sse::new(stream)
        .keep_alive(
            KeepAlive::new()
                .interval(Duration::from_secs(15))
                .text("keep-alive"),
        )
        .into_response())
}

/// `Last-Event-ID: N`, the version a reconnecting subscriber had. Empty is no event seen yet
/// (what a browser's `EventSource` means by it). A number beyond u64 is past any head: read
/// as `u64::MAX` it gets the 409 any version past the head gets.
fn last_event_id(headers: &HeaderMap) -> Result<Option<u64>, ApiError> {
    let Some(value) = headers.get("last-event-id") else {
        return Ok(None);
    };
    let text = value.to_str().map(str::trim).unwrap_or("?");
    if text.is_empty() {
        return Ok(None);
    }
    if text.len() > 20 || !text.bytes().all(|b| b.is_ascii_digit()) {
        return Err(ApiError::BadRequest(format!(
            "Last-Event-ID {value:?} must be a version number"
        )));
    }
    Ok(Some(text.parse().unwrap_or(u64::MAX)))
}

/// Where a feed subscriber is.
struct Feed {
    vol: Arc<LiveVolume>,
    /// Where the backlog is read (the CPU threads).
    state: AppState,
    rx: tokio::sync::broadcast::Receiver<Arc<FeedItem>>,
    /// Presence events (JSON), sent as they come; one missed is replaced by the next.
    presence: tokio::sync::broadcast::Receiver<Arc<String>>,
    /// Resolves when the server shuts down: the stream ends then (subscribers reconnect with
    /// `since=` to the next server and miss nothing), so the shutdown does not wait for it.
    closing: Pin<Box<dyn Future<Output = ()> + Send>>,
    /// Events to send before anything else.
    pending: VecDeque<Event>,
    /// The last version sent (or announced by `hello`).
    last: u64,
    /// Versions up to this one come from the file, not the channel.
    backlog_until: u64,
}

impl Feed {
    /// A subscriber of `vol` that first gets `hello`, then the versions after `since` (from
    /// the file, when given), then every new one, until `closing` resolves.
    fn start(
        vol: &Arc<LiveVolume>,
        since: Option<u64>,
        closing: impl Future<Output = ()> + Send + 'static,
        state: AppState,
    ) -> Result<Feed, ApiError> {
        // Subscribe before reading the head, so no version falls between the two.
        let rx = vol.subscribe();
        let presence = vol.subscribe_presence();
        let head = vol.head().version;
        if let Some(since) = since {
            vol.check_since(since)?;
        }
        let hello = Event::default()
            .event("hello")
            .data(format!("{{\"version\":{head}}}"));
        Ok(Feed {
            vol: vol.clone(),
            state,
            rx,
            presence,
            closing: Box::pin(closing),
            pending: VecDeque::from([hello]),
            last: since.unwrap_or(head),
            backlog_until: head,
        })
    }

    async fn next(&mut self) -> Option<Event> {
        loop {
            if let Some(e) = self.pending.pop_front() {
                return Some(e);
            }
            if self.last < self.backlog_until {
                let (vol, since) = (self.vol.clone(), self.last);
                let page = self
                    .state
                    .cpu
                    .run(Admission::Wait, move || vol.changes(since, DEFAULT_CHANGES));
                match page.await {
                    Ok((events, _)) if !events.is_empty() => {
                        for c in events
                            .into_iter()
                            .filter(|c| c.version <= self.backlog_until)
                        {
                            self.last = c.version;
                            let json = serde_json::to_string(&c).unwrap_or_default();
                            self.pending.push_back(commit_event(c.version, json));
                        }
                    }
                    Ok(_) => self.backlog_until = self.last,
                    Err(e) => {
                        tracing::warn!(error = ?e, "change feed backlog failed");
                        return None;
                    }
                }
                continue;
            }
            let received = tokio::select! {
                received = self.rx.recv() => received,
                presence = self.presence.recv() => match presence {
                    Ok(json) => {
                        return Some(Event::default().event("presence").data(json.as_str()))
                    }
                    // Missed cursors are replaced by the next ones. (Closed cannot happen: the
                    // sender is the volume's, which this feed holds.)
                    Err(_) => continue,
                },
                () = &mut self.closing => return None,
            };
            match received {
                Ok(item) if item.version <= self.last => continue,
                Ok(item) => {
                    self.last = item.version;
                    return Some(commit_event(item.version, item.json.clone()));
                }
                Err(RecvError::Lagged(_)) => {
                    let head = self.vol.head().version;
                    let since = self.last;
                    self.last = head;
                    return Some(
                        Event::default()
                            .event("resync")
                            .data(format!("{{\"since\":{since},\"version\":{head}}}")),
                    );
                }
                Err(RecvError::Closed) => return None,
            }
        }
    }
}

fn commit_event(version: u64, json: String) -> Event {
    Event::default()
        .event("commit")
        .id(version.to_string())
        .data(json)
}
