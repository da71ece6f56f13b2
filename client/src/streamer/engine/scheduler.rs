//! The scheduler: the plan (requests to start, in screen order), what runs, what failed and
//! when to retry it, and the requests themselves.

use super::{FastMap, FastSet};
use crate::client::{strip_answer, tile_answer, Brick, Client, ClientError};
use crate::streamer::limit::{lock_limit, InFlightLimit, Pacer, SharedLimit};
use crate::streamer::{RETRY_MAX, RETRY_MIN};
use bytes::Bytes;
use isovox_proto::api::LevelGrid;
use isovox_proto::mesh::{Mesh, TileMesh};
use isovox_proto::BrickKey;
use std::sync::{Arc, Mutex};
use tokio::task::{AbortHandle, JoinError, JoinSet};
use tokio::time::Instant;

/// A request the task can have in flight.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) enum JobKey {
    /// Content hashes of the bricks `min..max` (exclusive) of a level.
    Region {
        level: u8,
        min: [u32; 3],
        max: [u32; 3],
    },
    /// A brick by content hash.
    Blob(u64),
    /// A brick by position, at the engine's version: a brick whose hash the book lacks,
    /// wanted after a commit (so that no grid region is asked for because of an edit; see
    /// `Engine::plan_tile`).
    Brick(BrickKey),
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
            JobKey::Brick(k) => k.level == level && [k.x, k.y, k.z] == p,
            _ => false,
        }
    }
}

/// What a waiting tile needs: the requests, and the content it waits for (see
/// [`Scheduler::register`]).
#[derive(Debug, Default)]
pub(super) struct TilePlan {
    pub(super) jobs: Vec<JobKey>,
    pub(super) waits: Vec<Wait>,
    /// A mesh tile's drawing once its content keys are known: the tile's and the strips' of
    /// its mask's faces (what it waits for is the part of it not in the cache).
    pub(super) drawing: Option<(u64, [Option<u64>; 6])>,
}

impl TilePlan {
    /// Empties it, keeping its buffers.
    pub(super) fn clear(&mut self) {
        self.jobs.clear();
        self.waits.clear();
        self.drawing = None;
    }

    /// Whether planning the tile again would give this plan: none of the requests it needs
    /// has `ended` and none of the content it waits for is in `cache` (what else can change a
    /// plan, commits and face masks, the engine handles).
    pub(super) fn holds(&self, ended: &FastSet<JobKey>, cache: &super::cache::Lru) -> bool {
        !self.jobs.iter().any(|j| ended.contains(j))
            && !self.waits.iter().any(|w| cache.contains(w.content()))
    }
}

/// Content a waiting tile waits for, by content key.
#[derive(Debug, Clone, Copy)]
pub(super) enum Wait {
    /// A brick.
    Content(u64),
    /// Its mesh tile, to be requested under this key.
    Mesh(u64),
    /// The strip of a face, to be requested under this key.
    Strip(u8, u64),
}

impl Wait {
    pub(super) fn content(self) -> u64 {
        match self {
            Wait::Content(c) | Wait::Mesh(c) | Wait::Strip(_, c) => c,
        }
    }
}

/// What a request brought.
#[derive(Debug)]
pub(super) enum Output {
    Region(Result<LevelGrid, ClientError>),
    Blob(Result<Bytes, ClientError>),
    Brick(Result<Option<Brick>, ClientError>),
    /// The content key the tile was requested under, and the tile with its encoding's size.
    Mesh(u64, Result<(TileMesh, usize), ClientError>),
    /// The content key the strip was requested under, and the strip with its encoding's size.
    Strip(u64, Result<(Mesh, usize), ClientError>),
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

/// The scheduler: the plan (requests to start, in screen order), what runs, what failed and
/// when to retry it.
pub(super) struct Scheduler {
    /// Requests that may run at once (the requests' [`Pacer`]s adapt it to 503s).
    limit: SharedLimit,
    /// Content keys of the mesh tiles waiting for a request (from the last plan).
    mesh_keys: FastMap<BrickKey, u64>,
    /// Content keys of the strips (tile, face) waiting for a request (from the last plan).
    strip_keys: FastMap<(BrickKey, u8), u64>,
    /// Tiles waiting for content by content key (from the last plan).
    waiting: FastMap<u64, Vec<BrickKey>>,
    pub(super) jobs: JoinSet<(u64, JobKey, Output)>,
    running: FastMap<JobKey, Running>,
    next_id: u64,
    /// Requests to start, farthest first (started from the end).
    queue: Vec<(f32, JobKey)>,
    failures: FastMap<JobKey, Failure>,
    pub(super) retry_at: Option<Instant>,
    pub(super) replan_needed: bool,
    /// Requests that ended (answered or aborted) since the last plan.
    ended: FastSet<JobKey>,
}

impl Scheduler {
    pub(super) fn new(max_in_flight: usize) -> Scheduler {
        Scheduler {
            limit: Arc::new(Mutex::new(InFlightLimit::new(max_in_flight))),
            mesh_keys: FastMap::default(),
            strip_keys: FastMap::default(),
            waiting: FastMap::default(),
            jobs: JoinSet::new(),
            running: FastMap::default(),
            next_id: 0,
            queue: Vec::new(),
            failures: FastMap::default(),
            retry_at: None,
            replan_needed: false,
            ended: FastSet::default(),
        }
    }

    /// Forgets the last plan: what tiles wait for, and the content keys to request meshes and
    /// strips under.
    pub(super) fn clear_plan(&mut self) {
        self.waiting.clear();
        self.mesh_keys.clear();
        self.strip_keys.clear();
    }

    /// Tile `key` waits for `waits` (until the next plan).
    pub(super) fn register(&mut self, key: BrickKey, waits: &[Wait]) {
        for &w in waits {
            self.waiting.entry(w.content()).or_default().push(key);
            match w {
                Wait::Content(_) => {}
                Wait::Mesh(content) => {
                    self.mesh_keys.insert(key, content);
                }
                Wait::Strip(face, content) => {
                    self.strip_keys.insert((key, face), content);
                }
            }
        }
    }

    /// The requests that ended since the last call.
    pub(super) fn take_ended(&mut self) -> FastSet<JobKey> {
        std::mem::take(&mut self.ended)
    }

    /// The tiles that waited for content `content` (none wait any more).
    pub(super) fn take_waiting(&mut self, content: u64) -> Vec<BrickKey> {
        self.waiting.remove(&content).unwrap_or_default()
    }

    /// Whether requests of the last plan wait to start.
    pub(super) fn has_queued(&self) -> bool {
        !self.queue.is_empty()
    }

    /// How many requests of the last plan wait to start (some may have become unneeded).
    pub(super) fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Whether the last plan still asks for `job` (a grid region always does).
    pub(super) fn planned(&self, job: JobKey) -> bool {
        match job {
            JobKey::Region { .. } | JobKey::Brick(_) => true,
            JobKey::Blob(h) => self.waiting.contains_key(&h),
            JobKey::Mesh(k) => self.mesh_keys.contains_key(&k),
            JobKey::Strip(k, f) => self.strip_keys.contains_key(&(k, f)),
        }
    }

    /// The running requests that are not in `needed`.
    pub(super) fn unneeded(&self, needed: &FastMap<JobKey, f32>) -> Vec<JobKey> {
        self.running
            .keys()
            .filter(|k| !needed.contains_key(k))
            .copied()
            .collect()
    }

    /// Every running request.
    pub(super) fn running_jobs(&self) -> Vec<JobKey> {
        self.running.keys().copied().collect()
    }

    /// The running grid regions of `level` that cover one of the bricks `changed`.
    pub(super) fn covering(&self, level: u8, changed: &[[u32; 3]]) -> Vec<JobKey> {
        self.running
            .keys()
            .filter(|j| changed.iter().any(|&p| j.covers(level, p)))
            .copied()
            .collect()
    }

    /// Requests running now.
    pub(super) fn in_flight(&self) -> usize {
        self.running.len()
    }

    /// Requests that may run at once now.
    pub(super) fn limit(&self) -> usize {
        lock_limit(&self.limit).get()
    }

    /// Queues the `needed` requests (each with the screen order of the first tile that needs
    /// it, see `Engine::screen_order`) so that the first in that order starts first, but those
    /// running and those waiting out a failure's backoff; forgets the failures of requests
    /// nobody needs; `retry_at` becomes the end of the first backoff.
    pub(super) fn queue_needed(&mut self, needed: FastMap<JobKey, f32>) {
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

    /// The next queued request not running yet, while fewer than `limit` run.
    pub(super) fn next_queued(&mut self, limit: usize) -> Option<JobKey> {
        while self.running.len() < limit {
            let (_, job) = self.queue.pop()?;
            if !self.running.contains_key(&job) {
                return Some(job);
            }
        }
        None
    }

    /// Starts `job` through `client` (its exchanges pacing the limit), for volume `name` at
    /// `version`; mesh tiles and strips at `iso`, under the content keys of the last plan;
    /// bricks by position of `brick_bytes`.
    pub(super) fn start(
        &mut self,
        job: JobKey,
        client: &Client,
        name: &str,
        version: u64,
        iso: Option<f32>,
        brick_bytes: usize,
    ) {
        let id = self.next_id;
        self.next_id += 1;
        let pacer = Pacer {
            started: Instant::now(),
            limit: self.limit.clone(),
            next: client.observer(),
        };
        let client = client.clone().with_observer(Arc::new(pacer));
        let name = name.to_string();
        let version = Some(version);
        let abort = match job {
            JobKey::Region { level, min, max } => self.jobs.spawn(async move {
                let r = client
                    .level_grid(&name, level, Some((min, max)), version)
                    .await;
                (id, job, Output::Region(r))
            }),
            JobKey::Blob(h) => self.jobs.spawn(async move {
                let r = client.blob(&name, h).await;
                (id, job, Output::Blob(r))
            }),
            JobKey::Brick(key) => self.jobs.spawn(async move {
                let r = client.brick(&name, key, version, None, brick_bytes).await;
                (id, job, Output::Brick(r))
            }),
            JobKey::Mesh(key) => {
                let content = self.mesh_keys.get(&key).copied().unwrap_or_default();
                self.jobs.spawn(async move {
                    let r = client
                        .mesh_part(&name, key, None, iso, version)
                        .await
                        .and_then(|b| tile_answer(key, &b).map(|tile| (tile, b.len())));
                    (id, job, Output::Mesh(content, r))
                })
            }
            JobKey::Strip(key, face) => {
                let content = self
                    .strip_keys
                    .get(&(key, face))
                    .copied()
                    .unwrap_or_default();
                self.jobs.spawn(async move {
                    let face = usize::from(face);
                    let r = client
                        .mesh_part(&name, key, Some(face), iso, version)
                        .await
                        .and_then(|b| strip_answer(key, face, &b).map(|strip| (strip, b.len())));
                    (id, job, Output::Strip(content, r))
                })
            }
        };
        self.running.insert(job, Running { id, abort });
    }

    /// Aborts a running request; whether it was running.
    pub(super) fn abort(&mut self, job: JobKey) -> bool {
        let Some(r) = self.running.remove(&job) else {
            return false;
        };
        r.abort.abort();
        self.ended.insert(job);
        true
    }

    /// Aborts the requests of tile `key`: a brick's by position, or a mesh tile's and its
    /// strips'.
    pub(super) fn abort_tile(&mut self, key: BrickKey) {
        self.abort(JobKey::Brick(key));
        self.abort(JobKey::Mesh(key));
        for face in 0..6 {
            self.abort(JobKey::Strip(key, face));
        }
    }

    /// What a finished request brought, when it is still the one running for its job.
    pub(super) fn finish(
        &mut self,
        done: Result<(u64, JobKey, Output), JoinError>,
    ) -> Option<(JobKey, Output)> {
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
                return None;
            }
        };
        match self.running.get(&job) {
            Some(r) if r.id == id => {
                self.running.remove(&job);
                self.ended.insert(job);
            }
            _ => return None, // aborted (or superseded) before it finished
        }
        Some((job, output))
    }

    /// `job` failed: it is retried after a backoff that doubles with each attempt.
    pub(super) fn fail(&mut self, job: JobKey) {
        let attempts = self.failures.get(&job).map_or(0, |f| f.attempts) + 1;
        let delay = RETRY_MIN
            .saturating_mul(1 << (attempts - 1).min(16))
            .min(RETRY_MAX);
        let retry_at = Instant::now() + delay;
        self.failures.insert(job, Failure { attempts, retry_at });
        self.retry_at = Some(self.retry_at.map_or(retry_at, |r| r.min(retry_at)));
    }

    /// `job` succeeded: its failures are forgotten.
    pub(super) fn succeeded(&mut self, job: JobKey) {
        self.failures.remove(&job);
    }

    /// A backoff ended: plan again.
    pub(super) fn retry_now(&mut self) {
        self.retry_at = None;
        self.replan_needed = true;
    }

    /// Forgets every failure and the queue (after the running requests were aborted).
    pub(super) fn reset(&mut self) {
        self.failures.clear();
        self.queue.clear();
    }
}
