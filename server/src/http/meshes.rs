//! `POST /v1/meshes?format=stl|obj|ply|glb`: keeps a watertight model by its content hash, for
//! `mesh` leaves of edit terms.

use super::auth::WriteToken;
use super::cpu::blocking;
use super::extract::Query;
use super::request_body::read_limited;
use super::{ApiError, AppState};
use crate::voxelize::store::{MeshInfo, FORMATS};
use axum::body::Body;
use axum::extract::State;
use axum::http::HeaderMap;
use axum::Json;
use serde::Deserialize;

/// Largest mesh upload.
const MAX_MESH_BODY: usize = 256 << 20;

/// `?format=`.
#[derive(Debug, Deserialize)]
pub struct UploadQuery {
    /// The model's file format: stl, obj, ply or glb.
    pub format: Option<String>,
}

/// Reads the model (after the token check), checks and stores it off the async runtime.
pub async fn upload_mesh(
    WriteToken(token): WriteToken,
    State(state): State<AppState>,
    Query(query): Query<UploadQuery>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<MeshInfo>, ApiError> {
    let store = state
        .mesh_store
        .clone()
        .ok_or_else(|| ApiError::NotFound("this server keeps no meshes".into()))?;
    let format = query
        .format
        .filter(|f| FORMATS.contains(&f.as_str()))
        .ok_or_else(|| {
            ApiError::BadRequest("give the model's ?format=: stl, obj, ply or glb".into())
        })?;
    let body = read_limited(&headers, body, MAX_MESH_BODY, "a model").await?;
    let info = blocking(state.main_runtime(), move || {
        store.store(&body, &format).map_err(ApiError::Unprocessable)
    })
    .await?;
    tracing::info!(user = %token.user, hash = %format!("{:016x}", info.hash), triangles = info.triangles, "mesh stored");
    Ok(Json(info))
}
