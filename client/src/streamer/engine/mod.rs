//! The streamer's task: an [`Engine`] made of its parts (the desired set, the hash book, the
//! scheduler, the statistics) and the content cache, driven by the camera, finished requests,
//! the change feed and retry timers. Each part keeps its own state with its own methods; the
//! engine coordinates them and reports what happens.
//!
//! Layout:
//! - this file: the [`Engine`] and its loop.
//! - [`desired`]: the desired set.
//! - [`book`]: the hash book and the content keys computed from it.
//! - [`scheduler`]: the plan, the requests in flight, failures and retries.
//! - [`cache`]: the content cache.
//! - [`feed`]: the change-feed follower.

mod book;
mod cache;
mod descent;
mod desired;
mod feed;
mod scheduler;

pub(super) use feed::{follow, FeedMsg};

use super::*;
use crate::client::Brick;
use book::{HashBook, Shape};
use cache::{Content, Lru};
use descent::{side, Decision, Side};
use desired::Desired;
use scheduler::{JobKey, Output, Scheduler, TilePlan, Wait};

/// The engine's maps and sets, keyed by tiles, jobs and content hashes the client makes
/// itself: foldhash rather than the standard library's SipHash, whose resistance to chosen
/// keys buys nothing here and whose hashing was a third of a streamer's CPU (the desired set is
/// rebuilt on every camera move: `isovox-load --descent`).
type FastMap<K, V> = std::collections::HashMap<K, V, foldhash::fast::RandomState>;
/// See [`FastMap`].
type FastSet<K> = std::collections::HashSet<K, foldhash::fast::RandomState>;

/// A hasher for content keys (of tiles, strips and drawings): the same key for the same inputs
/// in every engine of a process (a fixed seed), fast over the dozens of brick hashes a tile
/// reads (SipHash took 6% of a 50-viewer load tester's time). Keys name content the engine
/// fetched itself, so a keyed hash against crafted collisions buys nothing here.
fn content_hasher() -> foldhash::quality::FoldHasher<'static> {
    use std::hash::BuildHasher;
    foldhash::quality::FixedState::with_seed(0x150f_0c5e_ed00_c0de).build_hasher()
}

/// The task's state: what it serves, and its four parts.
pub(super) struct Engine {
    client: Client,
    name: String,
    kind: TileKind,
    info: VolumeInfo,
    layout: VolumeLayout,
    radii: Vec<f32>,
    /// The iso value the descent skips surfaceless tiles at; `None`: no descent, every desired
    /// tile's grid entries are fetched (see [`descent`]).
    descent: Option<f32>,
    /// The iso value tiles are drawn at: the meshes' own, or the server's default.
    iso: f32,
    /// Without the descent, mesh tiles whose bricks' ranges rule out the surface are skipped.
    skip_empty: bool,
    /// Desired tiles that were complete (delivered, or skipped) until a commit invalidated
    /// them, and have not been complete since: the grid regions they need are counted as caused
    /// by edits.
    edited: FastSet<BrickKey>,
    /// The grid regions of the current plan that such tiles need.
    edit_regions: FastSet<JobKey>,
    /// Tiles the descent could not decide yet, with the bricks whose grid entries it waits for.
    /// Until one of those is learnt the decision stays the same (what else is learnt meanwhile
    /// only narrows bounds already on one side), so planning reuses it instead of walking every
    /// tile's bricks again on each answer. Cleared by commits, which change ranges.
    undecided: FastMap<BrickKey, Vec<BrickKey>>,
    /// The plans of waiting mesh tiles, kept while they hold (see [`Engine::replan`]). Cleared
    /// by commits, which change hashes.
    plans: FastMap<BrickKey, KeptPlan>,
    /// When the last replan ended.
    last_replan: Instant,
    /// The newest camera, and whether it is newer than the one selected for.
    camera_next: CameraMsg,
    camera_waiting: bool,
    /// When the last selection was made (see `Engine::run`).
    last_select: Instant,
    /// How far the camera moves before it is selected again without waiting to settle (see
    /// [`Engine::select_at`]): an eighth of the finest detail radius.
    reselect_distance: f32,
    /// Replans so far (see [`KeptPlan::checked`]).
    replans: u64,
    /// The desired tiles without current content in screen order (see
    /// [`Engine::screen_order`]), with their order keys: the order tiles are planned in. Kept
    /// from one replan to the next, each dropping the tiles that have content by then, until
    /// the camera moves or a commit makes tiles need content again (`None`: to be sorted again).
    in_order: Option<Vec<(f32, BrickKey)>>,
    /// The last replan stopped at the window: a tile that arrives asks for the next replan.
    plan_stopped_early: bool,
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

/// Statistics: requests, bytes, cache hits and misses, refetches of stale tiles.
#[derive(Debug, Default, Clone, Copy)]
struct Counters {
    requests: u64,
    bytes: u64,
    hits: u64,
    misses: u64,
    stale_refetches: u64,
    grid_requests: u64,
    grid_aborted: u64,
    edit_grid_requests: u64,
    skipped: u64,
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
        // The descent's iso value: the meshes' own, or the server's default, S - 0.5, which
        // bricks are drawn at too.
        let iso = match config.kind {
            TileKind::Meshes { iso: Some(iso) } => iso,
            _ => layout.voxel_type().surface() as f32 - 0.5,
        };
        let reselect_distance = reselect_distance(&radii, &layout, info.voxel_scale);
        Engine {
            client,
            name: name.to_string(),
            kind: config.kind,
            descent: config.descent.then_some(iso),
            iso,
            skip_empty: config.skip_empty,
            edited: FastSet::default(),
            edit_regions: FastSet::default(),
            undecided: FastMap::default(),
            plans: FastMap::default(),
            last_replan: Instant::now(),
            camera_next: CameraMsg::default(),
            camera_waiting: false,
            last_select: Instant::now()
                .checked_sub(SELECT_EVERY)
                .unwrap_or_else(Instant::now),
            reselect_distance,
            replans: 0,
            in_order: None,
            plan_stopped_early: false,
            layout,
            radii,
            version: info.version,
            outbox: vec![StreamEvent::Version {
                version: info.version,
            }],
            info,
            desired: Desired::default(),
            // (4x4x4 regions under the descent carry fewer unread entries, but on a 2048^3
            // world the server answered them at a third of the rate: docs/benchmarks.md.)
            book: HashBook::new(CHUNK),
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
            // A replan visits every waiting tile. Answers and camera moves each ask for one,
            // hundreds a second, while what the last plan queued is still being started: so
            // it is put off (at most REPLAN_EVERY) while the queue has work to start.
            let mut replan_at = None;
            if self.scheduler.replan_needed {
                let due = self.last_replan + REPLAN_EVERY;
                if !self.scheduler.has_queued() || Instant::now() >= due {
                    self.replan();
                    self.last_replan = Instant::now();
                } else {
                    replan_at = Some(due);
                }
            }
            self.fill();
            self.flush().await;
            let retry_at = self.scheduler.retry_at;
            let select_at = self.select_at();
            tokio::select! {
                () = sleep_until(replan_at) => {}
                () = sleep_until(select_at) => self.select(),
                // A shutdown, or the Streamer dropped.
                _ = &mut shutdown => break,
                changed = camera_rx.changed() => {
                    if changed.is_err() {
                        break;
                    }
                    let c = *camera_rx.borrow_and_update();
                    self.camera_waiting = true;
                    self.camera_next = c;
                    if self.select_at().is_some_and(|at| Instant::now() >= at) {
                        self.select();
                    }
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
                () = sleep_until(retry_at) => self.scheduler.retry_now(),
            }
        }
        if let Some(f) = follower {
            f.abort();
        }
        self.scheduler.jobs.abort_all();
    }

    /// When the newest camera is to be selected, if it is not yet.
    ///
    /// Selecting the tiles for a camera (thousands of them, balanced and masked) is the
    /// streamer's largest cost once planning is bounded, and cameras move every frame. A
    /// selection changes only where tiles cross the detail radii, so a move shorter than an
    /// eighth of the finest radius (`reselect_distance`) changes what a tile's distance says
    /// of its screen error by at most an eighth: such moves are taken once the camera has
    /// settled (SELECT_SETTLE after the last selection), longer ones at most every
    /// SELECT_EVERY (the newest position then).
    fn select_at(&self) -> Option<Instant> {
        if !self.camera_waiting {
            return None;
        }
        let moved_far = match (self.desired.camera, self.camera_next.position) {
            (Some(a), Some(b)) => {
                let d2: f32 = (0..3).map(|i| (a[i] - b[i]) * (a[i] - b[i])).sum();
                d2 >= self.reselect_distance * self.reselect_distance
            }
            _ => true,
        };
        let wait = if moved_far {
            SELECT_EVERY
        } else {
            SELECT_SETTLE
        };
        Some(self.last_select + wait)
    }

    /// Takes the newest camera: selects its tiles.
    fn select(&mut self) {
        self.camera_waiting = false;
        self.last_select = Instant::now();
        self.desired.camera = self.camera_next.position;
        self.desired.camera_seq = self.camera_next.seq;
        self.update_desired();
    }

    /// Where tile `key` comes in the order tiles are planned and requests started: its
    /// distance from the camera over its edge length, which is how small it shows on screen.
    ///
    /// The detail radii double per level as the tiles' edges do, so every selected tile of
    /// every level shows about as large as any other, and this order interleaves the levels:
    /// the coarse tiles at the near edge of their ring come as early as the fine tiles near
    /// the camera. Nearest first, a viewer above a large world planned the hundreds of fine
    /// air tiles around its camera before any coarse tile that holds the surface; each of
    /// those waited for a fine grid region to be skipped, and its first tile that drew came
    /// three times later (docs/benchmarks.md, "Many viewers on a large world").
    fn screen_order(&self, key: BrickKey) -> f32 {
        match self.desired.camera {
            Some(c) => {
                let d =
                    isovox_proto::lod::tile_distance(&self.layout, self.info.voxel_scale, key, c);
                d / (1u32 << key.level) as f32
            }
            None => 0.0,
        }
    }

    /// The volume's shape, as content keys describe it.
    fn shape(&self) -> Shape<'_> {
        (&self.layout, &self.info)
    }

    /// The desired set for the current camera; tiles that leave it are dropped, mesh tiles
    /// whose face mask changed are stitched again.
    fn update_desired(&mut self) {
        let scale = self.info.voxel_scale;
        let (new, masks) = match (self.desired.camera, self.kind) {
            (Some(c), TileKind::Bricks) => (
                isovox_proto::lod::adaptive_tiles(&self.layout, scale, c, &self.radii),
                None,
            ),
            (Some(c), TileKind::Meshes { .. }) => {
                let (tiles, masks) =
                    isovox_proto::lod::stitched_tiles(&self.layout, scale, c, &self.radii);
                (tiles, Some(masks))
            }
            (None, kind) => (
                Vec::new(),
                matches!(kind, TileKind::Meshes { .. }).then(Vec::new),
            ),
        };
        for key in self.desired.replace(new, masks) {
            lock(&self.shared).resident.remove(&key);
            self.outbox.push(StreamEvent::Dropped { key });
        }
        let desired = &self.desired;
        self.edited.retain(|k| desired.contains(*k));
        self.undecided.retain(|k, _| desired.contains(*k));
        self.plans.retain(|k, _| desired.contains(*k));
        self.in_order = None;
        self.scheduler.replan_needed = true;
    }

    /// The iso value mesh tiles are asked at (the server's default when `None`).
    fn mesh_iso(&self) -> Option<f32> {
        match self.kind {
            TileKind::Meshes { iso } => iso,
            TileKind::Bricks => None,
        }
    }

    /// Works out what the first desired tiles without current content (in screen order, see
    /// [`Engine::screen_order`]) need, makes cached ones ready, aborts requests nobody needs,
    /// and queues the rest in the same order.
    ///
    /// A replan runs after answers and camera moves, and a viewer of a large volume has
    /// thousands of tiles waiting (7,000 on a 2048^3 world): planning all of them each time
    /// kept 50 streamers of one process busy planning instead of reading answers. Only
    /// requests near the front of the queue can start before the next replan, so tiles are
    /// planned in order until [`PLAN_AHEAD`] of them wait for something; tiles that turn
    /// out complete (cached, or skipped for want of a surface) do not count, and the window
    /// moves on once fewer of its requests wait to start than may run (see `deliver`).
    ///
    /// Planning a tile (its content key from up to 27 bricks' hashes, its strips', the
    /// descent's bounds) costs microseconds, so a waiting mesh tile's plan is also kept and
    /// only its place in the order taken anew while it still holds: it was checked in the last
    /// replan, no request it needs has ended since, none of the content it waits for has come,
    /// and its face mask is the same (commits clear them). Tiles a commit made stale are
    /// planned afresh each time (their grid regions are counted as caused by the edit). A
    /// brick's plan is one hash lookup, cheaper than keeping it (with plans kept, viewers of
    /// bricks got their first tile later).
    fn replan(&mut self) {
        self.scheduler.replan_needed = false;
        self.scheduler.clear_plan();
        self.replans += 1;
        let ended = self.scheduler.take_ended();
        let mut needed: FastMap<JobKey, f32> = FastMap::default();
        let mut from_cache = Vec::new();
        let mut drawings = Vec::new();
        let mut skipped = Vec::new();
        self.edit_regions.clear();
        let keep_plans = matches!(self.kind, TileKind::Meshes { .. });
        // One plan's buffers for the tiles whose plan is not kept.
        let mut plan = TilePlan::default();
        let mut in_order = match self.in_order.take() {
            Some(in_order) => in_order,
            None => {
                let needing = self.desired.needing();
                let mut in_order: Vec<(f32, BrickKey)> = needing
                    .into_iter()
                    .map(|k| (self.screen_order(k), k))
                    .collect();
                in_order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                in_order
            }
        };
        let mut waiting_tiles = 0;
        let mut partial = false;
        // Tiles that have content are dropped from `in_order` as the loop passes them (those
        // after where it stops stay): once most tiles are complete, a replan no longer walks
        // past thousands of them.
        let mut retained = 0;
        let mut next = 0;
        while next < in_order.len() {
            let (d, key) = in_order[next];
            if !self.desired.needs(key) {
                next += 1;
                continue;
            }
            if waiting_tiles == PLAN_AHEAD {
                partial = true;
                break;
            }
            in_order[retained] = (d, key);
            retained += 1;
            next += 1;
            let edited = self.edited.contains(&key);
            let mask = self.desired.mask(key);
            if let Some(kept) = self.plans.get_mut(&key) {
                if !edited
                    && kept.mask == mask
                    && kept.checked + 1 == self.replans
                    && kept.plan.holds(&ended, &self.cache)
                {
                    kept.checked = self.replans;
                    for &job in &kept.plan.jobs {
                        need(&mut needed, job, d);
                    }
                    self.scheduler.register(key, &kept.plan.waits);
                    waiting_tiles += 1;
                    continue;
                }
            }
            plan.clear();
            let planned = self.plan_tile(key, &mut plan);
            for &job in &plan.jobs {
                // The grid regions a tile a commit made stale needs are caused by the edit.
                if edited && matches!(job, JobKey::Region { .. }) {
                    self.edit_regions.insert(job);
                }
                need(&mut needed, job, d);
            }
            self.scheduler.register(key, &plan.waits);
            match planned {
                Plan::Skip => skipped.push(key),
                Plan::Drawing(drawing) => drawings.push(drawing),
                Plan::Cached(h) => from_cache.push((key, h)),
                Plan::Waiting => waiting_tiles += 1,
            }
            if keep_plans && matches!(planned, Plan::Waiting) && !edited {
                let plan = std::mem::take(&mut plan);
                let checked = self.replans;
                self.plans.insert(
                    key,
                    KeptPlan {
                        mask,
                        plan,
                        checked,
                    },
                );
            } else {
                self.plans.remove(&key);
            }
        }
        in_order.copy_within(next.., retained);
        in_order.truncate(retained + (in_order.len() - next));
        self.in_order = Some(in_order);
        self.plan_stopped_early = partial;
        for key in skipped {
            self.stats.skipped += 1;
            self.edited.remove(&key);
            if self.desired.skip(key) {
                lock(&self.shared).resident.remove(&key);
                self.outbox.push(StreamEvent::Dropped { key });
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
        for job in self.scheduler.unneeded(&needed) {
            // Tiles beyond the window may need a running grid region or brick, and a tile's
            // own requests while it is desired: left to finish (their answers are cached).
            let beyond_window = partial
                && match job {
                    JobKey::Mesh(k) | JobKey::Strip(k, _) | JobKey::Brick(k) => {
                        self.desired.needs(k)
                    }
                    JobKey::Region { .. } | JobKey::Blob(_) => true,
                };
            if !beyond_window {
                self.abort(job, true);
            }
        }
        self.scheduler.queue_needed(needed);
    }

    /// Plans desired tile `key` (without current content): skipped when the descent (without
    /// it, for a mesh tile, its bricks' known ranges) finds no surface in it, else from the
    /// cache or the requests and content it waits for, recorded in `plan`.
    fn plan_tile(&mut self, key: BrickKey, plan: &mut TilePlan) -> Plan {
        if let Some(iso) = self.descent {
            if let Some(waiting) = self.undecided.get(&key) {
                if waiting.iter().all(|&u| self.book.range(u).is_none()) {
                    for &u in waiting {
                        plan.jobs.push(self.book.source_of(&self.layout, u));
                    }
                    return Plan::Waiting;
                }
            }
            self.undecided.remove(&key);
            let reads = match self.kind {
                // A brick is wanted where its mesh tile would have a surface: the surface
                // between two bricks is drawn from both.
                TileKind::Bricks => isovox_proto::tile::mesh_tile_reads(&self.layout, key),
                TileKind::Meshes { .. } => self.desired.drawing_reads(&self.layout, key),
            };
            match self.book.decide(&self.layout, &reads, iso) {
                Decision::Empty => return Plan::Skip,
                Decision::Unknown(bricks) => {
                    for &b in &bricks {
                        plan.jobs.push(self.book.source_of(&self.layout, b));
                        // The finer levels whose whole grid is one region are asked for at
                        // once, not one after the other as the descent reaches them: a few
                        // hundred entries against as many round trips before the first tile.
                        for level in (0..b.level).rev() {
                            let g = self.layout.grid(level);
                            if g.iter().any(|&n| n > self.book.chunk()) {
                                break;
                            }
                            let whole = JobKey::Region {
                                level,
                                min: [0; 3],
                                max: g,
                            };
                            if self
                                .book
                                .range(BrickKey {
                                    level,
                                    x: 0,
                                    y: 0,
                                    z: 0,
                                })
                                .is_none()
                            {
                                plan.jobs.push(whole);
                            }
                        }
                    }
                    self.undecided.insert(key, bricks);
                    return Plan::Waiting;
                }
                Decision::Surface => {}
            }
        } else if self.skip_empty
            && matches!(self.kind, TileKind::Meshes { .. })
            && self
                .book
                .range(key)
                .is_some_and(|r| side(r, self.iso) != Side::Both)
        {
            // Without the descent every desired tile's grid entries are asked for; a mesh tile
            // whose bricks' ranges rule out the surface has nothing to draw and is skipped, as
            // the descent would (most of a large world: ~95% of the tiles 50 load viewers of
            // a 2048^3 world wanted, each a request answered with an empty mesh). Its own
            // brick first: one lookup settles most tiles (unknown yet, or holding the surface).
            let reads = self.desired.drawing_reads(&self.layout, key);
            if self
                .book
                .ranges_rule_out_surface(&self.layout, &reads, self.iso)
            {
                return Plan::Skip;
            }
        }
        match self.kind {
            TileKind::Bricks => match self.book.hash(key) {
                Some(h) if self.cache.contains(h) => Plan::Cached(h),
                Some(h) => {
                    plan.jobs.push(JobKey::Blob(h));
                    plan.waits.push(Wait::Content(h));
                    Plan::Waiting
                }
                None if self.at_version(key, &[key]) => {
                    plan.jobs.push(JobKey::Brick(key));
                    Plan::Waiting
                }
                None => {
                    plan.jobs.push(self.book.source_of(&self.layout, key));
                    Plan::Waiting
                }
            },
            TileKind::Meshes { iso } => match self.plan_mesh(key, iso, plan) {
                Some(drawing) => Plan::Drawing(drawing),
                None => Plan::Waiting,
            },
        }
    }

    /// Whether tile `key`, whose inputs `unknown` have unknown hashes, is asked for at the
    /// engine's version rather than after their grid regions: a commit made it wanted, and
    /// the descent had skipped every one of them from a coarser brick's range, so their grid
    /// entries were never asked for (an edit beside them put the surface at their side). The
    /// tile at this version is an answer a cache can give; a grid region only the origin can.
    /// (Bricks a commit changed without saying what they hold now share one designated region
    /// instead, see `HashBook::bring_together`; after a reload nothing is bounded.)
    fn at_version(&self, key: BrickKey, unknown: &[BrickKey]) -> bool {
        let Some(iso) = self.descent else {
            return false;
        };
        self.edited.contains(&key)
            && unknown.iter().all(|&b| {
                !self.book.has_designated_source(b) && self.book.bound(&self.layout, b, iso).is_ok()
            })
    }

    /// Plans mesh tile `key` (at `iso`): the tile and the strips of its mask's faces, each from
    /// the cache or a request recorded in `plan`. Returns its drawing (content key and strips'
    /// content keys) when all are in the cache.
    fn plan_mesh(
        &mut self,
        key: BrickKey,
        iso: Option<f32>,
        plan: &mut TilePlan,
    ) -> Option<(BrickKey, u64, [Option<u64>; 6])> {
        let mask = self.desired.mask(key);
        let mut unknown = Vec::new();
        let mut known = |c: Result<u64, Vec<BrickKey>>| match c {
            Ok(c) => Some(c),
            Err(u) => {
                unknown.extend(u);
                None
            }
        };
        let content = known(self.book.mesh_content(self.shape(), key, iso));
        let mut strips = [None; 6];
        for face in (0..6u8).filter(|f| mask >> f & 1 == 1) {
            strips[usize::from(face)] =
                known(self.book.strip_content(self.shape(), key, face, iso));
        }
        let (content, strips) = if unknown.is_empty() {
            (content, strips)
        } else if self.at_version(key, &unknown) {
            // Keyed by this version: the parts are requested at it (see `at_version`).
            let at = |face| version_content(key, face, iso, self.version);
            let mut at_strips = [None; 6];
            for face in (0..6u8).filter(|f| mask >> f & 1 == 1) {
                at_strips[usize::from(face)] = Some(at(Some(face)));
            }
            (Some(at(None)), at_strips)
        } else {
            for b in unknown {
                plan.jobs.push(self.book.source_of(&self.layout, b));
            }
            return None;
        };
        let content = content?;
        plan.drawing = Some((content, strips));
        let mut complete = true;
        if !self.cache.contains(content) {
            complete = false;
            plan.jobs.push(JobKey::Mesh(key));
            plan.waits.push(Wait::Mesh(content));
        }
        for (face, strip) in strips.iter().enumerate() {
            let Some(strip) = *strip else { continue };
            if !self.cache.contains(strip) {
                complete = false;
                plan.jobs.push(JobKey::Strip(key, face as u8));
                plan.waits.push(Wait::Strip(face as u8, strip));
            }
        }
        complete.then_some((key, content, strips))
    }

    /// Starts queued requests up to the concurrency bound.
    fn fill(&mut self) {
        let limit = self.scheduler.limit();
        while let Some(job) = self.scheduler.next_queued(limit) {
            let still_needed = self.scheduler.planned(job)
                && match job {
                    JobKey::Mesh(k) | JobKey::Strip(k, _) | JobKey::Brick(k) => {
                        self.desired.needs(k)
                    }
                    JobKey::Region { .. } | JobKey::Blob(_) => true,
                };
            if still_needed {
                self.start(job);
            }
        }
    }

    fn start(&mut self, job: JobKey) {
        if let JobKey::Region { level, min, max } = job {
            self.book.claim(level, min, max, job);
            self.stats.grid_requests += 1;
            if self.edit_regions.contains(&job) {
                self.stats.edit_grid_requests += 1;
            }
        }
        let iso = self.mesh_iso();
        let brick_bytes = self.layout.brick_bytes();
        self.scheduler.start(
            job,
            &self.client,
            &self.name,
            self.version,
            iso,
            brick_bytes,
        );
        self.stats.requests += 1;
    }

    /// Aborts a running request; with `forget`, the bricks it was to bring lose it as their
    /// source (nobody needs them now).
    fn abort(&mut self, job: JobKey, forget: bool) {
        if !self.scheduler.abort(job) {
            return;
        }
        if matches!(job, JobKey::Region { .. }) {
            self.stats.grid_aborted += 1;
        }
        if let (true, JobKey::Region { level, min, max }) = (forget, job) {
            self.book.forget_source(level, min, max, job);
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
        let mask = self.desired.mask(key);
        let mut h = content_hasher();
        (content, mask, strips).hash(&mut h);
        let drawn_key = h.finish();
        // Not desired, or the same drawing as delivered (a mask that changed and changed back).
        if self.desired.redrawn(key, content, drawn_key) != Some(false) {
            return;
        }
        let mut mesh = Mesh::default();
        let drawn_strips = std::array::from_fn(|f| parts[f].as_deref());
        isovox_proto::mesh::stitch(&tile, mask, drawn_strips, &mut mesh);
        self.desired.set_drawn(key, tile.clone(), mask, drawn_key);
        let data = TileData::Mesh(MeshTile {
            tile,
            mask,
            strips: parts,
            mesh: Arc::new(mesh),
        });
        self.deliver(key, content, data);
    }

    fn deliver(&mut self, key: BrickKey, content: u64, data: TileData) {
        let Some(first_shown) = self.desired.deliver(key, content) else {
            return;
        };
        self.edited.remove(&key);
        if first_shown {
            lock(&self.shared).resident.insert(key);
        }
        // A tile of a window that left tiles unplanned arrived: the window moves on, once
        // fewer requests wait to start than may run at once (until then the queue has work).
        if self.plan_stopped_early && self.scheduler.queued() < self.scheduler.limit() {
            self.scheduler.replan_needed = true;
        }
        self.outbox.push(StreamEvent::Ready {
            key,
            hash: content,
            data,
            version: self.version,
        });
    }

    fn fail(&mut self, job: JobKey, key: Option<BrickKey>, error: String) {
        self.scheduler.fail(job);
        self.outbox.push(StreamEvent::Error { key, error });
    }

    fn on_join(&mut self, done: Result<(u64, JobKey, Output), JoinError>) {
        let Some((job, output)) = self.scheduler.finish(done) else {
            return;
        };
        match output {
            Output::Region(result) => self.on_region(job, result),
            Output::Blob(result) => self.on_blob(job, result),
            Output::Brick(result) => self.on_brick(job, result),
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
        let errors = self.book.learn_region(level, (min, max), &grid);
        self.outbox.extend(errors);
        self.book.forget_source(level, min, max, job);
        self.scheduler.succeeded(job);
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
        self.scheduler.succeeded(job);
        self.stats.bytes += bytes.len() as u64;
        self.stats.misses += 1;
        let data = Content::Brick(bytes);
        self.cache.put(h, data.clone(), self.layout.brick_bytes());
        let mut first = true;
        for key in self.scheduler.take_waiting(h) {
            let current = self.desired.needs(key) && self.book.hash(key) == Some(h);
            if current {
                if !first {
                    self.stats.hits += 1;
                }
                first = false;
                self.mark_ready(key, h, data.clone());
            }
        }
    }

    /// A brick fetched by position at the engine's version: its hash and value range are
    /// learnt (the descent reads the range), its voxels cached by hash and delivered.
    fn on_brick(&mut self, job: JobKey, result: Result<Option<Brick>, ClientError>) {
        let JobKey::Brick(key) = job else {
            return;
        };
        let brick = match result {
            Ok(Some(b)) if b.key == key => b,
            Ok(_) => {
                self.fail(job, Some(key), format!("brick {key}: no content"));
                return;
            }
            Err(e) => {
                self.fail(job, Some(key), format!("brick {key}: {e}"));
                return;
            }
        };
        self.scheduler.succeeded(job);
        self.stats.bytes += brick.voxels.len() as u64;
        self.stats.misses += 1;
        let range = isovox_proto::voxel::min_max(&brick.voxels, self.layout.voxel_type());
        self.book.learn(key, brick.hash, range);
        let data = Content::Brick(brick.voxels);
        self.cache
            .put(brick.hash, data.clone(), self.layout.brick_bytes());
        if self.desired.needs(key) {
            self.mark_ready(key, brick.hash, data);
        }
        self.scheduler.replan_needed = true;
    }

    fn on_mesh(
        &mut self,
        job: JobKey,
        content: u64,
        result: Result<(TileMesh, usize), ClientError>,
    ) {
        let JobKey::Mesh(key) = job else {
            return;
        };
        let (tile, encoded) = match result {
            Ok(t) => t,
            Err(e) => {
                self.fail(job, Some(key), format!("mesh tile {key}: {e}"));
                return;
            }
        };
        self.scheduler.succeeded(job);
        self.stats.bytes += encoded as u64;
        self.stats.misses += 1;
        let size = tile_size(&tile);
        self.cache.put(content, Content::Mesh(Arc::new(tile)), size);
        self.draw_waiters(content);
    }

    fn on_strip(&mut self, job: JobKey, content: u64, result: Result<(Mesh, usize), ClientError>) {
        let JobKey::Strip(key, face) = job else {
            return;
        };
        let (strip, encoded) = match result {
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
        self.scheduler.succeeded(job);
        self.stats.bytes += encoded as u64;
        let size = mesh_size(&strip) + 64;
        self.cache
            .put(content, Content::Strip(Arc::new(strip)), size);
        self.draw_waiters(content);
    }

    /// A mesh tile or strip with content key `content` is in the cache: the tiles that waited
    /// for it are drawn if nothing else is missing. Without a replan: a replan plans every tile
    /// of the window (512), and one per answer (two answers a tile, 85 tiles a second a viewer
    /// under load) took more of the load tester's CPU than anything else.
    fn draw_waiters(&mut self, content: u64) {
        let mut plan = TilePlan::default();
        for key in self.scheduler.take_waiting(content) {
            if !self.desired.needs(key) {
                continue;
            }
            // A kept plan (same mask, no commit since: commits clear them) names the drawing's
            // parts, which need no working out again.
            let cache = &self.cache;
            let kept = self
                .plans
                .get(&key)
                .filter(|k| k.mask == self.desired.mask(key))
                .and_then(|k| {
                    let came = k.plan.waits.iter().all(|w| cache.contains(w.content()));
                    k.plan.drawing.map(|d| (d, came))
                });
            if let Some(((content, strips), all_came)) = kept {
                let cached = |c: u64| self.cache.contains(c);
                if cached(content) && strips.iter().flatten().all(|&s| cached(s)) {
                    self.plans.remove(&key);
                    self.draw(key, content, strips);
                } else if all_came {
                    // What it waited for came, yet a part cached when it was planned has been
                    // evicted since: the next plan asks for it again.
                    self.scheduler.replan_needed = true;
                }
                continue;
            }
            plan.clear();
            match self.plan_tile(key, &mut plan) {
                Plan::Drawing((key, content, strips)) => {
                    self.plans.remove(&key);
                    self.draw(key, content, strips);
                }
                // It still waits: for parts already asked for, or for ones the next plan asks
                // for (this plan's requests are not queued).
                _ => self.scheduler.replan_needed = true,
            }
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
        // Only a tile that was complete (delivered, or skipped) needs content again because
        // of the commit: one still loading asks for what it asked for before.
        if self.desired.contains(key) && !self.desired.needs(key) {
            self.edited.insert(key);
            // It needs content again: the next replan sorts the tiles that do afresh.
            self.in_order = None;
        }
        let Some(newly_stale) = self.desired.invalidate(key) else {
            return;
        };
        if newly_stale {
            self.stats.stale_refetches += 1;
        }
        self.outbox.push(StreamEvent::Stale { key, version });
    }

    fn apply_commit(&mut self, ev: &ChangeEvent) {
        if ev.version <= self.version {
            return;
        }
        self.undecided.clear();
        self.plans.clear();
        // The descent's bounds on bricks under the changed ones, as they were before this
        // commit: they still hold for the bricks it did not change (see `descent`).
        let bounds_before = self
            .descent
            .map(|iso| self.book.bounds_before(&self.layout, &ev.changed, iso))
            .unwrap_or_default();
        // What the changed bricks hold now, when the event lists it (aligned with `changed`).
        let listed = (ev.bricks.len() == ev.changed.len()
            && ev
                .bricks
                .iter()
                .zip(&ev.changed)
                .all(|(b, c)| b.len() == c.len()))
        .then_some(&ev.bricks);
        for (level, changed) in ev.changed.iter().enumerate() {
            if level >= self.layout.levels() as usize || changed.is_empty() {
                continue;
            }
            let now = listed.map(|l| l[level].as_slice());
            let level = level as u8;
            let (affected, read) = self.changed_bricks(level, changed, now);
            // Grid regions in flight answer for the version before: abort those that cover a
            // changed brick (they start again at the new version if still needed).
            for job in self.scheduler.covering(level, changed) {
                self.abort(job, false);
            }
            // One region brings the new hashes of the changed bricks some desired tile reads.
            self.book.bring_together(level, read);
            for key in affected {
                self.scheduler.abort_tile(key);
                self.invalidate(key, ev.version);
            }
        }
        for (b, bound) in bounds_before {
            self.book.keep_bound(b, bound);
        }
        self.version = ev.version;
        self.outbox.push(StreamEvent::Version {
            version: ev.version,
        });
        self.scheduler.replan_needed = true;
    }

    /// Learns the new hashes of the bricks of `level` a commit `changed` from `now` (what the
    /// event says they hold, in the same order), or forgets them when it does not say; returns
    /// the desired tiles that read one of them, and those of them some desired tile reads whose
    /// new hash must come from a grid region.
    fn changed_bricks(
        &mut self,
        level: u8,
        changed: &[[u32; 3]],
        now: Option<&[LevelBrick]>,
    ) -> (BTreeSet<BrickKey>, Vec<BrickKey>) {
        let g = self.layout.grid(level);
        let mut affected = BTreeSet::new();
        let mut read = Vec::new();
        // Mesh tiles read bricks of their level, and the strips of their mask's faces those
        // of the next coarser one too.
        let readers = match self.kind {
            TileKind::Bricks => Vec::new(),
            TileKind::Meshes { .. } => self.desired.readers(&self.layout, level),
        };
        for (i, &p) in changed.iter().enumerate() {
            if (0..3).any(|a| p[a] >= g[a]) {
                continue;
            }
            let b = BrickKey {
                level,
                x: p[0],
                y: p[1],
                z: p[2],
            };
            let learnt = now.and_then(|now| now.get(i)).and_then(|e| {
                let hash = u64::from_str_radix(&e.hash, 16).ok()?;
                Some((hash, (e.min, e.max)))
            });
            match learnt {
                Some((hash, range)) => self.book.learn(b, hash, range),
                None => self.book.forget(b),
            }
            let mut is_read = false;
            match self.kind {
                TileKind::Bricks => {
                    if self.desired.contains(b) {
                        affected.insert(b);
                        is_read = true;
                    }
                    // The descent decided skipped bricks from their neighbours too (the
                    // bricks their mesh tile reads): those next to a changed brick are
                    // decided again.
                    if self.descent.is_some() {
                        for n in neighbours(b, g) {
                            if self.desired.is_skipped(n) {
                                affected.insert(n);
                            }
                        }
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
            if is_read && learnt.is_none() {
                read.push(b);
            }
        }
        (affected, read)
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
        for job in self.scheduler.running_jobs() {
            self.abort(job, true);
        }
        self.book.clear();
        self.undecided.clear();
        self.plans.clear();
        self.scheduler.reset();
        self.layout = layout;
        self.version = info.version;
        self.info = info;
        self.update_desired();
        for key in self.desired.sorted_keys() {
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
                in_flight: self.scheduler.in_flight(),
                in_flight_limit: self.scheduler.limit(),
                resident,
                cache_bytes: self.cache.bytes,
                version: self.version,
                stale_refetches: self.stats.stale_refetches,
                grid_requests: self.stats.grid_requests,
                grid_aborted: self.stats.grid_aborted,
                edit_grid_requests: self.stats.edit_grid_requests,
                skipped: self.stats.skipped,
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

/// The bricks of the same level around `b` (grid `g`), itself excluded.
fn neighbours(b: BrickKey, g: [u32; 3]) -> impl Iterator<Item = BrickKey> {
    let p = [b.x, b.y, b.z].map(i64::from);
    let g = g.map(i64::from);
    (-1..=1i64)
        .flat_map(|dz| (-1..=1i64).flat_map(move |dy| (-1..=1i64).map(move |dx| [dx, dy, dz])))
        .filter(|d| *d != [0, 0, 0])
        .map(move |d| [0, 1, 2].map(|a| p[a] + d[a]))
        .filter(move |c| (0..3).all(|a| c[a] >= 0 && c[a] < g[a]))
        .map(move |c| BrickKey {
            level: b.level,
            x: c[0] as u32,
            y: c[1] as u32,
            z: c[2] as u32,
        })
}

/// A waiting tile's plan as [`Engine::replan`] keeps it, made for the face mask `mask`.
struct KeptPlan {
    mask: u8,
    plan: TilePlan,
    /// The replan that last found it holding: a plan not checked in the replan before may
    /// have missed requests that ended meanwhile (its tile was beyond the window).
    checked: u64,
}

/// What planning a tile found.
enum Plan {
    /// The descent found no surface in it.
    Skip,
    /// A mesh tile whose drawing is all in the cache: its content key and strips'.
    Drawing((BrickKey, u64, [Option<u64>; 6])),
    /// A brick whose content (this key) is in the cache.
    Cached(u64),
    /// It waits for requests (now in the plan).
    Waiting,
}

/// The next feed message; never, without a feed.
async fn recv_feed(rx: &mut Option<mpsc::Receiver<FeedMsg>>) -> Option<FeedMsg> {
    match rx {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}

/// An eighth of the finest detail radius; with no radii (level 0 everywhere), half a brick
/// along its shortest side.
fn reselect_distance(radii: &[f32], layout: &VolumeLayout, voxel_scale: [f32; 3]) -> f32 {
    match radii.first() {
        Some(&r0) => r0 / 8.0,
        None => layout.brick() as f32 * voxel_scale.into_iter().fold(f32::INFINITY, f32::min) / 2.0,
    }
}

async fn sleep_until(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

/// The waiting tiles a replan plans, in screen order (see [`Engine::replan`]): far more
/// requests than a streamer keeps in flight between two replans.
const PLAN_AHEAD: usize = 512;

/// The least time between two selections of tiles while the camera moves far (see
/// [`Engine::select_at`]): answers take about as long.
const SELECT_EVERY: std::time::Duration = std::time::Duration::from_millis(100);

/// How long after the last selection a camera that moved less than the reselect distance is
/// selected (see [`Engine::select_at`]): where it came to rest, soon after it stopped.
const SELECT_SETTLE: std::time::Duration = std::time::Duration::from_millis(300);

/// The least time between two replans while requests of the last one wait to start: each
/// replan plans up to [`PLAN_AHEAD`] tiles, and at 25 ms fifty streamers of one process spent
/// more CPU planning than the requests it started gained them (docs/benchmarks.md, "What the
/// streamers' planning costs").
const REPLAN_EVERY: std::time::Duration = std::time::Duration::from_millis(50);

/// Records that `job` is needed by a tile at screen order `d` (the first tile that needs it
/// counts).
fn need(needed: &mut FastMap<JobKey, f32>, job: JobKey, d: f32) {
    let e = needed.entry(job).or_insert(d);
    *e = e.min(d);
}

/// The content key of a mesh tile (or of the strip of `face`) at `version`, for parts asked for
/// at a version because some input's hash is unknown (see `Engine::at_version`).
fn version_content(key: BrickKey, face: Option<u8>, iso: Option<f32>, version: u64) -> u64 {
    let mut h = content_hasher();
    (
        "isovox tile part at a version",
        key,
        face,
        iso.map(f32::to_bits),
        version,
    )
        .hash(&mut h);
    h.finish()
}
