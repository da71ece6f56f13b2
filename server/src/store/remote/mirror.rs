//! A replica's bounded local cache of a volume in an object store: a sparse local file laid out
//! as the volume's logical VOD 2 file, memory-mapped like a local volume, whose pages are
//! fetched from their segment objects by range requests the first time a reader needs them.
//!
//! Pages are [`PAGE`] bytes of one segment (a segment's last page may be shorter), so a page is
//! whole once fetched and never changes: segments are immutable. Which pages are here is one bit
//! each, set after the bytes are written (release) and tested before they are read (acquire).
//! The bytes under the mapping go from a hole (zeros no reader looks at) to the segment's
//! content, once, through `pwrite`, never through the mapping.
//!
//! Two rules keep the store's requests few when many readers start at once (fifty viewers
//! asking for the same grid regions in the same second):
//! - read-ahead: a fetch covers whole aligned blocks of [`CacheConfig::read_ahead`] bytes (64 KiB
//!   by default), so the index chunks a grid region reads, which lie in a row, and neighbouring
//!   bricks come in one request instead of one per page;
//! - one fetch per block at a time: a reader missing pages that another reader is fetching
//!   waits for that fetch instead of sending the same range request again (and fetches what is
//!   still missing itself if that fetch failed).
//!
//! The bound: the file is unlinked as soon as it is created (a crash leaves nothing behind) and
//! its pages count against the cache size; past it, the volume starts a fresh file (a new
//! generation) for new snapshots, and the old one is freed when the last reader of an older
//! snapshot lets go of it.

use super::super::region::Fill;
use super::super::StoreError;
use super::bucket::Bucket;
use super::head::Segment;
use super::CacheConfig;
use std::fs::{File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};

/// The unit fetched: small enough that a compressed brick costs one or two pages, large enough
/// that a brick's header and payload mostly share one.
pub const PAGE: u64 = 4096;

/// What a mirror fetched so far (for metrics and the benchmark).
#[derive(Debug, Default)]
pub struct FetchCounters {
    /// Range requests made.
    pub requests: AtomicU64,
    /// Bytes they returned.
    pub bytes: AtomicU64,
}

/// The sparse file and what it holds.
#[derive(Debug)]
pub struct MirrorFile {
    file: File,
    path: PathBuf,
    bucket: Bucket,
    /// Pages a fetch covers at least: aligned blocks of this many.
    block_pages: u64,
    /// Bytes of pages present.
    cached: AtomicU64,
    counters: Arc<FetchCounters>,
}

/// One segment's pages in a mirror file.
#[derive(Debug)]
pub struct Pages {
    segment: Segment,
    present: Box<[AtomicU64]>,
    /// The fetches of this segment's pages in flight.
    fetching: Mutex<Vec<Arc<Flight>>>,
}

/// A range request in flight for pages `first..=last` of one segment.
#[derive(Debug)]
struct Flight {
    first: u64,
    last: u64,
    landed: Mutex<bool>,
    wake: Condvar,
}

impl Flight {
    fn overlaps(&self, first: u64, last: u64) -> bool {
        self.first <= last && first <= self.last
    }

    /// Waits until the fetch has ended, well or not.
    fn wait(&self) {
        let mut landed = self.landed.lock().unwrap_or_else(|e| e.into_inner());
        while !*landed {
            landed = self.wake.wait(landed).unwrap_or_else(|e| e.into_inner());
        }
    }
}

/// Ends a flight when its fetcher is done with it, however it got there (an error, a panic):
/// a waiter must never wait for a fetch nobody is making.
struct Landing<'a> {
    pages: &'a Pages,
    flight: Arc<Flight>,
}

impl Drop for Landing<'_> {
    fn drop(&mut self) {
        self.pages
            .fetching
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .retain(|f| !Arc::ptr_eq(f, &self.flight));
        *self.flight.landed.lock().unwrap_or_else(|e| e.into_inner()) = true;
        self.flight.wake.notify_all();
    }
}

impl Pages {
    /// No page of `segment` present yet.
    pub fn new(segment: Segment) -> Pages {
        let n = segment.len.div_ceil(PAGE).div_ceil(64) as usize;
        Pages {
            segment,
            present: (0..n).map(|_| AtomicU64::new(0)).collect(),
            fetching: Mutex::new(Vec::new()),
        }
    }

    /// The segment.
    pub fn segment(&self) -> &Segment {
        &self.segment
    }

    #[inline]
    fn has(&self, page: u64) -> bool {
        let word = self.present[(page / 64) as usize].load(Ordering::Acquire);
        word & (1 << (page % 64)) != 0
    }

    /// Marks pages `first..=last` present; returns how many were not.
    fn mark(&self, first: u64, last: u64) -> u64 {
        let mut added = 0;
        for page in first..=last {
            let bit = 1u64 << (page % 64);
            let before = self.present[(page / 64) as usize].fetch_or(bit, Ordering::Release);
            added += u64::from(before & bit == 0);
        }
        added
    }

    fn page_len(&self, page: u64) -> u64 {
        PAGE.min(self.segment.len - page * PAGE)
    }

    /// The segment's last page.
    fn last_page(&self) -> u64 {
        self.segment.len.div_ceil(PAGE).max(1) - 1
    }
}

impl MirrorFile {
    /// A new, empty mirror file in `cache.dir` (unlinked at once: only this process's handle
    /// keeps it), fetching from `bucket` (the volume's objects) in blocks of
    /// `cache.read_ahead` bytes.
    ///
    /// # Errors
    /// The file cannot be created.
    pub fn create(
        cache: &CacheConfig,
        label: &str,
        bucket: Bucket,
        counters: Arc<FetchCounters>,
    ) -> Result<MirrorFile, StoreError> {
        let dir = &cache.dir;
        std::fs::create_dir_all(dir).map_err(StoreError::io_path(
            "cannot create the cache directory",
            dir,
        ))?;
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let path = dir.join(format!(
            "{label}.{}.{}.mirror",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        ));
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(StoreError::io_path("cannot create the cache file", &path))?;
        let _ = std::fs::remove_file(&path);
        Ok(MirrorFile {
            file,
            path,
            bucket,
            block_pages: (cache.read_ahead / PAGE).max(1),
            cached: AtomicU64::new(0),
            counters,
        })
    }

    /// Grows the file (sparse) to `len` bytes and maps it.
    ///
    /// # Errors
    /// The file cannot be grown or mapped.
    pub(crate) fn map(&self, len: u64) -> Result<super::super::mapping::Mapping, StoreError> {
        let now = self
            .file
            .metadata()
            .map_err(StoreError::io_path("cannot stat", &self.path))?
            .len();
        if len > now {
            self.file
                .set_len(len)
                .map_err(StoreError::io_path("cannot grow", &self.path))?;
        }
        super::super::mapping::Mapping::new(&self.file, len)
            .map_err(StoreError::io_path("cannot map", &self.path))
    }

    /// Bytes of pages held.
    pub fn cached(&self) -> u64 {
        self.cached.load(Ordering::Relaxed)
    }

    /// Writes a whole segment this process already has (its own commit) and marks it present.
    ///
    /// # Errors
    /// The file cannot be written.
    pub fn put_segment(&self, pages: &Pages, bytes: &[u8]) -> Result<(), StoreError> {
        if bytes.len() as u64 != pages.segment.len {
            return Err(StoreError::Internal(format!(
                "segment {} has {} bytes, {} were given",
                pages.segment.key,
                pages.segment.len,
                bytes.len()
            )));
        }
        self.file
            .write_all_at(bytes, pages.segment.start)
            .map_err(StoreError::io_path("cannot write", &self.path))?;
        let n = pages.segment.len.div_ceil(PAGE);
        if n > 0 {
            let added = pages.mark(0, n - 1);
            self.cached.fetch_add(added * PAGE, Ordering::Relaxed);
        }
        Ok(())
    }

    /// Writes bytes this process's writer staged and has not published (they start where the
    /// head's segments end) and returns them as pages present, for the writer's own reads of
    /// the versions it staged. They are not counted in the cache, and no view of a published
    /// head lists them: should the publication fail, the segment another writer published at
    /// the same offsets is fetched over them when first read.
    ///
    /// # Errors
    /// The file cannot be written.
    pub fn put_staged(&self, start: u64, bytes: &[u8]) -> Result<Pages, StoreError> {
        self.file
            .write_all_at(bytes, start)
            .map_err(StoreError::io_path("cannot write", &self.path))?;
        let pages = Pages::new(Segment::object(start, bytes.len() as u64, "staged".into()));
        for word in pages.present.iter() {
            word.store(u64::MAX, Ordering::Release);
        }
        Ok(pages)
    }

    /// Makes pages `first..=last` of `pages` present: the whole blocks they lie in, each
    /// missing span fetched in one range request, or waited for where another reader is
    /// fetching it.
    fn fetch(&self, pages: &Pages, first: u64, last: u64) -> Result<(), StoreError> {
        let first = first - first % self.block_pages;
        let last = (last - last % self.block_pages + self.block_pages - 1).min(pages.last_page());
        loop {
            let Some(lo) = (first..=last).find(|&p| !pages.has(p)) else {
                return Ok(());
            };
            let hi = (lo..=last).rev().find(|&p| !pages.has(p)).unwrap_or(lo);
            let flight = {
                let mut fetching = pages.fetching.lock().unwrap_or_else(|e| e.into_inner());
                if let Some(other) = fetching.iter().find(|f| f.overlaps(lo, hi)).cloned() {
                    drop(fetching);
                    other.wait();
                    continue;
                }
                let flight = Arc::new(Flight {
                    first: lo,
                    last: hi,
                    landed: Mutex::new(false),
                    wake: Condvar::new(),
                });
                fetching.push(flight.clone());
                flight
            };
            let _ended = Landing { pages, flight };
            self.fetch_span(pages, lo, hi)?;
        }
    }

    /// Fetches pages `lo..=hi` of `pages` in one range request and marks them present.
    fn fetch_span(&self, pages: &Pages, lo: u64, hi: u64) -> Result<(), StoreError> {
        let from = lo * PAGE;
        let to = hi * PAGE + pages.page_len(hi);
        let (object, at) = pages.segment.location();
        let bytes = self.bucket.get_range(object, at + from..at + to)?;
        if bytes.len() as u64 != to - from {
            return Err(StoreError::corrupt(
                pages.segment.start + from,
                format!("{} bytes of segment {}", to - from, pages.segment.key),
                format!("{} bytes", bytes.len()),
            ));
        }
        self.counters.requests.fetch_add(1, Ordering::Relaxed);
        self.counters
            .bytes
            .fetch_add(bytes.len() as u64, Ordering::Relaxed);
        self.file
            .write_all_at(&bytes, pages.segment.start + from)
            .map_err(StoreError::io_path("cannot write", &self.path))?;
        let added = pages.mark(lo, hi);
        self.cached.fetch_add(added * PAGE, Ordering::Relaxed);
        Ok(())
    }
}

thread_local! {
    /// Whether this thread runs a read that must not wait for the store
    /// ([`without_fetching`]): 0 no, 1 yes, 2 yes and it needed a fetch.
    static NO_FETCH: std::cell::Cell<u8> = const { std::cell::Cell::new(0) };
}

/// Runs `read` on this thread so that a fill that would fetch from the store fails at once
/// instead: `None` when one did. The read's result is then discarded whatever it was (it may
/// have failed with that failure, or handled it), and the caller runs the read again where it
/// may wait. So a read of pages already here never waits for a store-read thread.
pub fn without_fetching<T>(read: impl FnOnce() -> T) -> Option<T> {
    struct Disarm;
    impl Drop for Disarm {
        fn drop(&mut self) {
            NO_FETCH.set(0);
        }
    }
    NO_FETCH.set(1);
    let _disarm = Disarm;
    let out = read();
    (NO_FETCH.get() == 1).then_some(out)
}

/// Whether a fill must not fetch (see [`without_fetching`]); notes that one wanted to.
fn fetch_refused() -> bool {
    let armed = NO_FETCH.get() != 0;
    if armed {
        NO_FETCH.set(2);
    }
    armed
}

/// A mirror as of one head: the file and every segment's pages, in order (shared with the
/// views of earlier heads: a segment's pages are fetched once per file).
#[derive(Debug)]
pub struct MirrorView {
    file: Arc<MirrorFile>,
    pages: Vec<Arc<Pages>>,
}

impl MirrorView {
    /// The view of `pages` (contiguous from offset 0) in `file`.
    pub fn new(file: Arc<MirrorFile>, pages: Vec<Arc<Pages>>) -> MirrorView {
        MirrorView { file, pages }
    }
}

impl Fill for MirrorView {
    fn fill(&self, start: u64, len: u64) -> Result<(), StoreError> {
        let end = start + len;
        let mut i = self.pages.partition_point(|p| p.segment.end() <= start);
        while let Some(pages) = self.pages.get(i) {
            let s = &pages.segment;
            if s.start >= end {
                break;
            }
            let a = start.max(s.start) - s.start;
            let b = end.min(s.end()) - s.start;
            let (first, last) = (a / PAGE, (b - 1) / PAGE);
            if (first..=last).any(|p| !pages.has(p)) {
                if fetch_refused() {
                    return Err(StoreError::Internal(
                        "a page to fetch in a read that may not wait for the store".into(),
                    ));
                }
                self.file.fetch(pages, first, last)?;
            }
            i += 1;
        }
        let covered = self.pages.last().map_or(0, |p| p.segment.end());
        if end > covered {
            return Err(StoreError::Internal(format!(
                "bytes up to {end} asked of a mirror whose segments end at {covered}"
            )));
        }
        Ok(())
    }
}
