//! The read handlers beyond single bricks (those are in `bricks.rs`): what is served, many
//! bricks at once, levels, mesh tiles. Each extracts, calls the volume and maps the result.

use super::bricks::{brick_position, format_etag, if_none_match};
use super::compression::{accepts_zstd, Body};
use super::extract::{ChannelParam, Json, Named, Path, Query, RawPath, VersionParam};
use super::mesh_answers::MeshAnswer;
use super::{ApiError, AppState};
use crate::mesh::cache::MeshCache;
use crate::store::decoded::DecodedBricks;
use crate::volume::read::{LevelAnswer, LevelForm};
use crate::volume::{LiveVolume, VolumeError};
use axum::extract::State;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use isovox_proto::api::{VolumeInfo, VolumeList};
use isovox_proto::batch::BatchRequest;
use serde::Deserialize;
use std::sync::Arc;

/// Media type of the compact mesh encoding (`proto::mesh`).
pub const MESH_MEDIA_TYPE: &str = "application/x-isovox-mesh";

/// Media type of a batch of bricks (`proto::batch`).
pub const BATCH_MEDIA_TYPE: &str = "application/x-isovox-bricks";

/// `GET /healthz`.
pub async fn healthz() -> &'static str {
    "ok"
}

/// Every path no route serves.
pub async fn not_found() -> ApiError {
    ApiError::NotFound("no such route; the API is described at /openapi.json".into())
}

fn info(name: &str, volume: &LiveVolume) -> VolumeInfo {
    let vod = volume.current();
    VolumeInfo {
        channels: vod.header().channels.clone(),
        ..VolumeInfo::new(
            name,
            vod.layout(),
            vod.header().voxel_scale,
            vod.head().version,
        )
    }
}

/// `GET /v1/volumes`.
pub async fn list_volumes(State(state): State<AppState>) -> axum::Json<VolumeList> {
    axum::Json(VolumeList {
        volumes: state.catalog.iter().map(|(n, v)| info(n, v)).collect(),
    })
}

/// `GET /v1/volumes/{name}`.
pub async fn volume_info(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<axum::Json<VolumeInfo>, ApiError> {
    Ok(axum::Json(info(&name, state.catalog.get(&name)?)))
}

/// Query of a mesh tile.
#[derive(Debug, Deserialize)]
pub struct MeshQuery {
    // `?version=N` is read as sent, by `VersionParam`.
    /// Iso value; default S - 0.5.
    pub iso: Option<f32>,
    /// `compact` (the default) or `glb`.
    #[serde(default)]
    pub format: TileFormat,
}

/// How a mesh tile is encoded.
#[derive(Debug, Clone, Copy, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TileFormat {
    /// `application/x-isovox-mesh` (`docs/mesh-encoding.md`).
    #[default]
    Compact,
    /// `model/gltf-binary`: the regular mesh as a glTF primitive, the moves in a buffer view
    /// (a strip: a plain glTF mesh).
    Glb,
}

impl TileFormat {
    fn encode(self, tile: &isovox_proto::mesh::TileMesh) -> Vec<u8> {
        match self {
            TileFormat::Compact => isovox_proto::mesh::encode_tile(tile),
            TileFormat::Glb => isovox_proto::mesh::encode_glb_tile(tile),
        }
    }

    fn encode_strip(self, strip: &isovox_proto::mesh::Mesh) -> Vec<u8> {
        match self {
            TileFormat::Compact => isovox_proto::mesh::encode_compact(strip),
            TileFormat::Glb => isovox_proto::mesh::encode_glb(strip),
        }
    }

    fn media_type(self) -> &'static str {
        match self {
            TileFormat::Compact => MESH_MEDIA_TYPE,
            TileFormat::Glb => "model/gltf-binary",
        }
    }
}

/// One mesh tile with its moves (`docs/mesh-encoding.md`), with `?channel=NAME` its per-vertex
/// materials from that u8 channel (`docs/channels.md`): marching cubes over the brick and its
/// halo, through the content-keyed mesh cache, meshed, encoded and (for clients
/// that take it) zstd-compressed off the async runtime. `ETag` names the tile's inputs and
/// position, so a revalidation costs index lookups (27 bricks) and no meshing; caching headers as
/// [`validate`] says.
pub async fn mesh_tile(
    State(state): State<AppState>,
    Path(Named { name }): Path<Named>,
    raw: RawPath,
    VersionParam(version): VersionParam,
    ChannelParam(channel): ChannelParam,
    Query(query): Query<MeshQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let (format, iso) = (query.format, query.iso);
    let position = brick_position(&raw)?;
    let tile = state
        .read_volume(&name, move |_, vol| {
            vol.mesh_tile(version, position, iso, channel.as_deref())
        })
        .await?;
    let tag = tile.tag(format as u8);
    answer_mesh(
        &state,
        tag,
        version,
        &headers,
        (format.media_type(), tile.may_cross()),
        move |meshes, bricks| Ok(format.encode(&tile.mesh(meshes, bricks)?)),
    )
    .await
}

/// A mesh answer named by `tag`, of media type `media_type`: 304 when `If-None-Match` names it;
/// made here when no surface `may_cross` it (an empty mesh: microseconds, no voxel read); else
/// the answer kept from an earlier request or being made for another one (`mesh_answers.rs`),
/// else `make` run off the async runtime with the mesh cache and the decoded bricks. Its bytes
/// (zstd-compressed for clients that take it) go out with the caching headers [`validate`]
/// gives.
///
/// Most tiles of a large world hold no surface (air, rock): 50 viewers of a 2048^3 world asked
/// for about 120,000 of them in 20 s, each a job of the bounded CPU queue, which filled it and
/// refused thousands of requests with 503s.
async fn answer_mesh(
    state: &AppState,
    tag: u64,
    version: Option<u64>,
    headers: &HeaderMap,
    (media_type, may_cross): (&'static str, bool),
    make: impl FnOnce(&MeshCache, Arc<DecodedBricks>) -> Result<Vec<u8>, VolumeError> + Send + 'static,
) -> Result<Response, ApiError> {
    let response_headers = match validate(tag, version, headers) {
        Validated::NotModified(response) => return Ok(response),
        Validated::Changed(response_headers) => response_headers,
    };
    let zstd = accepts_zstd(headers);
    if !may_cross {
        let body = Body::new(make(&state.meshes, state.bricks.clone())?, zstd);
        return Ok(body.respond(media_type, response_headers));
    }
    let (meshes, bricks) = (state.meshes.clone(), state.bricks.clone());
    let answer = state
        .mesh_answers
        .get_or_make(tag, zstd, || {
            state.cpu.answer(0, move || {
                Ok::<_, VolumeError>(Body::new(make(&meshes, bricks)?, zstd))
            })
        })
        .await?;
    Ok(match answer {
        MeshAnswer::Made(body) => body.respond(media_type, response_headers),
        MeshAnswer::Kept(kept) => kept.respond(media_type, response_headers),
    })
}

/// The path parameters of a transition strip read as text: the volume and the face (the
/// tile's numbers are read as sent, by [`RawPath`]).
#[derive(Debug, Deserialize)]
pub struct StripPath {
    /// The volume.
    pub name: String,
    /// The face, one of [`isovox_proto::mesh::FACE_NAMES`].
    pub face: String,
}

/// Face `name` (one of [`isovox_proto::mesh::FACE_NAMES`]: `-x`, `+x`, `-y`, `+y`, `-z`, `+z`)
/// as its number.
fn face_number(name: &str) -> Result<usize, ApiError> {
    isovox_proto::mesh::FACE_NAMES
        .iter()
        .position(|&f| f == name)
        .ok_or_else(|| {
            ApiError::BadRequest(format!(
                "unknown face {name:?}: one of {}",
                isovox_proto::mesh::FACE_NAMES.join(", ")
            ))
        })
}

/// The transition strip of one face of a mesh tile (`docs/lod-meshes.md`): a plain mesh whose
/// vertices are at their drawn positions, drawn with the tile when that face touches a tile one
/// level coarser. Content-addressed like the tile: the mesh cache, a strong `ETag` naming its
/// inputs (a revalidation costs index lookups), caching headers as [`validate`] says. A face
/// that can never touch a coarser tile has an empty strip.
pub async fn mesh_strip(
    State(state): State<AppState>,
    Path(StripPath { name, face }): Path<StripPath>,
    raw: RawPath,
    VersionParam(version): VersionParam,
    ChannelParam(channel): ChannelParam,
    Query(query): Query<MeshQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let format = query.format;
    let position = brick_position(&raw)?;
    let face = face_number(&face)?;
    let iso = query.iso;
    let strip = state
        .read_volume(&name, move |_, vol| {
            vol.mesh_strip(version, position, face, iso, channel.as_deref())
        })
        .await?;
    let tag = strip.tag(format as u8);
    answer_mesh(
        &state,
        tag,
        version,
        &headers,
        (format.media_type(), strip.may_cross()),
        move |meshes, bricks| Ok(format.encode_strip(&strip.mesh(meshes, bricks)?)),
    )
    .await
}

/// Of a computed answer named by a tag (`tag` hashes everything its bytes depend on).
enum Validated {
    /// The client holds it: 304 with the caching headers.
    NotModified(Response),
    /// It must be made: the caching headers for its response.
    Changed(HeaderMap),
}

/// The caching headers of a computed answer (mesh tile, level) and whether `If-None-Match`
/// already names it, asked before the CPU job so a revalidation costs none.
///
/// `ETag` is the tag (strong: equal tags, equal bytes). The newest version's answer changes
/// with edits: `no-cache`, revalidated on every use. A pinned answer (`?version=N`) never
/// changes: immutable, cached for good.
fn validate(tag: u64, version: Option<u64>, headers: &HeaderMap) -> Validated {
    let mut etag = [0u8; 18];
    let etag = format_etag(tag, &mut etag);
    let mut out = HeaderMap::with_capacity(8);
    // Sixteen hex digits in quotes: always a valid header value.
    if let Ok(v) = HeaderValue::from_str(etag) {
        out.insert(header::ETAG, v);
    }
    out.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(match version {
            Some(_) => "public, max-age=31536000, immutable",
            None => "no-cache",
        }),
    );
    out.insert(header::VARY, HeaderValue::from_static("Accept-Encoding"));
    if if_none_match(headers, etag) {
        return Validated::NotModified((StatusCode::NOT_MODIFIED, out).into_response());
    }
    Validated::Changed(out)
}

/// Many bricks in one response (`proto::batch`), decoded (and compressed) off the async
/// runtime.
pub async fn batch(
    State(state): State<AppState>,
    Path(name): Path<String>,
    ChannelParam(channel): ChannelParam,
    headers: HeaderMap,
    Json(request): Json<BatchRequest>,
) -> Result<Response, ApiError> {
    let read = state
        .read_volume(&name, move |_, vol| vol.batch(&request, channel.as_deref()))
        .await?;
    let zstd = accepts_zstd(&headers);
    let bricks = state.bricks.clone();
    let body = state
        .cpu
        .answer(read.known_bytes(), move || {
            read.encode(&bricks).map(|bytes| Body::new(bytes, zstd))
        })
        .await?;
    Ok(body.respond(BATCH_MEDIA_TYPE, HeaderMap::new()))
}

/// A grid region of at most this many bricks (a streamer's chunk is 512) is answered where it
/// is read, never queued as CPU work: see [`level`].
const SMALL_GRID_BRICKS: u64 = 4096;

/// Query of a level.
#[derive(Debug, Deserialize)]
pub struct LevelQuery {
    // `?version=N` is read as sent, by `VersionParam`.
    /// `MINX,MINY,MINZ,MAXX,MAXY,MAXZ` (max exclusive): bricks for `format=grid`, voxels for
    /// `format=voxels`. The whole level by default.
    pub region: Option<String>,
    /// `grid` (default): the brick grid as JSON (content hash, min, max per brick); `voxels`:
    /// the voxels as one RAW array (x fastest), for levels or regions up to 64 MiB.
    pub format: Option<String>,
}

/// `MINX,MINY,MINZ,MAXX,MAXY,MAXZ` as (min, max): six numbers of 1 to 10 digits, nothing
/// else (the pattern `/openapi.json` states).
fn parse_region(s: &str) -> Result<([u64; 3], [u64; 3]), ApiError> {
    let number = |p: &str| {
        ((1..=10).contains(&p.len()) && p.bytes().all(|b| b.is_ascii_digit()))
            .then(|| p.parse::<u64>().ok())
            .flatten()
    };
    let v: Vec<u64> = s
        .split(',')
        .map(number)
        .collect::<Option<_>>()
        .ok_or_else(|| {
            ApiError::BadRequest(format!(
                "region {s:?}: six non-negative integers MINX,MINY,MINZ,MAXX,MAXY,MAXZ expected"
            ))
        })?;
    match v[..] {
        [x0, y0, z0, x1, y1, z1] => Ok(([x0, y0, z0], [x1, y1, z1])),
        _ => Err(ApiError::BadRequest(format!(
            "region {s:?}: six values MINX,MINY,MINZ,MAXX,MAXY,MAXZ expected"
        ))),
    }
}

/// A whole level (or a region of it): its brick grid with each brick's content hash and value
/// range, or its voxels as one array; read (and compressed) off the async runtime. `ETag`
/// names the version and the request, so a revalidation reads no brick; caching headers as
/// [`validate`] says.
pub async fn level(
    State(state): State<AppState>,
    Path(Named { name }): Path<Named>,
    raw: RawPath,
    VersionParam(version): VersionParam,
    ChannelParam(channel): ChannelParam,
    Query(query): Query<LevelQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let level = raw.number("level")?;
    let form = match query.format.as_deref() {
        None | Some("grid") => LevelForm::Grid,
        Some("voxels") => LevelForm::Voxels,
        Some(other) => {
            return Err(ApiError::BadRequest(format!(
                "unknown level format {other:?} (grid or voxels)"
            )))
        }
    };
    let region = query.region.as_deref().map(parse_region).transpose()?;
    let zstd = accepts_zstd(&headers);
    // A small region of a grid is a few index reads and a JSON document of tens of kilobytes:
    // about twice what answering a brick costs. Viewers ask for hundreds at once when they
    // start, and each tile waits for its region, so these are answered where they are read
    // (inline for a local volume, on the store-read threads for a remote one) instead of
    // waiting in the CPU queue behind mesh tiles or being refused when it is full. A
    // revalidation (a cache in front asks again) is answered from the tag, before any of that.
    let small = form == LevelForm::Grid
        && region.is_some_and(|(min, max)| {
            (0..3)
                .map(|a| max[a].saturating_sub(min[a]))
                .product::<u64>()
                <= SMALL_GRID_BRICKS
        });
    let request_headers = headers.clone();
    let job = state
        .read_volume(&name, move |_, vol| {
            let read = vol.level(version, channel.as_deref(), level, form, region)?;
            let response_headers = match validate(read.tag(), version, &request_headers) {
                Validated::NotModified(response) => return Ok(LevelJob::NotModified(response)),
                Validated::Changed(response_headers) => response_headers,
            };
            Ok::<_, VolumeError>(if small {
                LevelJob::Ready(level_body(read.run()?, zstd), response_headers)
            } else {
                LevelJob::Queued(read, response_headers)
            })
        })
        .await?;
    let media = match form {
        LevelForm::Grid => "application/json",
        LevelForm::Voxels => "application/octet-stream",
    };
    let (body, response_headers) = match job {
        LevelJob::NotModified(response) => return Ok(response),
        // Held against the response memory until sent, as the CPU queue's answers are.
        LevelJob::Ready(body, response_headers) => {
            let reservation = state.cpu.memory.reserve(body.len())?;
            (body.hold(reservation), response_headers)
        }
        LevelJob::Queued(read, response_headers) => {
            let body = state
                .cpu
                .answer(read.known_bytes(), move || {
                    Ok::<_, VolumeError>(level_body(read.run()?, zstd))
                })
                .await?;
            (body, response_headers)
        }
    };
    Ok(body.respond(media, response_headers))
}

/// A level read: the client holds it already, it is answered already, or it is to be run as
/// CPU work; with the answer's caching headers.
enum LevelJob {
    NotModified(Response),
    Ready(Body, HeaderMap),
    Queued(crate::volume::read::LevelRead, HeaderMap),
}

fn level_body(answer: LevelAnswer, zstd: bool) -> Body {
    match answer {
        LevelAnswer::Grid(grid) => Body::json(&grid, zstd),
        LevelAnswer::Voxels(voxels) => Body::new(voxels, zstd),
    }
}
