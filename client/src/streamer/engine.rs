//! The streamer's task: an [`Engine`] made of its parts (the desired set, the hash book, the
//! scheduler, the statistics) and the content cache, driven by the camera, finished requests,
//! the change feed and retry timers.

use super::limit::{lock_limit, InFlightLimit, Pacer, SharedLimit};
use super::*;

/// What the change-feed follower forwards to the task.
#[derive(Debug)]
pub(super) enum FeedMsg {
    /// Commits in version order, applied together: one live commit, or every version the
    /// server replayed after a (re)subscription.
    Commits(Vec<ChangeEvent>),
    /// The history the streamer followed is gone: start over from this metadata.
    Reload(VolumeInfo),
    Error(String),
}

/// Follows the change feed from `feed` (subscribed after version `last`), forwarding commits in
/// order; reconnects after `last` when the stream ends.
///
/// After a subscription the server first replays the versions after `last` up to the head its
/// `hello` names. Those are forwarded as one message, so the task applies them together and
/// fetches the newest content of what they changed, never the content of a version it already
/// knows is superseded (after a long disconnect, one grid region and one blob per changed brick
/// instead of one per missed version).
pub(super) async fn follow(
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
                Err(e) if matches!(e.status().map(|s| s.as_u16()), Some(409 | 410)) => {
                    // 410: versions after `last` were compacted away; 409: the volume is behind
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
        // Commits read but not forwarded yet: the replay, until it reaches `replayed_to`.
        let mut replay = Vec::new();
        let mut replayed_to = 0;
        let pause = loop {
            match f.next().await {
                Ok(Some(FeedEvent::Hello { version })) => {
                    delay = FEED_RETRY_MIN;
                    replayed_to = version;
                }
                Ok(Some(FeedEvent::Commit(ev))) => {
                    if ev.version > last {
                        last = ev.version;
                        replay.push(ev);
                        if last >= replayed_to
                            && tx
                                .send(FeedMsg::Commits(std::mem::take(&mut replay)))
                                .await
                                .is_err()
                        {
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
        // A stream that broke during the replay: what arrived of it is still history to apply.
        if !replay.is_empty() && tx.send(FeedMsg::Commits(replay)).await.is_err() {
            return;
        }
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
    /// The transition strip of a face (0..6) of a mesh tile.
    Strip(BrickKey, u8),
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
    Mesh(u64, Result<TileMesh, ClientError>),
    /// The content key the strip was requested under, and the strip.
    Strip(u64, Result<Mesh, ClientError>),
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
    /// A mesh tile's delivered content and the face mask it was stitched with.
    drawn: Option<(Arc<TileMesh>, u8)>,
    /// A mesh tile's delivered drawing: a hash of its content key, mask and strips' content
    /// keys, while current.
    drawn_key: Option<u64>,
}

/// What the cache keeps by content key.
#[derive(Debug, Clone)]
enum Content {
    Brick(Bytes),
    Mesh(Arc<TileMesh>),
    Strip(Arc<Mesh>),
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
    data: Content,
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

    fn get(&mut self, key: u64) -> Option<Content> {
        let e = self.map.get_mut(&key)?;
        self.order.remove(&e.tick);
        self.tick += 1;
        e.tick = self.tick;
        self.order.insert(self.tick, key);
        Some(e.data.clone())
    }

    fn put(&mut self, key: u64, data: Content, size: usize) {
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

/// The task's state: what it serves, and its four parts.
pub(super) struct Engine {
    client: Client,
    name: String,
    kind: TileKind,
    info: VolumeInfo,
    layout: VolumeLayout,
    radii: Vec<f32>,
    /// The version every known hash and requested tile describes.
    version: u64,
    /// What the camera needs.
    desired: Desired,
    /// What bricks hold, by content hash.
    book: HashBook,
    /// What is requested, running, waiting or failed.
    scheduler: Scheduler,
    /// What has been done so far.
    stats: Counters,
    cache: Lru,
    outbox: Vec<StreamEvent>,
    events: mpsc::Sender<StreamEvent>,
    events_open: bool,
    shared: Arc<Mutex<Shared>>,
    status: watch::Sender<Status>,
}

/// The desired set: the tiles the camera needs, and what is known about each.
#[derive(Debug, Default)]
struct Desired {
    camera: Option<[f32; 3]>,
    camera_seq: u64,
    tiles: HashMap<BrickKey, Tile>,
    /// Mesh tiles: each desired tile's face mask in the desired set.
    masks: HashMap<BrickKey, u8>,
    /// Desired tiles without current content.
    missing: usize,
}

/// The hash book: content hashes of bricks as of the engine's version, and where unknown ones
/// will come from.
#[derive(Debug, Default)]
struct HashBook {
    hashes: HashMap<BrickKey, u64>,
    /// The grid region (planned or running) that brings an unknown brick's hash, when it is
    /// not the brick's chunk.
    sources: HashMap<BrickKey, JobKey>,
}

/// The scheduler: the plan (requests to start, nearest first), what runs, what failed and when
/// to retry it.
struct Scheduler {
    /// Requests that may run at once (the requests' [`Pacer`]s adapt it to 503s).
    limit: SharedLimit,
    /// Content keys of the mesh tiles waiting for a request (from the last plan).
    mesh_keys: HashMap<BrickKey, u64>,
    /// Content keys of the strips (tile, face) waiting for a request (from the last plan).
    strip_keys: HashMap<(BrickKey, u8), u64>,
    /// Tiles waiting for content by content key (from the last plan).
    waiting: HashMap<u64, Vec<BrickKey>>,
    jobs: JoinSet<(u64, JobKey, Output)>,
    running: HashMap<JobKey, Running>,
    next_id: u64,
    /// Requests to start, farthest first (started from the end).
    queue: Vec<(f32, JobKey)>,
    failures: HashMap<JobKey, Failure>,
    retry_at: Option<Instant>,
    replan_needed: bool,
}

impl Scheduler {
    fn new(max_in_flight: usize) -> Scheduler {
        Scheduler {
            limit: Arc::new(Mutex::new(InFlightLimit::new(max_in_flight))),
            mesh_keys: HashMap::new(),
            strip_keys: HashMap::new(),
            waiting: HashMap::new(),
            jobs: JoinSet::new(),
            running: HashMap::new(),
            next_id: 0,
            queue: Vec::new(),
            failures: HashMap::new(),
            retry_at: None,
            replan_needed: false,
        }
    }
}

/// Statistics: requests, bytes, cache hits and misses, refetches of stale tiles.
#[derive(Debug, Default, Clone, Copy)]
struct Counters {
    requests: u64,
    bytes: u64,
    hits: u64,
    misses: u64,
    stale_refetches: u64,
}

impl Engine {
    /// An engine for volume `name` as `config` says, at the version `info` names, reporting
    /// through `events`, `shared` and `status`.
    #[allow(clippy::too_many_arguments)] // the task's channels, each made by `Streamer::start`
    pub(super) fn new(
        client: Client,
        name: &str,
        config: &StreamerConfig,
        layout: VolumeLayout,
        info: VolumeInfo,
        radii: Vec<f32>,
        events: mpsc::Sender<StreamEvent>,
        shared: Arc<Mutex<Shared>>,
        status: watch::Sender<Status>,
    ) -> Engine {
        Engine {
            client,
            name: name.to_string(),
            kind: config.kind,
            layout,
            radii,
            version: info.version,
            outbox: vec![StreamEvent::Version {
                version: info.version,
            }],
            info,
            desired: Desired::default(),
            book: HashBook::default(),
            scheduler: Scheduler::new(config.max_in_flight),
            stats: Counters::default(),
            cache: Lru::new(config.cache_bytes),
            events,
            events_open: true,
            shared,
            status,
        }
    }

    pub(super) async fn run(
        mut self,
        mut camera_rx: watch::Receiver<CameraMsg>,
        mut feed_rx: Option<mpsc::Receiver<FeedMsg>>,
        follower: Option<tokio::task::JoinHandle<()>>,
        mut shutdown: oneshot::Receiver<()>,
    ) {
        loop {
            if self.scheduler.replan_needed {
                self.replan();
            }
            self.fill();
            self.flush().await;
            let retry_at = self.scheduler.retry_at;
            tokio::select! {
                // A shutdown, or the Streamer dropped.
                _ = &mut shutdown => break,
                changed = camera_rx.changed() => {
                    if changed.is_err() {
                        break;
                    }
                    let c = *camera_rx.borrow_and_update();
                    self.desired.camera = c.position;
                    self.desired.camera_seq = c.seq;
                    self.update_desired();
                }
                Some(done) = self.scheduler.jobs.join_next(), if !self.scheduler.jobs.is_empty() => {
                    self.on_join(done);
                    while let Some(done) = self.scheduler.jobs.try_join_next() {
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
                    self.scheduler.retry_at = None;
                    self.scheduler.replan_needed = true;
                }
            }
        }
        if let Some(f) = follower {
            f.abort();
        }
        self.scheduler.jobs.abort_all();
    }

    fn distance(&self, key: BrickKey) -> f32 {
        match self.desired.camera {
            Some(c) => {
                isovox_proto::lod::tile_distance(&self.layout, self.info.voxel_scale, key, c)
            }
            None => 0.0,
        }
    }

    /// The desired set for the current camera; tiles that leave it are dropped, mesh tiles
    /// whose face mask changed are stitched again.
    fn update_desired(&mut self) {
        let new = match (self.desired.camera, self.kind) {
            (Some(c), TileKind::Bricks) => select_tiles(&self.info, c, &self.radii),
            (Some(c), TileKind::Meshes { .. }) => select_stitched_tiles(&self.info, c, &self.radii),
            (None, _) => Vec::new(),
        };
        if matches!(self.kind, TileKind::Meshes { .. }) {
            let masks = isovox_proto::lod::face_masks(&self.layout, &new);
            self.desired.masks = new.iter().copied().zip(masks).collect();
        }
        let keep: HashSet<BrickKey> = new.iter().copied().collect();
        let mut gone: Vec<BrickKey> = self
            .desired
            .tiles
            .keys()
            .filter(|k| !keep.contains(k))
            .copied()
            .collect();
        gone.sort();
        for key in gone {
            let Some(t) = self.desired.tiles.remove(&key) else {
                continue;
            };
            if t.ready.is_none() {
                self.desired.missing -= 1;
            }
            if t.shown {
                lock(&self.shared).resident.remove(&key);
                self.outbox.push(StreamEvent::Dropped { key });
            }
        }
        for key in new {
            let t = self.desired.tiles.entry(key).or_insert_with(|| {
                self.desired.missing += 1;
                Tile::default()
            });
            // A mesh tile whose mask changed is drawn again (its tile from the cache, the
            // strips of its new faces from the cache or a request; the old drawing stays until
            // then).
            let mask = self.desired.masks.get(&key).copied().unwrap_or(0);
            if let (Some(_), Some((_, drawn))) = (t.ready, &t.drawn) {
                if *drawn != mask {
                    t.ready = None;
                    self.desired.missing += 1;
                }
            }
        }
        self.scheduler.replan_needed = true;
    }

    /// The iso value mesh tiles are asked at (the server's default when `None`).
    fn mesh_iso(&self) -> Option<f32> {
        match self.kind {
            TileKind::Meshes { iso } => iso,
            TileKind::Bricks => None,
        }
    }

    /// The grid region that brings `brick`'s hash: a designated one, or its chunk.
    fn source_of(&self, brick: BrickKey) -> JobKey {
        if let Some(&s) = self.book.sources.get(&brick) {
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
        let reads = isovox_proto::tile::mesh_tile_reads(&self.layout, key);
        self.content_of("isovox mesh tile with moves", key, None, iso, &reads)
    }

    /// The content key of the strip of face `face` of mesh tile `key`, or the input bricks
    /// whose hashes are unknown.
    fn strip_content(
        &self,
        key: BrickKey,
        face: u8,
        iso: Option<f32>,
    ) -> Result<u64, Vec<BrickKey>> {
        let reads = isovox_proto::tile::strip_reads(&self.layout, key, usize::from(face));
        self.content_of("isovox transition strip", key, Some(face), iso, &reads)
    }

    /// A content key over what a tile or strip depends on: `what`, the tile, the face, the iso
    /// value, the volume's shape and the hashes of the bricks of `reads`.
    fn content_of(
        &self,
        what: &str,
        key: BrickKey,
        face: Option<u8>,
        iso: Option<f32>,
        reads: &[(u8, isovox_proto::tile::GridBox)],
    ) -> Result<u64, Vec<BrickKey>> {
        let mut h = DefaultHasher::new();
        what.hash(&mut h);
        key.hash(&mut h);
        face.hash(&mut h);
        iso.map(f32::to_bits).hash(&mut h);
        self.info.brick.hash(&mut h);
        self.layout.voxel_type().bytes().hash(&mut h);
        self.info.voxel_scale.map(f32::to_bits).hash(&mut h);
        let mut unknown = Vec::new();
        for &(level, (lo, hi)) in reads {
            let g = self.layout.grid(level).map(i64::from);
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let c = [x, y, z];
                        if (0..3).any(|a| c[a] < 0 || c[a] >= g[a]) {
                            0u8.hash(&mut h);
                            continue;
                        }
                        let b = BrickKey {
                            level,
                            x: x as u32,
                            y: y as u32,
                            z: z as u32,
                        };
                        match self.book.hashes.get(&b) {
                            Some(v) => (1u8, *v).hash(&mut h),
                            None => unknown.push(b),
                        }
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

    /// The bricks a desired mesh tile's drawing reads: its own, and those of the strips of the
    /// faces in its mask.
    fn drawing_reads(&self, key: BrickKey) -> Vec<(u8, isovox_proto::tile::GridBox)> {
        let mask = self.desired.masks.get(&key).copied().unwrap_or(0);
        let mut reads = isovox_proto::tile::mesh_tile_reads(&self.layout, key);
        for face in (0..6).filter(|f| mask >> f & 1 == 1) {
            reads.extend(isovox_proto::tile::strip_reads(&self.layout, key, face));
        }
        reads
    }

    /// Works out what every desired tile without current content needs, makes cached ones
    /// ready, aborts requests nobody needs, and queues the rest nearest first.
    fn replan(&mut self) {
        self.scheduler.replan_needed = false;
        self.scheduler.waiting.clear();
        self.scheduler.mesh_keys.clear();
        self.scheduler.strip_keys.clear();
        let mut needed: HashMap<JobKey, f32> = HashMap::new();
        let need = |needed: &mut HashMap<JobKey, f32>, job: JobKey, d: f32| {
            let e = needed.entry(job).or_insert(d);
            *e = e.min(d);
        };
        let mut from_cache = Vec::new();
        let mut drawings = Vec::new();
        let missing: Vec<BrickKey> = self
            .desired
            .tiles
            .iter()
            .filter(|(_, t)| t.ready.is_none())
            .map(|(k, _)| *k)
            .collect();
        for key in missing {
            let d = self.distance(key);
            match self.kind {
                TileKind::Bricks => match self.book.hashes.get(&key) {
                    Some(&h) if self.cache.contains(h) => from_cache.push((key, h)),
                    Some(&h) => {
                        need(&mut needed, JobKey::Blob(h), d);
                        self.scheduler.waiting.entry(h).or_default().push(key);
                    }
                    None => need(&mut needed, self.source_of(key), d),
                },
                TileKind::Meshes { iso } => {
                    // The tile and the strips of its mask's faces, each from the cache or a
                    // request; drawn once all are there.
                    let mask = self.desired.masks.get(&key).copied().unwrap_or(0);
                    let mut unknown = Vec::new();
                    let content = match self.mesh_content(key, iso) {
                        Ok(c) => Some(c),
                        Err(u) => {
                            unknown.extend(u);
                            None
                        }
                    };
                    let mut strips = [None; 6];
                    for face in (0..6u8).filter(|f| mask >> f & 1 == 1) {
                        match self.strip_content(key, face, iso) {
                            Ok(c) => strips[usize::from(face)] = Some(c),
                            Err(u) => unknown.extend(u),
                        }
                    }
                    let (Some(content), true) = (content, unknown.is_empty()) else {
                        for b in unknown {
                            need(&mut needed, self.source_of(b), d);
                        }
                        continue;
                    };
                    let mut complete = true;
                    if !self.cache.contains(content) {
                        complete = false;
                        need(&mut needed, JobKey::Mesh(key), d);
                        self.scheduler.waiting.entry(content).or_default().push(key);
                        self.scheduler.mesh_keys.insert(key, content);
                    }
                    for (face, strip) in strips.iter().enumerate() {
                        let Some(strip) = *strip else { continue };
                        if !self.cache.contains(strip) {
                            complete = false;
                            let job = JobKey::Strip(key, face as u8);
                            need(&mut needed, job, d);
                            self.scheduler.waiting.entry(strip).or_default().push(key);
                            self.scheduler.strip_keys.insert((key, face as u8), strip);
                        }
                    }
                    if complete {
                        drawings.push((key, content, strips));
                    }
                }
            }
        }
        for (key, content) in from_cache {
            if let Some(data) = self.cache.get(content) {
                self.stats.hits += 1;
                self.mark_ready(key, content, data);
            }
        }
        for (key, content, strips) in drawings {
            self.draw(key, content, strips);
        }
        let unneeded: Vec<JobKey> = self
            .scheduler
            .running
            .keys()
            .filter(|k| !needed.contains_key(k))
            .copied()
            .collect();
        for job in unneeded {
            self.abort(job, true);
        }
        self.scheduler
            .failures
            .retain(|k, _| needed.contains_key(k));
        let now = Instant::now();
        self.scheduler.retry_at = None;
        let mut queue = Vec::with_capacity(needed.len());
        for (job, d) in needed {
            if self.scheduler.running.contains_key(&job) {
                continue;
            }
            if let Some(f) = self
                .scheduler
                .failures
                .get(&job)
                .filter(|f| f.retry_at > now)
            {
                self.scheduler.retry_at = Some(
                    self.scheduler
                        .retry_at
                        .map_or(f.retry_at, |r| r.min(f.retry_at)),
                );
                continue;
            }
            queue.push((d, job));
        }
        queue.sort_by(|a, b| b.0.total_cmp(&a.0));
        self.scheduler.queue = queue;
    }

    /// Starts queued requests up to the concurrency bound.
    fn fill(&mut self) {
        let limit = lock_limit(&self.scheduler.limit).get();
        while self.scheduler.running.len() < limit {
            let Some((_, job)) = self.scheduler.queue.pop() else {
                break;
            };
            if self.scheduler.running.contains_key(&job) {
                continue;
            }
            let still_needed = match job {
                JobKey::Region { .. } => true,
                JobKey::Blob(h) => self.scheduler.waiting.contains_key(&h),
                JobKey::Mesh(k) => {
                    self.scheduler.mesh_keys.contains_key(&k)
                        && self
                            .desired
                            .tiles
                            .get(&k)
                            .is_some_and(|t| t.ready.is_none())
                }
                JobKey::Strip(k, f) => {
                    self.scheduler.strip_keys.contains_key(&(k, f))
                        && self
                            .desired
                            .tiles
                            .get(&k)
                            .is_some_and(|t| t.ready.is_none())
                }
            };
            if still_needed {
                self.start(job);
            }
        }
    }

    fn start(&mut self, job: JobKey) {
        let id = self.scheduler.next_id;
        self.scheduler.next_id += 1;
        let pacer = Pacer {
            started: Instant::now(),
            limit: self.scheduler.limit.clone(),
            next: self.client.observer(),
        };
        let client = self.client.clone().with_observer(Arc::new(pacer));
        let name = self.name.clone();
        let version = Some(self.version);
        let abort = match job {
            JobKey::Region { level, min, max } => {
                for z in min[2]..max[2] {
                    for y in min[1]..max[1] {
                        for x in min[0]..max[0] {
                            let b = BrickKey { level, x, y, z };
                            if !self.book.hashes.contains_key(&b) {
                                self.book.sources.entry(b).or_insert(job);
                            }
                        }
                    }
                }
                self.scheduler.jobs.spawn(async move {
                    let r = client
                        .level_grid(&name, level, Some((min, max)), version)
                        .await;
                    (id, job, Output::Region(r))
                })
            }
            JobKey::Blob(h) => self.scheduler.jobs.spawn(async move {
                let r = client.blob(&name, h).await;
                (id, job, Output::Blob(r))
            }),
            JobKey::Mesh(key) => {
                let content = self
                    .scheduler
                    .mesh_keys
                    .get(&key)
                    .copied()
                    .unwrap_or_default();
                let iso = self.mesh_iso();
                self.scheduler.jobs.spawn(async move {
                    let r = client.mesh_tile(&name, key, iso, version).await;
                    (id, job, Output::Mesh(content, r))
                })
            }
            JobKey::Strip(key, face) => {
                let content = self
                    .scheduler
                    .strip_keys
                    .get(&(key, face))
                    .copied()
                    .unwrap_or_default();
                let iso = self.mesh_iso();
                self.scheduler.jobs.spawn(async move {
                    let r = client
                        .mesh_strip(&name, key, usize::from(face), iso, version)
                        .await;
                    (id, job, Output::Strip(content, r))
                })
            }
        };
        self.scheduler.running.insert(job, Running { id, abort });
        self.stats.requests += 1;
    }

    /// Aborts a running request; with `forget`, the bricks it was to bring lose it as their
    /// source (nobody needs them now).
    fn abort(&mut self, job: JobKey, forget: bool) {
        let Some(r) = self.scheduler.running.remove(&job) else {
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
                    if self.book.sources.get(&b) == Some(&job) {
                        self.book.sources.remove(&b);
                    }
                }
            }
        }
    }

    fn mark_ready(&mut self, key: BrickKey, content: u64, data: Content) {
        let data = match data {
            Content::Brick(b) => TileData::Brick(b),
            // Mesh tiles and strips are delivered through `draw`.
            Content::Mesh(_) | Content::Strip(_) => return,
        };
        self.deliver(key, content, data);
    }

    /// Delivers mesh tile `key` drawn with its mask: its content (key `content`) and the strips
    /// of its mask's faces (content keys `strips`), all in the cache. Delivered again only when
    /// the drawing changed (another mask, another strip).
    fn draw(&mut self, key: BrickKey, content: u64, strips: [Option<u64>; 6]) {
        let Some(Content::Mesh(tile)) = self.cache.get(content) else {
            return;
        };
        let mut parts: [Option<Arc<Mesh>>; 6] = Default::default();
        for (face, strip) in strips.iter().enumerate() {
            if let Some(c) = *strip {
                match self.cache.get(c) {
                    Some(Content::Strip(s)) => parts[face] = Some(s),
                    _ => return,
                }
            }
        }
        let mask = self.desired.masks.get(&key).copied().unwrap_or(0);
        let mut h = DefaultHasher::new();
        (content, mask, strips).hash(&mut h);
        let drawn_key = h.finish();
        let Some(t) = self.desired.tiles.get_mut(&key) else {
            return;
        };
        if t.drawn_key == Some(drawn_key) && t.ready.is_none() && t.shown && !t.stale {
            // The same drawing as delivered (a mask that changed and changed back).
            t.ready = Some(content);
            self.desired.missing -= 1;
            return;
        }
        let mut mesh = Mesh::default();
        let drawn_strips = std::array::from_fn(|f| parts[f].as_deref());
        isovox_proto::mesh::stitch(&tile, mask, drawn_strips, &mut mesh);
        t.drawn = Some((tile.clone(), mask));
        t.drawn_key = Some(drawn_key);
        let data = TileData::Mesh(MeshTile {
            tile,
            mask,
            strips: parts,
            mesh: Arc::new(mesh),
        });
        self.deliver(key, content, data);
    }

    fn deliver(&mut self, key: BrickKey, content: u64, data: TileData) {
        let Some(t) = self.desired.tiles.get_mut(&key) else {
            return;
        };
        if t.ready.is_none() {
            self.desired.missing -= 1;
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
        let attempts = self.scheduler.failures.get(&job).map_or(0, |f| f.attempts) + 1;
        let delay = RETRY_MIN
            .saturating_mul(1 << (attempts - 1).min(16))
            .min(RETRY_MAX);
        let retry_at = Instant::now() + delay;
        self.scheduler
            .failures
            .insert(job, Failure { attempts, retry_at });
        self.scheduler.retry_at = Some(
            self.scheduler
                .retry_at
                .map_or(retry_at, |r| r.min(retry_at)),
        );
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
                    self.scheduler.running.retain(|_, r| r.abort.id() != task);
                    self.scheduler.replan_needed = true;
                }
                return;
            }
        };
        match self.scheduler.running.get(&job) {
            Some(r) if r.id == id => {
                self.scheduler.running.remove(&job);
            }
            _ => return, // aborted (or superseded) before it finished
        }
        match output {
            Output::Region(result) => self.on_region(job, result),
            Output::Blob(result) => self.on_blob(job, result),
            Output::Mesh(content, result) => self.on_mesh(job, content, result),
            Output::Strip(content, result) => self.on_strip(job, content, result),
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
                            self.book.hashes.insert(b, h);
                            self.book.sources.remove(&b);
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
        self.scheduler.failures.remove(&job);
        self.scheduler.replan_needed = true;
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
        self.scheduler.failures.remove(&job);
        self.stats.bytes += bytes.len() as u64;
        self.stats.misses += 1;
        let data = Content::Brick(bytes);
        self.cache.put(h, data.clone(), self.layout.brick_bytes());
        let mut first = true;
        for key in self.scheduler.waiting.remove(&h).unwrap_or_default() {
            let current = self
                .desired
                .tiles
                .get(&key)
                .is_some_and(|t| t.ready.is_none())
                && self.book.hashes.get(&key) == Some(&h);
            if current {
                if !first {
                    self.stats.hits += 1;
                }
                first = false;
                self.mark_ready(key, h, data.clone());
            }
        }
    }

    fn on_mesh(&mut self, job: JobKey, content: u64, result: Result<TileMesh, ClientError>) {
        let JobKey::Mesh(key) = job else {
            return;
        };
        let tile = match result {
            Ok(t) => t,
            Err(e) => {
                self.fail(job, Some(key), format!("mesh tile {key}: {e}"));
                return;
            }
        };
        self.scheduler.failures.remove(&job);
        self.stats.bytes += isovox_proto::mesh::encode_tile(&tile).len() as u64;
        self.stats.misses += 1;
        let size = tile_size(&tile);
        self.cache.put(content, Content::Mesh(Arc::new(tile)), size);
        self.on_arrival(content);
    }

    fn on_strip(&mut self, job: JobKey, content: u64, result: Result<Mesh, ClientError>) {
        let JobKey::Strip(key, face) = job else {
            return;
        };
        let strip = match result {
            Ok(s) => s,
            Err(e) => {
                let name = isovox_proto::mesh::FACE_NAMES[usize::from(face) % 6];
                self.fail(
                    job,
                    Some(key),
                    format!("strip {name} of mesh tile {key}: {e}"),
                );
                return;
            }
        };
        self.scheduler.failures.remove(&job);
        self.stats.bytes += isovox_proto::mesh::encode_compact(&strip).len() as u64;
        let size = mesh_size(&strip) + 64;
        self.cache
            .put(content, Content::Strip(Arc::new(strip)), size);
        self.on_arrival(content);
    }

    /// A mesh tile or strip with content key `content` is in the cache: the tiles waiting for
    /// it are drawn once all their parts are there (the next plan finds them complete).
    fn on_arrival(&mut self, content: u64) {
        if self.scheduler.waiting.remove(&content).is_some() {
            self.scheduler.replan_needed = true;
        }
    }

    fn on_feed(&mut self, msg: FeedMsg) {
        match msg {
            FeedMsg::Commits(commits) => {
                for ev in &commits {
                    self.apply_commit(ev);
                }
            }
            FeedMsg::Reload(info) => self.reload(info),
            FeedMsg::Error(error) => self.outbox.push(StreamEvent::Error { key: None, error }),
        }
    }

    /// Marks a delivered tile stale (emitting `Stale`) and any desired tile as needing content.
    fn invalidate(&mut self, key: BrickKey, version: u64) {
        let Some(t) = self.desired.tiles.get_mut(&key) else {
            return;
        };
        if t.shown {
            if !t.stale {
                t.stale = true;
                self.stats.stale_refetches += 1;
            }
            self.outbox.push(StreamEvent::Stale { key, version });
        }
        if t.ready.take().is_some() {
            self.desired.missing += 1;
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
            // Mesh tiles read bricks of their level, and the strips of their mask's faces those
            // of the next coarser one too.
            let readers: Vec<(BrickKey, Vec<(u8, isovox_proto::tile::GridBox)>)> = match self.kind {
                TileKind::Bricks => Vec::new(),
                TileKind::Meshes { .. } => self
                    .desired
                    .tiles
                    .keys()
                    .filter(|t| t.level == level || t.level + 1 == level)
                    .map(|&t| (t, self.drawing_reads(t)))
                    .collect(),
            };
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
                self.book.hashes.remove(&b);
                self.book.sources.remove(&b);
                let mut is_read = false;
                match self.kind {
                    TileKind::Bricks => {
                        if self.desired.tiles.contains_key(&b) {
                            affected.insert(b);
                            is_read = true;
                        }
                    }
                    TileKind::Meshes { .. } => {
                        let p = p.map(i64::from);
                        for (t, reads) in &readers {
                            let reads_p = reads.iter().any(|&(l, (lo, hi))| {
                                l == level && (0..3).all(|a| lo[a] <= p[a] && p[a] <= hi[a])
                            });
                            if reads_p {
                                affected.insert(*t);
                                is_read = true;
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
                .scheduler
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
                    self.book.sources.insert(b, region);
                }
            }
            for key in affected {
                if let Some(r) = self.scheduler.running.remove(&JobKey::Mesh(key)) {
                    r.abort.abort();
                }
                for face in 0..6 {
                    if let Some(r) = self.scheduler.running.remove(&JobKey::Strip(key, face)) {
                        r.abort.abort();
                    }
                }
                self.invalidate(key, ev.version);
            }
        }
        self.version = ev.version;
        self.outbox.push(StreamEvent::Version {
            version: ev.version,
        });
        self.scheduler.replan_needed = true;
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
        let jobs: Vec<JobKey> = self.scheduler.running.keys().copied().collect();
        for job in jobs {
            self.abort(job, true);
        }
        self.book.hashes.clear();
        self.book.sources.clear();
        self.scheduler.failures.clear();
        self.scheduler.queue.clear();
        self.layout = layout;
        self.version = info.version;
        self.info = info;
        self.update_desired();
        let mut keys: Vec<BrickKey> = self.desired.tiles.keys().copied().collect();
        keys.sort();
        for key in keys {
            self.invalidate(key, self.version);
        }
        self.outbox.push(StreamEvent::Version {
            version: self.version,
        });
        self.scheduler.replan_needed = true;
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
                requests: self.stats.requests,
                bytes: self.stats.bytes,
                cache_hits: self.stats.hits,
                cache_misses: self.stats.misses,
                in_flight: self.scheduler.running.len(),
                in_flight_limit: lock_limit(&self.scheduler.limit).get(),
                resident,
                cache_bytes: self.cache.bytes,
                version: self.version,
                stale_refetches: self.stats.stale_refetches,
            };
        }
        let now = Status {
            camera_seq: self.desired.camera_seq,
            idle: self.desired.missing == 0,
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
