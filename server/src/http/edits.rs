//! The write side: edits, compaction, the change feed and its catch-up list (`docs/editing.md`).

use super::auth::Scope;
use super::handlers::volume;
use super::{ApiError, AppState};
use crate::catalog::Catalog;
use crate::icvg::edit::{CheckpointPolicy, Edit};
use crate::icvg::term::{TermError, VolumeResolver};
use crate::store::Snapshot;
use crate::volume::{EditError, FeedItem, LiveVolume};
use crate::voxelize::solid::TriMesh;
use crate::voxelize::store::{MeshInfo, MeshStore};
use axum::body::Body;
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{Path, Query, Request, State};
use axum::http::{header, HeaderMap};
use axum::middleware::Next;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::Json;
use isovox_proto::api::{ChangeList, CompactResponse, EditResponse};
use isovox_proto::icvg::EditRequest;
use serde::Deserialize;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::broadcast::error::RecvError;

/// Versions listed by one `changes` answer, by default and at most.
const DEFAULT_CHANGES: usize = 1000;
const MAX_CHANGES: usize = 10_000;

/// Largest edit request body.
const MAX_EDIT_BODY: usize = 1 << 20;

/// With `--private-reads`: every `/v1` route needs a token of either scope.
pub async fn require_token(
    State(state): State<AppState>,
    request: Request,
    next: Next,
) -> Response {
    if request.uri().path().starts_with("/v1/") {
        if let Err(e) = state
            .config
            .tokens
            .authorize(request.headers(), Scope::Read)
        {
            return e.into_response();
        }
    }
    next.run(request).await
}

/// Volumes named in edit terms: the catalog's, at their current version; meshes: the uploads.
struct CatalogVolumes(Arc<Catalog>, Option<Arc<MeshStore>>);

impl VolumeResolver for CatalogVolumes {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        self.0
            .volume(name)
            .map(|v| v.head())
            .ok_or_else(|| TermError(format!("no volume named {name:?}")))
    }

    fn mesh(&self, hash: u64) -> Result<Arc<TriMesh>, TermError> {
        match &self.1 {
            Some(store) => store.get(hash).map_err(TermError),
            None => Err(TermError("this server keeps no meshes".into())),
        }
    }
}

/// Largest mesh upload.
const MAX_MESH_BODY: usize = 256 << 20;

#[derive(Debug, Deserialize)]
pub struct MeshQuery {
    pub format: Option<String>,
}

/// `POST /v1/meshes?format=stl|obj|ply|glb`: keeps a watertight model by its content hash,
/// for `mesh` leaves of edit terms.
pub async fn upload_mesh(
    State(state): State<AppState>,
    query: Result<Query<MeshQuery>, QueryRejection>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<MeshInfo>, ApiError> {
    let token = state
        .config
        .tokens
        .authorize(&headers, Scope::Write)?
        .clone();
    let Query(query) = query.map_err(|e| ApiError::BadRequest(format!("malformed query: {e}")))?;
    let store = state
        .mesh_store
        .clone()
        .ok_or_else(|| ApiError::NotFound("this server keeps no meshes".into()))?;
    let format = query
        .format
        .ok_or_else(|| {
            ApiError::BadRequest("give the model's ?format= (stl, obj, ply or glb)".into())
        })?
        .to_ascii_lowercase();
    let body = axum::body::to_bytes(body, MAX_MESH_BODY)
        .await
        .map_err(|_| ApiError::TooLarge(format!("a model takes at most {MAX_MESH_BODY} bytes")))?;
    let info = tokio::task::spawn_blocking(move || store.store(&body, &format))
        .await
        .map_err(|e| ApiError::Internal(format!("mesh task failed: {e}")))?
        .map_err(ApiError::Unprocessable)?;
    tracing::info!(token = %token.name, hash = %format!("{:016x}", info.hash), triangles = info.triangles, "mesh stored");
    Ok(Json(info))
}

/// `If-Match: N`, `"N"` or `W/"N"`.
fn if_match(headers: &HeaderMap) -> Result<Option<u64>, ApiError> {
    let Some(value) = headers.get(header::IF_MATCH) else {
        return Ok(None);
    };
    value
        .to_str()
        .ok()
        .map(|v| v.trim().trim_start_matches("W/").trim_matches('"'))
        .and_then(|v| v.parse::<u64>().ok())
        .map(Some)
        .ok_or_else(|| {
            ApiError::BadRequest("If-Match takes a version number, quoted or not".into())
        })
}

fn is_json(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .is_some_and(|m| {
            let m = m.trim();
            m.eq_ignore_ascii_case("application/json") || m.ends_with("+json")
        })
}

/// `POST /v1/volumes/{name}/edits`: validate, wait for the volume's writer (bounded queue),
/// apply and commit off the async runtime, answer with the new version.
pub async fn edit(
    State(state): State<AppState>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<EditResponse>, ApiError> {
    // The token is checked before the body is read: without one, nothing is read.
    let token = state
        .config
        .tokens
        .authorize(&headers, Scope::Write)?
        .clone();
    let Path(name) = path.map_err(|e| ApiError::BadRequest(format!("malformed path: {e}")))?;
    let vol = volume(&state, &name)?;
    if !is_json(&headers) {
        return Err(ApiError::UnsupportedMedia(
            "an edit is JSON: send Content-Type: application/json".into(),
        ));
    }
    let body = axum::body::to_bytes(body, MAX_EDIT_BODY)
        .await
        .map_err(|_| {
            ApiError::TooLarge(format!(
                "an edit request takes at most {MAX_EDIT_BODY} bytes (or the body was cut off)"
            ))
        })?;
    let request: EditRequest = serde_json::from_slice(&body)
        .map_err(|e| ApiError::BadRequest(format!("not an edit request: {e}")))?;
    let expected = if_match(&headers)?;
    state.edit_rate.take(&token.name)?;
    let head = vol.head();
    let layout = head.layout().clone();
    // Compiling can voxelize a mesh leaf: CPU work, off the async runtime.
    let (limits, resolver) = (
        state.config.term_limits,
        CatalogVolumes(state.catalog.clone(), state.mesh_store.clone()),
    );
    let voxel_type = layout.voxel_type();
    let edit = tokio::task::spawn_blocking(move || {
        Edit::from_request(&request, voxel_type, &limits, &resolver)
    })
    .await
    .map_err(|e| ApiError::Internal(format!("edit compile task failed: {e}")))?
    .map_err(|e| ApiError::Unprocessable(format!("invalid edit: {}", e.0)))?;
    let voxels = edit.evaluated_voxels(&layout);
    if voxels > state.config.max_edit_voxels {
        return Err(ApiError::Unprocessable(format!(
            "the edit reaches {voxels} voxels; this server allows {} per edit (give a region, or split it)",
            state.config.max_edit_voxels
        )));
    }
    if let Some(v) = expected.filter(|&v| v != head.version) {
        return Err(conflict(v, head.version));
    }
    let mut writer = wait_for_writer(&state, vol).await?;
    let applying = vol.clone();
    let response = tokio::task::spawn_blocking(move || {
        applying.apply(&mut writer, &edit, expected, CheckpointPolicy::default())
    })
    .await
    .map_err(|e| ApiError::Internal(format!("edit task failed: {e}")))?
    .map_err(|e| match e {
        EditError::Conflict { expected, current } => conflict(expected, current),
        EditError::Store(e) => ApiError::Internal(crate::store::error_chain(&e)),
    })?;
    tracing::info!(
        volume = %name,
        token = %token.name,
        version = response.version,
        changed = response.changed.iter().map(Vec::len).sum::<usize>(),
        elapsed_us = response.elapsed_us,
        "edit committed"
    );
    Ok(Json(response))
}

/// Takes a place in the volume's writer queue (503 when `--edit-queue` edits already wait) and
/// waits for the writer, in arrival order.
async fn wait_for_writer(
    state: &AppState,
    vol: &LiveVolume,
) -> Result<tokio::sync::OwnedMutexGuard<crate::volume::WriterSlot>, ApiError> {
    let ticket = vol
        .enqueue(state.config.edit_queue)
        .ok_or(ApiError::Overloaded(1))?;
    let writer = vol.lock_writer().await;
    drop(ticket);
    Ok(writer)
}

fn conflict(expected: u64, current: u64) -> ApiError {
    ApiError::Conflict {
        detail: format!("If-Match names version {expected}; the volume is at version {current}"),
        version: current,
    }
}

/// `POST /v1/volumes/{name}/compact`: rewrite the file with only the head version.
pub async fn compact(
    State(state): State<AppState>,
    path: Result<Path<String>, PathRejection>,
    headers: HeaderMap,
) -> Result<Json<CompactResponse>, ApiError> {
    let token = state
        .config
        .tokens
        .authorize(&headers, Scope::Write)?
        .clone();
    let Path(name) = path.map_err(|e| ApiError::BadRequest(format!("malformed path: {e}")))?;
    let vol = volume(&state, &name)?;
    let mut writer = wait_for_writer(&state, vol).await?;
    let compacting = vol.clone();
    let report = tokio::task::spawn_blocking(move || compacting.compact(&mut writer))
        .await
        .map_err(|e| ApiError::Internal(format!("compaction task failed: {e}")))?
        .map_err(|e| ApiError::Internal(crate::store::error_chain(&e)))?;
    tracing::info!(volume = %name, token = %token.name, version = report.version,
        bytes_before = report.bytes_before, bytes_after = report.bytes_after, "compacted");
    Ok(Json(CompactResponse {
        version: report.version,
        bytes_before: report.bytes_before,
        bytes_after: report.bytes_after,
        bricks: report.bricks,
        elapsed_us: report.elapsed.as_micros() as u64,
    }))
}

#[derive(Debug, Deserialize)]
pub struct ChangesQuery {
    pub since: Option<u64>,
    pub limit: Option<usize>,
}

/// Checks that the versions after `since` can be listed: 400 past the head, 410 when
/// compaction dropped some of them.
fn check_since(vol: &LiveVolume, since: u64) -> Result<(), ApiError> {
    let head = vol.head().version;
    let oldest = vol.oldest();
    if since > head {
        return Err(ApiError::BadRequest(format!(
            "since = {since} is after the current version {head}"
        )));
    }
    if since.saturating_add(1) < oldest {
        return Err(ApiError::Gone(format!(
            "versions before {oldest} were compacted away; reload the volume (metadata, then bricks by hash) and follow from version {head}"
        )));
    }
    Ok(())
}

/// `GET /v1/volumes/{name}/changes?since=N&limit=K`.
pub async fn changes(
    State(state): State<AppState>,
    path: Result<Path<String>, PathRejection>,
    query: Result<Query<ChangesQuery>, QueryRejection>,
) -> Result<Json<ChangeList>, ApiError> {
    let Path(name) = path.map_err(|e| ApiError::BadRequest(format!("malformed path: {e}")))?;
    let Query(query) = query.map_err(|e| ApiError::BadRequest(format!("malformed query: {e}")))?;
    let vol = volume(&state, &name)?;
    // Without `since`: everything the file holds.
    let since = query
        .since
        .unwrap_or_else(|| vol.oldest().saturating_sub(1));
    let limit = query.limit.unwrap_or(DEFAULT_CHANGES);
    if !(1..=MAX_CHANGES).contains(&limit) {
        return Err(ApiError::BadRequest(format!(
            "limit must be in 1..={MAX_CHANGES}"
        )));
    }
    check_since(vol, since)?;
    let listing = vol.clone();
    let (changes, more) = tokio::task::spawn_blocking(move || listing.changes(since, limit))
        .await
        .map_err(|e| ApiError::Internal(format!("changes task failed: {e}")))??;
    // Read after the listing: the head is at least the last version listed.
    let head = vol.head().version;
    Ok(Json(ChangeList {
        since,
        head: changes.last().map_or(head, |c| c.version.max(head)),
        oldest: vol.oldest(),
        more,
        changes,
    }))
}

/// Where a feed subscriber is.
struct Feed {
    vol: Arc<LiveVolume>,
    rx: tokio::sync::broadcast::Receiver<Arc<FeedItem>>,
    /// Events to send before anything else.
    pending: VecDeque<Event>,
    /// The last version sent (or announced by `hello`).
    last: u64,
    /// Versions up to this one come from the file, not the channel.
    backlog_until: u64,
}

impl Feed {
    async fn next(&mut self) -> Option<Event> {
        loop {
            if let Some(e) = self.pending.pop_front() {
                return Some(e);
            }
            if self.last < self.backlog_until {
                let (vol, since) = (self.vol.clone(), self.last);
                let page = tokio::task::spawn_blocking(move || vol.changes(since, DEFAULT_CHANGES))
                    .await
                    .ok()?;
                match page {
                    Ok((events, _)) if !events.is_empty() => {
                        for c in events
                            .into_iter()
                            .filter(|c| c.version <= self.backlog_until)
                        {
                            self.last = c.version;
                            let json = serde_json::to_string(&c).unwrap_or_default();
                            self.pending.push_back(commit_event(c.version, json));
                        }
                        continue;
                    }
                    Ok(_) => self.backlog_until = self.last,
                    Err(e) => {
                        tracing::warn!(error = %crate::store::error_chain(&e), "change feed backlog failed");
                        return None;
                    }
                }
                continue;
            }
            match self.rx.recv().await {
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

/// `GET /v1/volumes/{name}/events`: server-sent events, `hello` then one `commit` per version
/// (after `?since=N` or `Last-Event-ID: N` first the versions since then, from the file).
pub async fn events(
    State(state): State<AppState>,
    path: Result<Path<String>, PathRejection>,
    query: Result<Query<ChangesQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Path(name) = path.map_err(|e| ApiError::BadRequest(format!("malformed path: {e}")))?;
    let Query(query) = query.map_err(|e| ApiError::BadRequest(format!("malformed query: {e}")))?;
    let vol = volume(&state, &name)?;
    let last_event_id = match headers.get("last-event-id") {
        None => None,
        Some(v) => Some(
            v.to_str()
                .ok()
                .and_then(|v| v.trim().parse::<u64>().ok())
                .ok_or_else(|| ApiError::BadRequest("Last-Event-ID must be a version".into()))?,
        ),
    };
    // Subscribe before reading the head, so no version falls between the two.
    let rx = vol.subscribe();
    let head = vol.head().version;
    let since = query.since.or(last_event_id);
    if let Some(since) = since {
        check_since(vol, since)?;
    }
    let hello = Event::default()
        .event("hello")
        .data(format!("{{\"version\":{head}}}"));
    let feed = Feed {
        vol: vol.clone(),
        rx,
        pending: VecDeque::from([hello]),
        last: since.unwrap_or(head),
        backlog_until: head,
    };
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
