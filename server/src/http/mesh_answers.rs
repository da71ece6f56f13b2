//! Mesh answers kept as sent. A tile's mesh comes from the mesh cache when its inputs were
//! meshed before, but encoding it (GLB or the compact form) and compressing it were still a job
//! of the bounded CPU queue per request: in a 20 s run of 50 viewers on a 2048^3 world a server
//! meshed 22 tiles, took 6,477 from the mesh cache, and still answered bursts with 503. An
//! answer is named by its tag (the `ETag`: equal tags, equal bytes) and whether it was
//! compressed, so the same request again (many viewers start on the same tiles, and all of them
//! ask for the tiles an edit changed) is sent from here, with no CPU job: 971 answers of a run
//! like that one.

use super::compression::SharedBody;
use crate::store::lru::ByteLru;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// Encoded mesh answers by (tag, compressed), bounded by bytes.
#[derive(Debug)]
pub(crate) struct MeshAnswers {
    answers: ByteLru<SharedBody>,
    hits: AtomicU64,
}

impl MeshAnswers {
    /// At most `capacity` bytes of answers.
    pub(crate) fn new(capacity: usize) -> Self {
        MeshAnswers {
            answers: ByteLru::new(capacity),
            hits: AtomicU64::new(0),
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

    /// Keeps `body`, the answer named `tag` for a request that took zstd or not (`zstd`).
    pub(super) fn put(&self, tag: u64, zstd: bool, body: SharedBody) {
        let size = body.len();
        self.answers.put(Self::key(tag, zstd), Arc::new(body), size);
    }

    /// Answers sent from here so far.
    pub(crate) fn hits(&self) -> u64 {
        self.hits.load(Ordering::Relaxed)
    }

    /// Bytes held now.
    pub(crate) fn bytes(&self) -> usize {
        self.answers.bytes()
    }
}
