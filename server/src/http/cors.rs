//! CORS for browser clients, at the cost of two static headers per response.
//!
//! Every response says `Access-Control-Allow-Origin: *` and `Access-Control-Expose-Headers: *`
//! (reads are public and credentials travel in `Authorization`, not cookies, so any origin may
//! read and no response varies by origin: no `Vary: Origin` is needed, and HTTP caches may
//! share entries between origins). Preflight requests (`OPTIONS`) are answered on every route
//! with the methods and the request headers the API uses. tower-http's `CorsLayer` did the same
//! with a header map allocated and merged per request, which cost about a sixth of the brick
//! routes' throughput.

use axum::http::{header, HeaderName, HeaderValue, StatusCode};
use axum::response::IntoResponse;

/// Adds the two headers every response carries (unless the handler set them).
pub(super) fn add_headers(headers: &mut axum::http::HeaderMap) {
    for name in [
        header::ACCESS_CONTROL_ALLOW_ORIGIN,
        header::ACCESS_CONTROL_EXPOSE_HEADERS,
    ] {
        headers.entry(name).or_insert(HeaderValue::from_static("*"));
    }
}

/// The answer to a preflight request on any route.
pub(super) async fn preflight() -> impl IntoResponse {
    const HEADERS: [(HeaderName, &str); 3] = [
        (header::ACCESS_CONTROL_ALLOW_METHODS, "GET, POST, OPTIONS"),
        (
            header::ACCESS_CONTROL_ALLOW_HEADERS,
            "authorization, content-type, accept, accept-encoding, if-match, if-none-match, last-event-id",
        ),
        (header::ACCESS_CONTROL_MAX_AGE, "86400"),
    ];
    (
        StatusCode::NO_CONTENT,
        HEADERS.map(|(name, value)| (name, HeaderValue::from_static(value))),
    )
}
