//! `POST /v1/volumes/{name}/compact`: rewrite a served file with only its head version, while
//! serving it.

use super::auth::WriteToken;
use super::cpu::blocking;
use super::extract::Path;
use super::{ApiError, AppState};
use axum::extract::State;
use axum::Json;
use isovox_proto::api::CompactResponse;

/// Waits for the volume's writer, compacts off the async runtime, and serves the new file.
pub async fn compact(
    WriteToken(token): WriteToken,
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<CompactResponse>, ApiError> {
    let vol = state.catalog.get(&name)?.clone();
    let mut writer = vol.wait_for_writer(state.config.edit_queue).await?;
    let compacting = vol.clone();
    let report = blocking(state.main_runtime(), move || {
        compacting.compact(&mut writer)
    })
    .await?;
    tracing::info!(volume = %name, user = %token.user, version = report.version,
        bytes_before = report.bytes_before, bytes_after = report.bytes_after, "compacted");
    Ok(Json(CompactResponse {
        version: report.version,
        bytes_before: report.bytes_before,
        bytes_after: report.bytes_after,
        bricks: report.bricks,
        elapsed_us: report.elapsed.as_micros() as u64,
    }))
}
