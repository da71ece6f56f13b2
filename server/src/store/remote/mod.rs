//! Volumes kept in an object store (S3): one committed history, any number of replicas.
//!
//! A volume `NAME` under `s3://bucket/prefix` is the objects below `prefix/NAME/`:
//!
//! - `seg/{start}-{version}-{tag}`: immutable objects of segments, a segment being the bytes
//!   one commit appended to the volume's logical VOD 2 file (the first: the file's header pages
//!   and its first version, as an import or a compaction wrote them). Brick records, index
//!   checkpoints and commit records are where they would be in a local file, at the same
//!   offsets. An object holds one segment, or several spilled from the head together.
//! - `manifests/{end}-{tag}.json`: immutable lists of the segments up to `end` (a head past
//!   [`head::TAIL_MAX`] segments folds them into one, so the head stays small).
//! - `head`: the one object that changes: the head version, its commit record's offset, the
//!   committed length and the segments (JSON, [`head::Head`]), small ones with their bytes.
//!
//! A commit whose segment fits in the head (up to [`CacheConfig::inline_max`] bytes of
//! segments in all) writes only the head; otherwise it writes its segment and those the head
//! carried as one object (and a manifest, when due) first. Either way the head is replaced with
//! a conditional PUT (`If-Match` on the ETag it read). Of two writers that read the same head,
//! one wins; the other's PUT is refused and it learns the new head ([`StoreError::HeadMoved`]).
//! A writer that dies before the head leaves the head as it was: an object it wrote is garbage
//! that [`collect_garbage`] removes. No lock service is involved.
//!
//! A replica reads through a [`mirror`]: a sparse local file laid out as the logical file and
//! memory-mapped, so a brick read is the same index lookup and slice as for a local file, once
//! its page is there. It follows the head with conditional GETs (`If-None-Match`), which cost
//! one small request and no body while nothing changes.

pub mod backoff;
pub mod bucket;
pub mod head;
pub mod mirror;
pub mod parts;
pub mod turns;

pub use bucket::{bound_store_waits, Bucket, Conditional, StoreWaitBound};
pub use head::{Head, Inline, Manifest, ManifestRef, Segment, Within};
pub use mirror::FetchCounters;

use super::region::Fill;
use super::writer::Publish;
use super::{Snapshot, StoreError, Vod2};
use arc_swap::ArcSwap;
use bytes::Bytes;
use head::{HEAD_FORMAT, TAIL_MAX};
use isovox_proto::vod2::{FileHeader, HeaderSlot, DATA_PAGE};
use mirror::{MirrorFile, MirrorView, Pages};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, SystemTime};

/// The head object's key.
pub const HEAD_KEY: &str = "head";

/// Where replicas keep their mirrors and how large they may grow.
#[derive(Debug, Clone)]
pub struct CacheConfig {
    /// The directory of the mirror files (they are unlinked at creation).
    pub dir: PathBuf,
    /// Bytes of fetched pages per volume before a fresh mirror is started.
    pub max_bytes: u64,
    /// The smallest fetch: a cold read fetches the aligned blocks of this many bytes it lies
    /// in (rounded down to whole pages, at least one). On S3 a request costs tens of
    /// milliseconds before its first byte and a 64 KiB one little more than a 4 KiB one.
    pub read_ahead: u64,
    /// When a volume is opened, its head checkpoint's index (what level grids read) is fetched
    /// in the background if it is at most this many bytes; 0 turns that off.
    pub prefetch_index: u64,
    /// Bytes of small commits' segments this process's writer lets one head carry (at most
    /// [`head::INLINE_LIMIT`]); 0: every segment an object of its own.
    pub inline_max: u64,
}

/// The default [`CacheConfig::prefetch_index`]: the index of a 2048^3 world in bricks of 16 is
/// a few MB; one of a volume thousands of times larger is left to be fetched as it is read.
pub const DEFAULT_PREFETCH_INDEX: u64 = 64 << 20;

/// The default [`CacheConfig::read_ahead`].
pub const DEFAULT_READ_AHEAD: u64 = 64 << 10;

impl Default for CacheConfig {
    fn default() -> Self {
        CacheConfig {
            dir: std::env::temp_dir().join("isovox-cache"),
            max_bytes: 1 << 30,
            read_ahead: DEFAULT_READ_AHEAD,
            prefetch_index: DEFAULT_PREFETCH_INDEX,
            inline_max: head::DEFAULT_INLINE_MAX,
        }
    }
}

/// What following the head found.
#[derive(Debug)]
pub enum Refreshed {
    /// Nothing new.
    Same,
    /// New commits on top of the version given: the volume as of the new head.
    Advanced(Vod2),
    /// A head that does not extend it (a compaction), or a fresh mirror of the same head (the
    /// cache outgrew its bound): the volume reopened.
    Replaced(Vod2),
}

/// The head as this process last saw it, and the mirror that goes with it.
#[derive(Debug)]
struct Followed {
    etag: String,
    head: Head,
    /// Every segment the head names (the manifest's first), without inline bytes, each where
    /// the store says it is kept now: what a manifest this process writes lists.
    segments: Vec<Segment>,
    /// The same segments' pages in the mirror. A segment's pages keep where it was kept when
    /// this process first saw it: one first seen inline has every page present from then on.
    pages: Vec<Arc<Pages>>,
    file: Arc<MirrorFile>,
    /// A segment this process committed inline could not be written into the mirror: no
    /// object holds it, so the next poll starts a fresh mirror, which takes it from the head.
    missing_inline: bool,
}

/// The mirror's pages of `segments` (the ones carried inline written into `file` at once:
/// no object holds them), and the segments without their bytes.
fn pages_of(
    file: &MirrorFile,
    segments: Vec<Segment>,
) -> Result<(Vec<Segment>, Vec<Arc<Pages>>), StoreError> {
    let mut kept = Vec::with_capacity(segments.len());
    let mut pages = Vec::with_capacity(segments.len());
    for s in segments {
        let p = Arc::new(Pages::new(s.without_bytes()));
        if let Some(bytes) = &s.inline {
            file.put_segment(&p, &bytes.0)?;
        }
        kept.push(p.segment().clone());
        pages.push(p);
    }
    Ok((kept, pages))
}

/// One volume in an object store, as one process reads and writes it.
#[derive(Debug)]
pub struct RemoteVolume {
    name: String,
    bucket: Bucket,
    cache: CacheConfig,
    header: FileHeader,
    counters: Arc<FetchCounters>,
    state: Mutex<Followed>,
    /// The state's mirror file, readable without the state's lock: a follower holds that lock
    /// across a request to the store, and `/metrics` must not wait for the store.
    mirror: ArcSwap<MirrorFile>,
    /// Who waits for the head (`turns.rs`).
    turns: turns::Turns,
}

/// A unique tag for object names: this process and a counter, hashed with the time.
fn tag() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let nanos = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let seed = format!(
        "{}-{}-{nanos}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    );
    format!("{:016x}", xxhash_rust::xxh3::xxh3_64(seed.as_bytes()))
}

fn segment_key(start: u64, version: u64) -> String {
    format!("seg/{start:016x}-{version:016x}-{}", tag())
}

/// For fault-injection tests: `ISOVOX_STORE_PAUSE_BEFORE_HEAD_MS` makes a writer wait that long
/// between writing its segment and advancing the head (the window a crash or a stall of a
/// writer falls into).
fn pause_before_head() {
    static PAUSE: OnceLock<Option<Duration>> = OnceLock::new();
    let pause = PAUSE.get_or_init(|| {
        std::env::var("ISOVOX_STORE_PAUSE_BEFORE_HEAD_MS")
            .ok()
            .and_then(|v| v.parse().ok())
            .map(Duration::from_millis)
    });
    if let Some(pause) = pause {
        std::thread::sleep(*pause);
    }
}

/// Every segment a head names, the manifest's first.
fn all_segments(bucket: &Bucket, head: &Head) -> Result<Vec<Segment>, StoreError> {
    all_segments_after(bucket, head, None)
}

/// [`all_segments`], given the head a replica followed before and the segments it named
/// (`known`): a manifest is immutable (its key is unique), so when the new head names the same
/// one, its segments are the first ones known and it is not fetched again. (Every commit of
/// another replica moves the head, and a manifest lists every segment since the volume's
/// start: fetched at each catch-up, it would cost one more request and a download growing with
/// the volume's history per commit.)
fn all_segments_after(
    bucket: &Bucket,
    head: &Head,
    known: Option<(&Head, &[Segment])>,
) -> Result<Vec<Segment>, StoreError> {
    let mut out = match (&head.manifest, known) {
        (None, _) => Vec::new(),
        (Some(m), Some((before, segments)))
            if before.manifest.as_ref() == Some(m) && segments.len() as u64 >= m.segments =>
        {
            segments[..m.segments as usize].to_vec()
        }
        (Some(m), _) => {
            let bytes = bucket.get(&m.key)?.ok_or_else(|| {
                StoreError::corrupt(
                    0,
                    format!("manifest {} that the head names", m.key),
                    "no such object",
                )
            })?;
            Manifest::decode(&bytes, m)?.segments
        }
    };
    out.extend(head.segments.iter().cloned());
    Ok(out)
}

/// Reads the head object of the volume at `bucket`.
///
/// # Errors
/// No head ([`StoreError::Absent`]), or the store fails, or the head is malformed.
pub fn read_head(bucket: &Bucket) -> Result<(Head, String), StoreError> {
    match bucket.get_if_changed(HEAD_KEY, None)? {
        Conditional::Done(Some(bytes), etag) => Ok((Head::decode(&bytes)?, etag)),
        _ => Err(StoreError::Absent(format!(
            "no volume at {} (no head object)",
            bucket.url()
        ))),
    }
}

/// Fetches the index checkpoint `head` builds on, on a thread of its own, if it is at most
/// `limit` bytes: a cold replica's first grid regions (fifty viewers ask for hundreds at once)
/// then find their index chunks here or arriving, instead of each waiting for the store on a
/// store-read thread. A failure is logged and left to the readers, which fetch what they miss.
fn prefetch_index(name: &str, head: Arc<Snapshot>, limit: u64) {
    const STEP: u64 = 8 << 20;
    let name = name.to_string();
    let fetch = move || -> Result<(), StoreError> {
        let (start, len) = head.checkpoint_span()?;
        if len > limit {
            return Ok(());
        }
        for at in (start..start + len).step_by(STEP as usize) {
            head.prefetch(at, STEP.min(start + len - at))?;
        }
        Ok(())
    };
    let spawned = std::thread::Builder::new()
        .name("isovox-prefetch".into())
        .spawn(move || {
            if let Err(e) = fetch() {
                tracing::warn!(volume = %name, error = %e, "prefetching the index failed");
            }
        });
    if let Err(e) = spawned {
        tracing::warn!(error = %e, "cannot start a thread to prefetch the index");
    }
}

impl RemoteVolume {
    /// Opens volume `name` of `store`: reads its head (and manifest), maps a fresh mirror and
    /// reads the file header, the head's commit record and the fixed part of its index
    /// checkpoint, no brick.
    ///
    /// # Errors
    /// No such volume, the store fails, or what it holds is malformed.
    pub fn open(
        store: &Bucket,
        name: &str,
        cache: CacheConfig,
    ) -> Result<(Arc<RemoteVolume>, Vod2), StoreError> {
        let bucket = store.child(name);
        let (head, etag) = read_head(&bucket)?;
        let counters = Arc::new(FetchCounters::default());
        let file = Arc::new(MirrorFile::create(
            &cache,
            name,
            bucket.clone(),
            counters.clone(),
        )?);
        let (segments, pages) = pages_of(&file, all_segments(&bucket, &head)?)?;
        let view = Arc::new(MirrorView::new(file.clone(), pages.clone()));
        let map = file.map(head.committed_len)?;
        view.fill(0, DATA_PAGE as u64)?;
        let header = FileHeader::decode(map.bytes().get(..DATA_PAGE).unwrap_or_default())?;
        let volume = Arc::new(RemoteVolume {
            name: name.to_string(),
            header: header.clone(),
            cache,
            counters,
            mirror: ArcSwap::new(file.clone()),
            state: Mutex::new(Followed {
                etag,
                head: head.clone(),
                segments,
                pages,
                file,
                missing_inline: false,
            }),
            bucket,
            turns: turns::Turns::default(),
        });
        let vod = Vod2::open_mirror(
            PathBuf::from(volume.bucket.url()),
            header,
            head.slot(),
            map,
            view,
        )?;
        if volume.cache.prefetch_index > 0 {
            prefetch_index(name, vod.head(), volume.cache.prefetch_index);
        }
        Ok((volume, vod))
    }

    /// The volume's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The volume's objects.
    pub fn bucket(&self) -> &Bucket {
        &self.bucket
    }

    /// Range requests made and bytes fetched by this volume's mirrors.
    pub fn counters(&self) -> &FetchCounters {
        &self.counters
    }

    /// Bytes the current mirror holds.
    pub fn cached_bytes(&self) -> u64 {
        self.mirror.load().cached()
    }

    fn lock(&self) -> MutexGuard<'_, Followed> {
        // Every update of the state is a whole assignment: a poisoned lock holds a sound state.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The volume as of `head` in a fresh mirror file, which `state` follows from then on. On
    /// an error `state` is left as it was (its head and its pages still go together).
    fn reopen(&self, state: &mut Followed, head: Head, etag: String) -> Result<Vod2, StoreError> {
        let file = Arc::new(MirrorFile::create(
            &self.cache,
            &self.name,
            self.bucket.clone(),
            self.counters.clone(),
        )?);
        let (segments, pages) = pages_of(&file, all_segments(&self.bucket, &head)?)?;
        let map = file.map(head.committed_len)?;
        let view = Arc::new(MirrorView::new(file.clone(), pages.clone()));
        let vod = Vod2::open_mirror(
            PathBuf::from(self.bucket.url()),
            self.header.clone(),
            head.slot(),
            map,
            view,
        )?;
        self.mirror.store(file.clone());
        *state = Followed {
            etag,
            head,
            segments,
            pages,
            file,
            missing_inline: false,
        };
        Ok(vod)
    }

    /// Follows the head: one conditional GET; when the head moved, the volume as of the new
    /// head (`current` is the version this process serves now).
    ///
    /// # Errors
    /// The store fails or the new head is malformed (the old one stays in force).
    pub fn refresh(&self, current: &Vod2) -> Result<Refreshed, StoreError> {
        let mut state = self.lock();
        let got = self.bucket.get_if_changed(HEAD_KEY, Some(&state.etag))?;
        let (head, etag) = match got {
            Conditional::Refused => {
                if state.file.cached() > self.cache.max_bytes || state.missing_inline {
                    tracing::info!(volume = %self.name, cached = state.file.cached(), missing_inline = state.missing_inline, "the mirror outgrew its bound or misses a segment; starting a fresh one");
                    let (head, etag) = (state.head.clone(), state.etag.clone());
                    return Ok(Refreshed::Replaced(self.reopen(&mut state, head, etag)?));
                }
                return Ok(Refreshed::Same);
            }
            Conditional::Done(Some(bytes), etag) => (Head::decode(&bytes)?, etag),
            Conditional::Done(None, _) => {
                return Err(StoreError::Absent(format!(
                    "the head object of {} is gone",
                    self.bucket.url()
                )))
            }
        };
        let segments =
            all_segments_after(&self.bucket, &head, Some((&state.head, &state.segments)))?;
        let extends = segments.len() >= state.segments.len()
            && state
                .segments
                .iter()
                .zip(&segments)
                .all(|(known, s)| known.same_as(s))
            && head.version >= state.head.version;
        let outgrown = state.file.cached() > self.cache.max_bytes || state.missing_inline;
        if !extends || outgrown {
            return Ok(Refreshed::Replaced(self.reopen(&mut state, head, etag)?));
        }
        let mut segments = segments;
        let (new_segments, new_pages) =
            pages_of(&state.file, segments.split_off(state.segments.len()))?;
        segments.extend(new_segments);
        let view_pages = state.pages.iter().chain(&new_pages).cloned().collect();
        let map = state.file.map(head.committed_len)?;
        let view = Arc::new(MirrorView::new(state.file.clone(), view_pages));
        let next = current.advance_mirror(head.slot(), map, view)?;
        // Only now that all of it holds (where the known segments are kept may have changed:
        // inlined ones spilled).
        state.head = head;
        state.etag = etag;
        state.segments = segments;
        state.pages.extend(new_pages);
        Ok(Refreshed::Advanced(next))
    }

    /// A version this process's writer staged on top of `tip` and has not published yet, as
    /// `slot` names it: the writer's unpublished bytes (`unpublished`, starting at `from`, the
    /// end of the head's segments) are written into the mirror file where they belong, and the
    /// version is read from there. Only the writer reads such a version (to stage the next
    /// edit of a group on it) until its group is published, when it is served as it is.
    ///
    /// # Errors
    /// The head moved since the writer started (`from` is not where its segments end), the
    /// mirror cannot be written, or the staged commit record does not read back.
    pub fn staged(
        &self,
        tip: &Vod2,
        from: u64,
        unpublished: &[u8],
        slot: HeaderSlot,
    ) -> Result<Vod2, StoreError> {
        let state = self.lock();
        if from != state.head.committed_len {
            return Err(StoreError::HeadMoved {
                url: self.bucket.url().to_string(),
            });
        }
        let staged = Arc::new(state.file.put_staged(from, unpublished)?);
        let pages: Vec<Arc<Pages>> = state.pages.iter().cloned().chain([staged]).collect();
        let map = state.file.map(slot.committed_len)?;
        let view = Arc::new(MirrorView::new(state.file.clone(), pages));
        tip.advance_mirror(slot, map, view)
    }

    /// Asks the other replicas for a gap at the head (this one lost the race again; its
    /// attempt took `needs`).
    pub fn ask_for_a_turn(&self, needs: Duration) {
        self.turns.ask(&self.bucket, needs);
    }

    /// How long an attempt takes another replica that asked for a gap lately (see
    /// `turns.rs`).
    pub fn others_wait(&self) -> Option<Duration> {
        self.turns.others_wait(&self.bucket)
    }

    /// The head object's current content and ETag, read from the store.
    ///
    /// # Errors
    /// See [`read_head`].
    pub fn read_head(&self) -> Result<(Head, String), StoreError> {
        read_head(&self.bucket)
    }
}

impl Publish for RemoteVolume {
    /// Writes the commit's segment, then advances the head with a conditional PUT on the ETag
    /// of `base`, the head the commit was made on.
    fn publish(
        &self,
        base: Option<HeaderSlot>,
        from: u64,
        appended: &[u8],
        slot: &HeaderSlot,
    ) -> Result<(), StoreError> {
        let mut state = self.lock();
        let moved = || StoreError::HeadMoved {
            url: self.bucket.url().to_string(),
        };
        if base.map(|b| b.commit) != Some(state.head.commit) || from != state.head.committed_len {
            return Err(moved());
        }
        let segment = Segment::object(from, appended.len() as u64, segment_key(from, slot.version));
        let mut next = Head {
            format: HEAD_FORMAT.into(),
            version: slot.version,
            commit: slot.commit,
            committed_len: slot.committed_len,
            manifest: state.head.manifest.clone(),
            segments: state.head.segments.clone(),
        };
        let carried = next.carried();
        next.segments.push(segment.clone());
        let budget = self.cache.inline_max.min(head::INLINE_LIMIT);
        let fits = carried + segment.len <= budget && next.segments.len() <= TAIL_MAX;
        if fits {
            let last = next.segments.len() - 1;
            next.segments[last].inline = Some(Inline(Bytes::copy_from_slice(appended)));
        } else {
            spill(&self.bucket, &mut next.segments, appended, slot.version)?;
        }
        pause_before_head();
        // The segments after the manifest's as the store will say they are kept (a fold below
        // moves them into a manifest, after the ones before them).
        let before_tail = state.segments.len() - state.head.segments.len();
        let tail: Vec<Segment> = next.segments.iter().map(Segment::without_bytes).collect();
        if next.segments.len() > TAIL_MAX {
            let end = segment.end();
            let manifest = Manifest {
                format: HEAD_FORMAT.into(),
                segments: state.segments[..before_tail]
                    .iter()
                    .chain(&tail)
                    .cloned()
                    .collect(),
            };
            let key = format!("manifests/{end:016x}-{}.json", tag());
            self.bucket.put(
                &key,
                Bytes::from(serde_json::to_vec(&manifest).unwrap_or_default()),
            )?;
            next.manifest = Some(ManifestRef {
                key,
                segments: manifest.segments.len() as u64,
                end,
            });
            next.segments.clear();
        }
        // The head's PUT decides whether the edit is committed: given up half-way, it could
        // land after the caller heard it failed. So it waits as long as the store takes.
        let unbounded = bucket::bound_store_waits(None);
        let put = self
            .bucket
            .put_if(HEAD_KEY, Bytes::from(next.encode()), Some(&state.etag));
        drop(unbounded);
        match put? {
            Conditional::Refused => Err(moved()),
            Conditional::Done((), etag) => {
                // Where the store keeps it (in an object, or only in the head and this copy).
                let pages = Arc::new(Pages::new(tail.last().cloned().unwrap_or(segment)));
                // The commit is published; the mirror copy only saves fetching it back, but
                // for an inlined segment no object holds it: a fresh mirror reads it from the
                // head.
                if let Err(e) = state.file.put_segment(&pages, appended) {
                    tracing::warn!(error = %super::error_chain(&e), "cannot keep a committed segment in the mirror");
                    state.missing_inline |=
                        next.segments.last().is_some_and(|s| s.inline.is_some());
                }
                state.segments.truncate(before_tail);
                state.segments.extend(tail);
                state.pages.push(pages);
                state.head = next;
                state.etag = etag;
                Ok(())
            }
        }
    }
}

/// Writes the last of `segments` (a commit's, `appended`) and every one of them the head
/// carries inline into one object, in order, and says so in each (`within`): one PUT however
/// many were inlined. Alone, the commit's segment is an object of its own under its key.
///
/// # Errors
/// The store fails.
fn spill(
    bucket: &Bucket,
    segments: &mut [Segment],
    appended: &[u8],
    version: u64,
) -> Result<(), StoreError> {
    let (last, earlier) = segments
        .split_last_mut()
        .ok_or_else(|| StoreError::Internal("spilling no segment".into()))?;
    let carried: Vec<&mut Segment> = earlier.iter_mut().filter(|s| s.inline.is_some()).collect();
    if carried.is_empty() {
        return bucket.put(&last.key, Bytes::copy_from_slice(appended));
    }
    let key = segment_key(carried[0].start, version);
    let mut bytes =
        Vec::with_capacity(carried.iter().map(|s| s.len as usize).sum::<usize>() + appended.len());
    for s in carried {
        let at = bytes.len() as u64;
        if let Some(inline) = s.inline.take() {
            bytes.extend_from_slice(&inline.0);
        }
        s.within = Some(Within {
            key: key.clone(),
            at,
        });
    }
    last.within = Some(Within {
        key: key.clone(),
        at: bytes.len() as u64,
    });
    bytes.extend_from_slice(appended);
    bucket.put(&key, Bytes::from(bytes))
}

/// Uploads the local VOD 2 file `path` as the volume at `bucket` (`store.child(NAME)`; its
/// first segment is the whole committed file): creates the volume (`If-None-Match: *` on the
/// head), or, with `replace` (the ETag of the head it was read from, for a compaction),
/// replaces that head.
///
/// # Errors
/// The file does not open, the store fails, or the head exists (or moved, with `replace`):
/// [`StoreError::HeadMoved`].
pub fn upload(
    bucket: &Bucket,
    path: &std::path::Path,
    replace: Option<&str>,
) -> Result<Head, StoreError> {
    upload_with(bucket, path, replace, &crate::progress::Silent).map(|(head, _)| head)
}

/// [`upload`], telling `progress` the bytes sent; also returns how many parts the segment went
/// up in (1: one PUT; more: a multipart upload, see [`Bucket::put_file`]).
///
/// # Errors
/// See [`upload`].
pub fn upload_with(
    bucket: &Bucket,
    path: &std::path::Path,
    replace: Option<&str>,
    progress: &dyn crate::progress::Progress,
) -> Result<(Head, u32), StoreError> {
    let vod = Vod2::open(path)?;
    let slot = vod.head_slot();
    drop(vod);
    let segment = Segment::object(0, slot.committed_len, segment_key(0, slot.version));
    // Read from the file part by part: a volume of many GB never sits in memory whole.
    let parts = bucket.put_file(&segment.key, path, segment.len, progress)?;
    let head = Head {
        format: HEAD_FORMAT.into(),
        version: slot.version,
        commit: slot.commit,
        committed_len: slot.committed_len,
        manifest: None,
        segments: vec![segment],
    };
    match bucket.put_if(HEAD_KEY, Bytes::from(head.encode()), replace)? {
        Conditional::Done((), _) => Ok((head, parts)),
        Conditional::Refused => Err(StoreError::HeadMoved {
            url: bucket.url().to_string(),
        }),
    }
}

/// Deletes the objects of the volume at `bucket` that its head does not reference (segments of writers
/// that died before advancing the head, or that lost; what a compaction replaced) and that are
/// older than `grace`: a replica still reading an older head keeps its objects that long.
/// Returns how many objects were deleted.
///
/// # Errors
/// The store fails, or the head is malformed.
pub fn collect_garbage(bucket: &Bucket, grace: Duration) -> Result<usize, StoreError> {
    let (head, _) = read_head(bucket)?;
    let mut live: std::collections::HashSet<String> = all_segments(bucket, &head)?
        .iter()
        .map(|s| s.location().0.to_string())
        .collect();
    if let Some(m) = &head.manifest {
        live.insert(m.key.clone());
    }
    let now = SystemTime::now();
    let mut deleted = 0;
    for under in ["seg", "manifests"] {
        for object in bucket.list(under)? {
            let old = now
                .duration_since(object.modified)
                .is_ok_and(|age| age >= grace);
            if !live.contains(&object.key) && old {
                bucket.delete(&object.key)?;
                deleted += 1;
            }
        }
    }
    Ok(deleted)
}
