//! `POST /v1/volumes/{name}/edits`: an ICVG edit as the next version (`docs/editing.md`).

use super::auth::WriteToken;
use super::cpu::blocking;
use super::extract::Path;
use super::request_body::{is_json, read_limited};
use super::{ApiError, AppState};
use axum::body::Body;
use axum::extract::State;
use axum::http::{header, HeaderMap};
use axum::Json;
use isovox_proto::api::EditResponse;
use isovox_proto::icvg::EditRequest;

/// Largest edit request body.
const MAX_EDIT_BODY: usize = 1 << 20;

/// Checks the token before anything is read, compiles the edit off the async runtime, queues
/// it for the volume's writer (bounded queue; the writer commits the edits waiting together,
/// each as its own version), and answers with the new version once it is durable.
pub async fn edit(
    // First: without a token, nothing else is read.
    WriteToken(token): WriteToken,
    State(state): State<AppState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<EditResponse>, ApiError> {
    let vol = state.catalog.get(&name)?.clone();
    let request = edit_request(&headers, body).await?;
    let if_match = if_match(&headers)?;
    state.edit_rate.take(&token.name)?;
    let (limits, volumes, preparing) = (state.edit_limits(), state.resolver(), vol.clone());
    let edit =
        blocking(move || preparing.prepare_edit(&request, &limits, &volumes, if_match)).await?;
    let response = vol.submit(edit, if_match, state.group_commit()).await?;
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

/// The request body as an edit request: JSON, at most [`MAX_EDIT_BODY`] bytes.
async fn edit_request(headers: &HeaderMap, body: Body) -> Result<EditRequest, ApiError> {
    if !is_json(headers) {
        return Err(ApiError::UnsupportedMedia(
            "an edit is JSON: send Content-Type: application/json".into(),
        ));
    }
    let body = read_limited(headers, body, MAX_EDIT_BODY, "an edit request").await?;
    serde_json::from_slice(&body)
        .map_err(|e| ApiError::BadRequest(format!("not an edit request: {e}")))
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
