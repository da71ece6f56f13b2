//! Segments of a categorical channel: every non-zero value of a channel (a segmentation's ids,
//! the materials in use) with its level-0 voxel count and bounding box, kept per volume and
//! channel in memory and brought up to date from the commits since it was last asked for,
//! never by a scan per request; and the closed mesh of one segment (`docs/channels.md`,
//! "Segments").
//!
//! The index ([`ChannelIndex`]) holds, for each level-0 brick position, the summary of the
//! brick there: for each non-zero id, its voxel count and its box inside the brick. Summaries
//! are kept by content (the brick's content hash, or its constant) and by the part of the brick
//! inside the volume, so the many bricks deduplication makes equal share one, decoded once.
//! Per id it adds up the counts, and keeps the multiset of its bricks' box corners per axis, so
//! that removing a brick's share of an id takes the box back in O(log n) without looking at
//! the id's other bricks.
//!
//! It is built on the first request for a channel (one pass over the level-0 index, one decode
//! per distinct brick content), then each request first reads the commit records between the
//! version it describes and the head, collects the level-0 bricks of the channel they changed
//! (edits, undo, redo, revert alike: every commit lists the entries it changed) and
//! summarises those again: the cost follows the bricks the commits changed. A commit whose
//! changes are not relative to the version before it (the first commit of a compacted file),
//! or a head older than the index (a volume replaced by an older copy), make it rebuild.

use super::{stream_of, LiveVolume, VolumeError};
use crate::mesh::mc::{march, Field, Scratch};
use crate::store::{Snapshot, StoreError, StoredBrick, Vod2};
use isovox_proto::mesh::Mesh;
use isovox_proto::vod2::CommitHeader;
use isovox_proto::{BrickKey, VoxelType};
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::ops::Bound;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

/// Segments one list answers, by default and at most.
pub const DEFAULT_SEGMENTS: usize = 1000;
/// See [`DEFAULT_SEGMENTS`].
pub const MAX_SEGMENTS: usize = 10_000;
/// Level-0 voxels of a volume whose older versions (`?version=` below the head) are listed by
/// a scan of that version (the index describes the head only); larger volumes refuse them.
pub const MAX_SCAN_VOXELS: u64 = 1 << 24;
/// Voxels of a segment's box (at the level asked for) one mesh may march, 256^3.
pub const MAX_MESH_VOXELS: u64 = 1 << 24;
/// Vertices one segment mesh may have (its crossed grid edges, counted before marching):
/// about 25 MiB of mesh (positions, normals, twice as many triangles) and less encoded.
pub const MAX_MESH_VERTICES: u64 = 1 << 19;

/// A segment id as the JSON answers give it: a number, except in a u64 channel, where it is
/// a decimal string (JavaScript's numbers hold integers exactly only up to 2^53, and a u64
/// segmentation's ids use all 64 bits; Neuroglancer's segment properties spell ids so too).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SegmentId {
    /// The id.
    pub value: u64,
    /// Whether it is written as a string.
    pub as_text: bool,
}

impl Serialize for SegmentId {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        if self.as_text {
            s.collect_str(&self.value)
        } else {
            s.serialize_u64(self.value)
        }
    }
}

/// One segment: a non-zero value of a channel.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct SegmentInfo {
    /// The value.
    pub id: SegmentId,
    /// Level-0 voxels holding it.
    pub voxels: u64,
    /// The level-0 voxels' bounding box, `[[x0, y0, z0], [x1, y1, z1]]`, max exclusive.
    #[serde(rename = "box")]
    pub bounds: [[u32; 3]; 2],
}

/// `GET /v1/volumes/{name}/channels/{channel}/segments`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct SegmentList {
    /// The version listed.
    pub version: u64,
    /// The channel.
    pub channel: String,
    /// Segments at that version, on every page.
    pub total: usize,
    /// Segments with ids after `after`, ascending, at most `limit` of them.
    pub segments: Vec<SegmentInfo>,
    /// When more follow: the `after` of the next page (the last id listed). Absent on the last
    /// page.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next: Option<SegmentId>,
}

/// A segment's mesh, in world coordinates.
#[derive(Debug)]
pub struct SegmentMesh {
    /// The version meshed.
    pub version: u64,
    /// The level marched.
    pub level: u8,
    /// The mesh.
    pub mesh: Mesh,
}

/// One id's share of a brick: its voxels and their box in the brick (max exclusive).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Part {
    id: u64,
    voxels: u32,
    lo: [u32; 3],
    hi: [u32; 3],
}

/// What a brick's content is, for the summaries' cache.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Content {
    /// Every voxel holds this value.
    Constant(u64),
    /// A stored brick with this content hash.
    Hash(u64),
}

/// A brick's content and the part of it inside the volume (voxels past the volume's edge are
/// not counted, so an edge brick's summary differs from an inner one's with the same bytes).
type SummaryKey = (Content, [u32; 3]);

/// The non-zero ids of one brick, ascending.
#[derive(Debug, Default)]
struct BrickSummary {
    parts: Vec<Part>,
}

/// The sums over an id's bricks: its voxels, and per axis the multiset of its bricks' box
/// corners (value -> bricks), whose first low corner and last high corner are its box.
#[derive(Debug, Default)]
struct Aggregate {
    voxels: u64,
    lo: [BTreeMap<u32, u32>; 3],
    hi: [BTreeMap<u32, u32>; 3],
}

impl Aggregate {
    fn add(&mut self, origin: [u32; 3], part: &Part) {
        self.voxels += u64::from(part.voxels);
        for (a, &o) in origin.iter().enumerate() {
            *self.lo[a].entry(o + part.lo[a]).or_default() += 1;
            *self.hi[a].entry(o + part.hi[a]).or_default() += 1;
        }
    }

    fn remove(&mut self, origin: [u32; 3], part: &Part) {
        self.voxels = self.voxels.saturating_sub(u64::from(part.voxels));
        for (a, &o) in origin.iter().enumerate() {
            for (set, at) in [
                (&mut self.lo[a], o + part.lo[a]),
                (&mut self.hi[a], o + part.hi[a]),
            ] {
                if let Some(n) = set.get_mut(&at) {
                    *n -= 1;
                    if *n == 0 {
                        set.remove(&at);
                    }
                }
            }
        }
    }

    fn bounds(&self) -> [[u32; 3]; 2] {
        let first = |m: &BTreeMap<u32, u32>| m.keys().next().copied().unwrap_or(0);
        let last = |m: &BTreeMap<u32, u32>| m.keys().next_back().copied().unwrap_or(0);
        [
            [first(&self.lo[0]), first(&self.lo[1]), first(&self.lo[2])],
            [last(&self.hi[0]), last(&self.hi[1]), last(&self.hi[2])],
        ]
    }
}

/// The segments of one channel at one version (see the module's documentation).
#[derive(Debug)]
pub struct ChannelIndex {
    /// The channel's view of the version described.
    snap: Arc<Snapshot>,
    /// The summary of each level-0 brick (x fastest), `None` where it holds only 0.
    bricks: Vec<Option<Arc<BrickSummary>>>,
    /// Summaries by content, shared by every brick with that content.
    summaries: HashMap<SummaryKey, Arc<BrickSummary>>,
    /// Summaries kept after the last pruning of [`ChannelIndex::summaries`].
    kept_at_prune: usize,
    /// The sums per id.
    segments: BTreeMap<u64, Aggregate>,
}

impl ChannelIndex {
    /// The index of `snap` (a channel's view), from every level-0 brick.
    ///
    /// # Errors
    /// A brick does not read or decode.
    fn build(snap: Arc<Snapshot>) -> Result<ChannelIndex, StoreError> {
        let n = level0_bricks(&snap);
        let mut index = ChannelIndex {
            snap,
            bricks: vec![None; n],
            summaries: HashMap::new(),
            kept_at_prune: 0,
            segments: BTreeMap::new(),
        };
        for node in 0..n {
            let summary = index.summary_at(node)?;
            index.set(node, summary);
        }
        index.prune();
        Ok(index)
    }

    /// The version described.
    pub fn version(&self) -> u64 {
        self.snap.version
    }

    /// Distinct brick contents summarised, and segments.
    fn sizes(&self) -> (usize, usize) {
        (self.summaries.len(), self.segments.len())
    }

    /// The origin (level-0 voxels) and the extent inside the volume of level-0 brick `node`.
    fn place(&self, node: usize) -> ([u32; 3], [u32; 3]) {
        let layout = self.snap.layout();
        let (g, b, dims) = (layout.grid(0), layout.brick(), layout.dims());
        let n = node as u64;
        let k = [
            n % u64::from(g[0]),
            n / u64::from(g[0]) % u64::from(g[1]),
            n / (u64::from(g[0]) * u64::from(g[1])),
        ]
        .map(|c| c as u32);
        let origin = k.map(|c| c * b);
        let extent = std::array::from_fn(|a| b.min(dims[a] - origin[a]));
        (origin, extent)
    }

    /// The summary of level-0 brick `node` of the version described: from the cache when a
    /// brick with the same content and extent was summarised, else decoded and counted.
    fn summary_at(&mut self, node: usize) -> Result<Option<Arc<BrickSummary>>, StoreError> {
        let (origin, extent) = self.place(node);
        let b = self.snap.layout().brick();
        let key = BrickKey {
            level: 0,
            x: origin[0] / b,
            y: origin[1] / b,
            z: origin[2] / b,
        };
        let stored = self.snap.stored(key)?;
        let content = match stored {
            StoredBrick::Constant(0) => return Ok(None),
            StoredBrick::Constant(v) => Content::Constant(v),
            StoredBrick::Record { header, .. } => Content::Hash(header.hash),
        };
        if let Some(s) = self.summaries.get(&(content, extent)) {
            return Ok((!s.parts.is_empty()).then(|| s.clone()));
        }
        let summary = match content {
            Content::Constant(v) => BrickSummary {
                parts: vec![Part {
                    id: v,
                    voxels: extent.iter().product(),
                    lo: [0; 3],
                    hi: extent,
                }],
            },
            Content::Hash(_) => {
                let bytes = self.snap.read(key)?;
                summarize(&bytes, self.snap.layout().voxel_type(), b, extent)
            }
        };
        let summary = Arc::new(summary);
        self.summaries.insert((content, extent), summary.clone());
        Ok((!summary.parts.is_empty()).then_some(summary))
    }

    /// Makes `summary` the summary of brick `node`: the old one's parts taken out of the sums,
    /// the new one's added.
    fn set(&mut self, node: usize, summary: Option<Arc<BrickSummary>>) {
        let same = match (&self.bricks[node], &summary) {
            (Some(a), Some(b)) => Arc::ptr_eq(a, b),
            (None, None) => true,
            _ => false,
        };
        if same {
            return;
        }
        let (origin, _) = self.place(node);
        if let Some(old) = self.bricks[node].take() {
            for part in &old.parts {
                if let Some(agg) = self.segments.get_mut(&part.id) {
                    agg.remove(origin, part);
                    if agg.voxels == 0 {
                        self.segments.remove(&part.id);
                    }
                }
            }
        }
        if let Some(new) = &summary {
            for part in &new.parts {
                self.segments.entry(part.id).or_default().add(origin, part);
            }
        }
        self.bricks[node] = summary;
    }

    /// Forgets the summaries no brick uses any more, once they are twice as many as after the
    /// last pruning (so pruning costs O(1) per summary made).
    fn prune(&mut self) {
        if self.summaries.len() > (2 * self.kept_at_prune).max(1024) {
            self.summaries.retain(|_, s| Arc::strong_count(s) > 1);
            self.kept_at_prune = self.summaries.len();
        }
    }

    /// Brings the index to `head` (the same channel's view of a newer version of `vod`): the
    /// level-0 bricks the commits since changed, summarised again. `Ok(false)` when the
    /// commits do not lead from the version described to `head` (the caller rebuilds).
    ///
    /// # Errors
    /// A commit record or a brick does not read (the index is then half-updated: drop it).
    fn catch_up(&mut self, vod: &Vod2, head: Arc<Snapshot>) -> Result<bool, StoreError> {
        let from = self.version();
        if head.version == from {
            return Ok(true);
        }
        if head.version < from {
            return Ok(false);
        }
        let per_stream = head.layout().node_count();
        let (stream, n0) = (head.stream() as u64, level0_bricks(&head) as u64);
        let mut nodes = BTreeSet::new();
        let mut at = head.commit_offset();
        loop {
            let (h, record) = vod.commit_at(at)?;
            // A first commit (a compacted file's) is not relative to the version before it.
            if h.version <= from || h.parent == 0 {
                return Ok(false);
            }
            nodes.extend(
                CommitHeader::changes(record)
                    .map(|(node, _)| node)
                    .filter(|node| node / per_stream == stream && node % per_stream < n0)
                    .map(|node| (node % per_stream) as usize),
            );
            if h.version == from + 1 {
                break;
            }
            at = h.parent;
        }
        self.snap = head;
        for node in nodes {
            let summary = self.summary_at(node)?;
            self.set(node, summary);
        }
        self.prune();
        Ok(true)
    }

    /// The segments with ids after `after`, at most `limit` of them.
    fn list(&self, channel: &str, after: Option<u64>, limit: usize) -> SegmentList {
        let start = match after {
            None => Bound::Unbounded,
            Some(a) => Bound::Excluded(a),
        };
        let as_text = self.snap.layout().voxel_type() == VoxelType::U64;
        let id = |value| SegmentId { value, as_text };
        let mut segments: Vec<SegmentInfo> = self
            .segments
            .range((start, Bound::Unbounded))
            .take(limit + 1)
            .map(|(&value, agg)| SegmentInfo {
                id: id(value),
                voxels: agg.voxels,
                bounds: agg.bounds(),
            })
            .collect();
        let next = (segments.len() > limit).then(|| {
            segments.truncate(limit);
            segments.last().map_or(id(0), |s| s.id)
        });
        SegmentList {
            version: self.version(),
            channel: channel.to_string(),
            total: self.segments.len(),
            segments,
            next,
        }
    }

    /// Segment `id`'s box, if there is one.
    fn bounds_of(&self, id: u64) -> Option<[[u32; 3]; 2]> {
        self.segments.get(&id).map(Aggregate::bounds)
    }
}

/// Level-0 bricks of a snapshot's layout.
fn level0_bricks(snap: &Snapshot) -> usize {
    snap.layout().grid(0).iter().map(|&g| g as usize).product()
}

/// The non-zero ids of a decoded brick (`b`^3 voxels of `voxel_type`, x fastest) within
/// `extent`, with their counts and boxes, ascending by id.
fn summarize(bytes: &[u8], voxel_type: VoxelType, b: u32, extent: [u32; 3]) -> BrickSummary {
    let value = |i: usize| isovox_proto::voxel::value_at(bytes, voxel_type, i);
    let mut slot_of: HashMap<u64, usize> = HashMap::new();
    let mut parts: Vec<Part> = Vec::new();
    let b = b as usize;
    for z in 0..extent[2] {
        for y in 0..extent[1] {
            let row = (z as usize * b + y as usize) * b;
            let mut x = 0u32;
            // Runs of one value along the row: one update per run.
            while x < extent[0] {
                let v = value(row + x as usize);
                let start = x;
                while x < extent[0] && value(row + x as usize) == v {
                    x += 1;
                }
                if v == 0 {
                    continue;
                }
                let slot = *slot_of.entry(v).or_insert_with(|| {
                    parts.push(Part {
                        id: v,
                        voxels: 0,
                        lo: [u32::MAX; 3],
                        hi: [0; 3],
                    });
                    parts.len() - 1
                });
                let p = &mut parts[slot];
                p.voxels += x - start;
                p.lo = [p.lo[0].min(start), p.lo[1].min(y), p.lo[2].min(z)];
                p.hi = [p.hi[0].max(x), p.hi[1].max(y + 1), p.hi[2].max(z + 1)];
            }
        }
    }
    parts.sort_unstable_by_key(|p| p.id);
    BrickSummary { parts }
}

/// The indexes of one volume's channels, by stream, each built on first use.
#[derive(Debug, Default)]
pub struct SegmentIndexes {
    channels: Mutex<HashMap<usize, Arc<Mutex<Option<ChannelIndex>>>>>,
}

impl SegmentIndexes {
    fn slot(&self, stream: usize) -> Arc<Mutex<Option<ChannelIndex>>> {
        // One insert or lookup under the lock: never left half-changed.
        let mut channels = self.channels.lock().unwrap_or_else(|p| p.into_inner());
        channels.entry(stream).or_default().clone()
    }
}

/// The lock of a channel's index; a panic while it was held may have left the index
/// half-updated: it is dropped then (the next request rebuilds it).
fn lock(slot: &Mutex<Option<ChannelIndex>>) -> MutexGuard<'_, Option<ChannelIndex>> {
    slot.lock().unwrap_or_else(|p| {
        let mut guard = p.into_inner();
        *guard = None;
        guard
    })
}

impl LiveVolume {
    /// Runs `f` on the segments of `channel` at `version` (the head when `None`): the head's
    /// from the kept index (built or brought up to date first), an older version's from a
    /// scan when the volume has at most [`MAX_SCAN_VOXELS`] voxels. Blocking.
    ///
    /// # Errors
    /// [`VolumeError::OutOfRange`] for an unknown channel, [`VolumeError::NoSuchVersion`],
    /// [`VolumeError::Unsupported`] for an older version of a large volume, a store error.
    fn with_segments<R>(
        &self,
        version: Option<u64>,
        channel: &str,
        f: impl FnOnce(&ChannelIndex) -> Result<R, VolumeError>,
    ) -> Result<R, VolumeError> {
        let head = stream_of(self.head(), Some(channel))?;
        if let Some(v) = version.filter(|&v| v != head.version) {
            return self.scan_version(v, channel, f);
        }
        let slot = self.segments.slot(head.stream());
        let mut guard = lock(&slot);
        let vod = self.current();
        let head = stream_of(vod.head(), Some(channel))?;
        let current = match guard.take() {
            Some(mut index) => {
                let began = Instant::now();
                let from = index.version();
                if index.catch_up(&vod, head.clone())? {
                    if from != index.version() {
                        tracing::debug!(volume = %self.name(), channel, from, to = index.version(), us = began.elapsed().as_micros() as u64, "segment index brought up to date");
                    }
                    index
                } else {
                    self.build_index(head, channel)?
                }
            }
            None => self.build_index(head, channel)?,
        };
        let index = guard.insert(current);
        match version {
            // The head moved on between the two looks: that version by a scan.
            Some(v) if v != index.version() => {
                drop(guard);
                self.scan_version(v, channel, f)
            }
            _ => f(index),
        }
    }

    /// A new index of `head` (a channel's view), its cost logged.
    fn build_index(&self, head: Arc<Snapshot>, channel: &str) -> Result<ChannelIndex, StoreError> {
        let began = Instant::now();
        let bricks = level0_bricks(&head);
        let index = ChannelIndex::build(head)?;
        let (distinct, segments) = index.sizes();
        tracing::info!(
            volume = %self.name(),
            channel,
            version = index.version(),
            bricks,
            distinct,
            segments,
            ms = began.elapsed().as_millis() as u64,
            "segment index built"
        );
        Ok(index)
    }

    /// [`LiveVolume::with_segments`] of an older version: a scan, for small volumes only.
    fn scan_version<R>(
        &self,
        version: u64,
        channel: &str,
        f: impl FnOnce(&ChannelIndex) -> Result<R, VolumeError>,
    ) -> Result<R, VolumeError> {
        let snap = self.snapshot_of(Some(version), Some(channel))?;
        let voxels: u64 = snap.layout().dims().iter().map(|&d| u64::from(d)).product();
        if voxels > MAX_SCAN_VOXELS {
            return Err(VolumeError::Unsupported(format!(
                "segments are kept for the newest version ({}) only; an older version is listed by a scan, for volumes of at most {MAX_SCAN_VOXELS} voxels (this one has {voxels}): ask without ?version",
                self.head().version
            )));
        }
        f(&ChannelIndex::build(snap)?)
    }

    /// The segments of `channel` with ids after `after` (from the first when `None`), at most
    /// `limit` of them ([`DEFAULT_SEGMENTS`] when `None`), at `version` (the head when `None`).
    /// Blocking: may build the channel's index.
    ///
    /// # Errors
    /// A limit outside `1..=MAX_SEGMENTS` ([`VolumeError::BadRequest`]); see
    /// [`LiveVolume::with_segments`].
    pub fn segments(
        &self,
        version: Option<u64>,
        channel: &str,
        after: Option<u64>,
        limit: Option<u64>,
    ) -> Result<SegmentList, VolumeError> {
        let limit = limit.unwrap_or(DEFAULT_SEGMENTS as u64);
        if !(1..=MAX_SEGMENTS as u64).contains(&limit) {
            return Err(VolumeError::BadRequest(format!(
                "limit={limit}: a page lists 1..={MAX_SEGMENTS} segments"
            )));
        }
        self.with_segments(version, channel, |index| {
            Ok(index.list(channel, after, limit as usize))
        })
    }

    /// Every segment of `channel` at `version` (the head when `None`), on one page: a
    /// channel's ids are u16, so at most 65,535 of them. Blocking, as [`LiveVolume::segments`].
    ///
    /// # Errors
    /// See [`LiveVolume::with_segments`].
    pub fn all_segments(
        &self,
        version: Option<u64>,
        channel: &str,
    ) -> Result<SegmentList, VolumeError> {
        self.with_segments(version, channel, |index| {
            Ok(index.list(channel, None, usize::from(u16::MAX)))
        })
    }

    /// The closed mesh of segment `id` of `channel` at `level` (0 when `None`) and `version`
    /// (the head when `None`): marching cubes on the indicator of `id` (1 where the channel's
    /// level-`level` voxel is `id`, 0 elsewhere; iso 0.5) over the segment's box at that level
    /// padded by a voxel of zeros, in world coordinates (as mesh tiles: level-0 voxel units
    /// times the voxel scale). Blocking.
    ///
    /// # Errors
    /// [`VolumeError::OutOfRange`] for an id the channel does not hold at that version (or
    /// cannot hold: beyond its type, or 0) and a level beyond its pyramid;
    /// [`VolumeError::TooLarge`] when the box holds more than [`MAX_MESH_VOXELS`] voxels at
    /// that level (the error names the finest level that fits); see
    /// [`LiveVolume::with_segments`].
    pub fn segment_mesh(
        &self,
        version: Option<u64>,
        channel: &str,
        id: u64,
        level: Option<u8>,
    ) -> Result<SegmentMesh, VolumeError> {
        let head = stream_of(self.head(), Some(channel))?;
        let layout = head.layout();
        let max = layout.voxel_type().max_value();
        if id == 0 || id > max {
            return Err(VolumeError::OutOfRange(format!(
                "segment {id}: channel {channel:?} holds segments 1..={max} (0 is unlabelled)"
            )));
        }
        let level = level.unwrap_or(0);
        if level >= layout.levels() {
            return Err(VolumeError::OutOfRange(format!(
                "level {level}: channel {channel:?} has levels 0..={}",
                layout.levels() - 1
            )));
        }
        let (snap, bounds) = self.with_segments(version, channel, |index| {
            Ok((index.snap.clone(), index.bounds_of(id)))
        })?;
        let Some([lo0, hi0]) = bounds else {
            return Err(VolumeError::OutOfRange(format!(
                "segment {id}: no voxel of channel {channel:?} holds it at version {}",
                snap.version
            )));
        };
        let (lo, hi, voxels) = level_box([lo0, hi0], level);
        if voxels > MAX_MESH_VOXELS {
            let fits = finest_fitting([lo0, hi0], level, layout.levels(), MAX_MESH_VOXELS);
            return Err(VolumeError::TooLarge(format!(
                "segment {id}'s box {lo0:?}..{hi0:?} holds {voxels} voxels at level {level}; a mesh marches at most {MAX_MESH_VOXELS}: ask for level {}",
                fits.map_or("none".into(), |l| l.to_string())
            )));
        }
        let mesh = mesh_indicator(&snap, level, lo, hi, id)?;
        Ok(SegmentMesh {
            version: snap.version,
            level,
            mesh,
        })
    }
}

/// A level-0 box `[lo, hi)` at `level`: `[floor(lo / 2^level), ceil(hi / 2^level))` (a voxel of
/// a mode pyramid holds a value of one of its level-0 voxels, so a segment's voxels at `level`
/// lie in it), and its voxel count.
fn level_box([lo, hi]: [[u32; 3]; 2], level: u8) -> ([u32; 3], [u32; 3], u64) {
    let step = 1u64 << level.min(63);
    let lo = lo.map(|c| (u64::from(c) / step) as u32);
    let hi: [u32; 3] = hi.map(|c| u64::from(c).div_ceil(step) as u32);
    let n = (0..3).map(|a| u64::from(hi[a] - lo[a])).product();
    (lo, hi, n)
}

/// The finest level from `from` up (below `levels`) whose box holds at most `cap` voxels.
fn finest_fitting(bounds: [[u32; 3]; 2], from: u8, levels: u8, cap: u64) -> Option<u8> {
    (from..levels).find(|&l| level_box(bounds, l).2 <= cap)
}

/// The indicator of `id` over the voxels `[lo, hi)` of `level` of `snap` (1 where the voxel is
/// `id`), with two samples of zeros more on each side (the padding that closes the mesh, and
/// the halo `march` reads for its normals), x fastest; read brick by brick, so the job holds
/// the indicator and one decoded brick.
fn indicator(
    snap: &Snapshot,
    level: u8,
    lo: [u32; 3],
    hi: [u32; 3],
    id: u64,
) -> Result<(Vec<u8>, [usize; 3]), StoreError> {
    let n = [0, 1, 2].map(|a| (hi[a] - lo[a]) as usize);
    let size = n.map(|c| c + 4);
    let mut values = vec![0u8; size.iter().product()];
    let layout = snap.layout();
    let b = layout.brick();
    let t = layout.voxel_type();
    for bz in lo[2] / b..=(hi[2] - 1) / b {
        for by in lo[1] / b..=(hi[1] - 1) / b {
            for bx in lo[0] / b..=(hi[0] - 1) / b {
                let key = BrickKey {
                    level,
                    x: bx,
                    y: by,
                    z: bz,
                };
                let origin = [bx, by, bz].map(|c| c * b);
                // The part of the box in this brick, in voxels of the level.
                let from: [u32; 3] = std::array::from_fn(|a| lo[a].max(origin[a]));
                let to: [u32; 3] = std::array::from_fn(|a| hi[a].min(origin[a] + b));
                let voxels = snap.voxels(key)?;
                for z in from[2]..to[2] {
                    for y in from[1]..to[1] {
                        let row = ((z - lo[2]) as usize + 2) * size[1] + (y - lo[1]) as usize + 2;
                        let out = &mut values[row * size[0] + 2..][..n[0]];
                        let local = ((z - origin[2]) * b + (y - origin[1])) * b;
                        for x in from[0]..to[0] {
                            let inside = match &voxels {
                                crate::store::BrickVoxels::Constant(v) => *v == id,
                                crate::store::BrickVoxels::Data(d) => {
                                    let i = (local + x - origin[0]) as usize;
                                    isovox_proto::voxel::value_at(d, t, i) == id
                                }
                            };
                            out[(x - lo[0]) as usize] = u8::from(inside);
                        }
                    }
                }
            }
        }
    }
    Ok((values, size))
}

/// The grid edges between samples of `values` (x fastest, `size`) whose two ends differ: the
/// vertices marching cubes makes on it, one per crossed edge.
fn crossed_edges(values: &[u8], size: [usize; 3]) -> u64 {
    let (sx, sxy) = (size[0], size[0] * size[1]);
    let mut crossed = 0u64;
    for (i, &v) in values.iter().enumerate() {
        let x = i % sx;
        let y = i / sx % size[1];
        let z = i / sxy;
        if x + 1 < size[0] && values[i + 1] != v {
            crossed += 1;
        }
        if y + 1 < size[1] && values[i + sx] != v {
            crossed += 1;
        }
        if z + 1 < size[2] && values[i + sxy] != v {
            crossed += 1;
        }
    }
    crossed
}

/// Marching cubes on the indicator of `id` over the voxels `[lo, hi)` of `level` of `snap`,
/// padded by a voxel of zeros on every side (so the mesh is closed), in world coordinates.
///
/// # Errors
/// A brick does not read; [`VolumeError::TooLarge`] when the surface would have more than
/// [`MAX_MESH_VERTICES`] vertices.
fn mesh_indicator(
    snap: &Snapshot,
    level: u8,
    lo: [u32; 3],
    hi: [u32; 3],
    id: u64,
) -> Result<Mesh, VolumeError> {
    let (values, size) = indicator(snap, level, lo, hi, id)?;
    let vertices = crossed_edges(&values, size);
    if vertices > MAX_MESH_VERTICES {
        return Err(VolumeError::TooLarge(format!(
            "segment {id}'s surface at level {level} has {vertices} vertices; a mesh has at most {MAX_MESH_VERTICES}: ask for a coarser level (each level has about a quarter of the one below's)"
        )));
    }
    let origin = lo.map(|c| i64::from(c) - 2);
    let field = Field {
        origin,
        size,
        values: &values,
    };
    let mut mesh = Mesh::default();
    march(
        &field,
        lo.map(|c| i64::from(c) - 1),
        [0; 3],
        hi.map(i64::from),
        0.5,
        &mut mesh,
        &mut Scratch::default(),
    );
    let step = (1u64 << level) as f32;
    let scale = snap.header().voxel_scale;
    for p in &mut mesh.positions {
        for a in 0..3 {
            p[a] *= step * scale[a];
        }
    }
    if scale[0] != scale[1] || scale[1] != scale[2] {
        for n in &mut mesh.normals {
            let m = [n[0] / scale[0], n[1] / scale[1], n[2] / scale[2]];
            let len = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
            if len > 0.0 {
                *n = m.map(|c| c / len);
            }
        }
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn a_brick_summary_counts_and_boxes_each_id_by_hand() {
        // A 4^3 u16 brick: id 3 at (1,0,0) and (2,0,0); id 7 at (0,1,2) and (3,3,3); id 9 at
        // (3,0,0), past an extent of 3 on x: not counted.
        let b = 4usize;
        let mut v = vec![0u16; b * b * b];
        let at = |x: usize, y: usize, z: usize| (z * b + y) * b + x;
        v[at(1, 0, 0)] = 3;
        v[at(2, 0, 0)] = 3;
        v[at(0, 1, 2)] = 7;
        v[at(2, 3, 3)] = 7;
        v[at(3, 0, 0)] = 9;
        let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        let s = summarize(&bytes, VoxelType::U16, 4, [3, 4, 4]);
        assert_eq!(
            s.parts,
            vec![
                Part {
                    id: 3,
                    voxels: 2,
                    lo: [1, 0, 0],
                    hi: [3, 1, 1]
                },
                Part {
                    id: 7,
                    voxels: 2,
                    lo: [0, 1, 2],
                    hi: [3, 4, 4]
                },
            ]
        );
    }

    #[test]
    fn a_box_too_large_for_a_mesh_names_the_finest_level_that_fits() {
        // 600 x 600 x 100 = 36,000,000 voxels at level 0, over 2^24 = 16,777,216; at level 1
        // [0, 300) x [0, 300) x [0, 50) = 4,500,000.
        let bounds = [[0, 0, 0], [600, 600, 100]];
        assert_eq!(level_box(bounds, 0).2, 36_000_000);
        assert_eq!(finest_fitting(bounds, 0, 8, MAX_MESH_VOXELS), Some(1));
        // Rounded outwards: [3, 9) at level 0 is [1, 5) at level 1 and [0, 3) at level 2.
        let odd = [[3, 3, 3], [9, 9, 9]];
        assert_eq!(level_box(odd, 1), ([1; 3], [5; 3], 64));
        assert_eq!(level_box(odd, 2), ([0; 3], [3; 3], 27));
        // No level fits a cap of nothing.
        assert_eq!(finest_fitting(bounds, 0, 8, 0), None);
    }

    /// Every non-zero value of `view`'s level 0, counted voxel by voxel.
    fn brute_force(view: &Snapshot) -> Vec<SegmentInfo> {
        let layout = view.layout();
        let (dims, b) = (layout.dims(), layout.brick());
        let mut found: BTreeMap<u16, SegmentInfo> = BTreeMap::new();
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let key = BrickKey {
                        level: 0,
                        x: x / b,
                        y: y / b,
                        z: z / b,
                    };
                    let bytes = view.read(key).unwrap();
                    let i = (((z % b) * b + y % b) * b + x % b) as usize;
                    let v = u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]]);
                    if v == 0 {
                        continue;
                    }
                    let s = found.entry(v).or_insert(SegmentInfo {
                        id: SegmentId {
                            value: v.into(),
                            as_text: false,
                        },
                        voxels: 0,
                        bounds: [[u32::MAX; 3], [0; 3]],
                    });
                    s.voxels += 1;
                    for (a, c) in [x, y, z].into_iter().enumerate() {
                        s.bounds[0][a] = s.bounds[0][a].min(c);
                        s.bounds[1][a] = s.bounds[1][a].max(c + 1);
                    }
                }
            }
        }
        found.into_values().collect()
    }

    #[test]
    fn the_index_kept_across_random_paints_equals_a_count_of_every_voxel() {
        use crate::store::{build_streams, BuildOptions, DenseGrid, Vod2};
        use isovox_proto::channel::ChannelInfo;
        use isovox_proto::vod2::FileHeader;
        use isovox_proto::VolumeLayout;

        // 20 x 18 x 17 (edge bricks cut by the volume's end), brick 8, a sparse u16 label.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.vod");
        let dims = [20u32, 18, 17];
        let n = dims.iter().product::<u32>() as usize;
        let density = vec![0u8; n];
        let label = vec![0u8; 2 * n];
        let sources = [
            DenseGrid::new(dims, VoxelType::U8, 8, &density),
            DenseGrid::new(dims, VoxelType::U16, 8, &label),
        ];
        let sources: Vec<&dyn crate::store::BrickSource> = sources.iter().map(|s| s as _).collect();
        let layout = VolumeLayout::new(dims, 8, VoxelType::U8).unwrap();
        let channels = vec![ChannelInfo {
            sparse: true,
            ..ChannelInfo::new("label", VoxelType::U16)
        }];
        let header = FileHeader::with_channels(layout, [1.0; 3], channels).unwrap();
        build_streams(&path, header, &sources, &BuildOptions::default()).unwrap();
        let volume = LiveVolume::new("v", Vod2::open(&path).unwrap()).unwrap();
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = |below: u64| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed % below
        };
        for step in 0..24 {
            // Ids from a few (0 erases), so that paints cover others whole and ids come and
            // go; some paints reach past the volume's end.
            let origin = [0, 1, 2].map(|a| next(u64::from(dims[a])) as i64 - 2);
            let size = [0, 1, 2].map(|_| 3 + next(9) as u32);
            let id = [0, 3, 7, 300, 65535][next(5) as usize];
            let request: isovox_proto::icvg::EditRequest =
                serde_json::from_value(serde_json::json!(
                    {"op": "paint", "channel": "label",
                     "term": {"cuboid": {"origin": origin, "size": size, "label": id}}}
                ))
                .unwrap();
            super::super::write::edit_file(&path, &request).unwrap();
            // Several commits between two looks, sometimes.
            if next(3) == 0 {
                continue;
            }
            volume.reload().unwrap();
            let list = volume.segments(None, "label", None, None).unwrap();
            let head = volume.head().channel("label").unwrap();
            assert_eq!(list.version, head.version);
            assert_eq!(list.segments, brute_force(&head), "step {step}");
        }
    }

    #[test]
    fn crossed_edges_are_the_faces_of_the_voxels_inside() {
        // A 2 x 1 x 1 bar of ones in a 6 x 5 x 5 field of zeros: its faces, 2 (2 + 2 + 1) = 10.
        let size = [6, 5, 5];
        let mut values = vec![0u8; 150];
        values[(2 * 5 + 2) * 6 + 2] = 1;
        values[(2 * 5 + 2) * 6 + 3] = 1;
        assert_eq!(crossed_edges(&values, size), 10);
        assert_eq!(crossed_edges(&[0; 150], size), 0);
    }

    #[test]
    fn an_aggregate_takes_a_brick_s_box_back_without_the_others() {
        let mut agg = Aggregate::default();
        let part = |lo: [u32; 3], hi: [u32; 3]| Part {
            id: 1,
            voxels: 1,
            lo,
            hi,
        };
        agg.add([0, 0, 0], &part([2, 2, 2], [3, 3, 3]));
        agg.add([8, 0, 0], &part([0, 1, 1], [5, 4, 2]));
        agg.add([8, 0, 0], &part([0, 1, 1], [5, 4, 2]));
        assert_eq!(agg.bounds(), [[2, 1, 1], [13, 4, 3]]);
        agg.remove([8, 0, 0], &part([0, 1, 1], [5, 4, 2]));
        // One of the two equal shares left: the box stays.
        assert_eq!(agg.bounds(), [[2, 1, 1], [13, 4, 3]]);
        agg.remove([8, 0, 0], &part([0, 1, 1], [5, 4, 2]));
        assert_eq!(agg.bounds(), [[2, 2, 2], [3, 3, 3]]);
        assert_eq!(agg.voxels, 1);
    }
}
