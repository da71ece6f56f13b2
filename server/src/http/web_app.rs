//! The web viewer at `/`: the files `build.rs` built from `web/` and embedded in the binary.
//!
//! `index.html` is revalidated on every load (`no-cache`, ETag = content hash), so a new server
//! is picked up at once; the files under `/assets/` have content hashes in their names (Vite),
//! so they are cacheable forever. Text files go out as zstd to browsers that accept it,
//! compressed once at first use.

use super::bricks::{accepts, if_none_match};
use super::cpu::blocking;
use super::{ApiError, AppState};
use axum::extract::{Path, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use std::collections::HashMap;
use std::convert::Infallible;
use std::sync::OnceLock;

mod embedded {
    include!(concat!(env!("OUT_DIR"), "/web_assets.rs"));
}

/// zstd level for the text files: about a third of a second once, for a third fewer bytes than
/// the default level on the viewer's script.
const ZSTD_LEVEL: i32 = 19;

#[derive(Debug)]
struct Asset {
    media: &'static str,
    raw: bytes::Bytes,
    /// Compressed, when that is smaller.
    zstd: Option<bytes::Bytes>,
    etag: HeaderValue,
}

type Assets = HashMap<&'static str, Asset>;

/// The embedded files, their text ones compressed once, on first use.
static ASSETS: OnceLock<Assets> = OnceLock::new();

fn compress_all() -> Assets {
    embedded::ASSETS
        .iter()
        .map(|&(path, media, raw)| {
            let text =
                media.starts_with("text/") || media.ends_with("json") || media.ends_with("xml");
            let zstd = text
                .then(|| zstd::bulk::compress(raw, ZSTD_LEVEL).ok())
                .flatten()
                .filter(|z| z.len() < raw.len())
                .map(bytes::Bytes::from);
            let etag = format!("\"{:016x}\"", xxhash_rust::xxh3::xxh3_64(raw));
            let asset = Asset {
                media,
                raw: bytes::Bytes::from_static(raw),
                zstd,
                // Quoted hex digits: always a valid header value.
                etag: HeaderValue::from_str(&etag).unwrap_or(HeaderValue::from_static("\"0\"")),
            };
            (path, asset)
        })
        .collect()
}

/// The files, compressing them on the main runtime's blocking pool the first time (level 19
/// is CPU work a connection thread must not do).
async fn assets(state: &AppState) -> Result<&'static Assets, ApiError> {
    match ASSETS.get() {
        Some(assets) => Ok(assets),
        None => {
            let compress = || Ok::<_, Infallible>(ASSETS.get_or_init(compress_all));
            blocking(state.main_runtime(), compress).await
        }
    }
}

/// The viewer's routes: the page at `/` (and `/index.html`) and its files under `/assets/`.
pub(super) fn routes() -> Router<AppState> {
    Router::new()
        .route("/", get(page))
        .route("/index.html", get(page))
        .route("/assets/{*file}", get(asset))
}

async fn page(State(state): State<AppState>, headers: HeaderMap) -> Result<Response, ApiError> {
    respond(&state, "/index.html", &headers, "no-cache").await
}

async fn asset(
    State(state): State<AppState>,
    Path(file): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let path = format!("/assets/{file}");
    respond(
        &state,
        &path,
        &headers,
        "public, max-age=31536000, immutable",
    )
    .await
}

/// The file at `path`: 304 when `If-None-Match` names it, zstd to clients that take it; a path
/// the viewer has no file for is answered as any unknown route.
async fn respond(
    state: &AppState,
    path: &str,
    headers: &HeaderMap,
    cache: &'static str,
) -> Result<Response, ApiError> {
    let Some(asset) = assets(state).await?.get(path) else {
        return Err(super::handlers::not_found().await);
    };
    let mut out = HeaderMap::with_capacity(6);
    out.insert(header::ETAG, asset.etag.clone());
    out.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    out.insert(header::VARY, HeaderValue::from_static("Accept-Encoding"));
    if if_none_match(headers, asset.etag.to_str().unwrap_or_default()) {
        return Ok((StatusCode::NOT_MODIFIED, out).into_response());
    }
    out.insert(header::CONTENT_TYPE, HeaderValue::from_static(asset.media));
    let body = match &asset.zstd {
        Some(z) if accepts(headers, header::ACCEPT_ENCODING, "zstd") => {
            out.insert(header::CONTENT_ENCODING, HeaderValue::from_static("zstd"));
            z.clone()
        }
        _ => asset.raw.clone(),
    };
    Ok((out, body).into_response())
}
