//! The camera-distance streamer: keeps the tiles a viewer at a camera position needs, in the
//! order they show on screen, and keeps them current while other users edit the volume.
//!
//! # What it selects
//!
//! The thesis's spherical detail bias, exactly as the server's offline selection
//! (`isovox_proto::lod::adaptive_tiles`) computes it: with radii `r0 < r1 < ... <
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
//! Mesh tiles are stitched where levels meet, so the selection for them is balanced first
//! ([`select_stitched_tiles`], `isovox_proto::lod::balanced_tiles`: refined until tiles that
//! touch differ by at most one level), and each tile is drawn with the face mask
//! `isovox_proto::lod::face_masks` gives it in that selection: the faces touching a coarser
//! tile, whose transition strips it draws (`docs/lod-meshes.md`). When a neighbour's level
//! changes (the camera moved), a delivered tile whose mask changed is stitched again and
//! delivered again (`Ready` with the same content key), without a request.
//!
//! # Tiles and their content keys
//!
//! A tile is a [`BrickKey`]. With [`TileKind::Bricks`] its content is the brick's voxels and its
//! content key is the brick's content hash (xxh3-64, as the server names it). With
//! [`TileKind::Meshes`] its content is the server's marching-cubes tile with its transition data,
//! which reads the bricks around it at its level and the next coarser level's bricks around its
//! faces (`isovox_proto::tile::mesh_tile_reads`); its content key hashes the tile's position,
//! the iso value, the brick shape and the content hashes of those inputs (absent ones marked). A
//! tile is stale exactly when one of its inputs changed.
//!
//! Content hashes come from the levels' brick grids (`GET .../levels/{l}?format=grid&region=`),
//! fetched in regions of 8x8x8 bricks as tiles need them and kept per brick. Brick content is then
//! fetched by hash (`GET .../blobs/{hash}`), once per hash: a brick shared by many positions (air,
//! solid rock) costs one request. Mesh tiles are fetched by position (`GET .../meshes/...`) when
//! their content key is not cached. The cache holds content by key, LRU, bounded by
//! [`StreamerConfig::cache_bytes`] (brick: its voxel bytes; mesh: positions, normals, indices,
//! transition data).
//!
//! Without the descent below, a mesh tile whose input bricks' value ranges (from the same grid
//! regions) lie wholly below the iso value, or wholly above, has no surface: it is complete
//! without a request, and without `Ready` (as a tile the descent skips). Without this
//! ([`StreamerConfig::skip_empty`]), most of the mesh requests of a viewer of a large world ask
//! for empty meshes.
//!
//! # The octree descent
//!
//! Most of a large volume is air or rock, and a tile there has nothing to draw. With
//! [`StreamerConfig::descent`] (on by default, see there) the streamer decides, before asking
//! for a tile's grid region, whether the surface at the iso value (the meshes' iso, or S - 0.5
//! for bricks) can cross it, from the value ranges the grids give for coarser bricks: it asks
//! for the coarsest level's grid first and for a finer level's region only under bricks where
//! the answer is "maybe". A tile it rules out is complete without content: no grid region, no
//! blob, no mesh, no `Ready` (and `Dropped` if it had been delivered before an edit emptied it).
//!
//! The rule never drops a surface because it rests on a bound, not on the coarse values
//! themselves: a level-(k+1) voxel is the mean of its 2x2x2 children rounded half up, so a
//! parent brick with values in `[lo, hi]` has children in `[max(0, 8 lo - 4 - 7H), min(H, 8 hi +
//! 3)]` (H the type's highest value). A brick's bound is its own range when known, else its
//! parent's carried down while that lies wholly on one side of the iso value. A tile is ruled
//! out when every brick it reads (a mesh tile's own bricks and its strips'; for a brick, the
//! bricks its mesh tile reads, since a surface between two bricks is drawn from both) is bounded
//! wholly below the iso value, or every one wholly above. In practice it rules out the tiles
//! under parents that are nearly all air (u8 at the default iso: max <= 15) or nearly all rock
//! (min >= 240). An edit's event carries the new ranges of the bricks it changed, so the tiles it
//! reaches (and, for bricks, the skipped ones next to them) are decided again from those.
//!
//! Deciding again asks for no grid region. The bricks an edit did not change keep the bound they
//! had from a coarser brick before the commit changed it (their content is what it was). A tile
//! an edit makes wanted whose inputs were only ever bounded, never listed in a grid answer, is
//! asked for at the new version (a brick by position, a mesh tile and its strips under a content
//! key of that version): answers a cache can give, where a grid region only the origin can.
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
//! requests in flight (a [`JoinSet`](tokio::task::JoinSet) with one abort handle per request).
//! The camera reaches it through a `watch` (only the latest position matters); events leave
//! through a bounded channel of 4,096 (`send().await`: a slow consumer slows the streamer down;
//! a dropped receiver is ignored and the streamer keeps working). A second task follows the
//! change feed and forwards commits in order.
//!
//! Each time the camera, the feed or a grid region changes what is known, the task plans again:
//! for the desired tiles not yet current, in screen order, it finds what is missing (a grid
//! region, a blob, a mesh), cached content makes tiles ready at once, requests no planned tile
//! needs any more are aborted (their results are never delivered), and the rest are queued in
//! the screen order of the first tile that needs them. A tile's screen order is its distance
//! from the camera over its edge length (how small it shows): the radii double per level as
//! tiles do, so the levels interleave and the coarse tiles that hold a distant surface come as
//! early as the fine ones around the camera, not after all of them. A failed request is
//! reported as [`StreamEvent::Error`] and retried after a backoff (250 ms doubling to 10 s)
//! while a tile still needs it.
//!
//! Planning is bounded, because a viewer of a large volume has thousands of tiles waiting and
//! one load tester runs fifty streamers:
//!
//! - a plan stops once 512 tiles wait for something (tiles found complete do not count), since
//!   only requests near the front of the queue start before the next plan; requests of tiles
//!   beyond the window that are running are left to finish. The window moves on once fewer of
//!   its requests wait to start than may run at once;
//! - a mesh tile or strip that arrives draws the tiles that waited for it without a plan;
//! - the screen order of the tiles still without content is kept until the camera moves
//!   or a commit makes tiles need content again, each plan dropping from it the tiles that got
//!   content meanwhile (once most tiles are complete, a plan does not walk past thousands);
//! - the camera's tiles are selected again at most every 100 ms while it moves an eighth of the
//!   finest detail radius or more since the last selection, and 300 ms after the last
//!   selection when it moved less (the newest position then: a camera at rest is always
//!   selected where it rests);
//! - while requests of the last plan wait to start, planning runs at most every 50 ms however
//!   many answers come;
//! - a waiting mesh tile's plan (content keys from up to 27 bricks' hashes) is kept until a
//!   request it needs ends, content it waits for comes, a commit comes or its face mask
//!   changes.
//!
//! # Requests in flight
//!
//! At most [`StreamerConfig::max_in_flight`] requests run at once (the feed's connection is not
//! counted), fewer while the server is overloaded. The server answers 503 with `Retry-After`
//! when its queue of CPU work (mesh tiles, grid regions) is full, and that queue is small (8
//! places per core): three streamers at 16 requests each already fill a two-core server's. So
//! the limit is additive-increase, multiplicative-decrease, as TCP's congestion window: it
//! starts at the maximum; a 503 (or 429) halves it, not below 1; after as many successful
//! answers as the limit, it grows by one, up to the maximum. A 503 to a request started before
//! the last cut does not cut again (it answers load that cut already relieved). Requests
//! already running are not cancelled when it drops; no new one starts until fewer than the
//! limit run. The refused request itself waits the `Retry-After` pause and is asked again by
//! the [`Client`]'s retries. [`StreamerStats::in_flight_limit`] is the limit now.
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
//! For each commit, in version order: every brick in `changed[level]` takes the hash the event
//! lists for it (`bricks`), or forgets it when the event does not list them (a commit of more
//! than `EVENT_GRID_LIMIT` bricks, an older server); the desired tiles whose inputs include one
//! of them (bricks: the brick itself; meshes: the tiles that read it, of its level and the next
//! finer one) lose their current content, and the delivered ones get `Stale`.
//! Requests in flight whose answers predate the commit and touch a changed brick are aborted.
//! For hashes the event did not give, one grid region per level, the bounding box of the changed
//! bricks that some desired tile reads, brings them; content then comes from the cache or one
//! request per new content key.
//! Tiles whose inputs did not change are not refetched.
//!
//! When the feed ends or fails, the follower reconnects with `since` = the last version it
//! forwarded (backoff 100 ms doubling to 2 s); the server replays the versions in between from
//! the file, which the streamer applies like live ones but all in one step: it then fetches
//! only the newest content of what they changed, not that of versions already superseded. A `resync` event (the subscriber fell
//! behind) reconnects the same way. When the server answers 410 Gone (the history after that
//! version was compacted away) or 409 Conflict (the volume is now behind the streamer), the streamer
//! reloads: new metadata, every hash forgotten, every delivered tile stale and refetched (content
//! already cached by key is reused).

use crate::client::{Client, ClientError};
use bytes::Bytes;
use isovox_proto::api::{ChangeEvent, LevelBrick, LevelGrid, VolumeInfo};
use isovox_proto::mesh::{Mesh, TileMesh};
use isovox_proto::{BrickKey, VolumeLayout};
use std::collections::BTreeSet;
use std::hash::{Hash, Hasher};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::JoinError;
use tokio::time::Instant;

mod engine;
mod limit;

use engine::{follow, Engine};

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
    Meshes {
        /// The iso value; the server's default when `None`.
        iso: Option<f32>,
    },
}

/// How a [`Streamer`] runs.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamerConfig {
    /// Bricks or mesh tiles.
    pub kind: TileKind,
    /// World units (voxel_scale applied); r_0 < r_1 < ...; level k within r_k, coarser beyond.
    /// Empty: derived at start with [`StreamerConfig::radii_for_screen_error`] for a 60 degree
    /// vertical field of view, a 1080-pixel viewport and one pixel of error.
    pub radii: Vec<f32>,
    /// The most requests running at once (at least 1). Default 16. Fewer run while the server
    /// is overloaded: the limit halves on each 503 and grows back by one per window of
    /// successes (see the module documentation).
    pub max_in_flight: usize,
    /// Bytes of tile content kept by content key. Default 256 MiB.
    pub cache_bytes: usize,
    /// Follow the change feed. Default true. Without it the streamer stays at the start version.
    pub follow_edits: bool,
    /// Octree descent: skip the desired tiles that cannot hold the surface at the iso value
    /// (the meshes' iso, or S - 0.5 for bricks), decided from coarser bricks' value ranges, so
    /// that their grid regions, bricks and meshes are never asked for. True (the default): a
    /// viewer reaches the surface sooner, because the tiles next to the camera are mostly air
    /// and the descent rules them out from a few coarse ranges (on a 2048^3 world, one mesh
    /// viewer drew its first triangle after 67 ms with it and 141 ms without; fifty at once
    /// on two cores, 4.3-4.6 s against 9.4-9.8 s at p99: docs/benchmarks.md, "Many viewers on
    /// a large world"). False: every desired tile's grid entries are fetched, and every tile
    /// but the mesh tiles [`StreamerConfig::skip_empty`] skips.
    pub descent: bool,
    /// Mesh tiles whose input bricks' value ranges (from the grid regions asked for anyway)
    /// rule out the surface are complete without a request. Default true. False asks for every
    /// desired mesh tile, empty ones included (the reference the skipping is tested against).
    pub skip_empty: bool,
}

impl Default for StreamerConfig {
    fn default() -> Self {
        StreamerConfig {
            kind: TileKind::Bricks,
            radii: Vec::new(),
            max_in_flight: 16,
            cache_bytes: 256 << 20,
            follow_edits: true,
            descent: true,
            skip_empty: true,
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

/// The tiles to stitch for a camera (sorted), from metadata only: [`select_tiles`] refined until
/// tiles that touch differ by at most one level ([`isovox_proto::lod::balanced_tiles`], as the
/// server's `isovox mesh --camera` and the web viewer select them).
pub fn select_stitched_tiles(info: &VolumeInfo, camera: [f32; 3], radii: &[f32]) -> Vec<BrickKey> {
    match VolumeLayout::new(info.dims, info.brick, info.voxel_type) {
        Ok(layout) => isovox_proto::lod::balanced_tiles(&layout, info.voxel_scale, camera, radii),
        Err(_) => Vec::new(),
    }
}

/// A mesh tile as drawn next to its neighbours of the current selection.
#[derive(Debug, Clone)]
pub struct MeshTile {
    /// The tile as the server sends it, in world coordinates (normals quantized): its regular
    /// mesh and its moves.
    pub tile: Arc<TileMesh>,
    /// The faces touching a coarser tile in the current selection (bit f: face f, in the order
    /// -x, +x, -y, +y, -z, +z).
    pub mask: u8,
    /// The transition strips of the faces in `mask`, as the server sends them (`None` for the
    /// other faces).
    pub strips: [Option<Arc<Mesh>>; 6],
    /// `tile` stitched with `mask` and `strips` (`isovox_proto::mesh::stitch`): what to draw.
    pub mesh: Arc<Mesh>,
}

/// A tile's content.
#[derive(Debug, Clone)]
pub enum TileData {
    /// The brick's voxels (raw, x fastest, u16 little endian).
    Brick(Bytes),
    /// The mesh tile, and how it is drawn now.
    Mesh(MeshTile),
}

impl TileData {
    /// The tile's size in memory: voxel bytes, or the mesh's arrays (the tile's, with its
    /// transition data, and the stitched mesh's).
    pub fn bytes(&self) -> u64 {
        match self {
            TileData::Brick(b) => b.len() as u64,
            TileData::Mesh(m) => (tile_size(&m.tile) + mesh_size(&m.mesh)) as u64,
        }
    }
}

/// Memory a mesh holds.
fn mesh_size(m: &Mesh) -> usize {
    m.positions.len() * 24 + m.indices.len() * 4
}

/// Memory a tile holds: its regular mesh and its moves.
fn tile_size(t: &TileMesh) -> usize {
    mesh_size(&t.mesh) + t.moves.len() * std::mem::size_of::<isovox_proto::mesh::VertexMove>()
}

/// What the streamer reports.
#[derive(Debug, Clone)]
pub enum StreamEvent {
    /// `key` has content `data` (content key `hash`: the brick's content hash, or for a mesh
    /// tile the hash of its position, iso and inputs), current as of `version`. A mesh tile is
    /// delivered again with the same `hash` when its face mask changed (see [`MeshTile`]).
    Ready {
        /// The tile.
        key: BrickKey,
        /// Its content key.
        hash: u64,
        /// Its content.
        data: TileData,
        /// The version it is current as of.
        version: u64,
    },
    /// `key` left the desired set; it had been delivered.
    Dropped {
        /// The tile.
        key: BrickKey,
    },
    /// Commit `version` changed an input of `key`; new content follows as `Ready`.
    Stale {
        /// The tile.
        key: BrickKey,
        /// The commit that changed it.
        version: u64,
    },
    /// The streamer applied every commit up to `version`.
    Version {
        /// The version.
        version: u64,
    },
    /// A request (for `key`, when it served one tile) or the change feed failed; retried.
    Error {
        /// The tile the request was for, if one.
        key: Option<BrickKey>,
        /// What failed.
        error: String,
    },
}

/// Counters of a [`Streamer`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StreamerStats {
    /// HTTP requests started (grid regions, blobs, mesh tiles; not the change feed).
    pub requests: u64,
    /// Payload bytes received: brick voxels, and mesh tiles' compact encodings (with their
    /// transition data).
    pub bytes: u64,
    /// Tiles made ready without a request of their own (cached, or shared with another tile).
    pub cache_hits: u64,
    /// Content requests completed (blobs, mesh tiles).
    pub cache_misses: u64,
    /// Requests running now.
    pub in_flight: usize,
    /// Requests that may run at once now: [`StreamerConfig::max_in_flight`], less while the
    /// server answers 503.
    pub in_flight_limit: usize,
    /// Delivered tiles of the desired set (see [`Streamer::resident`]).
    pub resident: usize,
    /// Bytes held by the content cache.
    pub cache_bytes: usize,
    /// The version the streamer is at.
    pub version: u64,
    /// Delivered tiles refetched because a commit changed their inputs.
    pub stale_refetches: u64,
    /// Grid regions requested (`GET .../levels/{l}?format=grid`), every cause.
    pub grid_requests: u64,
    /// Of those, the regions aborted before their answer was used (no tile needed them any
    /// more, or a commit made them stale): some of those never reached the server.
    pub grid_aborted: u64,
    /// Of those, the regions a tile needed because a commit invalidated it (a hash the event
    /// did not list, or a descent the new value ranges opened).
    pub edit_grid_requests: u64,
    /// Times a desired tile was found without surface and skipped (by the descent, or
    /// without it, a mesh tile from its bricks' ranges).
    pub skipped: u64,
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
        let mut shared = Shared::default();
        shared.stats.in_flight_limit = config.max_in_flight.max(1);
        let shared = Arc::new(Mutex::new(shared));
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
        let engine = Engine::new(
            client,
            volume,
            &config,
            layout,
            info.clone(),
            radii.clone(),
            events_tx,
            shared.clone(),
            status_tx,
        );
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

    /// What the streamer has done so far.
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
