//! Whole-file statistics for `isovox inspect`: levels, bricks by codec, unique bricks,
//! compression ratio, each attribute channel's, and the bytes the head version no longer
//! references.

use super::vod2::{Snapshot, StoredBrick, Vod2};
use super::StoreError;
use isovox_proto::vod2::{Codec, CommitHeader, DATA_START};
use isovox_proto::VoxelType;
use serde::Serialize;
use std::collections::HashSet;

/// What `inspect --json` prints. Field names are an interface scripts rely on (`docs/cli.md`).
#[derive(Debug, Clone, Serialize)]
pub struct Inspection {
    /// "VOD 2".
    pub format: &'static str,
    /// Level-0 size in voxels.
    pub dims: [u32; 3],
    /// The voxel type.
    pub voxel_type: VoxelType,
    /// Brick edge in voxels.
    pub brick: u32,
    /// World size of one level-0 voxel.
    pub voxel_scale: [f32; 3],
    /// The head version.
    pub version: u64,
    /// Commit records on the head's chain.
    pub commits: u64,
    /// Per level: grid, bricks, constants, records.
    pub levels: Vec<LevelStats>,
    /// Bricks addressed by the index (every level).
    pub bricks_total: u64,
    /// Distinct brick contents: distinct stored records plus distinct constant values.
    pub bricks_unique: u64,
    /// Bricks and bytes by codec.
    pub codecs: CodecStats,
    /// The file's size on disk.
    pub file_bytes: u64,
    /// The size of every voxel as RAW.
    pub raw_bytes: u64,
    /// raw_bytes / file_bytes.
    pub ratio: f64,
    /// Bytes the head version needs: fixed header and slots, its bricks, its index checkpoint
    /// and the commit records from it to the head.
    pub live_bytes: u64,
    /// file_bytes - live_bytes: older versions' bricks and index, and any unfinished commit;
    /// `isovox compact` reclaims them.
    pub garbage_bytes: u64,
    /// Bytes of index checkpoints and commit records.
    pub index_bytes: u64,
    /// The attribute channels' pyramids, in stream order (their records count in
    /// `live_bytes`; the fields above are density's).
    pub channels: Vec<ChannelStats>,
}

/// One attribute channel of an inspected file.
#[derive(Debug, Clone, Serialize)]
pub struct ChannelStats {
    /// Its name.
    pub name: String,
    /// The type of its values.
    pub voxel_type: VoxelType,
    /// Per level: grid, bricks, constants, records.
    pub levels: Vec<LevelStats>,
    /// Distinct brick contents of the channel.
    pub bricks_unique: u64,
    /// Bricks and bytes by codec.
    pub codecs: CodecStats,
    /// The size of its voxels as RAW.
    pub raw_bytes: u64,
}

/// What scanning one stream's pyramid found.
struct StreamScan {
    levels: Vec<LevelStats>,
    bricks_unique: u64,
    codecs: CodecStats,
}

/// One level of an inspected file.
#[derive(Debug, Clone, Serialize)]
pub struct LevelStats {
    /// The level.
    pub level: u8,
    /// Its brick grid.
    pub grid: [u32; 3],
    /// Its bricks.
    pub bricks: u64,
    /// Of them constant (no payload).
    pub constant: u64,
    /// Of them stored as records.
    pub stored: u64,
}

/// Bricks and payload bytes by codec, counting each stored record once.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CodecStats {
    /// Bricks stored as constants in the index.
    pub constant_bricks: u64,
    /// Distinct records stored raw.
    pub raw_records: u64,
    /// Their payload bytes.
    pub raw_bytes: u64,
    /// Distinct records stored as lz4.
    pub lz4_records: u64,
    /// Their payload bytes.
    pub lz4_bytes: u64,
    /// Distinct records stored as zstd.
    pub zstd_records: u64,
    /// Their payload bytes.
    pub zstd_bytes: u64,
    /// Distinct records stored with the palette codec (u32 and u64 channels).
    pub palette_records: u64,
    /// Their payload bytes.
    pub palette_bytes: u64,
}

/// Scans every index entry of the head version.
///
/// # Errors
/// Any entry, brick header or commit record on the way is malformed.
pub fn inspect(vod: &Vod2) -> Result<Inspection, StoreError> {
    let snap = vod.head();
    let layout = snap.layout();
    // Records the head references, each once whichever streams share it.
    let mut live_records = HashSet::new();
    let mut live = DATA_START;
    let density = scan_stream(&snap, &mut live_records, &mut live)?;
    let mut channels = Vec::new();
    for (info, view) in snap.header().channels.iter().zip(snap.channel_views()) {
        let scan = scan_stream(view, &mut live_records, &mut live)?;
        channels.push(ChannelStats {
            name: info.name.clone(),
            voxel_type: info.voxel_type,
            levels: scan.levels,
            bricks_unique: scan.bricks_unique,
            codecs: scan.codecs,
            raw_bytes: view.layout().raw_bytes(),
        });
    }
    let (checkpoint_at, checkpoint_len) = snap.checkpoint_span()?;
    live += checkpoint_len;
    let commits = vod.commits()?;
    for (_, h) in commits
        .iter()
        .take_while(|(_, h)| h.version >= checkpoint_version(&commits, checkpoint_at))
    {
        live += h.total_len();
    }
    let file_bytes = vod.file_len();
    let raw_bytes = layout.raw_bytes();
    Ok(Inspection {
        format: "VOD 2",
        dims: layout.dims(),
        voxel_type: layout.voxel_type(),
        brick: layout.brick(),
        voxel_scale: snap.header().voxel_scale,
        version: snap.version,
        commits: commits.len() as u64,
        levels: density.levels,
        bricks_total: layout.node_count(),
        bricks_unique: density.bricks_unique,
        codecs: density.codecs,
        file_bytes,
        raw_bytes,
        ratio: raw_bytes as f64 / file_bytes as f64,
        live_bytes: live,
        garbage_bytes: file_bytes.saturating_sub(live),
        index_bytes: checkpoint_len,
        channels,
    })
}

/// The levels and codecs of one stream's pyramid (`view`: density's snapshot or a channel's
/// view), adding the records it references to `live_records` and, the first time one is
/// seen, its bytes to `live`.
fn scan_stream(
    view: &Snapshot,
    live_records: &mut HashSet<u64>,
    live: &mut u64,
) -> Result<StreamScan, StoreError> {
    let layout = view.layout();
    let mut records = HashSet::new();
    let mut constants = HashSet::new();
    let mut codecs = CodecStats::default();
    let mut levels = Vec::new();
    for level in 0..layout.levels() {
        let (first, count) = layout.level_range(level);
        let mut stats = LevelStats {
            level,
            grid: layout.grid(level),
            bricks: count,
            constant: 0,
            stored: 0,
        };
        for node in first..first + count {
            match view.stored_entry(view.entry_at(node)?)? {
                StoredBrick::Constant(v) => {
                    stats.constant += 1;
                    codecs.constant_bricks += 1;
                    constants.insert(v);
                }
                StoredBrick::Record { offset, header, .. } => {
                    stats.stored += 1;
                    if live_records.insert(offset) {
                        *live += header.record_len();
                    }
                    if records.insert(offset) {
                        let len = header.stored_len as u64;
                        let (records, bytes) = match header.codec {
                            Codec::Raw => (&mut codecs.raw_records, &mut codecs.raw_bytes),
                            Codec::Lz4 => (&mut codecs.lz4_records, &mut codecs.lz4_bytes),
                            Codec::Zstd => (&mut codecs.zstd_records, &mut codecs.zstd_bytes),
                            Codec::Palette => {
                                (&mut codecs.palette_records, &mut codecs.palette_bytes)
                            }
                        };
                        *records += 1;
                        *bytes += len;
                    }
                }
            }
        }
        levels.push(stats);
    }
    Ok(StreamScan {
        levels,
        bricks_unique: records.len() as u64 + constants.len() as u64,
        codecs,
    })
}

/// The version of the commit that wrote the checkpoint at `checkpoint_at`.
fn checkpoint_version(commits: &[(u64, CommitHeader)], checkpoint_at: u64) -> u64 {
    commits
        .iter()
        .find(|(_, h)| h.checkpoint == checkpoint_at)
        .map(|(_, h)| h.version)
        .unwrap_or(0)
}
