//! Building a whole VOD 2 volume from a level-0 source, streaming.
//!
//! Level 0 is produced one z-slab of bricks at a time (all bricks with the same z). Two slabs of
//! level k make one slab of level k+1, so memory holds at most two slabs per level, whatever the
//! volume's size. Within a slab, bricks are filled, classified, hashed and compressed in parallel
//! (rayon); deduplication and appending run in order on one thread, so the file is deterministic.

use super::codec::Compression;
use super::pyramid::{constant_parent, downsample, BrickSource, BrickVoxels, Downsampling};
use super::transaction::{CheckpointPolicy, Transaction};
use super::writer::{Vod2Writer, WriteStats};
use super::StoreError;
use crate::progress::{Progress, Silent};
use isovox_proto::vod2::FileHeader;
use isovox_proto::{BrickKey, VolumeLayout};
use rayon::prelude::*;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How to build.
#[derive(Clone)]
pub struct BuildOptions {
    /// How bricks are compressed (each is stored raw where compression does not shrink it;
    /// constants and deduplication apply in every case).
    pub compression: Compression,
    /// Advanced once per brick written (all levels).
    pub progress: Arc<dyn Progress>,
}

impl std::fmt::Debug for BuildOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BuildOptions")
            .field("compression", &self.compression)
            .finish_non_exhaustive()
    }
}

impl Default for BuildOptions {
    fn default() -> Self {
        BuildOptions {
            compression: Compression::default(),
            progress: Arc::new(Silent),
        }
    }
}

/// What a build wrote.
#[derive(Debug, Clone)]
pub struct BuildReport {
    /// What the writer stored.
    pub stats: WriteStats,
    /// The file's size.
    pub file_bytes: u64,
    /// How long the build took.
    pub elapsed: Duration,
}

/// Builds `path` as version 1 of a volume whose level-0 voxels come from `source`.
///
/// # Errors
/// The file cannot be written.
pub fn build_vod2(
    path: &Path,
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    source: &dyn BrickSource,
    options: &BuildOptions,
) -> Result<BuildReport, StoreError> {
    let header = FileHeader::new(layout.clone(), voxel_scale);
    build_streams(path, header, &[source], options)
}

/// Builds `path` as version 1 of a volume with the header `header` (which may list attribute
/// channels): `sources[0]` gives density's level 0, `sources[i]` channel `i - 1`'s. Each
/// stream's pyramid is built as [`build_vod2`] builds density's, a channel's levels by
/// [`Downsampling::of_channel`].
///
/// # Errors
/// A source is missing or extra, or the file cannot be written.
pub fn build_streams(
    path: &Path,
    header: FileHeader,
    sources: &[&dyn BrickSource],
    options: &BuildOptions,
) -> Result<BuildReport, StoreError> {
    let start = Instant::now();
    if sources.len() != 1 + header.channels.len() {
        return Err(StoreError::Internal(format!(
            "{} sources for {} streams",
            sources.len(),
            1 + header.channels.len()
        )));
    }
    let streams: Vec<(VolumeLayout, Downsampling)> = (0..sources.len())
        .filter_map(|s| {
            let how = match s {
                0 => Downsampling::Mean,
                s => Downsampling::of_channel(&header.channels[s - 1]),
            };
            Some((header.stream_layout(s)?, how))
        })
        .collect();
    let mut writer = Vod2Writer::create(path, header.clone(), options.compression)?;
    let mut transaction = Transaction::first(&mut writer);
    options.progress.start(header.node_count());
    let mut built = Ok(());
    for (stream, ((layout, how), source)) in streams.iter().zip(sources).enumerate() {
        let mut sink = FileSink {
            transaction: &mut transaction,
            first_node: stream as u64 * layout.node_count(),
        };
        built = stream_pyramid_by(layout, *how, *source, &mut sink, options.progress.as_ref());
        if built.is_err() {
            break;
        }
    }
    options.progress.finish();
    built?;
    transaction.commit(CheckpointPolicy::default())?;
    Ok(BuildReport {
        stats: writer.stats(),
        file_bytes: writer.end(),
        elapsed: start.elapsed(),
    })
}

/// Receives each level's bricks, one z-slab at a time, as the pyramid is built.
pub trait SlabSink {
    /// # Errors
    /// Whatever storing the slab can fail with.
    fn slab(
        &mut self,
        layout: &VolumeLayout,
        level: u8,
        z: u32,
        slab: &[BrickVoxels],
    ) -> Result<(), StoreError>;
}

/// Keeps every brick of every level in memory, in node order (for measuring what building the
/// octree from RAW costs, as the thesis's Table 5 does).
#[derive(Debug, Default)]
pub struct MemorySink {
    /// Every brick of every level.
    pub bricks: Vec<BrickVoxels>,
}

impl SlabSink for MemorySink {
    fn slab(
        &mut self,
        _: &VolumeLayout,
        _: u8,
        _: u32,
        slab: &[BrickVoxels],
    ) -> Result<(), StoreError> {
        // Slabs arrive interleaved across levels; keep them all, order does not matter here.
        self.bricks.extend_from_slice(slab);
        Ok(())
    }
}

/// Stores every brick of one stream as part of the first version of a new file.
struct FileSink<'t, 'w> {
    transaction: &'t mut Transaction<'w>,
    /// The file-wide node of the stream's first brick.
    first_node: u64,
}

impl SlabSink for FileSink<'_, '_> {
    fn slab(
        &mut self,
        layout: &VolumeLayout,
        level: u8,
        z: u32,
        slab: &[BrickVoxels],
    ) -> Result<(), StoreError> {
        let writer = self.transaction.writer();
        let t = layout.voxel_type();
        // Stream 0 (density) starts at node 0; an attribute channel's pyramid after it.
        let channel = self.first_node > 0;
        let prepared: Vec<_> = slab
            .par_iter()
            .map(|v| match channel {
                true => writer.prepare_channel(v, t),
                false => writer.prepare_as(v, t),
            })
            .collect();
        let first = self.first_node
            + layout.node_index(BrickKey {
                level,
                x: 0,
                y: 0,
                z,
            });
        for (i, (voxels, p)) in slab.iter().zip(prepared).enumerate() {
            self.transaction.put_as(first + i as u64, voxels, p, t)?;
        }
        Ok(())
    }
}

/// Produces every brick of every level from a level-0 source and hands them to `sink`.
///
/// # Errors
/// What the sink returns.
pub fn stream_pyramid(
    layout: &VolumeLayout,
    source: &dyn BrickSource,
    sink: &mut dyn SlabSink,
    progress: &dyn Progress,
) -> Result<(), StoreError> {
    stream_pyramid_by(layout, Downsampling::Mean, source, sink, progress)
}

/// [`stream_pyramid`] with the levels above level 0 made by `how`.
///
/// # Errors
/// What the sink returns.
pub fn stream_pyramid_by(
    layout: &VolumeLayout,
    how: Downsampling,
    source: &dyn BrickSource,
    sink: &mut dyn SlabSink,
    progress: &dyn Progress,
) -> Result<(), StoreError> {
    let mut b = Builder {
        layout,
        how,
        sink,
        pending: vec![None; layout.levels() as usize],
        progress,
    };
    for z in 0..layout.grid(0)[2] {
        let slab = level0_row(layout, source, z);
        if source.failed() {
            return Err(StoreError::BadInput(format!(
                "the input failed at brick row {z}; the build stopped"
            )));
        }
        b.add_slab(0, z, slab)?;
    }
    Ok(())
}

/// The level-0 bricks of brick row `z` (x fastest, then y), filled in parallel. A split import
/// ([`super::remote::parts`]) stores these rows as the single build hands them on.
pub fn level0_row(layout: &VolumeLayout, source: &dyn BrickSource, z: u32) -> Vec<BrickVoxels> {
    let g = layout.grid(0);
    let brick_bytes = layout.brick_bytes();
    (0..g[0] * g[1])
        .into_par_iter()
        .map(|i| {
            let key = BrickKey {
                level: 0,
                x: i % g[0],
                y: i / g[0],
                z,
            };
            if let Some(v) = source.constant(key) {
                return BrickVoxels::Constant(v);
            }
            let mut out = vec![0u8; brick_bytes];
            source.fill(key, &mut out);
            BrickVoxels::from_bytes(out, layout.voxel_type())
        })
        .collect()
}

struct Builder<'a> {
    layout: &'a VolumeLayout,
    how: Downsampling,
    sink: &'a mut dyn SlabSink,
    /// Per level: an even slab waiting for its odd partner.
    pending: Vec<Option<Vec<BrickVoxels>>>,
    progress: &'a dyn Progress,
}

impl Builder<'_> {
    fn add_slab(&mut self, level: u8, z: u32, slab: Vec<BrickVoxels>) -> Result<(), StoreError> {
        self.write_slab(level, z, &slab)?;
        if level + 1 == self.layout.levels() {
            return Ok(());
        }
        let gz = self.layout.grid(level)[2];
        let (lower, upper) = if z.is_multiple_of(2) {
            if z + 1 < gz {
                self.pending[level as usize] = Some(slab);
                return Ok(());
            }
            (slab, None)
        } else {
            let lower = self.pending[level as usize].take().ok_or_else(|| {
                StoreError::Internal(format!("level {level} slab {z} has no partner"))
            })?;
            (lower, Some(slab))
        };
        let parent = self.parent_slab(level, &lower, upper.as_deref());
        self.add_slab(level + 1, z / 2, parent)
    }

    fn parent_slab(
        &self,
        level: u8,
        lower: &[BrickVoxels],
        upper: Option<&[BrickVoxels]>,
    ) -> Vec<BrickVoxels> {
        let child = self.layout.grid(level);
        let parent = self.layout.grid(level + 1);
        let brick = self.layout.brick();
        let voxel_type = self.layout.voxel_type();
        let brick_bytes = self.layout.brick_bytes();
        let how = self.how;
        (0..parent[0] * parent[1])
            .into_par_iter()
            .map(|i| {
                let (px, py) = (i % parent[0], i / parent[0]);
                let mut children: [Option<&BrickVoxels>; 8] = [None; 8];
                for (octant, slot) in children.iter_mut().enumerate() {
                    let (cx, cy) = (
                        px * 2 + (octant & 1) as u32,
                        py * 2 + (octant >> 1 & 1) as u32,
                    );
                    let slab = if octant >> 2 == 0 { Some(lower) } else { upper };
                    if let Some(slab) = slab {
                        if cx < child[0] && cy < child[1] {
                            *slot = Some(&slab[(cy * child[0] + cx) as usize]);
                        }
                    }
                }
                if let Some(v) = constant_parent(&children) {
                    return BrickVoxels::Constant(v);
                }
                let mut out = vec![0u8; brick_bytes];
                downsample(&children, brick, voxel_type, how, &mut out);
                BrickVoxels::from_bytes(out, voxel_type)
            })
            .collect()
    }

    fn write_slab(&mut self, level: u8, z: u32, slab: &[BrickVoxels]) -> Result<(), StoreError> {
        self.sink.slab(self.layout, level, z, slab)?;
        self.progress.advance(slab.len() as u64);
        Ok(())
    }
}

/// The layout of a built file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileFormat {
    /// VOD 2 (what Isovox serves).
    Vod2,
    /// The thesis's VOD 1 (for its tools; read-only here).
    Vod1,
}

/// The path `path` with `suffix` appended (for temporaries beside an output).
pub fn sibling(path: &Path, suffix: &str) -> std::path::PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(suffix);
    std::path::PathBuf::from(s)
}

/// [`build_streams`] into `output` through a temporary file beside it, renamed into place (as
/// [`build_file`] does for one stream).
///
/// # Errors
/// The build or the rename fails.
pub fn build_streams_file(
    output: &Path,
    header: FileHeader,
    sources: &[&dyn BrickSource],
    options: &BuildOptions,
) -> Result<BuildReport, StoreError> {
    let tmp = sibling(output, ".isovox-tmp");
    let report = build_streams(&tmp, header, sources, options)?;
    std::fs::rename(&tmp, output)
        .map_err(StoreError::io_path("cannot move the result to", output))?;
    Ok(report)
}

/// Builds `output` from `source` through a temporary file beside it, renamed into place, so an
/// interrupted build never leaves a half-written volume under the final name. As VOD 1, the
/// VOD 2 build is converted (lz4 unless `options` say no compression) and removed.
///
/// # Errors
/// The build, the conversion or the rename fails.
pub fn build_file(
    output: &Path,
    layout: &VolumeLayout,
    voxel_scale: [f32; 3],
    source: &dyn BrickSource,
    options: &BuildOptions,
    format: FileFormat,
) -> Result<BuildReport, StoreError> {
    let tmp = sibling(output, ".isovox-tmp");
    let report = build_vod2(&tmp, layout, voxel_scale, source, options)?;
    match format {
        FileFormat::Vod1 => {
            let vod = super::Vod2::open(&tmp)?;
            let file = std::fs::File::create(output)
                .map_err(StoreError::io_path("cannot create", output))?;
            let mut out = std::io::BufWriter::new(file);
            let compress = options.compression != Compression::None;
            super::vod1::write_vod1(&vod.head(), compress, &mut out)?;
            std::io::Write::flush(&mut out).map_err(StoreError::io_path("cannot write", output))?;
            drop(vod);
            let _ = std::fs::remove_file(&tmp);
        }
        FileFormat::Vod2 => std::fs::rename(&tmp, output)
            .map_err(StoreError::io_path("cannot move the result to", output))?,
    }
    tracing::info!(
        output = %output.display(),
        bytes = report.file_bytes,
        seconds = report.elapsed.as_secs_f64(),
        "built volume"
    );
    Ok(report)
}
