//! Mesh answers kept as sent. A tile's mesh comes from the mesh cache when its inputs were
//! meshed before, but encoding it (GLB or the compact form) and compressing it were still a job
//! of the bounded CPU queue per request: in a 20 s run of 50 viewers on a 2048^3 world a server
//! meshed 22 tiles, took 6,477 from the mesh cache, and still answered bursts with 503. An
//! answer is named by its tag (the `ETag`: equal tags, equal bytes) and whether it was
//! compressed, so the same request again (many viewers start on the same tiles, and all of them
//! ask for the tiles an edit changed) is sent from here, with no CPU job: 971 answers of a run
//! like that one.
//!
//! Requests for an answer that is being made wait for it instead of making it again: viewers
//! starting together on a server that meshed nothing ask for the same coarse tiles at the same
//! moment, and each of those requests took a place in the CPU queue for the same work (48
//! requests at once for one cold strip made 16 jobs, one per place of the queue).

use super::compression::{Body, SharedBody};
use super::ApiError;
use crate::store::lru::ByteLru;
use std::collections::HashMap;
use std::future::Future;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, Weak};
use tokio::sync::OnceCell;

/// Dead entries of [`MeshAnswers::making`] (their requests all went away before the answer was
/// made) are swept when the map grows past this.
const MAKING_SWEEP: usize = 4096;

/// An answer being made, shared by the requests waiting for it.
type Making = OnceCell<Arc<SharedBody>>;

/// What [`MeshAnswers::get_or_make`] answers with.
pub(super) enum MeshAnswer {
    /// Made for this request: the body holds its share of the response memory until sent.
    Made(Body),
    /// Kept from an earlier request, or made by another request meanwhile.
    Kept(Arc<SharedBody>),
}

/// Encoded mesh answers by (tag, compressed), bounded by bytes.
#[derive(Debug)]
pub(crate) struct MeshAnswers {
    answers: ByteLru<SharedBody>,
    /// Answers being made, by key.
    making: Mutex<HashMap<u128, Weak<Making>>>,
    hits: AtomicU64,
    joined: AtomicU64,
}

impl MeshAnswers {
    /// At most `capacity` bytes of answers.
    pub(crate) fn new(capacity: usize) -> Self {
        MeshAnswers {
            answers: ByteLru::new(capacity),
            making: Mutex::new(HashMap::new()),
            hits: AtomicU64::new(0),
            joined: AtomicU64::new(0),
        }
    }

    fn key(tag: u64, zstd: bool) -> u128 {
        (u128::from(tag) << 1) | u128::from(zstd)
    }

    /// The answer named `tag`, compressed or not as `zstd` says, if kept.
    pub(super) fn get(&self, tag: u64, zstd: bool) -> Option<Arc<SharedBody>> {
        let hit = self.answers.get(Self::key(tag, zstd))?;
        self.hits.fetch_add(1, Ordering::Relaxed);
        Some(hit)
    }

    /// The answer named `tag` (compressed or not as `zstd` says): kept, else made by `make`
    /// once for all the requests that ask for it meanwhile, and kept. If the request making it
    /// fails or goes away, the next one waiting makes it.
    ///
    /// # Errors
    /// What `make` fails with, for the request whose `make` ran.
    pub(super) async fn get_or_make<F, Fut>(
        &self,
        tag: u64,
        zstd: bool,
        make: F,
    ) -> Result<MeshAnswer, ApiError>
    where
        F: FnOnce() -> Fut,
        Fut: Future<Output = Result<Body, ApiError>>,
    {
        if let Some(kept) = self.get(tag, zstd) {
            return Ok(MeshAnswer::Kept(kept));
        }
        let key = Self::key(tag, zstd);
        let cell = self.making_cell(key);
        let mut made = None;
        let made_here = &mut made;
        let answer: Result<Arc<SharedBody>, ApiError> = cell
            .get_or_try_init(|| async move {
                // Made and kept by another request between the lookup above and here (it is
                // kept before it leaves `making`): counted as joined, not as a hit.
                if let Some(kept) = self.answers.get(key) {
                    return Ok(kept);
                }
                let body = make().await?;
                let shared = Arc::new(body.share());
                self.answers.put(key, shared.clone(), shared.len());
                *made_here = Some(body);
                Ok(shared)
            })
            .await
            .cloned();
        let mut making = self.making.lock().unwrap_or_else(PoisonError::into_inner);
        if answer.is_ok()
            && making
                .get(&key)
                .is_some_and(|w| w.as_ptr() == Arc::as_ptr(&cell))
        {
            making.remove(&key);
        }
        drop(making);
        let answer = answer?;
        Ok(match made {
            Some(body) => MeshAnswer::Made(body),
            None => {
                self.joined.fetch_add(1, Ordering::Relaxed);
                MeshAnswer::Kept(answer)
            }
        })
    }

    /// The cell of the answer `key` being made: the one requests already wait on, or a new one.
    fn making_cell(&self, key: u128) -> Arc<Making> {
        let mut making = self.making.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(cell) = making.get(&key).and_then(Weak::upgrade) {
            return cell;
        }
        if making.len() >= MAKING_SWEEP {
            making.retain(|_, w| w.strong_count() > 0);
        }
        let cell = Arc::new(OnceCell::new());
        making.insert(key, Arc::downgrade(&cell));
        cell
    }

    /// Answers sent from here so far.
    pub(crate) fn hits(&self) -> u64 {
        self.hits.load(Ordering::Relaxed)
    }

    /// Answers another request was making when they were asked for, sent when it was made.
    pub(crate) fn joined(&self) -> u64 {
        self.joined.load(Ordering::Relaxed)
    }

    /// Bytes held now.
    pub(crate) fn bytes(&self) -> usize {
        self.answers.bytes()
    }
}
