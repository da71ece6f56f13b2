//! Reading a request body with a size limit, and answering "too large" so the client hears it;
//! JSON bodies parsed as JSON Schema (and so `/openapi.json`) reads them.
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
use serde::de::DeserializeOwned;
use serde_json::Value;
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

/// A JSON body of at most `limit` bytes as a `T`: 415 unless it is declared JSON, 413 over the
/// limit, 400 when it is not JSON or not a `T` (`what` names it in the detail: "a batch
/// request").
pub(super) async fn read_json<T: DeserializeOwned>(
    headers: &HeaderMap,
    body: Body,
    limit: usize,
    what: &str,
) -> Result<T, ApiError> {
    if !is_json(headers) {
        return Err(ApiError::UnsupportedMedia(format!(
            "{what} is JSON: send Content-Type: application/json"
        )));
    }
    let bytes = read_limited(headers, body, limit, what).await?;
    parse_json(&bytes).map_err(|e| ApiError::BadRequest(format!("{what} is malformed: {e}")))
}

/// Parses JSON as a `T`. A number written with a zero fraction (`680.0`) counts as the integer
/// it is, as JSON Schema counts it: a client whose JSON library writes every number as a float
/// is not refused an integer field for it (`680.5` still is).
fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, serde_json::Error> {
    let mut value: Value = serde_json::from_slice(bytes)?;
    integral_floats_as_integers(&mut value);
    serde_json::from_value(value)
}

/// Rewrites every float without a fraction that fits an i64 or a u64 as that integer. The
/// recursion is bounded by serde_json's nesting limit (128) on what it parses.
fn integral_floats_as_integers(v: &mut Value) {
    match v {
        Value::Number(n) => {
            let Some(f) = n.as_f64().filter(|f| n.is_f64() && f.fract() == 0.0) else {
                return;
            };
            // 2^63 and 2^64 are exact in f64; the casts below are exact inside these bounds.
            if (-9.223_372_036_854_776e18..9.223_372_036_854_776e18).contains(&f) {
                *n = (f as i64).into();
            } else if (0.0..1.844_674_407_370_955_2e19).contains(&f) {
                *n = (f as u64).into();
            }
        }
        Value::Array(items) => items.iter_mut().for_each(integral_floats_as_integers),
        Value::Object(fields) => fields.values_mut().for_each(integral_floats_as_integers),
        Value::Null | Value::Bool(_) | Value::String(_) => {}
    }
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

#[cfg(test)]
mod tests {
    use super::parse_json;

    #[test]
    fn integral_floats_are_integers_and_fractions_are_not() {
        let v: (u32, i64, u64, f64) = parse_json(b"[680.0, -164.0, 1e19, 2.0]").unwrap();
        assert_eq!(v, (680, -164, 10_000_000_000_000_000_000, 2.0));
        let v: Vec<i64> = parse_json(b"[-0.0, -9.0e18]").unwrap();
        assert_eq!(v, vec![0, -9_000_000_000_000_000_000]);
        assert!(parse_json::<u32>(b"680.5").is_err());
        assert!(parse_json::<u32>(b"-1.0").is_err());
        assert!(parse_json::<u64>(b"1e20").is_err());
        assert!(parse_json::<i32>(b"3e9").is_err());
    }
}
