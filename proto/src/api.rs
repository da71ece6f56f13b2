//! HTTP API types (JSON), shared by the server and the client.

use crate::history::CommitInfo;
use crate::layout::VolumeLayout;
use crate::voxel::VoxelType;
use serde::{Deserialize, Serialize};

/// One level of detail of a volume.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelInfo {
    /// The level (0 = full resolution).
    pub level: u8,
    /// Bricks per axis.
    pub grid: [u32; 3],
    /// Meaningful voxels per axis at this level: `ceil(dims / 2^level)`.
    pub dims: [u32; 3],
}

/// `GET /v1/volumes/{name}`: what a client needs to address any brick.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolumeInfo {
    /// The name it is served under.
    pub name: String,
    /// Level-0 size in voxels (x, y, z).
    pub dims: [u32; 3],
    /// The voxel type (u8 or u16).
    pub voxel_type: VoxelType,
    /// L, H and S of the voxel type (`docs/icvg.md`).
    pub low: u16,
    /// H, the largest value.
    pub high: u16,
    /// S, the surface threshold: a voxel is inside when its value is at least S.
    pub surface: u16,
    /// Brick edge in voxels (every level's bricks have it).
    pub brick: u32,
    /// Every level, finest first.
    pub levels: Vec<LevelInfo>,
    /// World size of one level-0 voxel (x, y, z).
    pub voxel_scale: [f32; 3],
    /// The current version; edits increase it.
    pub version: u64,
    /// The attribute channels beside density (materials, labels), read with `?channel=NAME`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub channels: Vec<crate::channel::ChannelInfo>,
}

impl VolumeInfo {
    /// The metadata of volume `name` with `layout`, at `version`.
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
            channels: Vec::new(),
        }
    }
}

/// `GET /v1/volumes`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolumeList {
    /// Every served volume, by name.
    pub volumes: Vec<VolumeInfo>,
}

/// An error as RFC 9457 problem details (`application/problem+json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Problem {
    /// A URI naming the kind of problem (`about:blank` when the status says it all).
    #[serde(rename = "type")]
    pub kind: String,
    /// The status's reason phrase.
    pub title: String,
    /// The HTTP status code.
    pub status: u16,
    /// What went wrong, for a person (generic for server errors).
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
    /// The brick's smallest voxel value.
    pub min: u64,
    /// The brick's largest voxel value.
    pub max: u64,
}

/// `GET /v1/volumes/{name}/levels/{level}`: the brick grid of a level, or of the box
/// `min..max` (brick coordinates, max exclusive) of it; bricks x fastest, then y, then z.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LevelGrid {
    /// The level.
    pub level: u8,
    /// The level's whole brick grid.
    pub grid: [u32; 3],
    /// The first brick of the region listed (inclusive).
    pub min: [u32; 3],
    /// The end of the region listed (exclusive).
    pub max: [u32; 3],
    /// The version the grid describes.
    pub version: u64,
    /// The region's bricks, x fastest, then y, then z.
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
    /// The bricks whose content changed, per level.
    pub changed: ChangedBricks,
    /// Level-0 bricks whose voxels were evaluated.
    pub evaluated: u64,
    /// Brick records appended to the file (content not stored before).
    pub new_records: u64,
    /// Whether the commit wrote a full index checkpoint.
    pub checkpoint: bool,
    /// Time from the start of the evaluation to the durable commit.
    pub elapsed_us: u64,
    /// Whether the edit made a version. `false` for an edit that reaches no voxel of the
    /// volume (wholly outside it, or outside its region): nothing is committed, `version` and
    /// `previous` are the current version, and the change feed announces nothing.
    #[serde(default = "committed_by_default")]
    pub committed: bool,
    /// For an undo or redo: the later edits applied again over the bricks it changed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replayed: Option<u64>,
    /// For a dry run (`?dry_run=true`): `true`, and nothing was committed (`version` is what
    /// the edit would have made).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub dry_run: bool,
    /// For an edit: the level-0 voxels whose density it changed (or would, in a dry run).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub voxels_changed: Option<u64>,
    /// The bricks of attribute channels whose content changed, by channel, per level; only
    /// channels that changed.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub channels: std::collections::BTreeMap<String, ChangedBricks>,
}

/// Answers from servers before `committed` existed made a version each.
fn committed_by_default() -> bool {
    true
}

/// The most changed bricks whose hashes and value ranges a [`ChangeEvent`] lists (about 45
/// bytes of JSON each: 200 kB at most per event and subscriber). An edit's event stays well under
/// it (a radius-30 sphere in 32^3 bricks changes about 30 bricks a level); an import-sized
/// revert goes over, and its streamers ask the grids.
pub const EVENT_GRID_LIMIT: usize = 4096;

/// One committed version as the change feed announces it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChangeEvent {
    /// The version committed.
    pub version: u64,
    /// When it was committed (Unix milliseconds).
    pub timestamp_ms: u64,
    /// The bricks whose content changed, per level.
    pub changed: ChangedBricks,
    /// What each brick of `changed` holds now, in the same order (per level, one entry per
    /// brick): its content hash and value range, as `levels/{l}` would list it at this version.
    /// A streamer updates its grids from the event alone, and fetches the new bricks and
    /// meshes by hash or version. Empty when the commit changed more than
    /// [`EVENT_GRID_LIMIT`] bricks (then ask the grids), and from servers before it existed.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub bricks: Vec<Vec<LevelBrick>>,
    /// The bricks of attribute channels whose content changed, by channel, per level; only
    /// channels that changed.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub channels: std::collections::BTreeMap<String, ChangedBricks>,
    /// Who made it and what it did (absent fields: not recorded).
    #[serde(flatten)]
    pub info: CommitInfo,
}

/// `GET /v1/volumes/{name}/changes?since=N`: the versions after `since`, oldest first.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChangeList {
    /// The version the list starts after.
    pub since: u64,
    /// The current version.
    pub head: u64,
    /// The oldest version the file still holds.
    pub oldest: u64,
    /// Versions after the last listed one exist: ask again from it.
    pub more: bool,
    /// The versions after `since`, oldest first.
    pub changes: Vec<ChangeEvent>,
}

/// `POST /v1/volumes/{name}/compact`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompactResponse {
    /// The head version, unchanged by compaction.
    pub version: u64,
    /// File size before compaction.
    pub bytes_before: u64,
    /// File size after compaction.
    pub bytes_after: u64,
    /// Distinct brick records in the new file.
    pub bricks: u64,
    /// How long compaction took, in microseconds.
    pub elapsed_us: u64,
}
