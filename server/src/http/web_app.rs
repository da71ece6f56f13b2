//! The web viewer at `/`: the files `build.rs` built from `web/` and embedded in the binary.
//!
//! `index.html` is revalidated on every load (`no-cache`, ETag = content hash), so a new server
//! is picked up at once; the files under `/assets/` have content hashes in their names (Vite),
//! so they are cacheable forever. Text files go out as zstd to browsers that accept it,
//! compressed once at first use.

use super::ApiError;
use axum::extract::Path;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use std::collections::HashMap;
use std::sync::LazyLock;

mod embedded {
    include!(concat!(env!("OUT_DIR"), "/web_assets.rs"));
}

/// zstd level for the text files: about a third of a second once, for a third fewer bytes than
/// the default level on the viewer's script.
const ZSTD_LEVEL: i32 = 19;

struct Asset {
    media: &'static str,
    raw: bytes::Bytes,
    /// Compressed, when that is smaller.
    zstd: Option<bytes::Bytes>,
    etag: HeaderValue,
}

static ASSETS: LazyLock<HashMap<&'static str, Asset>> = LazyLock::new(|| {
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
            let hash = xxhash_rust::xxh3::xxh3_64(raw);
            let etag = HeaderValue::from_str(&format!("\"{hash:016x}\""))
                .unwrap_or_else(|_| HeaderValue::from_static("\"0\""));
            let asset = Asset {
                media,
                raw: bytes::Bytes::from_static(raw),
                zstd,
                etag,
            };
            (path, asset)
        })
        .collect()
});

/// The viewer's routes: the page at `/` (and `/index.html`) and its files under `/assets/`.
pub(super) fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route("/", get(page))
        .route("/index.html", get(page))
        .route("/assets/{*file}", get(asset))
}

async fn page(headers: HeaderMap) -> Result<Response, ApiError> {
    respond("/index.html", &headers, "no-cache")
}

async fn asset(Path(file): Path<String>, headers: HeaderMap) -> Result<Response, ApiError> {
    respond(
        &format!("/assets/{file}"),
        &headers,
        "public, max-age=31536000, immutable",
    )
}

fn respond(path: &str, headers: &HeaderMap, cache: &'static str) -> Result<Response, ApiError> {
    let asset = ASSETS
        .get(path)
        .ok_or_else(|| ApiError::NotFound(format!("no file {path} in the viewer")))?;
    let mut out = HeaderMap::with_capacity(6);
    out.insert(header::ETAG, asset.etag.clone());
    out.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    out.insert(header::VARY, HeaderValue::from_static("Accept-Encoding"));
    let matches = headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim().trim_start_matches("W/").as_bytes() == asset.etag.as_bytes());
    if matches {
        return Ok((StatusCode::NOT_MODIFIED, out).into_response());
    }
    out.insert(header::CONTENT_TYPE, HeaderValue::from_static(asset.media));
    let body = match &asset.zstd {
        Some(z) if super::bricks::accepts(headers, header::ACCEPT_ENCODING, "zstd") => {
            out.insert(header::CONTENT_ENCODING, HeaderValue::from_static("zstd"));
            z.clone()
        }
        _ => asset.raw.clone(),
    };
    Ok((out, body).into_response())
}
