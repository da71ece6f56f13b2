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
    /// L, H and S of the voxel type (`spec/icvg.md`).
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
