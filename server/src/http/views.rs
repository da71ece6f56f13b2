//! The field's formats over HTTP: thin handlers for the OME-Zarr and Neuroglancer precomputed
//! views (`formats::view` does the work).
//!
//! - `GET /v1/volumes/{name}/zarr/{*path}`, `GET /v1/volumes/{name}/precomputed/{*path}`: the
//!   live views, of the newest version: `Cache-Control: public, max-age=1`, a strong `ETag`
//!   (xxh3-64 of the body; 304 on `If-None-Match`), and `Content-Location` naming the pinned
//!   URL of the version answered.
//! - `GET /v1/volumes/{name}/versions/{version}/zarr/{*path}` and `.../precomputed/{*path}`:
//!   the same documents of one version, which never change:
//!   `Cache-Control: public, max-age=31536000, immutable`.
//!
//! A Zarr chunk of fill values only answers 404 (clients read it as the fill value) with the
//! same caching headers as a chunk.

use super::{handlers, ApiError, AppState};
use crate::formats::view::{read, ViewBody, ViewKind};
use axum::extract::rejection::PathRejection;
use axum::extract::{Path, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

/// Live views: short-lived in caches, revalidated by ETag.
const LIVE: &str = "public, max-age=1";
/// Pinned views: one version's documents never change.
const PINNED: &str = "public, max-age=31536000, immutable";

type LivePath = Result<Path<(String, String)>, PathRejection>;
type PinnedPath = Result<Path<(String, u64, String)>, PathRejection>;
type Reply = Result<Response, ApiError>;

// The request itself, not a `HeaderMap` extractor (which clones every header).

pub async fn zarr(State(s): State<AppState>, path: LivePath, request: Request) -> Reply {
    let Path((name, rest)) = path.map_err(malformed)?;
    answer(&s, ViewKind::Zarr, &name, None, &rest, request.headers())
}

pub async fn precomputed(State(s): State<AppState>, path: LivePath, request: Request) -> Reply {
    let Path((name, rest)) = path.map_err(malformed)?;
    answer(
        &s,
        ViewKind::Precomputed,
        &name,
        None,
        &rest,
        request.headers(),
    )
}

pub async fn zarr_pinned(State(s): State<AppState>, path: PinnedPath, request: Request) -> Reply {
    let Path((name, v, rest)) = path.map_err(malformed)?;
    answer(&s, ViewKind::Zarr, &name, Some(v), &rest, request.headers())
}

pub async fn precomputed_pinned(
    State(s): State<AppState>,
    path: PinnedPath,
    request: Request,
) -> Reply {
    let Path((name, v, rest)) = path.map_err(malformed)?;
    answer(
        &s,
        ViewKind::Precomputed,
        &name,
        Some(v),
        &rest,
        request.headers(),
    )
}

fn malformed(e: PathRejection) -> ApiError {
    ApiError::BadRequest(format!("malformed view path: {e}"))
}

/// Reads the document and maps it to a response with the view's caching headers.
fn answer(
    state: &AppState,
    kind: ViewKind,
    name: &str,
    version: Option<u64>,
    path: &str,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let volume = handlers::volume(state, name)?;
    let got = read(volume, kind, version, path, &*state.view_chunks)?;
    let mut out = HeaderMap::with_capacity(8);
    out.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(if version.is_some() { PINNED } else { LIVE }),
    );
    if version.is_none() {
        let pinned = format!(
            "/v1/volumes/{name}/versions/{}/{}/{path}",
            got.version,
            kind.segment()
        );
        if let Ok(v) = HeaderValue::from_str(&pinned) {
            out.insert(header::CONTENT_LOCATION, v);
        }
    }
    let (media, body) = match got.body {
        ViewBody::Json(b) => ("application/json", b),
        ViewBody::Chunk(b) => ("application/octet-stream", b),
        ViewBody::Absent => {
            let mut r = ApiError::not_found(format!(
                "chunk {path} holds only the fill value 0 (Zarr reads a missing chunk as the fill value)"
            ))
            .into_response();
            r.headers_mut().extend(out);
            return Ok(r);
        }
    };
    let etag = format!("\"{:016x}\"", xxhash_rust::xxh3::xxh3_64(&body));
    out.insert(
        header::ETAG,
        HeaderValue::from_str(&etag).map_err(|e| ApiError::Internal(e.to_string()))?,
    );
    if handlers::if_none_match(headers, &etag) {
        return Ok((StatusCode::NOT_MODIFIED, out).into_response());
    }
    out.insert(header::CONTENT_TYPE, HeaderValue::from_static(media));
    Ok((out, body).into_response())
}
