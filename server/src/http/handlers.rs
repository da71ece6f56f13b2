//! Thin handlers: extract, call the store, map the result.

use super::bodies::BodyKind;
use super::{ApiError, AppState};
use crate::store::codec;
use crate::store::{Snapshot, StoredBrick};
use crate::volume::LiveVolume;
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use isovox_proto::api::{VolumeInfo, VolumeList};
use isovox_proto::vod2::{content_hash, Codec};
use isovox_proto::VolumeLayout;
use serde::Deserialize;
use std::sync::Arc;

/// The media type of an lz4 block (lz4_flex block format, decoding to one brick).
pub const LZ4_MEDIA_TYPE: &str = "application/x-lz4";

pub async fn healthz() -> &'static str {
    "ok"
}

pub async fn not_found() -> ApiError {
    ApiError::not_found("no such route; the API is described at /openapi.json")
}

pub(super) fn volume<'a>(state: &'a AppState, name: &str) -> Result<&'a Arc<LiveVolume>, ApiError> {
    state
        .catalog
        .volume(name)
        .ok_or_else(|| ApiError::not_found(format!("no volume named {name:?}")))
}

fn info(name: &str, volume: &LiveVolume) -> VolumeInfo {
    let vod = volume.current();
    VolumeInfo::new(
        name,
        vod.layout(),
        vod.header().voxel_scale,
        vod.head().version,
    )
}

pub async fn list_volumes(State(state): State<AppState>) -> Json<VolumeList> {
    Json(VolumeList {
        volumes: state.catalog.iter().map(|(n, v)| info(n, v)).collect(),
    })
}

pub async fn volume_info(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<VolumeInfo>, ApiError> {
    let vod = volume(&state, &name)?;
    Ok(Json(info(&name, vod)))
}

/// `{name}/bricks/{level}/{x}/{y}/{z}`.
pub type BrickPath = (String, u8, u32, u32, u32);

#[derive(Debug, Deserialize)]
pub struct VersionQuery {
    pub version: Option<u64>,
}

fn accepts(headers: &HeaderMap, name: header::HeaderName, token: &str) -> bool {
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

/// One brick.
///
/// - Default: the decoded voxels (`application/octet-stream`, x fastest, u16 little endian).
///   A brick stored as zstd goes out as it is, with `Content-Encoding: zstd`, to clients that
///   send `Accept-Encoding: zstd` (browsers decode it transparently).
/// - `Accept: application/x-lz4`: an lz4 block of the voxels (the stored block when the brick is
///   stored as lz4, else compressed on the fly).
/// - `ETag` is the content hash; `If-None-Match` with it answers 304.
/// - `?version=N` reads an older version while the file still holds it.
pub async fn brick(
    State(state): State<AppState>,
    path: Result<Path<BrickPath>, PathRejection>,
    query: Result<Query<VersionQuery>, QueryRejection>,
    // The request itself, not a `HeaderMap` extractor (which clones every header).
    request: axum::extract::Request,
) -> Result<Response, ApiError> {
    let headers = request.headers();
    let Path((name, level, x, y, z)) =
        path.map_err(|e| ApiError::BadRequest(format!("malformed brick path: {e}")))?;
    let Query(query) = query.map_err(|e| ApiError::BadRequest(format!("malformed query: {e}")))?;
    brick_at(&state, &name, query.version, (level, x, y, z), headers)
}

/// The response for brick (level, x, y, z) of volume `name` at `version` (the head if `None`):
/// the brick route's work once its request is parsed, shared with the fast path.
pub(super) fn brick_at(
    state: &AppState,
    name: &str,
    version: Option<u64>,
    (level, x, y, z): (u8, u32, u32, u32),
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let vod = volume(state, name)?;
    // The head is borrowed from the volume's current file (no reference count touched).
    let (current, older);
    let snap: &Snapshot = match version {
        Some(v) => {
            older = vod.version(v)?;
            &older
        }
        None => {
            current = vod.load();
            current.head_ref()
        }
    };
    let key = snap
        .layout()
        .key(level, x, y, z)
        .map_err(|e| ApiError::not_found(e.to_string()))?;
    let stored = snap.stored(key)?;
    brick_response(state, snap, stored, headers, "no-cache")
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

/// The response for one stored brick, shared by the position and the content-hash routes:
/// ETag = content hash (304 on a match); the stored zstd frame as `Content-Encoding: zstd` to
/// clients that accept it, an lz4 block for `Accept: application/x-lz4`, else the raw voxels.
///
/// Stored payloads go out as they are stored (small ones copied, large ones as shared slices of
/// the mapping: see `Snapshot::payload_bytes`); decoded voxels and transcoded lz4 blocks come
/// from the body cache, keyed by content hash, so a hot brick is decoded once.
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
        StoredBrick::Record {
            offset, header: h, ..
        } if want_lz4 && h.codec == Codec::Lz4 => {
            (LZ4_MEDIA_TYPE, None, snap.payload_bytes(offset, &h)?)
        }
        StoredBrick::Record {
            offset, header: h, ..
        } if !want_lz4
            && h.codec == Codec::Zstd
            && accepts(headers, header::ACCEPT_ENCODING, "zstd") =>
        {
            (
                "application/octet-stream",
                Some("zstd"),
                snap.payload_bytes(offset, &h)?,
            )
        }
        StoredBrick::Constant(v) if want_lz4 => (
            LZ4_MEDIA_TYPE,
            None,
            state.constants.body(v, layout, BodyKind::Lz4),
        ),
        _ if want_lz4 => (
            LZ4_MEDIA_TYPE,
            None,
            state.bodies.get_or_make(hash, BodyKind::Lz4, || {
                Ok(lz4_flex::block::compress(&decoded(state, layout, stored, hash)?).into())
            })?,
        ),
        _ => (
            "application/octet-stream",
            None,
            decoded(state, layout, stored, hash)?,
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
fn format_etag(hash: u64, out: &mut [u8; 18]) -> &str {
    const HEX: &[u8; 16] = b"0123456789abcdef";
    out[0] = b'"';
    out[17] = b'"';
    for i in 0..16 {
        out[1 + i] = HEX[((hash >> (60 - 4 * i)) & 0xf) as usize];
    }
    std::str::from_utf8(out).unwrap_or("\"0\"")
}

/// A brick's voxels: constants from the constant table, records from the body cache.
fn decoded(
    state: &AppState,
    layout: &VolumeLayout,
    stored: StoredBrick<'_>,
    hash: u64,
) -> Result<bytes::Bytes, ApiError> {
    if let StoredBrick::Constant(v) = stored {
        return Ok(state.constants.body(v, layout, BodyKind::Raw));
    }
    state.bodies.get_or_make(hash, BodyKind::Raw, || {
        let mut out = vec![0u8; layout.brick_bytes()];
        crate::store::vod2::decode_stored(&stored, layout, &mut out)?;
        Ok(out.into())
    })
}

/// A brick by content hash (16 hex digits): immutable, so any HTTP cache or CDN may keep it
/// forever. Bricks of the newest version are found.
pub async fn blob(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
    request: axum::extract::Request,
) -> Result<Response, ApiError> {
    let headers = request.headers();
    let Path((name, hex)) =
        path.map_err(|e| ApiError::BadRequest(format!("malformed blob path: {e}")))?;
    let hash = (hex.len() == 16 && hex.bytes().all(|b| b.is_ascii_hexdigit()))
        .then(|| u64::from_str_radix(&hex, 16).ok())
        .flatten()
        .ok_or_else(|| {
            ApiError::BadRequest(format!("{hex:?} is not a content hash (16 hex digits)"))
        })?;
    let vod = volume(&state, &name)?;
    let snap = vod.head();
    let entry = snap
        .find_by_hash(hash)?
        .ok_or_else(|| ApiError::not_found(format!("no brick with hash {hex} in {name:?}")))?;
    let stored = snap.stored_entry(entry)?;
    brick_response(
        &state,
        &snap,
        stored,
        headers,
        "public, max-age=31536000, immutable",
    )
}

/// Query of a mesh tile.
#[derive(Debug, Deserialize)]
pub struct MeshQuery {
    pub version: Option<u64>,
    /// Iso value; default S - 0.5.
    pub iso: Option<f32>,
    /// `compact` (default, `application/x-isovox-mesh`) or `glb` (`model/gltf-binary`).
    pub format: Option<String>,
}

/// Media type of the compact mesh encoding (`proto::mesh`).
pub const MESH_MEDIA_TYPE: &str = "application/x-isovox-mesh";

/// One mesh tile: marching cubes over the brick and its halo, through the content-keyed mesh
/// cache, meshed on the blocking pool (never on the async workers). `ETag` names the tile's
/// inputs and position, so a revalidation costs 27 index lookups and no meshing.
pub async fn mesh_tile(
    State(state): State<AppState>,
    path: Result<Path<BrickPath>, PathRejection>,
    query: Result<Query<MeshQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Path((name, level, x, y, z)) =
        path.map_err(|e| ApiError::BadRequest(format!("malformed mesh path: {e}")))?;
    let Query(query) = query.map_err(|e| ApiError::BadRequest(format!("malformed query: {e}")))?;
    let glb = match query.format.as_deref() {
        None | Some("compact") => false,
        Some("glb") => true,
        Some(other) => {
            return Err(ApiError::BadRequest(format!(
                "unknown mesh format {other:?} (compact or glb)"
            )))
        }
    };
    let vod = volume(&state, &name)?;
    let snap = match query.version {
        Some(v) => vod.version(v)?,
        None => vod.head(),
    };
    let key = snap
        .layout()
        .key(level, x, y, z)
        .map_err(|e| ApiError::not_found(e.to_string()))?;
    let iso = query
        .iso
        .unwrap_or_else(|| crate::mesh::tile::default_iso(snap.layout().voxel_type()));
    if !iso.is_finite() {
        return Err(ApiError::BadRequest(format!(
            "iso must be a finite number, got {iso}"
        )));
    }
    let inputs = crate::mesh::tile::tile_inputs(&snap, key, iso)?;
    let mut tag = Vec::with_capacity(64);
    tag.extend_from_slice(&inputs.key.to_le_bytes());
    for c in [x, y, z] {
        tag.extend_from_slice(&c.to_le_bytes());
    }
    for s in snap.header().voxel_scale {
        tag.extend_from_slice(&s.to_le_bytes());
    }
    tag.push(glb as u8);
    let etag = format!("\"{:016x}\"", xxhash_rust::xxh3::xxh3_64(&tag));
    let mut response_headers = HeaderMap::new();
    response_headers.insert(
        header::ETAG,
        HeaderValue::from_str(&etag).map_err(|e| ApiError::Internal(e.to_string()))?,
    );
    response_headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    if if_none_match(&headers, &etag) {
        return Ok((StatusCode::NOT_MODIFIED, response_headers).into_response());
    }
    let permit = state
        .cpu
        .clone()
        .try_acquire_owned()
        .map_err(|_| ApiError::Overloaded(1))?;
    let cache = state.meshes.clone();
    let body = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, crate::store::StoreError> {
        let _permit = permit;
        let mut scratch = crate::mesh::tile::TileScratch::default();
        let tile = cache.tile_with(&snap, key, iso, &inputs, &mut scratch)?;
        let mut mesh = (*tile.mesh).clone();
        crate::mesh::tile::to_world(&mut mesh, key, &snap);
        Ok(if glb {
            isovox_proto::mesh::encode_glb(&mesh)
        } else {
            isovox_proto::mesh::encode_compact(&mesh)
        })
    })
    .await
    .map_err(|e| ApiError::Internal(format!("meshing task failed: {e}")))??;
    let media = if glb {
        "model/gltf-binary"
    } else {
        MESH_MEDIA_TYPE
    };
    response_headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(media));
    Ok((response_headers, body).into_response())
}

/// Most decoded bytes one batch or level answer may carry (413 beyond).
pub const MAX_RESPONSE_BYTES: usize = 64 << 20;

/// Many bricks in one response (`proto::batch`): decoding runs on the blocking pool.
pub async fn batch(
    State(state): State<AppState>,
    path: Result<Path<String>, PathRejection>,
    body: Result<Json<isovox_proto::batch::BatchRequest>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, ApiError> {
    use isovox_proto::batch::{encode_batch, BatchCodec, BatchEncoding, BatchEntry, MAX_BATCH};
    let Path(name) = path.map_err(|e| ApiError::BadRequest(format!("malformed path: {e}")))?;
    let Json(req) = body.map_err(|e| match e.status() {
        StatusCode::PAYLOAD_TOO_LARGE => ApiError::TooLarge(format!("batch request: {e}")),
        StatusCode::UNSUPPORTED_MEDIA_TYPE => {
            ApiError::UnsupportedMedia(format!("batch request: {e}"))
        }
        _ => ApiError::BadRequest(format!("malformed batch request: {e}")),
    })?;
    if req.keys.len() > MAX_BATCH {
        return Err(ApiError::TooLarge(format!(
            "{} keys; a batch takes at most {MAX_BATCH}",
            req.keys.len()
        )));
    }
    let vod = volume(&state, &name)?;
    let snap = match req.version {
        Some(v) => vod.version(v)?,
        None => vod.head(),
    };
    let layout = snap.layout();
    if req.encoding == BatchEncoding::Raw
        && req.keys.len() * layout.brick_bytes() > MAX_RESPONSE_BYTES
    {
        return Err(ApiError::TooLarge(format!(
            "{} raw bricks of {} bytes exceed {MAX_RESPONSE_BYTES} bytes; ask for fewer or for \"encoding\": \"stored\"",
            req.keys.len(),
            layout.brick_bytes()
        )));
    }
    let keys = req
        .keys
        .iter()
        .map(|&(l, x, y, z)| layout.key(l, x, y, z))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| ApiError::not_found(e.to_string()))?;
    let permit = state
        .cpu
        .clone()
        .try_acquire_owned()
        .map_err(|_| ApiError::Overloaded(1))?;
    let encoding = req.encoding;
    let body = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, crate::store::StoreError> {
        let _permit = permit;
        let layout = snap.layout();
        let mut entries = Vec::with_capacity(keys.len());
        for key in keys {
            let stored = snap.stored(key)?;
            let entry = match (encoding, stored) {
                (BatchEncoding::Stored, StoredBrick::Constant(v)) => {
                    let mut full = vec![0u8; layout.brick_bytes()];
                    codec::fill_constant(&mut full, v, layout.voxel_type());
                    BatchEntry {
                        key,
                        codec: BatchCodec::Constant,
                        hash: content_hash(&full),
                        payload: v.to_le_bytes().to_vec(),
                    }
                }
                (
                    BatchEncoding::Stored,
                    StoredBrick::Record {
                        header, payload, ..
                    },
                ) => {
                    let codec = match header.codec {
                        Codec::Raw => BatchCodec::Raw,
                        Codec::Lz4 => BatchCodec::Lz4,
                        Codec::Zstd => BatchCodec::Zstd,
                    };
                    BatchEntry {
                        key,
                        codec,
                        hash: header.hash,
                        payload: payload.to_vec(),
                    }
                }
                (BatchEncoding::Raw, stored) => {
                    let mut out = vec![0u8; layout.brick_bytes()];
                    crate::store::vod2::decode_stored(&stored, layout, &mut out)?;
                    BatchEntry {
                        key,
                        codec: BatchCodec::Raw,
                        hash: content_hash(&out),
                        payload: out,
                    }
                }
            };
            entries.push(entry);
        }
        Ok(encode_batch(&entries))
    })
    .await
    .map_err(|e| ApiError::Internal(format!("batch task failed: {e}")))??;
    Ok((
        [(header::CONTENT_TYPE, "application/x-isovox-bricks")],
        body,
    )
        .into_response())
}

/// Query of a level.
#[derive(Debug, Deserialize)]
pub struct LevelQuery {
    pub version: Option<u64>,
    /// `MINX,MINY,MINZ,MAXX,MAXY,MAXZ` (max exclusive): bricks for `format=grid`, voxels for
    /// `format=voxels`. The whole level by default.
    pub region: Option<String>,
    /// `grid` (default): the brick grid as JSON (content hash, min, max per brick); `voxels`:
    /// the voxels as one RAW array (x fastest), for levels or regions up to 64 MiB.
    pub format: Option<String>,
}

fn parse_region(s: &str, extent: [u32; 3]) -> Result<([u32; 3], [u32; 3]), ApiError> {
    let v: Vec<u32> = s
        .split(',')
        .map(|p| p.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|_| {
            ApiError::BadRequest(format!("region {s:?}: six non-negative integers expected"))
        })?;
    if v.len() != 6 {
        return Err(ApiError::BadRequest(format!(
            "region {s:?}: six values MINX,MINY,MINZ,MAXX,MAXY,MAXZ expected"
        )));
    }
    let (min, max) = ([v[0], v[1], v[2]], [v[3], v[4], v[5]]);
    if (0..3).any(|a| min[a] >= max[a] || max[a] > extent[a]) {
        return Err(ApiError::BadRequest(format!(
            "region {s:?} is empty or outside {extent:?}"
        )));
    }
    Ok((min, max))
}

/// A whole level (or a region of it): its brick grid with each brick's content hash and value
/// range, or its voxels as one array.
pub async fn level(
    State(state): State<AppState>,
    path: Result<Path<(String, u8)>, PathRejection>,
    query: Result<Query<LevelQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    let Path((name, level)) =
        path.map_err(|e| ApiError::BadRequest(format!("malformed level path: {e}")))?;
    let Query(query) = query.map_err(|e| ApiError::BadRequest(format!("malformed query: {e}")))?;
    let vod = volume(&state, &name)?;
    let snap = match query.version {
        Some(v) => vod.version(v)?,
        None => vod.head(),
    };
    let layout = snap.layout().clone();
    if level >= layout.levels() {
        return Err(ApiError::not_found(format!(
            "level {level}: the volume has levels 0..{}",
            layout.levels() - 1
        )));
    }
    let voxels = match query.format.as_deref() {
        None | Some("grid") => false,
        Some("voxels") => true,
        Some(other) => {
            return Err(ApiError::BadRequest(format!(
                "unknown level format {other:?} (grid or voxels)"
            )))
        }
    };
    let extent = if voxels {
        layout.level_dims(level)
    } else {
        layout.grid(level)
    };
    let (min, max) = match &query.region {
        Some(r) => parse_region(r, extent)?,
        None => ([0; 3], extent),
    };
    let count: u64 = (0..3).map(|a| (max[a] - min[a]) as u64).product();
    if voxels && count * layout.voxel_type().bytes() as u64 > MAX_RESPONSE_BYTES as u64 {
        return Err(ApiError::TooLarge(format!(
            "{count} voxels exceed {MAX_RESPONSE_BYTES} bytes; ask for a region or a coarser level"
        )));
    }
    let permit = state
        .cpu
        .clone()
        .try_acquire_owned()
        .map_err(|_| ApiError::Overloaded(1))?;
    let body =
        tokio::task::spawn_blocking(move || -> Result<Response, crate::store::StoreError> {
            let _permit = permit;
            if voxels {
                let mut out = Vec::with_capacity(count as usize * layout.voxel_type().bytes());
                let region = crate::store::raw::Region { min, max };
                crate::store::raw::export_raw(
                    &snap,
                    level,
                    region,
                    &mut out,
                    &indicatif::ProgressBar::hidden(),
                )?;
                return Ok(
                    ([(header::CONTENT_TYPE, "application/octet-stream")], out).into_response()
                );
            }
            let mut bricks = Vec::with_capacity(count as usize);
            for z in min[2]..max[2] {
                for y in min[1]..max[1] {
                    for x in min[0]..max[0] {
                        let key = isovox_proto::BrickKey { level, x, y, z };
                        let stored = snap.stored(key)?;
                        let (lo, hi) = stored.min_max();
                        let hash = match stored {
                            StoredBrick::Record { header, .. } => header.hash,
                            StoredBrick::Constant(_) => snap.hash(key)?,
                        };
                        bricks.push(isovox_proto::api::LevelBrick {
                            hash: format!("{hash:016x}"),
                            min: lo,
                            max: hi,
                        });
                    }
                }
            }
            let grid = isovox_proto::api::LevelGrid {
                level,
                grid: layout.grid(level),
                min,
                max,
                version: snap.version,
                bricks,
            };
            Ok(Json(grid).into_response())
        })
        .await
        .map_err(|e| ApiError::Internal(format!("level task failed: {e}")))??;
    Ok(body)
}
