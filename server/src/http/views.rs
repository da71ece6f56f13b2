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
//! The path within the view and the pinned version are read as the client spelled them: a
//! number only in its canonical decimal spelling, nothing percent-escaped (`crate::decimal`),
//! so each document has one URL and caches keep one copy of it.
//!
//! A precomputed segmentation source's `segment_properties/info` comes from the channel's
//! segments (`docs/channels.md`), made on the CPU queue as the segments list is.
//!
//! A Zarr chunk of fill values only answers 404 (clients read it as the fill value) with the
//! same caching headers as a chunk. A chunk that must be decoded or compressed (not stored as a
//! frame that goes out as it is, not in the shared cache) is made on the CPU queue, waiting up
//! to a second for a place there.

use super::bricks::{format_etag, if_none_match};
use super::cpu::Admission;
use super::extract::{Named, Path, RawPath};
use super::{ApiError, AppState};
use crate::formats::view::{read, ViewAnswer, ViewBody, ViewRead};
use crate::formats::{precomputed, ViewError, ViewKind};
use crate::volume::{LiveVolume, VolumeError};
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

/// Live views: short-lived in caches, revalidated by ETag.
const LIVE: &str = "public, max-age=1";
/// Pinned views: one version's documents never change.
const PINNED: &str = "public, max-age=31536000, immutable";

/// How long a chunk to make waits for a place in the CPU queue before it is refused (503).
/// tensorstore's first read of a level asks for 32 chunks at once, and the queue (16 places on
/// two cores) is sized for mesh tiles: refused at once, those were retried with backoff, and the
/// first read took several times longer than with a short wait for a place.
const CHUNK_PATIENCE: std::time::Duration = std::time::Duration::from_secs(1);

/// `GET /v1/volumes/{name}/zarr/{*path}`.
pub async fn zarr(
    State(state): State<AppState>,
    Path(Named { name }): Path<Named>,
    raw: RawPath,
    request: Request,
) -> Result<Response, ApiError> {
    view(&state, ViewKind::Zarr, &name, false, &raw, request).await
}

/// `GET /v1/volumes/{name}/precomputed/{*path}`.
pub async fn precomputed(
    State(state): State<AppState>,
    Path(Named { name }): Path<Named>,
    raw: RawPath,
    request: Request,
) -> Result<Response, ApiError> {
    view(&state, ViewKind::Precomputed, &name, false, &raw, request).await
}

/// `GET /v1/volumes/{name}/versions/{version}/zarr/{*path}`.
pub async fn zarr_pinned(
    State(state): State<AppState>,
    Path(Named { name }): Path<Named>,
    raw: RawPath,
    request: Request,
) -> Result<Response, ApiError> {
    view(&state, ViewKind::Zarr, &name, true, &raw, request).await
}

/// `GET /v1/volumes/{name}/versions/{version}/precomputed/{*path}`.
pub async fn precomputed_pinned(
    State(state): State<AppState>,
    Path(Named { name }): Path<Named>,
    raw: RawPath,
    request: Request,
) -> Result<Response, ApiError> {
    view(&state, ViewKind::Precomputed, &name, true, &raw, request).await
}

/// Reads the document (in place, or on the store-read threads for a volume kept in an object
/// store: [`AppState::read_volume`]; made on the CPU queue when it takes work) and answers it:
/// `{*path}`, and `{version}` when `pinned`, as the client spelled them.
async fn view(
    state: &AppState,
    kind: ViewKind,
    name: &str,
    pinned: bool,
    raw: &RawPath,
    // The request itself, not a `HeaderMap` extractor (which clones every header).
    request: Request,
) -> Result<Response, ApiError> {
    let version = if pinned {
        Some(raw.number("version")?)
    } else {
        None
    };
    let path = raw
        .param("path")
        .ok_or_else(|| ApiError::Internal("a view route without {*path}".into()))?
        .to_string();
    if kind == ViewKind::Precomputed {
        if let Some(channel) = precomputed::segment_properties_channel(&path) {
            let answer = segment_properties(state, name, version, channel.to_string()).await?;
            return respond(kind, name, version, &path, answer, request.headers());
        }
    }
    let (made, path) = state
        .read_volume(name, move |state, vol| {
            read(vol, kind, version, &path, &state.bricks).map(|made| (made, path.clone()))
        })
        .await?;
    let answer = match made {
        ViewRead::Ready(answer) => answer,
        ViewRead::Make(chunk) => {
            let bricks = state.bricks.clone();
            state
                .cpu
                .run(Admission::WaitFor(CHUNK_PATIENCE), move || {
                    chunk.run(&bricks)
                })
                .await?
        }
    };
    respond(kind, name, version, &path, answer, request.headers())
}

/// The segment properties of `channel` of volume `name` at `version` (the head when `None`),
/// from the channel's segment index, which may have to be built or brought up to date: CPU
/// work, as the segments list is.
async fn segment_properties(
    state: &AppState,
    name: &str,
    version: Option<u64>,
    channel: String,
) -> Result<ViewAnswer, ApiError> {
    let vol = state.catalog.get(name)?.clone();
    state
        .cpu
        .run(Admission::Place, move || {
            let list = vol.all_segments(version, &channel)?;
            let doc = precomputed::segment_properties(&list.segments);
            Ok::<_, VolumeError>(ViewAnswer {
                version: list.version,
                body: ViewBody::Json(serde_json::to_vec(&doc).unwrap_or_default().into()),
            })
        })
        .await
}

/// The response to a request of a live view that takes no work (metadata, a stored frame, a
/// cached chunk, a chunk of fill values), else `None`: the request then goes to the router
/// (see `fast_path.rs`), which answers it (and any error) as [`zarr`] and [`precomputed`] do.
pub(super) fn answer_ready(
    state: &AppState,
    volume: &LiveVolume,
    kind: ViewKind,
    name: &str,
    path: &str,
    headers: &HeaderMap,
) -> Option<Response> {
    match read(volume, kind, None, path, &state.bricks).ok()? {
        ViewRead::Ready(answer) => respond(kind, name, None, path, answer, headers).ok(),
        ViewRead::Make(_) => None,
    }
}

/// The response for a document of a view, with the view's caching headers.
fn respond(
    kind: ViewKind,
    name: &str,
    version: Option<u64>,
    path: &str,
    answer: ViewAnswer,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let mut out = HeaderMap::with_capacity(8);
    out.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(if version.is_some() { PINNED } else { LIVE }),
    );
    if version.is_none() {
        let pinned = format!(
            "/v1/volumes/{name}/versions/{}/{}/{path}",
            answer.version,
            kind.segment()
        );
        if let Ok(v) = HeaderValue::from_str(&pinned) {
            out.insert(header::CONTENT_LOCATION, v);
        }
    }
    let (media, body) = match answer.body {
        ViewBody::Json(b) => ("application/json", b),
        ViewBody::Chunk(b) => ("application/octet-stream", b),
        ViewBody::Absent => {
            let mut r = ApiError::from(ViewError::FillValue(path.to_string())).into_response();
            r.headers_mut().extend(out);
            return Ok(r);
        }
    };
    let mut etag = [0u8; 18];
    let etag = format_etag(xxhash_rust::xxh3::xxh3_64(&body), &mut etag);
    out.insert(
        header::ETAG,
        HeaderValue::from_str(etag).map_err(|e| ApiError::Internal(e.to_string()))?,
    );
    if if_none_match(headers, etag) {
        return Ok((StatusCode::NOT_MODIFIED, out).into_response());
    }
    out.insert(header::CONTENT_TYPE, HeaderValue::from_static(media));
    Ok((out, body).into_response())
}
