//! HTTP API types (JSON), shared by the server and the client.

use crate::layout::VolumeLayout;
use crate::voxel::VoxelType;
use serde::{Deserialize, Serialize};

/// One level of detail of a volume.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelInfo {
    pub level: u8,
    /// Bricks per axis.
    pub grid: [u32; 3],
    /// Meaningful voxels per axis at this level: `ceil(dims / 2^level)`.
    pub dims: [u32; 3],
}

/// `GET /v1/volumes/{name}`: what a client needs to address any brick.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolumeInfo {
    pub name: String,
    pub dims: [u32; 3],
    pub voxel_type: VoxelType,
    /// L, H and S of the voxel type (`docs/icvg.md`).
    pub low: u16,
    pub high: u16,
    pub surface: u16,
    pub brick: u32,
    pub levels: Vec<LevelInfo>,
    pub voxel_scale: [f32; 3],
    /// The current version; edits increase it.
    pub version: u64,
}

impl VolumeInfo {
    pub fn new(name: &str, layout: &VolumeLayout, voxel_scale: [f32; 3], version: u64) -> Self {
        let t = layout.voxel_type();
        VolumeInfo {
            name: name.to_string(),
            dims: layout.dims(),
            voxel_type: t,
            low: t.low(),
            high: t.high(),
            surface: t.surface(),
            brick: layout.brick(),
            levels: (0..layout.levels())
                .map(|level| LevelInfo {
                    level,
                    grid: layout.grid(level),
                    dims: layout.level_dims(level),
                })
                .collect(),
            voxel_scale,
            version,
        }
    }
}

/// `GET /v1/volumes`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolumeList {
    pub volumes: Vec<VolumeInfo>,
}

/// An error as RFC 9457 problem details (`application/problem+json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Problem {
    /// A URI naming the kind of problem (`about:blank` when the status says it all).
    #[serde(rename = "type")]
    pub kind: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    /// The volume's current version, on a 409 from a conditional edit (`If-Match`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<u64>,
}

/// One brick in a level's grid.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LevelBrick {
    /// Content hash, 16 hex digits: `GET .../blobs/{hash}` fetches it.
    pub hash: String,
    pub min: u16,
    pub max: u16,
}

/// `GET /v1/volumes/{name}/levels/{level}`: the brick grid of a level, or of the box
/// `min..max` (brick coordinates, max exclusive) of it; bricks x fastest, then y, then z.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LevelGrid {
    pub level: u8,
    pub grid: [u32; 3],
    pub min: [u32; 3],
    pub max: [u32; 3],
    pub version: u64,
    pub bricks: Vec<LevelBrick>,
}

/// Changed bricks per level (level 0 first), each list sorted by z, then y, then x.
pub type ChangedBricks = Vec<Vec<[u32; 3]>>;

/// `POST /v1/volumes/{name}/edits`: what one acknowledged edit did.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EditResponse {
    /// The version the edit created.
    pub version: u64,
    /// The version it was applied to.
    pub previous: u64,
    pub changed: ChangedBricks,
    /// Level-0 bricks whose voxels were evaluated.
    pub evaluated: u64,
    /// Brick records appended to the file (content not stored before).
    pub new_records: u64,
    /// Whether the commit wrote a full index checkpoint.
    pub checkpoint: bool,
    /// Time from the start of the evaluation to the durable commit.
    pub elapsed_us: u64,
}

/// One committed version as the change feed announces it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChangeEvent {
    pub version: u64,
    pub timestamp_ms: u64,
    pub changed: ChangedBricks,
}

/// `GET /v1/volumes/{name}/changes?since=N`: the versions after `since`, oldest first.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChangeList {
    pub since: u64,
    /// The current version.
    pub head: u64,
    /// The oldest version the file still holds.
    pub oldest: u64,
    /// Versions after the last listed one exist: ask again from it.
    pub more: bool,
    pub changes: Vec<ChangeEvent>,
}

/// `POST /v1/volumes/{name}/compact`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompactResponse {
    /// The head version, unchanged by compaction.
    pub version: u64,
    pub bytes_before: u64,
    pub bytes_after: u64,
    /// Distinct brick records in the new file.
    pub bricks: u64,
    pub elapsed_us: u64,
}
