//! Who did what, and taking it back (`docs/editing.md`, "History and undo"):
//! `GET .../history`, `GET .../tags`, `PUT .../tags/{tag}`, `POST .../undo`,
//! `POST .../revert`, and presence (`POST`/`GET .../presence`).
//!
//! Undo, revert and tags are commits: they queue for the volume's writer as edits do, are
//! durable when answered and are announced on the change feed with their author.

use super::auth::{ReadToken, WriteToken};
use super::cpu::Admission;
use super::edit::{check_message, if_match};
use super::extract::{Json, Path, Query};
use super::{ApiError, AppState};
use crate::cancel::CancelToken;
use crate::volume::group::Work;
use crate::volume::history::valid_tag;
use crate::volume::presence;
use crate::volume::undo::UndoJob;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use isovox_proto::api::EditResponse;
use isovox_proto::history::{
    CommitInfo, CommitNote, HistoryList, PresenceList, PresenceRequest, RevertRequest, TagList,
    TagRequest, UndoRequest, MAX_TAG_LEN,
};
use serde::Deserialize;
use std::sync::Arc;

/// `?before=V&limit=N`.
#[derive(Debug, Deserialize)]
pub struct HistoryQuery {
    /// List the commits before this version; from the head when absent.
    pub before: Option<u64>,
    /// Commits listed at most (100 by default, at most 1000).
    pub limit: Option<usize>,
}

/// `GET /v1/volumes/{name}/history?before=V&limit=N`: commits newest first, read from their
/// records on the CPU threads.
pub async fn history(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(query): Query<HistoryQuery>,
) -> Result<axum::Json<HistoryList>, ApiError> {
    let vol = state.catalog.get(&name)?.clone();
    let list = state
        .cpu
        .run(Admission::Wait, move || {
            vol.history(query.before, query.limit)
        })
        .await?;
    Ok(axum::Json(list))
}

/// `GET /v1/volumes/{name}/tags`.
pub async fn tags(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<axum::Json<TagList>, ApiError> {
    let vol = state.catalog.get(&name)?.clone();
    let list = state.cpu.run(Admission::Wait, move || vol.tags()).await?;
    Ok(axum::Json(list))
}

/// A commit note naming `user` with `message`.
fn note_by(user: &str, message: Option<String>) -> CommitNote {
    CommitNote {
        info: CommitInfo {
            author: Some(user.to_string()),
            message,
            ..CommitInfo::default()
        },
        ..CommitNote::default()
    }
}

/// Queues `work` for the writer of `name` and waits until it is durable.
async fn commit(
    state: &AppState,
    name: &str,
    work: Work,
    headers: &HeaderMap,
) -> Result<EditResponse, ApiError> {
    let vol = state.catalog.get(name)?.clone();
    vol.check_writable()?;
    let if_match = if_match(headers)?;
    let cancel = CancelToken::with_timeout(state.config.edit_timeout);
    let _stop_when_dropped = cancel.cancel_on_drop();
    let response = vol
        .submit(
            work,
            if_match,
            cancel,
            state.group_commit(),
            &state.main_runtime(),
        )
        .await?;
    Ok(response)
}

/// `PUT /v1/volumes/{name}/tags/{tag}` with `{"version": V}`: names version V (write role).
/// A tag is a commit that changes no brick; setting a tag again moves it.
pub async fn put_tag(
    WriteToken(token): WriteToken,
    State(state): State<AppState>,
    Path((name, tag)): Path<(String, String)>,
    headers: HeaderMap,
    Json(request): Json<TagRequest>,
) -> Result<(StatusCode, axum::Json<EditResponse>), ApiError> {
    if !valid_tag(&tag) {
        return Err(ApiError::BadRequest(format!(
            "tag {tag:?}: 1 to {MAX_TAG_LEN} of A-Z, a-z, 0-9, '.', '_', '-', not all digits"
        )));
    }
    state.edit_rate.take(&token.user)?;
    let work = Work::Tag {
        tag: tag.clone(),
        version: request.version,
        note: note_by(&token.user, None),
    };
    let response = commit(&state, &name, work, &headers).await?;
    tracing::info!(volume = %name, user = %token.user, tag = %tag, version = request.version, "tag set");
    Ok((StatusCode::OK, axum::Json(response)))
}

/// `POST /v1/volumes/{name}/undo` with `{"version": V}`: a new version without the edit of V
/// (or, for an undo's version, with its edit again), later edits over it applied again.
pub async fn undo(
    WriteToken(token): WriteToken,
    State(state): State<AppState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    Json(request): Json<UndoRequest>,
) -> Result<axum::Json<EditResponse>, ApiError> {
    check_message(request.message.as_deref())?;
    state.edit_rate.take(&token.user)?;
    let job = UndoJob {
        version: request.version,
        user: token.user.clone(),
        admin: token.admin,
        message: request.message,
        limits: state.edit_limits(),
        volumes: Arc::new(state.resolver()),
    };
    let response = commit(&state, &name, Work::Undo(job), &headers).await?;
    tracing::info!(volume = %name, user = %token.user, undone = request.version,
        version = response.version, replayed = response.replayed, "undo committed");
    Ok(axum::Json(response))
}

/// `POST /v1/volumes/{name}/revert` with `{"to": V}`: a new version whose content is V's.
pub async fn revert(
    WriteToken(token): WriteToken,
    State(state): State<AppState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    Json(request): Json<RevertRequest>,
) -> Result<axum::Json<EditResponse>, ApiError> {
    check_message(request.message.as_deref())?;
    state.edit_rate.take(&token.user)?;
    let work = Work::Revert {
        to: request.to,
        note: note_by(&token.user, request.message),
    };
    let response = commit(&state, &name, work, &headers).await?;
    tracing::info!(volume = %name, user = %token.user, to = request.to,
        version = response.version, "revert committed");
    Ok(axum::Json(response))
}

/// `POST /v1/volumes/{name}/presence`: where the user is (read role enough), at most a few
/// times a second per user; sent to the feed's other subscribers, never stored.
pub async fn post_presence(
    // First: without a token, nothing else is read.
    ReadToken(principal): ReadToken,
    State(state): State<AppState>,
    Path(name): Path<String>,
    Json(request): Json<PresenceRequest>,
) -> Result<StatusCode, ApiError> {
    let vol = state.catalog.get(&name)?.clone();
    presence::check(&request).map_err(ApiError::BadRequest)?;
    state.presence_rate.take(&principal.user)?;
    vol.present(&principal.user, request, &state.main_runtime());
    Ok(StatusCode::NO_CONTENT)
}

/// `GET /v1/volumes/{name}/presence`: who is there now.
pub async fn presence(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<axum::Json<PresenceList>, ApiError> {
    let vol = state.catalog.get(&name)?;
    Ok(axum::Json(PresenceList {
        present: vol.presences(),
    }))
}
