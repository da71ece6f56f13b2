//! Errors as responses: the one place that decides every status code (RFC 9457 problem
//! details). The domain's errors ([`VolumeError`], [`StoreError`], [`TermError`],
//! [`ViewError`]) and axum's rejections of malformed requests convert into [`ApiError`], so
//! handlers use `?`.
//!
//! A caller's mistake is a 4xx whose detail tells what to fix, and is not logged as an error.
//! Damage (a corrupt record), a failing system and bugs are a 500 with a generic body; the
//! cause goes to the log.

use crate::cancel::Stopped;
use crate::formats::ViewError;
use crate::icvg::term::TermError;
use crate::store::{error_chain, StoreError};
use crate::volume::VolumeError;
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use isovox_proto::api::Problem;

/// An error a handler returns. Client errors (4xx) carry their detail to the client and are not
/// logged as errors; server errors (5xx) return a generic body and log the cause.
#[derive(Debug)]
pub enum ApiError {
    /// The request is malformed (400).
    BadRequest(String),
    /// What the request names is not there (404).
    NotFound(String),
    /// No representation the request accepts (406).
    NotAcceptable(String),
    /// The request asks for more than a response may carry.
    TooLarge(String),
    /// The request body is not of a media type the route reads.
    UnsupportedMedia(String),
    /// Too much work queued: retry after this many seconds.
    Overloaded(u32),
    /// A system the request waited on (the object store) did not answer in time: 503 with
    /// `Retry-After`, the cause logged as a warning (not the client's fault, not a bug).
    Stalled {
        /// What stalled, for the log and the detail.
        cause: String,
        /// Seconds to wait before retrying.
        retry_after: u32,
    },
    /// No credentials, or unknown ones (401, with `WWW-Authenticate: Bearer`).
    Unauthorized(String),
    /// Valid credentials without the right (403).
    Forbidden(String),
    /// The request conflicts with the volume's state (409): a conditional edit found another
    /// version (the current one in the body), or the volume is read-only (no version: there is
    /// nothing to retry against).
    Conflict {
        /// What differs.
        detail: String,
        /// The current version, for a conditional edit.
        version: Option<u64>,
    },
    /// What was asked for existed once and is gone for good (410).
    Gone(String),
    /// Well-formed but invalid (422): an edit that does not compile or exceeds a limit.
    Unprocessable(String),
    /// The caller's rate limit: retry after this many seconds (429).
    TooManyRequests(u32),
    /// Damage, a failing system or a bug (500): the cause is logged, the body is generic.
    Internal(String),
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::Absent(detail) | StoreError::OutOfRange(detail) => {
                ApiError::NotFound(detail)
            }
            StoreError::BadInput(detail) => ApiError::BadRequest(detail),
            // Writers on other replicas kept winning: come back in a second.
            StoreError::HeadMoved { .. } => ApiError::Overloaded(1),
            // Come back after about as long as was waited: a stall is rarely shorter.
            StoreError::Stalled { limit } => ApiError::Stalled {
                cause: e.to_string(),
                retry_after: limit.as_secs_f64().ceil().clamp(1.0, 60.0) as u32,
            },
            StoreError::Io { .. }
            | StoreError::ObjectStore { .. }
            | StoreError::Format(_)
            | StoreError::Corrupt { .. }
            | StoreError::Internal(_) => ApiError::Internal(error_chain(&e)),
        }
    }
}

impl From<VolumeError> for ApiError {
    fn from(e: VolumeError) -> Self {
        let detail = e.to_string();
        match e {
            VolumeError::NoSuchVolume(_)
            | VolumeError::NoSuchVersion { .. }
            | VolumeError::OutOfRange(_) => ApiError::NotFound(detail),
            VolumeError::BadRequest(_) => ApiError::BadRequest(detail),
            // Well-formed, but in conflict with the volume's state: the caller is ahead of it.
            VolumeError::SinceAfterHead { head, .. } => ApiError::Conflict {
                detail,
                version: Some(head),
            },
            VolumeError::TooLarge(_) => ApiError::TooLarge(detail),
            // A volume or mesh the term names that is not there: as any resource not there.
            VolumeError::InvalidEdit(TermError::Unknown(_)) => ApiError::NotFound(detail),
            VolumeError::InvalidEdit(_) | VolumeError::EditTooLarge { .. } => {
                ApiError::Unprocessable(detail)
            }
            VolumeError::Conflict { current, .. } => ApiError::Conflict {
                detail,
                version: Some(current),
            },
            VolumeError::ReadOnly { .. }
            | VolumeError::NotUndoable(_)
            | VolumeError::Unsupported(_) => ApiError::Conflict {
                detail,
                version: None,
            },
            VolumeError::NotAllowed(_) => ApiError::Forbidden(detail),
            VolumeError::UndoTooLarge { .. } | VolumeError::Unprocessable(_) => {
                ApiError::Unprocessable(detail)
            }
            VolumeError::Compacted { .. } => ApiError::Gone(detail),
            VolumeError::WriterBusy => ApiError::Overloaded(1),
            // Too costly for this server: like an edit over the voxel budget.
            VolumeError::Stopped(Stopped::TimedOut(_)) => ApiError::Unprocessable(detail),
            // The server is shutting down (a client that left hears nothing).
            VolumeError::Stopped(Stopped::Cancelled) => ApiError::Overloaded(1),
            VolumeError::Store(e) => e.into(),
        }
    }
}

impl From<ViewError> for ApiError {
    fn from(e: ViewError) -> Self {
        let detail = e.to_string();
        match e {
            ViewError::NoSuchDocument(_) | ViewError::FillValue(_) => ApiError::NotFound(detail),
            ViewError::NotAChunk(_) => ApiError::BadRequest(detail),
            ViewError::Compacted { .. } => ApiError::Gone(detail),
            ViewError::Volume(e) => e.into(),
        }
    }
}

impl From<TermError> for ApiError {
    fn from(e: TermError) -> Self {
        VolumeError::from(e).into()
    }
}

impl From<PathRejection> for ApiError {
    fn from(e: PathRejection) -> Self {
        ApiError::BadRequest(format!("malformed path: {e}"))
    }
}

impl From<QueryRejection> for ApiError {
    fn from(e: QueryRejection) -> Self {
        ApiError::BadRequest(format!("malformed query: {e}"))
    }
}

/// Work that cannot fail, run through the same helpers (`cpu.rs`) as work that can.
impl From<std::convert::Infallible> for ApiError {
    fn from(e: std::convert::Infallible) -> Self {
        match e {}
    }
}

/// A task on the blocking pool panicked or was cancelled: a bug.
impl From<tokio::task::JoinError> for ApiError {
    fn from(e: tokio::task::JoinError) -> Self {
        ApiError::Internal(format!("a blocking task failed: {e}"))
    }
}

fn problem(status: StatusCode, detail: String) -> Response {
    problem_with_version(status, detail, None)
}

fn problem_with_version(status: StatusCode, detail: String, version: Option<u64>) -> Response {
    let problem = Problem {
        kind: "about:blank".into(),
        title: status.canonical_reason().unwrap_or("Error").into(),
        status: status.as_u16(),
        detail,
        version,
    };
    let body = serde_json::to_vec(&problem).unwrap_or_default();
    (
        status,
        [(header::CONTENT_TYPE, "application/problem+json")],
        body,
    )
        .into_response()
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        match self {
            ApiError::BadRequest(d) => problem(StatusCode::BAD_REQUEST, d),
            ApiError::NotFound(d) => problem(StatusCode::NOT_FOUND, d),
            ApiError::NotAcceptable(d) => problem(StatusCode::NOT_ACCEPTABLE, d),
            ApiError::TooLarge(d) => problem(StatusCode::PAYLOAD_TOO_LARGE, d),
            ApiError::UnsupportedMedia(d) => problem(StatusCode::UNSUPPORTED_MEDIA_TYPE, d),
            ApiError::Overloaded(after) => {
                let mut r = problem(
                    StatusCode::SERVICE_UNAVAILABLE,
                    format!("the server is busy; retry in {after} s"),
                );
                r.headers_mut()
                    .insert(header::RETRY_AFTER, HeaderValue::from(after));
                r
            }
            ApiError::Stalled { cause, retry_after } => {
                tracing::warn!(%cause, retry_after, "answered 503: the store stalled");
                let mut r = problem(
                    StatusCode::SERVICE_UNAVAILABLE,
                    format!("{cause}; nothing was committed; retry in {retry_after} s"),
                );
                r.headers_mut()
                    .insert(header::RETRY_AFTER, HeaderValue::from(retry_after));
                r
            }
            ApiError::Unauthorized(d) => {
                let mut r = problem(StatusCode::UNAUTHORIZED, d);
                r.headers_mut().insert(
                    header::WWW_AUTHENTICATE,
                    HeaderValue::from_static("Bearer realm=\"isovox\""),
                );
                r
            }
            ApiError::Forbidden(d) => problem(StatusCode::FORBIDDEN, d),
            ApiError::Conflict { detail, version } => {
                problem_with_version(StatusCode::CONFLICT, detail, version)
            }
            ApiError::Gone(d) => problem(StatusCode::GONE, d),
            ApiError::Unprocessable(d) => problem(StatusCode::UNPROCESSABLE_ENTITY, d),
            ApiError::TooManyRequests(after) => {
                let mut r = problem(
                    StatusCode::TOO_MANY_REQUESTS,
                    format!("edit rate exceeded; retry in {after} s"),
                );
                r.headers_mut()
                    .insert(header::RETRY_AFTER, HeaderValue::from(after));
                r
            }
            ApiError::Internal(cause) => {
                tracing::error!(%cause, "internal error");
                problem(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "the server failed to answer; the cause is in its log".into(),
                )
            }
        }
    }
}
