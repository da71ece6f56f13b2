//! The hash book: content hashes of bricks as of the engine's version, where unknown ones will
//! come from, and the content keys of mesh tiles and strips computed from them.

use super::scheduler::JobKey;
use super::FastMap;
use crate::streamer::StreamEvent;
use isovox_proto::api::{LevelGrid, VolumeInfo};
use isovox_proto::tile::GridBox;
use isovox_proto::{BrickKey, VolumeLayout};
use std::cell::RefCell;
use std::hash::{Hash, Hasher};

/// The volume's shape as content keys describe it: its layout and metadata.
pub(super) type Shape<'a> = (&'a VolumeLayout, &'a VolumeInfo);

/// The hash book: content hashes of bricks as of the engine's version, and where unknown ones
/// will come from.
#[derive(Debug)]
pub(super) struct HashBook {
    /// Bricks per axis of the regions unknown hashes come from (aligned).
    chunk: u32,
    hashes: FastMap<BrickKey, u64>,
    /// Each known brick's smallest and largest voxel value (from the same grid entry or event
    /// as its hash), which the descent reads.
    ranges: FastMap<BrickKey, (u16, u16)>,
    /// Bounds on the voxels of bricks whose range is unknown, kept from before a commit changed
    /// a coarser brick they were bounded by (the descent reads them; see
    /// [`HashBook::keep_bounds`]).
    kept_bounds: FastMap<BrickKey, (u16, u16)>,
    /// The grid region (planned or running) that brings an unknown brick's hash, when it is
    /// not the brick's chunk.
    sources: FastMap<BrickKey, JobKey>,
    /// Counts the changes to `ranges` and `kept_bounds`, which the descent's bounds are drawn
    /// from.
    generation: u64,
    /// The descent's bounds worked out since the last such change.
    pub(super) memo: RefCell<BoundMemo>,
}

/// The bounds the descent worked out ([`HashBook::bound`]), kept while the ranges they were
/// drawn from stay as they were. Tiles a moving camera brings into view read many of the same
/// bricks (a tile reads its neighbours, and they share ancestors): a bound is then one lookup
/// instead of a walk up the octree.
#[derive(Debug, Default)]
pub(super) struct BoundMemo {
    /// The book's generation they were worked out at.
    pub(super) generation: u64,
    /// The iso value's bits they were worked out for.
    pub(super) iso: u32,
    /// Each brick's bound, or the brick whose grid entry is needed first.
    pub(super) bounds: FastMap<BrickKey, Result<(u16, u16), BrickKey>>,
}

impl HashBook {
    /// An empty book whose regions have `chunk` bricks per axis.
    pub(super) fn new(chunk: u32) -> HashBook {
        HashBook {
            chunk: chunk.max(1),
            hashes: FastMap::default(),
            ranges: FastMap::default(),
            kept_bounds: FastMap::default(),
            sources: FastMap::default(),
            generation: 0,
            memo: RefCell::default(),
        }
    }

    /// Bricks per axis of the regions.
    pub(super) fn chunk(&self) -> u32 {
        self.chunk
    }

    /// Brick `b`'s content hash, if known.
    pub(super) fn hash(&self, b: BrickKey) -> Option<u64> {
        self.hashes.get(&b).copied()
    }

    /// Brick `b`'s smallest and largest voxel value, if known.
    pub(super) fn range(&self, b: BrickKey) -> Option<(u16, u16)> {
        self.ranges.get(&b).copied()
    }

    /// The count of changes to what the descent's bounds are drawn from.
    pub(super) fn generation(&self) -> u64 {
        self.generation
    }

    /// A bound kept on brick `b`'s voxels while its range is unknown.
    pub(super) fn kept_bound(&self, b: BrickKey) -> Option<(u16, u16)> {
        self.kept_bounds.get(&b).copied()
    }

    /// Keeps `bound` on the voxels of brick `b`, whose range is unknown and whose content no
    /// commit changed since the bound was drawn (with any bound it had: both hold).
    pub(super) fn keep_bound(&mut self, b: BrickKey, (lo, hi): (u16, u16)) {
        if self.ranges.contains_key(&b) {
            return;
        }
        let kept = self.kept_bounds.entry(b).or_insert((lo, hi));
        *kept = (kept.0.max(lo), kept.1.min(hi));
        self.generation += 1;
    }

    /// Whether a grid region was designated to bring `brick`'s hash (a commit changed it and
    /// did not say what it holds now).
    pub(super) fn has_designated_source(&self, brick: BrickKey) -> bool {
        self.sources.contains_key(&brick)
    }

    /// The grid region that brings `brick`'s hash: a designated one, or its chunk.
    pub(super) fn source_of(&self, layout: &VolumeLayout, brick: BrickKey) -> JobKey {
        if let Some(&s) = self.sources.get(&brick) {
            return s;
        }
        let g = layout.grid(brick.level);
        let p = [brick.x, brick.y, brick.z];
        let chunk = self.chunk;
        let min = p.map(|c| c / chunk * chunk);
        JobKey::Region {
            level: brick.level,
            min,
            max: [0, 1, 2].map(|a| (min[a] + chunk).min(g[a])),
        }
    }

    /// A mesh tile's content key, or the input bricks whose hashes are unknown.
    pub(super) fn mesh_content(
        &self,
        shape: Shape<'_>,
        key: BrickKey,
        iso: Option<f32>,
    ) -> Result<u64, Vec<BrickKey>> {
        let reads = isovox_proto::tile::mesh_tile_reads(shape.0, key);
        self.content_of(shape, "isovox mesh tile with moves", key, None, iso, &reads)
    }

    /// The content key of the strip of face `face` of mesh tile `key`, or the input bricks
    /// whose hashes are unknown.
    pub(super) fn strip_content(
        &self,
        shape: Shape<'_>,
        key: BrickKey,
        face: u8,
        iso: Option<f32>,
    ) -> Result<u64, Vec<BrickKey>> {
        let reads = isovox_proto::tile::strip_reads(shape.0, key, usize::from(face));
        self.content_of(
            shape,
            "isovox transition strip",
            key,
            Some(face),
            iso,
            &reads,
        )
    }

    /// A content key over what a tile or strip depends on: `what`, the tile, the face, the iso
    /// value, the volume's shape and the hashes of the bricks of `reads`.
    fn content_of(
        &self,
        (layout, info): Shape<'_>,
        what: &str,
        key: BrickKey,
        face: Option<u8>,
        iso: Option<f32>,
        reads: &[(u8, GridBox)],
    ) -> Result<u64, Vec<BrickKey>> {
        let mut h = super::content_hasher();
        what.hash(&mut h);
        key.hash(&mut h);
        face.hash(&mut h);
        iso.map(f32::to_bits).hash(&mut h);
        info.brick.hash(&mut h);
        layout.voxel_type().bytes().hash(&mut h);
        info.voxel_scale.map(f32::to_bits).hash(&mut h);
        let mut unknown = Vec::new();
        for b in bricks_read(layout, reads) {
            match b.map(|b| (b, self.hashes.get(&b))) {
                None => 0u8.hash(&mut h),
                Some((_, Some(v))) => (1u8, *v).hash(&mut h),
                Some((b, None)) => unknown.push(b),
            }
        }
        if unknown.is_empty() {
            Ok(h.finish())
        } else {
            Err(unknown)
        }
    }

    /// The grid region `job` (bricks `min..max` of `level`) brings the hashes of its bricks
    /// that are not known yet, unless another region was designated for them.
    pub(super) fn claim(&mut self, level: u8, min: [u32; 3], max: [u32; 3], job: JobKey) {
        for z in min[2]..max[2] {
            for y in min[1]..max[1] {
                for x in min[0]..max[0] {
                    let b = BrickKey { level, x, y, z };
                    if !self.hashes.contains_key(&b) {
                        self.sources.entry(b).or_insert(job);
                    }
                }
            }
        }
    }

    /// The bricks `min..max` of `level` that `job` was to bring lose it as their source.
    pub(super) fn forget_source(&mut self, level: u8, min: [u32; 3], max: [u32; 3], job: JobKey) {
        for z in min[2]..max[2] {
            for y in min[1]..max[1] {
                for x in min[0]..max[0] {
                    let b = BrickKey { level, x, y, z };
                    if self.sources.get(&b) == Some(&job) {
                        self.sources.remove(&b);
                    }
                }
            }
        }
    }

    /// Learns the hashes of the bricks `min..max` of `level` from `grid` (checked to cover
    /// them); returns an error event for each entry that is not a content hash.
    pub(super) fn learn_region(
        &mut self,
        level: u8,
        (min, max): ([u32; 3], [u32; 3]),
        grid: &LevelGrid,
    ) -> Vec<StreamEvent> {
        self.generation += 1;
        let mut errors = Vec::new();
        let mut bricks = grid.bricks.iter();
        for z in min[2]..max[2] {
            for y in min[1]..max[1] {
                for x in min[0]..max[0] {
                    let b = BrickKey { level, x, y, z };
                    let Some(entry) = bricks.next() else {
                        continue;
                    };
                    match u64::from_str_radix(&entry.hash, 16) {
                        Ok(h) => {
                            self.hashes.insert(b, h);
                            self.ranges.insert(b, density_range(entry.min, entry.max));
                            self.kept_bounds.remove(&b);
                            self.sources.remove(&b);
                        }
                        Err(_) => errors.push(StreamEvent::Error {
                            key: Some(b),
                            error: format!("brick {b}: {:?} is not a content hash", entry.hash),
                        }),
                    }
                }
            }
        }
        errors
    }

    /// Brick `b` changed and holds `hash`, with values in `range`, now (a commit event said so).
    pub(super) fn learn(&mut self, b: BrickKey, hash: u64, range: (u64, u64)) {
        let range = density_range(range.0, range.1);
        self.generation += 1;
        self.hashes.insert(b, hash);
        self.ranges.insert(b, range);
        self.kept_bounds.remove(&b);
        self.sources.remove(&b);
    }

    /// Brick `b` changed: its hash is unknown again.
    pub(super) fn forget(&mut self, b: BrickKey) {
        self.generation += 1;
        self.hashes.remove(&b);
        self.ranges.remove(&b);
        self.kept_bounds.remove(&b);
        self.sources.remove(&b);
    }

    /// One region of `level` brings the new hashes of the changed bricks `read` (some desired
    /// tile reads them).
    pub(super) fn bring_together(&mut self, level: u8, read: Vec<BrickKey>) {
        let Some(first) = read.first() else {
            return;
        };
        let (mut min, mut max) = ([first.x, first.y, first.z], [0u32; 3]);
        for b in &read {
            let p = [b.x, b.y, b.z];
            for a in 0..3 {
                min[a] = min[a].min(p[a]);
                max[a] = max[a].max(p[a] + 1);
            }
        }
        let region = JobKey::Region { level, min, max };
        for b in read {
            self.sources.insert(b, region);
        }
    }

    /// Forgets every hash and source.
    pub(super) fn clear(&mut self) {
        self.generation += 1;
        self.hashes.clear();
        self.ranges.clear();
        self.kept_bounds.clear();
        self.sources.clear();
    }
}

/// The bricks of `reads` (boxes of brick positions per level), in order: `None` for a position
/// beyond the level's grid (read as 0 by the meshes).
pub(super) fn bricks_read<'a>(
    layout: &'a VolumeLayout,
    reads: &'a [(u8, GridBox)],
) -> impl Iterator<Item = Option<BrickKey>> + 'a {
    reads.iter().flat_map(move |&(level, (lo, hi))| {
        let g = layout.grid(level).map(i64::from);
        (lo[2]..=hi[2]).flat_map(move |z| {
            (lo[1]..=hi[1]).flat_map(move |y| {
                (lo[0]..=hi[0]).map(move |x| {
                    let c = [x, y, z];
                    (!(0..3).any(|a| c[a] < 0 || c[a] >= g[a])).then_some(BrickKey {
                        level,
                        x: x as u32,
                        y: y as u32,
                        z: z as u32,
                    })
                })
            })
        })
    })
}

/// A density brick's value range as the book keeps it: density is u8 or u16, so a range past
/// u16 (only a damaged or hostile answer has one) saturates instead of wrapping.
fn density_range(min: u64, max: u64) -> (u16, u16) {
    let narrow = |v: u64| u16::try_from(v).unwrap_or(u16::MAX);
    (narrow(min), narrow(max))
}
