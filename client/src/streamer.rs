//! The camera-distance streamer: keeps the tiles a viewer at a camera position needs, nearest
//! first, and keeps them current while other users edit the volume.
//!
//! # What it selects
//!
//! The thesis's spherical detail bias, exactly as the server's offline selection
//! (`isovox_server::mesh::level::adaptive_tiles`) computes it: with radii `r0 < r1 < ... <
//! r(n-1)` (world units, `voxel_scale` applied), a tile of level k is used where its nearest
//! point lies within `r(k)` of the camera, and level n (or the coarsest, if the volume has fewer
//! levels) beyond the last radius. Walking down from the root, a tile of level k+1 is refined into
//! its children when its box (the brick's cell, `brick * 2^(k+1)` level-0 voxels per side, times
//! the voxel scale) is within `r(k)`, and always while k+1 > n. [`select_tiles`] is that walk, on
//! the metadata alone, with the same `f32` arithmetic, so it selects the same set for the same
//! radii. Empty radii select level 0 everywhere. [`StreamerConfig::radii_for_screen_error`]
//! derives radii from a screen-space error target; an empty [`StreamerConfig::radii`] means
//! "derive them" with a 60 degree vertical field of view, a 1080-pixel viewport and one pixel of
//! error (see [`StreamerConfig`]).
//!
//! # Tiles and their content keys
//!
//! A tile is a [`BrickKey`]. With [`TileKind::Bricks`] its content is the brick's voxels and its
//! content key is the brick's content hash (xxh3-64, as the server names it). With
//! [`TileKind::Meshes`] its content is the server's marching-cubes tile, which reads the 3x3x3
//! bricks around it at the same level (`server/src/mesh/tile.rs`: its cells reach into the +1
//! neighbours, its normals' central differences one sample further on every side); its content
//! key hashes the tile's position, the iso value, the brick shape and the content hashes of those
//! 27 inputs (absent ones marked). A tile is stale exactly when one of its inputs changed.
//!
//! Content hashes come from the levels' brick grids (`GET .../levels/{l}?format=grid&region=`),
//! fetched in regions of 8x8x8 bricks as tiles need them and kept per brick. Brick content is then
//! fetched by hash (`GET .../blobs/{hash}`), once per hash: a brick shared by many positions (air,
//! solid rock) costs one request. Mesh tiles are fetched by position (`GET .../meshes/...`) when
//! their content key is not cached. The cache holds content by key, LRU, bounded by
//! [`StreamerConfig::cache_bytes`] (brick: its voxel bytes; mesh: positions, normals, indices).
//!
//! # Versions
//!
//! The streamer works at one version at a time: the version of the last commit it applied from
//! the change feed (at start, the version the metadata reported). Grid regions and mesh tiles are
//! requested at that version (`?version=N`), so every content key it holds describes that
//! version, whatever the server's head is meanwhile. Blobs are immutable. Without
//! `follow_edits` the streamer stays at the start version (a consistent snapshot, readable until
//! a compaction drops that version).
//!
//! # The task
//!
//! [`Streamer::start`] fetches the metadata, subscribes to the change feed from that version (so
//! no commit falls between the two), and spawns one task that owns all state: the desired set,
//! per tile whether its current content was delivered, the known brick hashes, the cache, and the
//! requests in flight (a [`JoinSet`] with one abort handle per request). The camera reaches it
//! through a `watch` (only the latest position matters); events leave through a bounded channel
//! of 4,096 (`send().await`: a slow consumer slows the streamer down; a dropped receiver is
//! ignored and the streamer keeps working). A second task follows the change feed and forwards
//! commits in order.
//!
//! Each time the camera, the feed or a grid region changes what is known, the task plans again:
//! for every desired tile not yet current it finds what is missing (a grid region, a blob, a
//! mesh), cached content makes tiles ready at once, requests no desired tile needs any more are
//! aborted (their results are never delivered), and the rest are queued by the distance from the
//! camera to the nearest tile box that needs them. At most [`StreamerConfig::max_in_flight`]
//! requests run at once (the feed's connection is not counted). A failed request is reported as
//! [`StreamEvent::Error`] and retried after a backoff (250 ms doubling to 10 s) while a tile still
//! needs it.
//!
//! # Events
//!
//! - [`StreamEvent::Ready`] when a tile of the desired set gets its content: the first time, and
//!   again after it went stale.
//! - [`StreamEvent::Dropped`] when a tile that was delivered (`Ready`) leaves the desired set.
//!   Tiles that leave before their content arrived are cancelled silently.
//! - [`StreamEvent::Stale`] when a commit changes an input of a delivered tile; it is refetched at
//!   once and followed by `Ready` with the new content. The old content stays usable meanwhile, so
//!   the tile stays in [`Streamer::resident`].
//! - [`StreamEvent::Version`] after each applied commit (and once at start).
//! - [`StreamEvent::Error`] for failed requests and feed disconnects (the streamer retries).
//!
//! # Edits and reconnects
//!
//! For each commit, in version order: every brick in `changed[level]` forgets its hash; the
//! desired tiles whose inputs include one of them (bricks: the brick itself; meshes: the tiles
//! at offsets -1..=1 around it) lose their current content, and the delivered ones get `Stale`.
//! Requests in flight whose answers predate the commit and touch a changed brick are aborted. One
//! grid region per level, the bounding box of the changed bricks that some desired tile reads,
//! brings the new hashes; content then comes from the cache or one request per new content key.
//! Tiles whose inputs did not change are not refetched.
//!
//! When the feed ends or fails, the follower reconnects with `since` = the last version it
//! forwarded (backoff 100 ms doubling to 2 s); the server replays the versions in between from
//! the file, which the streamer applies like live ones. A `resync` event (the subscriber fell
//! behind) reconnects the same way. When the server answers 410 Gone (the history after that
//! version was compacted away) or 400 (the volume is now behind the streamer), the streamer
//! reloads: new metadata, every hash forgotten, every delivered tile stale and refetched (content
//! already cached by key is reused).

use crate::client::{Client, ClientError, Feed, FeedEvent};
use bytes::Bytes;
use isovox_proto::api::{ChangeEvent, LevelGrid, VolumeInfo};
use isovox_proto::mesh::Mesh;
use isovox_proto::{BrickKey, VolumeLayout};
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::hash::{DefaultHasher, Hash, Hasher};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::{AbortHandle, JoinError, JoinSet};
use tokio::time::Instant;

/// Capacity of the event channel.
const EVENT_CAPACITY: usize = 4096;
/// Bricks per axis of the grid regions fetched to learn content hashes.
const CHUNK: u32 = 8;
/// Backoff of a failed request: first delay, doubled per failure up to the last.
const RETRY_MIN: Duration = Duration::from_millis(250);
const RETRY_MAX: Duration = Duration::from_secs(10);
/// Backoff of the change feed's reconnects.
const FEED_RETRY_MIN: Duration = Duration::from_millis(100);
const FEED_RETRY_MAX: Duration = Duration::from_secs(2);

/// What the tiles are.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TileKind {
    /// Bricks' voxels (raw, x fastest, u16 little endian).
    Bricks,
    /// Marching-cubes tiles at `iso` (the server's default, S - 0.5, when `None`).
    Meshes { iso: Option<f32> },
}

/// How a [`Streamer`] runs.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamerConfig {
    pub kind: TileKind,
    /// World units (voxel_scale applied); r_0 < r_1 < ...; level k within r_k, coarser beyond.
    /// Empty: derived at start with [`StreamerConfig::radii_for_screen_error`] for a 60 degree
    /// vertical field of view, a 1080-pixel viewport and one pixel of error.
    pub radii: Vec<f32>,
    /// Requests running at once (at least 1). Default 16.
    pub max_in_flight: usize,
    /// Bytes of tile content kept by content key. Default 256 MiB.
    pub cache_bytes: usize,
    /// Follow the change feed. Default true. Without it the streamer stays at the start version.
    pub follow_edits: bool,
}

impl Default for StreamerConfig {
    fn default() -> Self {
        StreamerConfig {
            kind: TileKind::Bricks,
            radii: Vec::new(),
            max_in_flight: 16,
            cache_bytes: 256 << 20,
            follow_edits: true,
        }
    }
}

impl StreamerConfig {
    /// Radii from a screen-space error target: level k's tiles have a geometric error of about
    /// 2^k voxels; choose r_k so that error projects to at most max_error_px pixels.
    ///
    /// An error of `e` world units at distance `d` covers `e * H / (2 d tan(fov/2))` pixels of a
    /// viewport `H` pixels high. Level k+1 (error `2^(k+1)` voxels of the largest voxel-scale
    /// component) is therefore good enough beyond `r_k = 2^(k+1) s H / (2 tan(fov/2) max_error_px)`,
    /// and level k is used within it. One radius per level but the coarsest. Arguments that are
    /// not positive and finite give no radii (level 0 everywhere).
    pub fn radii_for_screen_error(
        info: &VolumeInfo,
        fov_y_radians: f32,
        viewport_height_px: f32,
        max_error_px: f32,
    ) -> Vec<f32> {
        let s = info.voxel_scale.iter().fold(0f32, |a, &b| a.max(b.abs()));
        let per_world = viewport_height_px / (2.0 * (fov_y_radians / 2.0).tan() * max_error_px);
        if !(per_world.is_finite() && per_world > 0.0 && s.is_finite() && s > 0.0) {
            return Vec::new();
        }
        (0..info.levels.len().saturating_sub(1))
            .map(|k| (2f32).powi(k as i32 + 1) * s * per_world)
            .collect()
    }
}

/// The desired set for a camera (sorted), from metadata only.
///
/// Level k where the tile's nearest point lies within `radii[k]` of `camera`, coarser beyond
/// (see the module documentation): [`isovox_proto::lod::adaptive_tiles`], as the server's
/// adaptive meshes select them.
pub fn select_tiles(info: &VolumeInfo, camera: [f32; 3], radii: &[f32]) -> Vec<BrickKey> {
    match VolumeLayout::new(info.dims, info.brick, info.voxel_type) {
        Ok(layout) => isovox_proto::lod::adaptive_tiles(&layout, info.voxel_scale, camera, radii),
        // Metadata no server sends (it describes a valid layout); nothing to select.
        Err(_) => Vec::new(),
    }
}

/// A tile's content.
#[derive(Debug, Clone)]
pub enum TileData {
    /// The brick's voxels (raw, x fastest, u16 little endian).
    Brick(Bytes),
    /// The tile's mesh in world coordinates, as the server encodes it (normals quantized).
    Mesh(Arc<Mesh>),
}

impl TileData {
    /// The tile's size in memory: voxel bytes, or the mesh's arrays.
    pub fn bytes(&self) -> u64 {
        match self {
            TileData::Brick(b) => b.len() as u64,
            TileData::Mesh(m) => {
                (m.positions.len() * 12 + m.normals.len() * 12 + m.indices.len() * 4) as u64
            }
        }
    }
}

/// What the streamer reports.
#[derive(Debug, Clone)]
pub enum StreamEvent {
    /// `key` has content `data` (content key `hash`: the brick's content hash, or for a mesh
    /// tile the hash of its position, iso and inputs), current as of `version`.
    Ready {
        key: BrickKey,
        hash: u64,
        data: TileData,
        version: u64,
    },
    /// `key` left the desired set; it had been delivered.
    Dropped { key: BrickKey },
    /// Commit `version` changed an input of `key`; new content follows as `Ready`.
    Stale { key: BrickKey, version: u64 },
    /// The streamer applied every commit up to `version`.
    Version { version: u64 },
    /// A request (for `key`, when it served one tile) or the change feed failed; retried.
    Error {
        key: Option<BrickKey>,
        error: String,
    },
}

/// Counters of a [`Streamer`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StreamerStats {
    /// HTTP requests started (grid regions, blobs, mesh tiles; not the change feed).
    pub requests: u64,
    /// Payload bytes received: brick voxels, and mesh tiles' compact encodings.
    pub bytes: u64,
    /// Tiles made ready without a request of their own (cached, or shared with another tile).
    pub cache_hits: u64,
    /// Content requests completed (blobs, mesh tiles).
    pub cache_misses: u64,
    pub in_flight: usize,
    /// Delivered tiles of the desired set (see [`Streamer::resident`]).
    pub resident: usize,
    /// Bytes held by the content cache.
    pub cache_bytes: usize,
    /// The version the streamer is at.
    pub version: u64,
    /// Delivered tiles refetched because a commit changed their inputs.
    pub stale_refetches: u64,
}

/// The camera as the task sees it: a sequence number per [`Streamer::set_camera`].
#[derive(Debug, Clone, Copy, Default)]
struct CameraMsg {
    seq: u64,
    position: Option<[f32; 3]>,
}

/// What the task last published.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct Status {
    /// The camera (sequence number) the desired set was computed for.
    camera_seq: u64,
    /// Every desired tile has current content.
    idle: bool,
    version: u64,
}

#[derive(Debug, Default)]
struct Shared {
    stats: StreamerStats,
    resident: BTreeSet<BrickKey>,
}

fn lock(shared: &Mutex<Shared>) -> std::sync::MutexGuard<'_, Shared> {
    // The task never panics while holding the lock; a poisoned lock still holds whole values.
    shared.lock().unwrap_or_else(|p| p.into_inner())
}

/// A running streamer (see the module documentation). Dropping it stops the task.
#[derive(Debug)]
pub struct Streamer {
    info: VolumeInfo,
    radii: Vec<f32>,
    camera: watch::Sender<CameraMsg>,
    status: watch::Receiver<Status>,
    shared: Arc<Mutex<Shared>>,
    shutdown: Option<oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl Streamer {
    /// Fetches the volume's metadata, subscribes to the feed (if follow_edits), starts the task.
    ///
    /// # Errors
    /// The metadata or the subscription fails; `Decode` when the metadata is inconsistent.
    pub async fn start(
        client: Client,
        volume: &str,
        config: StreamerConfig,
    ) -> Result<(Streamer, mpsc::Receiver<StreamEvent>), ClientError> {
        let info = client.volume(volume).await?;
        let layout = VolumeLayout::new(info.dims, info.brick, info.voxel_type)
            .map_err(|e| ClientError::Decode(format!("volume {volume}: {e}")))?;
        if layout.levels() as usize != info.levels.len() {
            return Err(ClientError::Decode(format!(
                "volume {volume}: {} levels listed, its dimensions give {}",
                info.levels.len(),
                layout.levels()
            )));
        }
        let radii = if config.radii.is_empty() {
            StreamerConfig::radii_for_screen_error(&info, 60f32.to_radians(), 1080.0, 1.0)
        } else {
            config.radii.clone()
        };
        let feed = if config.follow_edits {
            Some(client.events(volume, Some(info.version)).await?)
        } else {
            None
        };
        let (events_tx, events_rx) = mpsc::channel(EVENT_CAPACITY);
        let (camera_tx, camera_rx) = watch::channel(CameraMsg::default());
        let (status_tx, status_rx) = watch::channel(Status {
            camera_seq: 0,
            idle: true,
            version: info.version,
        });
        let (shutdown_tx, shutdown_rx) = oneshot::channel();
        let shared = Arc::new(Mutex::new(Shared::default()));
        let (feed_rx, follower) = match feed {
            Some(feed) => {
                let (tx, rx) = mpsc::channel(1024);
                let follower = tokio::spawn(follow(
                    client.clone(),
                    volume.to_string(),
                    feed,
                    info.version,
                    tx,
                ));
                (Some(rx), Some(follower))
            }
            None => (None, None),
        };
        let engine = Engine {
            client,
            name: volume.to_string(),
            kind: config.kind,
            layout,
            radii: radii.clone(),
            max_in_flight: config.max_in_flight.max(1),
            version: info.version,
            info: info.clone(),
            camera: None,
            camera_seq: 0,
            tiles: HashMap::new(),
            missing: 0,
            hashes: HashMap::new(),
            hash_source: HashMap::new(),
            mesh_keys: HashMap::new(),
            waiting: HashMap::new(),
            cache: Lru::new(config.cache_bytes),
            jobs: JoinSet::new(),
            running: HashMap::new(),
            next_id: 0,
            queue: Vec::new(),
            failures: HashMap::new(),
            retry_at: None,
            replan_needed: false,
            outbox: vec![StreamEvent::Version {
                version: info.version,
            }],
            events: events_tx,
            events_open: true,
            shared: shared.clone(),
            status: status_tx,
            requests: 0,
            bytes: 0,
            hits: 0,
            misses: 0,
            stale_refetches: 0,
        };
        let task = tokio::spawn(engine.run(camera_rx, feed_rx, follower, shutdown_rx));
        Ok((
            Streamer {
                info,
                radii,
                camera: camera_tx,
                status: status_rx,
                shared,
                shutdown: Some(shutdown_tx),
                task: Some(task),
            },
            events_rx,
        ))
    }

    /// The volume's metadata as fetched at start (its `version` is the start version;
    /// [`Streamer::stats`] has the current one).
    pub fn info(&self) -> &VolumeInfo {
        &self.info
    }

    /// The radii in use (derived at start when the configuration gave none).
    pub fn radii(&self) -> &[f32] {
        &self.radii
    }

    /// Moves the camera (world units). Cheap: call it every frame.
    pub fn set_camera(&self, camera: [f32; 3]) {
        self.camera.send_modify(|c| {
            c.seq += 1;
            c.position = Some(camera);
        });
    }

    pub fn stats(&self) -> StreamerStats {
        lock(&self.shared).stats.clone()
    }

    /// Tiles currently ready for the current camera: delivered (`Ready`) and not dropped,
    /// sorted. A stale tile being refetched stays in (its old content is still shown).
    pub fn resident(&self) -> Vec<BrickKey> {
        lock(&self.shared).resident.iter().copied().collect()
    }

    /// Resolves when every tile of the current camera's set is ready and none is stale.
    /// (Returns at once if the streamer's task has stopped.)
    pub async fn wait_idle(&self) {
        self.wait(0).await;
    }

    /// [`Streamer::wait_idle`], and the streamer has applied every commit up to `version`.
    pub async fn wait_version(&self, version: u64) {
        self.wait(version).await;
    }

    async fn wait(&self, version: u64) {
        let target = self.camera.borrow().seq;
        let mut rx = self.status.clone();
        let _ = rx
            .wait_for(|s| s.camera_seq >= target && s.idle && s.version >= version)
            .await;
    }

    /// Stops the task (requests in flight are aborted) and waits for it.
    pub async fn shutdown(mut self) {
        if let Some(s) = self.shutdown.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.task.take() {
            let _ = t.await;
        }
    }
}

/// What the change-feed follower forwards to the task.
#[derive(Debug)]
enum FeedMsg {
    Commit(ChangeEvent),
    /// The history the streamer followed is gone: start over from this metadata.
    Reload(VolumeInfo),
    Error(String),
}

/// Follows the change feed from `feed` (subscribed after version `last`), forwarding commits in
/// order; reconnects after `last` when the stream ends.
async fn follow(
    client: Client,
    name: String,
    feed: Feed,
    mut last: u64,
    tx: mpsc::Sender<FeedMsg>,
) {
    let mut feed = Some(feed);
    let mut delay = FEED_RETRY_MIN;
    loop {
        let mut f = match feed.take() {
            Some(f) => f,
            None => match client.events(&name, Some(last)).await {
                Ok(f) => f,
                Err(e) if matches!(e.status().map(|s| s.as_u16()), Some(400 | 410)) => {
                    // 410: versions after `last` were compacted away; 400: the volume is behind
                    // `last` (replaced). Either way what the streamer holds cannot be updated.
                    match client.volume(&name).await {
                        Ok(info) => {
                            last = info.version;
                            if tx.send(FeedMsg::Reload(info)).await.is_err() {
                                return;
                            }
                        }
                        Err(e) => {
                            let msg = format!("change feed: reloading the metadata: {e}");
                            if tx.send(FeedMsg::Error(msg)).await.is_err() {
                                return;
                            }
                            tokio::time::sleep(delay).await;
                            delay = (delay * 2).min(FEED_RETRY_MAX);
                        }
                    }
                    continue;
                }
                Err(e) => {
                    let msg = format!("change feed: cannot subscribe after version {last}: {e}");
                    if tx.send(FeedMsg::Error(msg)).await.is_err() {
                        return;
                    }
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(FEED_RETRY_MAX);
                    continue;
                }
            },
        };
        let pause = loop {
            match f.next().await {
                Ok(Some(FeedEvent::Hello { .. })) => delay = FEED_RETRY_MIN,
                Ok(Some(FeedEvent::Commit(ev))) => {
                    if ev.version > last {
                        last = ev.version;
                        if tx.send(FeedMsg::Commit(ev)).await.is_err() {
                            return;
                        }
                    }
                }
                // Fell behind: subscribing again after `last` replays the gap from the file.
                Ok(Some(FeedEvent::Resync { .. })) => break false,
                Ok(None) => {
                    let msg = format!("change feed closed after version {last}; reconnecting");
                    if tx.send(FeedMsg::Error(msg)).await.is_err() {
                        return;
                    }
                    break true;
                }
                Err(e) => {
                    let msg = format!("change feed failed after version {last}: {e}");
                    if tx.send(FeedMsg::Error(msg)).await.is_err() {
                        return;
                    }
                    break true;
                }
            }
        };
        if pause {
            tokio::time::sleep(delay).await;
            delay = (delay * 2).min(FEED_RETRY_MAX);
        }
    }
}

/// A request the task can have in flight.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum JobKey {
    /// Content hashes of the bricks `min..max` (exclusive) of a level.
    Region {
        level: u8,
        min: [u32; 3],
        max: [u32; 3],
    },
    /// A brick by content hash.
    Blob(u64),
    /// A mesh tile.
    Mesh(BrickKey),
}

impl JobKey {
    fn covers(&self, level: u8, p: [u32; 3]) -> bool {
        match *self {
            JobKey::Region {
                level: l, min, max, ..
            } => l == level && (0..3).all(|a| p[a] >= min[a] && p[a] < max[a]),
            _ => false,
        }
    }
}

/// What a request brought.
#[derive(Debug)]
enum Output {
    Region(Result<LevelGrid, ClientError>),
    Blob(Result<Bytes, ClientError>),
    /// The content key the tile was requested under, and the tile.
    Mesh(u64, Result<Mesh, ClientError>),
}

#[derive(Debug)]
struct Running {
    id: u64,
    abort: AbortHandle,
}

#[derive(Debug, Clone, Copy)]
struct Failure {
    attempts: u32,
    retry_at: Instant,
}

/// One tile of the desired set.
#[derive(Debug, Default)]
struct Tile {
    /// The content key of the delivered content, while it is current.
    ready: Option<u64>,
    /// `Ready` was emitted (and the tile has not left the set since).
    shown: bool,
    /// `Stale` was emitted and the new content has not been delivered yet.
    stale: bool,
}

/// Tile content by content key, least recently used first out, bounded by bytes.
#[derive(Debug)]
struct Lru {
    cap: usize,
    bytes: usize,
    tick: u64,
    map: HashMap<u64, LruEntry>,
    order: BTreeMap<u64, u64>,
}

#[derive(Debug)]
struct LruEntry {
    data: TileData,
    size: usize,
    tick: u64,
}

impl Lru {
    fn new(cap: usize) -> Lru {
        Lru {
            cap,
            bytes: 0,
            tick: 0,
            map: HashMap::new(),
            order: BTreeMap::new(),
        }
    }

    fn contains(&self, key: u64) -> bool {
        self.map.contains_key(&key)
    }

    fn get(&mut self, key: u64) -> Option<TileData> {
        let e = self.map.get_mut(&key)?;
        self.order.remove(&e.tick);
        self.tick += 1;
        e.tick = self.tick;
        self.order.insert(self.tick, key);
        Some(e.data.clone())
    }

    fn put(&mut self, key: u64, data: TileData, size: usize) {
        if size > self.cap {
            return;
        }
        if let Some(old) = self.map.remove(&key) {
            self.order.remove(&old.tick);
            self.bytes -= old.size;
        }
        self.tick += 1;
        self.map.insert(
            key,
            LruEntry {
                data,
                size,
                tick: self.tick,
            },
        );
        self.order.insert(self.tick, key);
        self.bytes += size;
        while self.bytes > self.cap {
            let Some((_, victim)) = self.order.pop_first() else {
                break;
            };
            if let Some(e) = self.map.remove(&victim) {
                self.bytes -= e.size;
            }
        }
    }
}

/// Memory a mesh holds (the cache's measure).
fn mesh_size(m: &Mesh) -> usize {
    m.positions.len() * 24 + m.indices.len() * 4
}

/// Bytes of a mesh's compact encoding (`proto::mesh`).
fn compact_size(m: &Mesh) -> u64 {
    let n = m.positions.len() as u64;
    let index = if n > 65536 { 4 } else { 2 };
    (40 + n * 18 + m.indices.len() as u64 * index).next_multiple_of(4)
}

/// The task's state.
struct Engine {
    client: Client,
    name: String,
    kind: TileKind,
    info: VolumeInfo,
    layout: VolumeLayout,
    radii: Vec<f32>,
    max_in_flight: usize,
    /// The version every known hash and requested tile describes.
    version: u64,
    camera: Option<[f32; 3]>,
    camera_seq: u64,
    /// The desired set.
    tiles: HashMap<BrickKey, Tile>,
    /// Desired tiles without current content.
    missing: usize,
    /// Content hashes of bricks, as of `version`.
    hashes: HashMap<BrickKey, u64>,
    /// The grid region (planned or running) that brings an unknown brick's hash, when it is
    /// not the brick's chunk.
    hash_source: HashMap<BrickKey, JobKey>,
    /// Content keys of the mesh tiles waiting for a request (from the last plan).
    mesh_keys: HashMap<BrickKey, u64>,
    /// Tiles waiting for content by content key (from the last plan).
    waiting: HashMap<u64, Vec<BrickKey>>,
    cache: Lru,
    jobs: JoinSet<(u64, JobKey, Output)>,
    running: HashMap<JobKey, Running>,
    next_id: u64,
    /// Requests to start, farthest first (started from the end).
    queue: Vec<(f32, JobKey)>,
    failures: HashMap<JobKey, Failure>,
    retry_at: Option<Instant>,
    replan_needed: bool,
    outbox: Vec<StreamEvent>,
    events: mpsc::Sender<StreamEvent>,
    events_open: bool,
    shared: Arc<Mutex<Shared>>,
    status: watch::Sender<Status>,
    requests: u64,
    bytes: u64,
    hits: u64,
    misses: u64,
    stale_refetches: u64,
}

impl Engine {
    async fn run(
        mut self,
        mut camera_rx: watch::Receiver<CameraMsg>,
        mut feed_rx: Option<mpsc::Receiver<FeedMsg>>,
        follower: Option<tokio::task::JoinHandle<()>>,
        mut shutdown: oneshot::Receiver<()>,
    ) {
        loop {
            if self.replan_needed {
                self.replan();
            }
            self.fill();
            self.flush().await;
            let retry_at = self.retry_at;
            tokio::select! {
                // A shutdown, or the Streamer dropped.
                _ = &mut shutdown => break,
                changed = camera_rx.changed() => {
                    if changed.is_err() {
                        break;
                    }
                    let c = *camera_rx.borrow_and_update();
                    self.camera = c.position;
                    self.camera_seq = c.seq;
                    self.update_desired();
                }
                Some(done) = self.jobs.join_next(), if !self.jobs.is_empty() => {
                    self.on_join(done);
                    while let Some(done) = self.jobs.try_join_next() {
                        self.on_join(done);
                    }
                }
                msg = recv_feed(&mut feed_rx) => match msg {
                    Some(m) => {
                        self.on_feed(m);
                        while let Some(Ok(m)) = feed_rx.as_mut().map(|rx| rx.try_recv()) {
                            self.on_feed(m);
                        }
                    }
                    None => feed_rx = None,
                },
                () = sleep_until(retry_at) => {
                    self.retry_at = None;
                    self.replan_needed = true;
                }
            }
        }
        if let Some(f) = follower {
            f.abort();
        }
        self.jobs.abort_all();
    }

    fn distance(&self, key: BrickKey) -> f32 {
        match self.camera {
            Some(c) => {
                isovox_proto::lod::tile_distance(&self.layout, self.info.voxel_scale, key, c)
            }
            None => 0.0,
        }
    }

    /// The desired set for the current camera; tiles that leave it are dropped.
    fn update_desired(&mut self) {
        let new = match self.camera {
            Some(c) => select_tiles(&self.info, c, &self.radii),
            None => Vec::new(),
        };
        let keep: HashSet<BrickKey> = new.iter().copied().collect();
        let mut gone: Vec<BrickKey> = self
            .tiles
            .keys()
            .filter(|k| !keep.contains(k))
            .copied()
            .collect();
        gone.sort();
        for key in gone {
            let Some(t) = self.tiles.remove(&key) else {
                continue;
            };
            if t.ready.is_none() {
                self.missing -= 1;
            }
            if t.shown {
                lock(&self.shared).resident.remove(&key);
                self.outbox.push(StreamEvent::Dropped { key });
            }
        }
        for key in new {
            self.tiles.entry(key).or_insert_with(|| {
                self.missing += 1;
                Tile::default()
            });
        }
        self.replan_needed = true;
    }

    /// The grid region that brings `brick`'s hash: a designated one, or its chunk.
    fn source_of(&self, brick: BrickKey) -> JobKey {
        if let Some(&s) = self.hash_source.get(&brick) {
            return s;
        }
        let g = self.layout.grid(brick.level);
        let p = [brick.x, brick.y, brick.z];
        let min = p.map(|c| c / CHUNK * CHUNK);
        JobKey::Region {
            level: brick.level,
            min,
            max: [0, 1, 2].map(|a| (min[a] + CHUNK).min(g[a])),
        }
    }

    /// A mesh tile's content key, or the input bricks whose hashes are unknown.
    fn mesh_content(&self, key: BrickKey, iso: Option<f32>) -> Result<u64, Vec<BrickKey>> {
        let mut h = DefaultHasher::new();
        "isovox mesh tile".hash(&mut h);
        key.hash(&mut h);
        iso.map(f32::to_bits).hash(&mut h);
        self.info.brick.hash(&mut h);
        self.layout.voxel_type().bytes().hash(&mut h);
        self.info.voxel_scale.map(f32::to_bits).hash(&mut h);
        let g = self.layout.grid(key.level);
        let pos = [key.x, key.y, key.z].map(i64::from);
        let mut unknown = Vec::new();
        for dz in -1i64..=1 {
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    let c = [pos[0] + dx, pos[1] + dy, pos[2] + dz];
                    if (0..3).any(|a| c[a] < 0 || c[a] >= i64::from(g[a])) {
                        0u8.hash(&mut h);
                        continue;
                    }
                    let b = BrickKey {
                        level: key.level,
                        x: c[0] as u32,
                        y: c[1] as u32,
                        z: c[2] as u32,
                    };
                    match self.hashes.get(&b) {
                        Some(v) => (1u8, *v).hash(&mut h),
                        None => unknown.push(b),
                    }
                }
            }
        }
        if unknown.is_empty() {
            Ok(h.finish())
        } else {
            Err(unknown)
        }
    }

    /// Works out what every desired tile without current content needs, makes cached ones
    /// ready, aborts requests nobody needs, and queues the rest nearest first.
    fn replan(&mut self) {
        self.replan_needed = false;
        self.waiting.clear();
        self.mesh_keys.clear();
        let mut needed: HashMap<JobKey, f32> = HashMap::new();
        let need = |needed: &mut HashMap<JobKey, f32>, job: JobKey, d: f32| {
            let e = needed.entry(job).or_insert(d);
            *e = e.min(d);
        };
        let mut from_cache = Vec::new();
        let missing: Vec<BrickKey> = self
            .tiles
            .iter()
            .filter(|(_, t)| t.ready.is_none())
            .map(|(k, _)| *k)
            .collect();
        for key in missing {
            let d = self.distance(key);
            match self.kind {
                TileKind::Bricks => match self.hashes.get(&key) {
                    Some(&h) if self.cache.contains(h) => from_cache.push((key, h)),
                    Some(&h) => {
                        need(&mut needed, JobKey::Blob(h), d);
                        self.waiting.entry(h).or_default().push(key);
                    }
                    None => need(&mut needed, self.source_of(key), d),
                },
                TileKind::Meshes { iso } => match self.mesh_content(key, iso) {
                    Ok(content) if self.cache.contains(content) => from_cache.push((key, content)),
                    Ok(content) => {
                        need(&mut needed, JobKey::Mesh(key), d);
                        self.waiting.entry(content).or_default().push(key);
                        self.mesh_keys.insert(key, content);
                    }
                    Err(unknown) => {
                        for b in unknown {
                            need(&mut needed, self.source_of(b), d);
                        }
                    }
                },
            }
        }
        for (key, content) in from_cache {
            if let Some(data) = self.cache.get(content) {
                self.hits += 1;
                self.mark_ready(key, content, data);
            }
        }
        let unneeded: Vec<JobKey> = self
            .running
            .keys()
            .filter(|k| !needed.contains_key(k))
            .copied()
            .collect();
        for job in unneeded {
            self.abort(job, true);
        }
        self.failures.retain(|k, _| needed.contains_key(k));
        let now = Instant::now();
        self.retry_at = None;
        let mut queue = Vec::with_capacity(needed.len());
        for (job, d) in needed {
            if self.running.contains_key(&job) {
                continue;
            }
            if let Some(f) = self.failures.get(&job).filter(|f| f.retry_at > now) {
                self.retry_at = Some(self.retry_at.map_or(f.retry_at, |r| r.min(f.retry_at)));
                continue;
            }
            queue.push((d, job));
        }
        queue.sort_by(|a, b| b.0.total_cmp(&a.0));
        self.queue = queue;
    }

    /// Starts queued requests up to the concurrency bound.
    fn fill(&mut self) {
        while self.running.len() < self.max_in_flight {
            let Some((_, job)) = self.queue.pop() else {
                break;
            };
            if self.running.contains_key(&job) {
                continue;
            }
            let still_needed = match job {
                JobKey::Region { .. } => true,
                JobKey::Blob(h) => self.waiting.contains_key(&h),
                JobKey::Mesh(k) => {
                    self.mesh_keys.contains_key(&k)
                        && self.tiles.get(&k).is_some_and(|t| t.ready.is_none())
                }
            };
            if still_needed {
                self.start(job);
            }
        }
    }

    fn start(&mut self, job: JobKey) {
        let id = self.next_id;
        self.next_id += 1;
        let client = self.client.clone();
        let name = self.name.clone();
        let version = Some(self.version);
        let abort = match job {
            JobKey::Region { level, min, max } => {
                for z in min[2]..max[2] {
                    for y in min[1]..max[1] {
                        for x in min[0]..max[0] {
                            let b = BrickKey { level, x, y, z };
                            if !self.hashes.contains_key(&b) {
                                self.hash_source.entry(b).or_insert(job);
                            }
                        }
                    }
                }
                self.jobs.spawn(async move {
                    let r = client
                        .level_grid(&name, level, Some((min, max)), version)
                        .await;
                    (id, job, Output::Region(r))
                })
            }
            JobKey::Blob(h) => self.jobs.spawn(async move {
                let r = client.blob(&name, h).await;
                (id, job, Output::Blob(r))
            }),
            JobKey::Mesh(key) => {
                let content = self.mesh_keys.get(&key).copied().unwrap_or_default();
                let iso = match self.kind {
                    TileKind::Meshes { iso } => iso,
                    TileKind::Bricks => None,
                };
                self.jobs.spawn(async move {
                    let r = client.mesh_tile(&name, key, iso, version).await;
                    (id, job, Output::Mesh(content, r))
                })
            }
        };
        self.running.insert(job, Running { id, abort });
        self.requests += 1;
    }

    /// Aborts a running request; with `forget`, the bricks it was to bring lose it as their
    /// source (nobody needs them now).
    fn abort(&mut self, job: JobKey, forget: bool) {
        let Some(r) = self.running.remove(&job) else {
            return;
        };
        r.abort.abort();
        if let (true, JobKey::Region { level, min, max }) = (forget, job) {
            self.forget_source(level, min, max, job);
        }
    }

    fn forget_source(&mut self, level: u8, min: [u32; 3], max: [u32; 3], job: JobKey) {
        for z in min[2]..max[2] {
            for y in min[1]..max[1] {
                for x in min[0]..max[0] {
                    let b = BrickKey { level, x, y, z };
                    if self.hash_source.get(&b) == Some(&job) {
                        self.hash_source.remove(&b);
                    }
                }
            }
        }
    }

    fn mark_ready(&mut self, key: BrickKey, content: u64, data: TileData) {
        let Some(t) = self.tiles.get_mut(&key) else {
            return;
        };
        if t.ready.is_none() {
            self.missing -= 1;
        }
        t.ready = Some(content);
        t.stale = false;
        if !t.shown {
            t.shown = true;
            lock(&self.shared).resident.insert(key);
        }
        self.outbox.push(StreamEvent::Ready {
            key,
            hash: content,
            data,
            version: self.version,
        });
    }

    fn fail(&mut self, job: JobKey, key: Option<BrickKey>, error: String) {
        let attempts = self.failures.get(&job).map_or(0, |f| f.attempts) + 1;
        let delay = RETRY_MIN
            .saturating_mul(1 << (attempts - 1).min(16))
            .min(RETRY_MAX);
        let retry_at = Instant::now() + delay;
        self.failures.insert(job, Failure { attempts, retry_at });
        self.retry_at = Some(self.retry_at.map_or(retry_at, |r| r.min(retry_at)));
        self.outbox.push(StreamEvent::Error { key, error });
    }

    fn on_join(&mut self, done: Result<(u64, JobKey, Output), JoinError>) {
        // Aborted requests were removed from `running` when aborted. A request that panicked
        // (it should not) is removed here, so that it can start again.
        let (id, job, output) = match done {
            Ok(d) => d,
            Err(e) => {
                if e.is_panic() {
                    let task = e.id();
                    self.running.retain(|_, r| r.abort.id() != task);
                    self.replan_needed = true;
                }
                return;
            }
        };
        match self.running.get(&job) {
            Some(r) if r.id == id => {
                self.running.remove(&job);
            }
            _ => return, // aborted (or superseded) before it finished
        }
        match output {
            Output::Region(result) => self.on_region(job, result),
            Output::Blob(result) => self.on_blob(job, result),
            Output::Mesh(content, result) => self.on_mesh(job, content, result),
        }
    }

    fn on_region(&mut self, job: JobKey, result: Result<LevelGrid, ClientError>) {
        let JobKey::Region { level, min, max } = job else {
            return;
        };
        let grid = match result {
            Ok(g) => g,
            Err(e) => {
                let msg = format!("level {level} grid {min:?}..{max:?}: {e}");
                self.fail(job, None, msg);
                return;
            }
        };
        let count: usize = (0..3).map(|a| (max[a] - min[a]) as usize).product();
        if grid.bricks.len() != count || grid.min != min || grid.max != max {
            let msg = format!(
                "level {level} grid {min:?}..{max:?}: the answer covers {:?}..{:?} with {} bricks",
                grid.min,
                grid.max,
                grid.bricks.len()
            );
            self.fail(job, None, msg);
            return;
        }
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
                            self.hash_source.remove(&b);
                        }
                        Err(_) => self.outbox.push(StreamEvent::Error {
                            key: Some(b),
                            error: format!("brick {b}: {:?} is not a content hash", entry.hash),
                        }),
                    }
                }
            }
        }
        self.forget_source(level, min, max, job);
        self.failures.remove(&job);
        self.replan_needed = true;
    }

    fn on_blob(&mut self, job: JobKey, result: Result<Bytes, ClientError>) {
        let JobKey::Blob(h) = job else {
            return;
        };
        let bytes = match result {
            Ok(b) if b.len() == self.layout.brick_bytes() => b,
            Ok(b) => {
                let msg = format!(
                    "blob {h:016x}: {} bytes, expected {}",
                    b.len(),
                    self.layout.brick_bytes()
                );
                self.fail(job, None, msg);
                return;
            }
            Err(e) => {
                self.fail(job, None, format!("blob {h:016x}: {e}"));
                return;
            }
        };
        self.failures.remove(&job);
        self.bytes += bytes.len() as u64;
        self.misses += 1;
        let data = TileData::Brick(bytes);
        self.cache.put(h, data.clone(), self.layout.brick_bytes());
        let mut first = true;
        for key in self.waiting.remove(&h).unwrap_or_default() {
            let current = self.tiles.get(&key).is_some_and(|t| t.ready.is_none())
                && self.hashes.get(&key) == Some(&h);
            if current {
                if !first {
                    self.hits += 1;
                }
                first = false;
                self.mark_ready(key, h, data.clone());
            }
        }
    }

    fn on_mesh(&mut self, job: JobKey, content: u64, result: Result<Mesh, ClientError>) {
        let JobKey::Mesh(key) = job else {
            return;
        };
        let mesh = match result {
            Ok(m) => m,
            Err(e) => {
                self.fail(job, Some(key), format!("mesh tile {key}: {e}"));
                return;
            }
        };
        self.failures.remove(&job);
        self.bytes += compact_size(&mesh);
        self.misses += 1;
        let size = mesh_size(&mesh);
        let data = TileData::Mesh(Arc::new(mesh));
        self.cache.put(content, data.clone(), size);
        let mut first = true;
        for k in self.waiting.remove(&content).unwrap_or_default() {
            let current = self.tiles.get(&k).is_some_and(|t| t.ready.is_none())
                && self.mesh_keys.get(&k) == Some(&content);
            if current {
                if !first {
                    self.hits += 1;
                }
                first = false;
                self.mark_ready(k, content, data.clone());
            }
        }
    }

    fn on_feed(&mut self, msg: FeedMsg) {
        match msg {
            FeedMsg::Commit(ev) => self.apply_commit(&ev),
            FeedMsg::Reload(info) => self.reload(info),
            FeedMsg::Error(error) => self.outbox.push(StreamEvent::Error { key: None, error }),
        }
    }

    /// Marks a delivered tile stale (emitting `Stale`) and any desired tile as needing content.
    fn invalidate(&mut self, key: BrickKey, version: u64) {
        let Some(t) = self.tiles.get_mut(&key) else {
            return;
        };
        if t.shown {
            if !t.stale {
                t.stale = true;
                self.stale_refetches += 1;
            }
            self.outbox.push(StreamEvent::Stale { key, version });
        }
        if t.ready.take().is_some() {
            self.missing += 1;
        }
    }

    fn apply_commit(&mut self, ev: &ChangeEvent) {
        if ev.version <= self.version {
            return;
        }
        for (level, changed) in ev.changed.iter().enumerate() {
            if level >= self.layout.levels() as usize || changed.is_empty() {
                continue;
            }
            let level = level as u8;
            let g = self.layout.grid(level);
            let mut affected = BTreeSet::new();
            let mut read = Vec::new();
            for &p in changed {
                if (0..3).any(|a| p[a] >= g[a]) {
                    continue;
                }
                let b = BrickKey {
                    level,
                    x: p[0],
                    y: p[1],
                    z: p[2],
                };
                self.hashes.remove(&b);
                self.hash_source.remove(&b);
                let mut is_read = false;
                match self.kind {
                    TileKind::Bricks => {
                        if self.tiles.contains_key(&b) {
                            affected.insert(b);
                            is_read = true;
                        }
                    }
                    TileKind::Meshes { .. } => {
                        // The tiles that read brick p: those at p - 1 ..= p + 1.
                        for dz in -1i64..=1 {
                            for dy in -1i64..=1 {
                                for dx in -1i64..=1 {
                                    let c = [p[0] as i64 + dx, p[1] as i64 + dy, p[2] as i64 + dz];
                                    if (0..3).any(|a| c[a] < 0 || c[a] >= i64::from(g[a])) {
                                        continue;
                                    }
                                    let t = BrickKey {
                                        level,
                                        x: c[0] as u32,
                                        y: c[1] as u32,
                                        z: c[2] as u32,
                                    };
                                    if self.tiles.contains_key(&t) {
                                        affected.insert(t);
                                        is_read = true;
                                    }
                                }
                            }
                        }
                    }
                }
                if is_read {
                    read.push(b);
                }
            }
            // Grid regions in flight answer for the version before: abort those that cover a
            // changed brick (they start again at the new version if still needed).
            let overlapping: Vec<JobKey> = self
                .running
                .keys()
                .filter(|j| changed.iter().any(|&p| j.covers(level, p)))
                .copied()
                .collect();
            for job in overlapping {
                self.abort(job, false);
            }
            // One region brings the new hashes of the changed bricks some desired tile reads.
            if let Some(first) = read.first() {
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
                    self.hash_source.insert(b, region);
                }
            }
            for key in affected {
                if let Some(r) = self.running.remove(&JobKey::Mesh(key)) {
                    r.abort.abort();
                }
                self.invalidate(key, ev.version);
            }
        }
        self.version = ev.version;
        self.outbox.push(StreamEvent::Version {
            version: ev.version,
        });
        self.replan_needed = true;
    }

    /// Starts over from new metadata: every hash forgotten, every delivered tile stale.
    fn reload(&mut self, info: VolumeInfo) {
        let layout = match VolumeLayout::new(info.dims, info.brick, info.voxel_type) {
            Ok(l) if l.levels() as usize == info.levels.len() => l,
            _ => {
                self.outbox.push(StreamEvent::Error {
                    key: None,
                    error: format!("reload: inconsistent metadata for {}", info.name),
                });
                return;
            }
        };
        let jobs: Vec<JobKey> = self.running.keys().copied().collect();
        for job in jobs {
            self.abort(job, true);
        }
        self.hashes.clear();
        self.hash_source.clear();
        self.failures.clear();
        self.queue.clear();
        self.layout = layout;
        self.version = info.version;
        self.info = info;
        self.update_desired();
        let mut keys: Vec<BrickKey> = self.tiles.keys().copied().collect();
        keys.sort();
        for key in keys {
            self.invalidate(key, self.version);
        }
        self.outbox.push(StreamEvent::Version {
            version: self.version,
        });
        self.replan_needed = true;
    }

    /// Sends the events gathered so far, then publishes statistics and status (in that order, so
    /// a waiter woken by the status finds every event in the channel).
    async fn flush(&mut self) {
        for ev in std::mem::take(&mut self.outbox) {
            if self.events_open && self.events.send(ev).await.is_err() {
                self.events_open = false;
            }
        }
        {
            let mut shared = lock(&self.shared);
            let resident = shared.resident.len();
            shared.stats = StreamerStats {
                requests: self.requests,
                bytes: self.bytes,
                cache_hits: self.hits,
                cache_misses: self.misses,
                in_flight: self.running.len(),
                resident,
                cache_bytes: self.cache.bytes,
                version: self.version,
                stale_refetches: self.stale_refetches,
            };
        }
        let now = Status {
            camera_seq: self.camera_seq,
            idle: self.missing == 0,
            version: self.version,
        };
        self.status.send_if_modified(|s| {
            let changed = *s != now;
            *s = now;
            changed
        });
    }
}

/// The next feed message; never, without a feed.
async fn recv_feed(rx: &mut Option<mpsc::Receiver<FeedMsg>>) -> Option<FeedMsg> {
    match rx {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}

async fn sleep_until(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}
