//! The brick routes: one brick by position, one brick by content hash.
//!
//! Both answer through [`brick_response`]: `ETag` = content hash (304 on a match); the stored
//! zstd frame as `Content-Encoding: zstd` to clients that accept it, an lz4 block for
//! `Accept: application/x-lz4`, else the raw voxels. These are the hottest routes by far, so
//! the code avoids per-request work the other routes do not mind (see the comments).

use super::extract::{ChannelParam, Named, Path, RawPath, VersionParam};
use super::{ApiError, AppState};
use crate::store::decoded::Form;
use crate::store::{Snapshot, StoredBrick};
use crate::volume::LiveVolume;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use isovox_proto::vod2::Codec;
use isovox_proto::VolumeLayout;

/// The media type of an lz4 block (lz4_flex block format, decoding to one brick).
pub const LZ4_MEDIA_TYPE: &str = "application/x-lz4";

/// `{level}/{x}/{y}/{z}` of a brick or tile route, as sent (see [`crate::decimal`]).
///
/// # Errors
/// 404 for a number spelled otherwise, 400 for one that is not a number.
pub(super) fn brick_position(raw: &RawPath) -> Result<(u8, u32, u32, u32), ApiError> {
    Ok((
        raw.number("level")?,
        raw.number("x")?,
        raw.number("y")?,
        raw.number("z")?,
    ))
}

/// One brick.
///
/// - Default: the decoded voxels (`application/octet-stream`, x fastest, u16 little endian).
///   A brick stored as zstd goes out as it is, with `Content-Encoding: zstd`, to clients that
///   send `Accept-Encoding: zstd` (browsers decode it transparently).
/// - `Accept: application/x-lz4`: an lz4 block of the voxels (the stored block when the brick is
///   stored as lz4, else compressed on the fly).
/// - `ETag` is the content hash; `If-None-Match` with it answers 304.
/// - `?version=N` reads an older version while the file still holds it.
///
/// Read in place for a local volume, on the store-read threads for a volume kept in an object
/// store ([`AppState::read_volume`]).
pub async fn brick(
    State(state): State<AppState>,
    Path(Named { name }): Path<Named>,
    raw: RawPath,
    VersionParam(version): VersionParam,
    ChannelParam(channel): ChannelParam,
    // The request itself, not a `HeaderMap` extractor (which clones every header).
    request: Request,
) -> Result<Response, ApiError> {
    let position = brick_position(&raw)?;
    state
        .read_volume(&name, move |state, vol| match &channel {
            None => brick_at(state, vol, version, position, request.headers()),
            Some(channel) => {
                let snap = vol.snapshot_of(version, Some(channel))?;
                brick_of(state, &snap, position, request.headers())
            }
        })
        .await
}

/// The response for brick (level, x, y, z) of `vol` at `version` (the head if `None`): the
/// brick route's work once its request is parsed and its volume found, shared with the fast
/// path.
pub(super) fn brick_at(
    state: &AppState,
    vol: &LiveVolume,
    version: Option<u64>,
    (level, x, y, z): (u8, u32, u32, u32),
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    // The head is borrowed from the volume's current file (no reference count touched).
    let (current, older);
    let snap: &Snapshot = match version {
        Some(v) => {
            older = vol.version(v)?;
            &older
        }
        None => {
            current = vol.load();
            current.head_ref()
        }
    };
    brick_of(state, snap, (level, x, y, z), headers)
}

/// The response for brick (level, x, y, z) of the stream `snap` (density, or a channel's view).
fn brick_of(
    state: &AppState,
    snap: &Snapshot,
    (level, x, y, z): (u8, u32, u32, u32),
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let key = snap
        .layout()
        .key(level, x, y, z)
        .map_err(|e| ApiError::NotFound(e.to_string()))?;
    let stored = snap.stored(key)?;
    brick_response(state, snap, stored, headers, "no-cache")
}

/// A brick by content hash (16 hex digits): immutable, so any HTTP cache or CDN may keep it
/// forever. A brick of any version the file still holds is found (a client that read a grid at
/// `?version=N` asks for its hashes), whether or not this process saw the commits since. Read
/// where [`AppState::read_volume`] says.
pub async fn blob(
    State(state): State<AppState>,
    Path((name, hex)): Path<(String, String)>,
    ChannelParam(channel): ChannelParam,
    request: Request,
) -> Result<Response, ApiError> {
    let hash = (hex.len() == 16 && hex.bytes().all(|b| b.is_ascii_hexdigit()))
        .then(|| u64::from_str_radix(&hex, 16).ok())
        .flatten()
        .ok_or_else(|| {
            ApiError::BadRequest(format!("{hex:?} is not a content hash (16 hex digits)"))
        })?;
    state
        .read_volume(&name, move |state, vol| {
            let snap = vol.snapshot_of(None, channel.as_deref())?;
            let entry = snap.find_by_hash(hash)?.ok_or_else(|| {
                ApiError::NotFound(format!("no brick with hash {hex} in {:?}", vol.name()))
            })?;
            let stored = snap.stored_entry(entry)?;
            brick_response(
                state,
                &snap,
                stored,
                request.headers(),
                "public, max-age=31536000, immutable",
            )
        })
        .await
}

/// Whether a header of `name` lists `token` (and does not refuse it with `q=0`).
pub(super) fn accepts(headers: &HeaderMap, name: header::HeaderName, token: &str) -> bool {
    headers
        .get_all(name)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|item| {
            let mut parts = item.split(';');
            let value = parts.next().unwrap_or("").trim();
            let refused = parts.any(|p| p.trim().replace(' ', "") == "q=0");
            value.eq_ignore_ascii_case(token) && !refused
        })
}

/// Whether `If-None-Match` names `etag` (or `*`).
pub(super) fn if_none_match(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        // If-None-Match compares weakly (RFC 9110 13.1.2): W/"x" matches "x".
        .map(|t| t.trim().trim_start_matches("W/"))
        .any(|t| t == etag || t == "*")
}

/// The response for one stored brick, shared by the position and the content-hash routes.
///
/// Stored payloads go out as they are stored, verified first (small ones copied, large ones as
/// shared slices of the mapping: see `Snapshot::verified_payload`); decoded voxels and
/// transcoded lz4 blocks come from the shared cache of decoded bricks, keyed by content hash
/// and verified when made, so a hot brick is decoded once. A brick that fails verification is
/// a 500 for that brick only.
fn brick_response(
    state: &AppState,
    snap: &Snapshot,
    stored: StoredBrick<'_>,
    headers: &HeaderMap,
    cache_control: &'static str,
) -> Result<Response, ApiError> {
    let layout = snap.layout();
    let hash = match stored {
        StoredBrick::Record { header, .. } => header.hash,
        StoredBrick::Constant(v) => state.constants.hash(v, layout),
    };
    let mut etag = [0u8; 18];
    let etag = format_etag(hash, &mut etag);
    // Room for every header the response will carry (these, CORS, length, date): growing the
    // map rehashes it.
    let mut response_headers = HeaderMap::with_capacity(12);
    response_headers.insert(
        header::ETAG,
        HeaderValue::from_str(etag).map_err(|e| ApiError::Internal(e.to_string()))?,
    );
    response_headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(cache_control),
    );
    response_headers.insert(
        header::VARY,
        HeaderValue::from_static("Accept, Accept-Encoding"),
    );
    if if_none_match(headers, etag) {
        return Ok((StatusCode::NOT_MODIFIED, response_headers).into_response());
    }
    let want_lz4 = accepts(headers, header::ACCEPT, LZ4_MEDIA_TYPE);
    let (media, encoding, body) = match stored {
        StoredBrick::Record { header: h, .. } if want_lz4 && h.codec == Codec::Lz4 => (
            LZ4_MEDIA_TYPE,
            None,
            snap.verified_payload(&stored, &state.bricks)?,
        ),
        StoredBrick::Record { header: h, .. }
            if !want_lz4
                && h.codec == Codec::Zstd
                && accepts(headers, header::ACCEPT_ENCODING, "zstd") =>
        {
            (
                "application/octet-stream",
                Some("zstd"),
                snap.verified_payload(&stored, &state.bricks)?,
            )
        }
        StoredBrick::Constant(v) if want_lz4 => {
            (LZ4_MEDIA_TYPE, None, state.constants.lz4(v, layout))
        }
        _ if want_lz4 => (
            LZ4_MEDIA_TYPE,
            None,
            state
                .bricks
                .get_or_make(hash, layout.brick_bytes(), Form::Lz4, || {
                    Ok::<_, ApiError>(
                        lz4_flex::block::compress(&voxels(state, layout, stored, hash)?).into(),
                    )
                })?,
        ),
        _ => (
            "application/octet-stream",
            None,
            voxels(state, layout, stored, hash)?,
        ),
    };
    response_headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(media));
    if let Some(e) = encoding {
        response_headers.insert(header::CONTENT_ENCODING, HeaderValue::from_static(e));
    }
    // Built in place: `(headers, body).into_response()` would copy the headers into a new map.
    let mut response = Response::new(axum::body::Body::from(body));
    *response.headers_mut() = response_headers;
    Ok(response)
}

/// `"` + 16 hex digits + `"`, without allocating.
pub(super) fn format_etag(hash: u64, out: &mut [u8; 18]) -> &str {
    const HEX: &[u8; 16] = b"0123456789abcdef";
    out[0] = b'"';
    out[17] = b'"';
    for i in 0..16 {
        out[1 + i] = HEX[((hash >> (60 - 4 * i)) & 0xf) as usize];
    }
    std::str::from_utf8(out).unwrap_or("\"0\"")
}

/// A brick's voxels: constants from the constant table, records from the brick cache.
fn voxels(
    state: &AppState,
    layout: &VolumeLayout,
    stored: StoredBrick<'_>,
    hash: u64,
) -> Result<bytes::Bytes, ApiError> {
    if let StoredBrick::Constant(v) = stored {
        return Ok(state.constants.raw(v, layout));
    }
    Ok(state.bricks.voxels(hash, &stored, layout)?)
}
