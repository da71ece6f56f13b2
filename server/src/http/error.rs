//! Errors as responses: one place decides every status code (RFC 9457 problem details).

use crate::store::StoreError;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use isovox_proto::api::Problem;

/// An error a handler returns. Client errors (4xx) carry their detail to the client and are not
/// logged as errors; server errors (5xx) return a generic body and log the cause.
#[derive(Debug)]
pub enum ApiError {
    BadRequest(String),
    NotFound(String),
    NotAcceptable(String),
    /// The request asks for more than a response may carry.
    TooLarge(String),
    /// The request body is not of a media type the route reads.
    UnsupportedMedia(String),
    /// Too much work queued: retry after this many seconds.
    Overloaded(u32),
    /// No credentials, or unknown ones (401, with `WWW-Authenticate: Bearer`).
    Unauthorized(String),
    /// Valid credentials without the right (403).
    Forbidden(String),
    /// A conditional edit found another version (409, the current one in the body).
    Conflict {
        detail: String,
        version: u64,
    },
    /// What was asked for existed once and is gone for good (410).
    Gone(String),
    /// Well-formed but invalid (422): an edit that does not compile or exceeds a limit.
    Unprocessable(String),
    /// The caller's rate limit: retry after this many seconds (429).
    TooManyRequests(u32),
    Internal(String),
}

impl ApiError {
    pub fn not_found(what: impl Into<String>) -> Self {
        ApiError::NotFound(what.into())
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        match e {
            // Raised by lookups for things that do not exist (a version no longer in the file,
            // a key outside the volume): the client asked for something absent.
            StoreError::Invalid(detail) => ApiError::NotFound(detail),
            other => ApiError::Internal(crate::store::error_chain(&other)),
        }
    }
}

impl From<crate::formats::ViewError> for ApiError {
    fn from(e: crate::formats::ViewError) -> Self {
        use crate::formats::ViewError;
        match e {
            ViewError::NotFound(d) => ApiError::NotFound(d),
            ViewError::BadRequest(d) => ApiError::BadRequest(d),
            ViewError::Gone(d) => ApiError::Gone(d),
            ViewError::Store(e) => e.into(),
        }
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
                problem_with_version(StatusCode::CONFLICT, detail, Some(version))
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
