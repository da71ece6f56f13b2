//! `POST /v1/volumes/{name}/edits`: an ICVG edit as the next version (`docs/editing.md`);
//! with `?dry_run=true`, what it would change, committing nothing.

use super::auth::WriteToken;
use super::cpu::blocking;
use super::extract::Path;
use super::request_body::read_json;
use super::{ApiError, AppState};
use crate::cancel::CancelToken;
use crate::volume::group::Work;
use axum::body::Body;
use axum::extract::State;
use axum::http::{header, HeaderMap, Uri};
use axum::Json;
use isovox_proto::api::EditResponse;
use isovox_proto::history::MAX_MESSAGE_CHARS;
use isovox_proto::icvg::EditRequest;

/// Largest edit request body.
const MAX_EDIT_BODY: usize = 1 << 20;

/// Checks the token before anything is read, compiles the edit on the main runtime's blocking
/// pool (`cpu::blocking`), queues
/// it for the volume's writer (bounded queue; the writer commits the edits waiting together,
/// each as its own version), and answers with the new version once it is durable. Compiling and
/// evaluating each get the server's edit timeout (waiting for the writer does not count); the
/// work stops as soon as this request's future is dropped (the client left, or a shutdown
/// closed the connection), and nothing of the edit is committed then.
pub async fn edit(
    // First: without a token, nothing else is read.
    WriteToken(token): WriteToken,
    State(state): State<AppState>,
    Path(name): Path<String>,
    uri: Uri,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<EditResponse>, ApiError> {
    let vol = state.catalog.get(&name)?.clone();
    let dry_run = query_flag(&uri, "dry_run")?;
    let request: EditRequest = read_json(&headers, body, MAX_EDIT_BODY, "an edit request").await?;
    check_message(request.message.as_deref())?;
    let if_match = if_match(&headers)?;
    state.edit_rate.take(&token.user)?;
    let cancel = CancelToken::with_timeout(state.config.edit_timeout);
    let _stop_when_dropped = cancel.cancel_on_drop();
    let (limits, volumes, preparing) = (state.edit_limits(), state.resolver(), vol.clone());
    let compiling = cancel.clone();
    let runtime = state.main_runtime();
    let mut edit = blocking(runtime.clone(), move || {
        preparing.prepare_edit(&request, &limits, &volumes, if_match, &compiling)
    })
    .await?;
    edit.note.info.author = Some(token.user.clone());
    let work = Work::edit(edit, dry_run);
    let response = vol
        .submit(work, if_match, cancel, state.group_commit(), &runtime)
        .await?;
    if dry_run {
        tracing::debug!(volume = %name, user = %token.user, "dry run answered");
    } else if response.committed {
        tracing::info!(
            volume = %name,
            user = %token.user,
            version = response.version,
            changed = response.changed.iter().map(Vec::len).sum::<usize>(),
            elapsed_us = response.elapsed_us,
            "edit committed"
        );
    } else {
        tracing::info!(volume = %name, user = %token.user, version = response.version, "edit reaches nothing in the volume; nothing committed");
    }
    Ok(Json(response))
}

/// `?KEY=true` or `?KEY=false` (absent: false).
///
/// # Errors
/// 400 for another value, or the key given twice.
pub fn query_flag(uri: &Uri, key: &str) -> Result<bool, ApiError> {
    let mut values = uri
        .query()
        .unwrap_or_default()
        .split('&')
        .filter_map(|pair| pair.split_once('=').filter(|(k, _)| *k == key));
    let value = match (values.next(), values.next()) {
        (None, _) => return Ok(false),
        (Some(_), Some(_)) => {
            return Err(ApiError::BadRequest(format!(
                "malformed query: {key} is given more than once"
            )))
        }
        (Some((_, v)), None) => v,
    };
    match value {
        "true" => Ok(true),
        "false" => Ok(false),
        other => Err(ApiError::BadRequest(format!(
            "?{key}={other}: true or false expected"
        ))),
    }
}

/// A commit message: at most [`MAX_MESSAGE_CHARS`] characters.
///
/// # Errors
/// 400 for a longer one.
pub fn check_message(message: Option<&str>) -> Result<(), ApiError> {
    match message {
        Some(m) if m.chars().count() > MAX_MESSAGE_CHARS => Err(ApiError::BadRequest(format!(
            "a message is at most {MAX_MESSAGE_CHARS} characters; this one has {}",
            m.chars().count()
        ))),
        _ => Ok(()),
    }
}

/// `If-Match`: `*` (whatever version is current: no condition), or a version `N`, `"N"` or
/// `W/"N"` (the ETag forms; `/openapi.json` states the same pattern). A number beyond u64
/// names a version no volume reaches; read as `u64::MAX` it gets the 409 any version but the
/// current one gets.
pub(super) fn if_match(headers: &HeaderMap) -> Result<Option<u64>, ApiError> {
    let Some(value) = headers.get(header::IF_MATCH) else {
        return Ok(None);
    };
    let text = value.to_str().unwrap_or_default().trim();
    if text == "*" {
        return Ok(None);
    }
    let digits = match text.strip_prefix("W/") {
        Some(weak) => quoted(weak),
        None => quoted(text).or(Some(text)),
    }
    .filter(|d| (1..=20).contains(&d.len()) && d.bytes().all(|b| b.is_ascii_digit()))
    .ok_or_else(|| {
        ApiError::BadRequest(format!(
            "If-Match {text:?}: `*` or a version number (N, \"N\" or W/\"N\") expected"
        ))
    })?;
    Ok(Some(digits.parse().unwrap_or(u64::MAX)))
}

/// The text between a leading and a trailing double quote.
fn quoted(s: &str) -> Option<&str> {
    s.strip_prefix('"')?.strip_suffix('"')
}
