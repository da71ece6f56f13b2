//! Reading a request body with a size limit, and answering "too large" so the client hears it.
//!
//! An HTTP/1.1 client writes its whole body before it reads the answer. A server that answers
//! 413 after reading part of the body and then closes the connection leaves the rest unread;
//! the kernel resets the connection, and the client usually sees "broken pipe" or "connection
//! reset" instead of the 413. So, like nginx's lingering close, a body over the limit is read on
//! and thrown away, up to a bound in bytes and time, before the answer goes out. A body that
//! declares (Content-Length) more than the limit plus that bound is refused before any of it is
//! read: draining it would cost more than the answer is worth.

use super::ApiError;
use axum::body::Body;
use axum::http::{header, HeaderMap};
use bytes::{Bytes, BytesMut};
use futures_util::StreamExt;
use std::time::Duration;

/// Bytes past the limit that are read and discarded so the client can read its 413.
const DRAIN_BYTES: usize = 1 << 20;
/// How long draining may take.
const DRAIN_TIME: Duration = Duration::from_secs(2);

/// The whole body, at most `limit` bytes. `what` names the body in the 413's detail ("an edit
/// request"). A body cut off by the client is a 400.
pub(super) async fn read_limited(
    headers: &HeaderMap,
    body: Body,
    limit: usize,
    what: &str,
) -> Result<Bytes, ApiError> {
    let too_large = || ApiError::TooLarge(format!("{what} takes at most {limit} bytes"));
    let declared = declared_length(headers);
    if declared.is_some_and(|n| n > limit as u64 + DRAIN_BYTES as u64) {
        return Err(too_large());
    }
    let mut stream = body.into_data_stream();
    // The declared length is only trusted for the initial allocation, and only up to the limit.
    let mut bytes = BytesMut::with_capacity(declared.map_or(0, |n| n.min(limit as u64) as usize));
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| ApiError::BadRequest(format!("{what}: {e}")))?;
        if bytes.len() + chunk.len() > limit {
            drain(&mut stream, bytes.len() + chunk.len() - limit).await;
            return Err(too_large());
        }
        bytes.extend_from_slice(&chunk);
    }
    Ok(bytes.freeze())
}

/// Reads and drops what is left of the body, up to [`DRAIN_BYTES`] past the limit and
/// [`DRAIN_TIME`]; errors end it quietly (the answer is a 413 either way).
async fn drain(stream: &mut axum::body::BodyDataStream, already_over: usize) {
    let mut left = DRAIN_BYTES.saturating_sub(already_over);
    let _ = tokio::time::timeout(DRAIN_TIME, async {
        while left > 0 {
            match stream.next().await {
                Some(Ok(chunk)) => left = left.saturating_sub(chunk.len()),
                _ => break,
            }
        }
    })
    .await;
}

fn declared_length(headers: &HeaderMap) -> Option<u64> {
    headers
        .get(header::CONTENT_LENGTH)?
        .to_str()
        .ok()?
        .parse()
        .ok()
}

/// Whether the body is declared JSON (`application/json` or a `+json` type).
pub(super) fn is_json(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .is_some_and(|m| {
            let m = m.trim();
            m.eq_ignore_ascii_case("application/json") || m.ends_with("+json")
        })
}
