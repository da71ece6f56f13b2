//! Thin handlers: extract, call the store, map the result.

use super::{ApiError, AppState};
use crate::store::codec;
use crate::store::{StoredBrick, Vod2};
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use isovox_proto::api::{VolumeInfo, VolumeList};
use isovox_proto::vod2::{content_hash, Codec};
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

fn volume(state: &AppState, name: &str) -> Result<Arc<Vod2>, ApiError> {
    state
        .catalog
        .get(name)
        .ok_or_else(|| ApiError::not_found(format!("no volume named {name:?}")))
}

fn info(name: &str, vod: &Vod2) -> VolumeInfo {
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
    Ok(Json(info(&name, &vod)))
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
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Path((name, level, x, y, z)) =
        path.map_err(|e| ApiError::BadRequest(format!("malformed brick path: {e}")))?;
    let Query(query) = query.map_err(|e| ApiError::BadRequest(format!("malformed query: {e}")))?;
    let vod = volume(&state, &name)?;
    let snap = match query.version {
        Some(v) => vod.version(v)?,
        None => vod.head(),
    };
    let layout = snap.layout();
    let key = layout
        .key(level, x, y, z)
        .map_err(|e| ApiError::not_found(e.to_string()))?;
    let stored = snap.stored(key)?;
    let mut decoded = vec![0u8; layout.brick_bytes()];
    let hash = match stored {
        StoredBrick::Record { header, .. } => header.hash,
        StoredBrick::Constant(v) => {
            codec::fill_constant(&mut decoded, v, layout.voxel_type());
            content_hash(&decoded)
        }
    };
    let etag = format!("\"{hash:016x}\"");
    let etag_value = HeaderValue::from_str(&etag).map_err(|e| ApiError::Internal(e.to_string()))?;
    let matches = headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim() == etag || t.trim() == "*");
    let mut response_headers = HeaderMap::new();
    response_headers.insert(header::ETAG, etag_value);
    response_headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response_headers.insert(
        header::VARY,
        HeaderValue::from_static("Accept, Accept-Encoding"),
    );
    if matches {
        return Ok((StatusCode::NOT_MODIFIED, response_headers).into_response());
    }
    let want_lz4 = accepts(&headers, header::ACCEPT, LZ4_MEDIA_TYPE);
    if let StoredBrick::Record {
        header: h, payload, ..
    } = stored
    {
        if want_lz4 && h.codec == Codec::Lz4 {
            response_headers.insert(
                header::CONTENT_TYPE,
                HeaderValue::from_static(LZ4_MEDIA_TYPE),
            );
            return Ok((response_headers, payload.to_vec()).into_response());
        }
        if !want_lz4 && h.codec == Codec::Zstd && accepts(&headers, header::ACCEPT_ENCODING, "zstd")
        {
            response_headers.insert(
                header::CONTENT_TYPE,
                HeaderValue::from_static("application/octet-stream"),
            );
            response_headers.insert(header::CONTENT_ENCODING, HeaderValue::from_static("zstd"));
            return Ok((response_headers, payload.to_vec()).into_response());
        }
        crate::store::vod2::decode_stored(&stored, layout, &mut decoded)?;
    }
    if want_lz4 {
        response_headers.insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static(LZ4_MEDIA_TYPE),
        );
        return Ok((response_headers, lz4_flex::block::compress(&decoded)).into_response());
    }
    response_headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/octet-stream"),
    );
    Ok((response_headers, decoded).into_response())
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
    let revalidated = headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim() == etag || t.trim() == "*");
    if revalidated {
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
        let tile = cache.tile(&snap, key, iso, &mut scratch)?;
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
