//! The segments of a categorical channel (`docs/channels.md`, "Segments"): their list, and one
//! segment's closed mesh. Each extracts, calls the volume on the CPU queue (the channel's index
//! may have to be built or brought up to date, a mesh marched) and maps the result.

use super::compression::{accepts_zstd, Body};
use super::extract::{query_number, Path, RawPath, VersionParam};
use super::handlers::MESH_MEDIA_TYPE;
use super::{ApiError, AppState};
use crate::volume::VolumeError;
use axum::extract::State;
use axum::http::{HeaderMap, Uri};
use axum::response::Response;
use serde::Deserialize;

/// The path parameters read as text: the volume and the channel (the id is read as sent, by
/// [`RawPath`]).
#[derive(Debug, Deserialize)]
pub struct ChannelPath {
    /// The volume.
    pub name: String,
    /// The channel.
    pub channel: String,
}

/// `channel` as the name of a categorical channel: 400 for what is no channel name, 422 for
/// density (its values are amounts, not ids). Whether the volume has it is the volume's to say
/// (404 naming the channels it has).
fn categorical(channel: &str) -> Result<(), ApiError> {
    let plain = !channel.is_empty()
        && channel.len() <= isovox_proto::channel::MAX_NAME_LEN
        && channel
            .bytes()
            .all(|c| c.is_ascii_alphanumeric() || c == b'_');
    if !plain {
        return Err(ApiError::BadRequest(format!(
            "{channel:?} is not a channel name (letters, digits and _)"
        )));
    }
    if channel == "density" {
        return Err(ApiError::Unprocessable(
            "density is not categorical: its values are amounts, not ids; segments are listed for attribute channels (label, material)".into(),
        ));
    }
    Ok(())
}

/// `GET /v1/volumes/{name}/channels/{channel}/segments?after=ID&limit=N`: the channel's
/// non-zero ids with their level-0 voxel counts and boxes, ascending, one page at a time.
pub async fn segments(
    State(state): State<AppState>,
    Path(ChannelPath { name, channel }): Path<ChannelPath>,
    VersionParam(version): VersionParam,
    uri: Uri,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    categorical(&channel)?;
    let after = query_number::<u64>(&uri, "after")?;
    let limit = query_number::<u64>(&uri, "limit")?;
    let vol = state.catalog.get(&name)?.clone();
    let zstd = accepts_zstd(&headers);
    let body = state
        .cpu
        .answer(0, move || {
            let list = vol.segments(version, &channel, after, limit)?;
            Ok::<_, VolumeError>(Body::json(&list, zstd))
        })
        .await?;
    Ok(body.respond("application/json", HeaderMap::new()))
}

/// How a segment's mesh is encoded.
#[derive(Debug, Clone, Copy, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MeshFormat {
    /// `application/x-isovox-mesh`, version 1 (`docs/mesh-encoding.md`).
    #[default]
    Compact,
    /// `model/gltf-binary`, a plain GLB.
    Glb,
}

/// Query of a segment's mesh (`?version=` and `?level=` are read as sent).
#[derive(Debug, Deserialize)]
pub struct SegmentMeshQuery {
    /// `compact` (the default) or `glb`.
    #[serde(default)]
    pub format: MeshFormat,
}

/// `GET /v1/volumes/{name}/channels/{channel}/segments/{id}/mesh?level=L&format=F`: the closed
/// mesh of the voxels whose value is `id` at level `L` (0 by default), in world coordinates.
/// `Isovox-Version` names the version meshed.
pub async fn segment_mesh(
    State(state): State<AppState>,
    Path(ChannelPath { name, channel }): Path<ChannelPath>,
    raw: RawPath,
    VersionParam(version): VersionParam,
    super::extract::Query(query): super::extract::Query<SegmentMeshQuery>,
    uri: Uri,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    categorical(&channel)?;
    let id = raw.number::<u64>("id")?;
    let level = query_number::<u8>(&uri, "level")?;
    let format = query.format;
    let vol = state.catalog.get(&name)?.clone();
    let zstd = accepts_zstd(&headers);
    // The version meshed, told by the job (its body is all `answer` hands back).
    let meshed = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let told = meshed.clone();
    let body = state
        .cpu
        .answer(0, move || {
            let made = vol.segment_mesh(version, &channel, id, level)?;
            told.store(made.version, std::sync::atomic::Ordering::Relaxed);
            let bytes = match format {
                MeshFormat::Compact => isovox_proto::mesh::encode_compact(&made.mesh),
                MeshFormat::Glb => isovox_proto::mesh::encode_glb(&made.mesh),
            };
            Ok::<_, VolumeError>(Body::new(bytes, zstd))
        })
        .await?;
    let mut out = HeaderMap::new();
    out.insert(
        "isovox-version",
        meshed.load(std::sync::atomic::Ordering::Relaxed).into(),
    );
    let media = match format {
        MeshFormat::Compact => MESH_MEDIA_TYPE,
        MeshFormat::Glb => "model/gltf-binary",
    };
    Ok(body.respond(media, out))
}
