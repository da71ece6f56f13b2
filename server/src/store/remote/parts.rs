//! Imports split across machines: `isovox import SRC -o s3://.../NAME --part I/N` on N
//! machines (or N processes), then `isovox import --finish -o s3://.../NAME` once.
//!
//! A part reads the level-0 bricks of its share of the input's brick rows (the brick rows
//! along z, split into N runs of whole rows) and stores each row, every stream of it (density,
//! then each channel), as one object below the volume's `parts/`. It never touches `head`:
//! until the finish commits it, the volume does not exist for replicas.
//!
//! Objects (keys below the volume's prefix):
//! - `parts/{fingerprint}/s{stream}-z{row}`: one brick row of one stream, as [`encode_row`]
//!   writes it. The fingerprint names the volume's header and compression, so rows of
//!   different imports never mix, and a row is the same whichever part (or N) wrote it.
//! - `parts/{I}-of-{N}.json`: the marker of a finished part ([`Marker`]), written after its
//!   last row. A part that finds its marker is skipped; one that was killed finds the rows it
//!   stored and writes only the others (a PUT lands whole or not at all, so a stored row is
//!   complete).
//!
//! The finish checks that every part of 0..N has its marker and that all markers describe the
//! same volume, then builds the volume as the single-process import does, level 0 read from the
//! rows instead of the input: the same pyramid code (mean for density, mode for channels), so
//! the same voxels at every level (and the same file, but for the commit record's time). It uploads that file as the volume's
//! first segment and creates the head with `If-None-Match: *`, then deletes `parts/`.

use super::bucket::Bucket;
use super::{read_head, upload_with, Head};
use crate::progress::Progress;
use crate::store::build::{build_streams, level0_row, BuildOptions};
use crate::store::codec::{fill_constant, Compression};
use crate::store::pyramid::{BrickSource, BrickVoxels, FirstError};
use crate::store::StoreError;
use bytes::Bytes;
use isovox_proto::vod2::FileHeader;
use isovox_proto::{BrickKey, VolumeLayout};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use std::ops::Range;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

/// The folder of a split import's objects, below the volume's prefix.
pub const PARTS_DIR: &str = "parts";

/// The `format` of a marker.
const MARKER_FORMAT: &str = "isovox-import-part-1";

/// The first bytes of a stored row (before its zstd frame).
const ROW_MAGIC: &[u8; 8] = b"IVXROW02";

/// The zstd level of stored rows: they are read once, by the finish, so fast beats small.
const ROW_ZSTD_LEVEL: i32 = 1;

/// The most parts an import may be split into.
pub const MAX_PARTS: u32 = 10_000;

/// `I/N` of `--part`: part I (0-based, as Kubernetes' `JOB_COMPLETION_INDEX`) of N.
///
/// # Errors
/// Not `I/N` with `N` in 1..=[`MAX_PARTS`] and `I` below `N`.
pub fn parse_part(s: &str) -> Result<(u32, u32), String> {
    let bad = || format!("--part {s:?}: I/N expected, I from 0 to N-1 (0/4, 1/4, 2/4, 3/4)");
    let (i, n) = s.split_once('/').ok_or_else(bad)?;
    let (i, n): (u32, u32) = (
        i.trim().parse().map_err(|_| bad())?,
        n.trim().parse().map_err(|_| bad())?,
    );
    if n == 0 || n > MAX_PARTS {
        return Err(format!("--part {s:?}: N must be 1 to {MAX_PARTS}"));
    }
    if i >= n {
        return Err(format!(
            "--part {s:?}: parts are numbered 0 to {} (the first is 0/{n})",
            n - 1
        ));
    }
    Ok((i, n))
}

/// The brick rows (level 0, along z) of part `part` of `parts`: runs of whole rows, as even
/// as they can be in pairs of rows. Parts therefore share no brick, and no parent brick of
/// level 1 has children in two parts. They share no index chunk either: parts write no index;
/// the finish writes it once. A part past the end of the volume gets no rows (it still writes
/// its marker).
pub fn part_rows(layout: &VolumeLayout, part: u32, parts: u32) -> Range<u32> {
    let gz = layout.grid(0)[2];
    let rows = gz.div_ceil(parts.max(1)).next_multiple_of(2);
    let start = part.saturating_mul(rows).min(gz);
    let end = part.saturating_add(1).saturating_mul(rows).min(gz);
    start..end
}

/// `compression` as markers record it.
fn compression_name(c: Compression) -> String {
    match c {
        Compression::Zstd(level) => format!("zstd:{level}"),
        Compression::Lz4 => "lz4".into(),
        Compression::None => "none".into(),
    }
}

fn parse_compression(s: &str) -> Option<Compression> {
    match s {
        "lz4" => Some(Compression::Lz4),
        "none" => Some(Compression::None),
        _ => s
            .strip_prefix("zstd:")
            .and_then(|l| l.parse().ok())
            .map(Compression::Zstd),
    }
}

/// The volume a header describes, for people: `96 x 64 x 96 u8, brick 16, scale 1,1,1,
/// channels: material (u8)`.
fn describe(header: &FileHeader) -> String {
    let l = &header.layout;
    let [x, y, z] = l.dims();
    let [sx, sy, sz] = header.voxel_scale;
    let channels = if header.channels.is_empty() {
        "no channels".to_string()
    } else {
        let names: Vec<String> = header
            .channels
            .iter()
            .map(|c| format!("{} ({})", c.name, c.voxel_type))
            .collect();
        format!("channels: {}", names.join(", "))
    };
    format!(
        "{x} x {y} x {z} {}, brick {}, scale {sx},{sy},{sz}, {channels}",
        l.voxel_type(),
        l.brick()
    )
}

fn to_hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn from_hex(s: &str) -> Option<Vec<u8>> {
    if !s.len().is_multiple_of(2) {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok())
        .collect()
}

/// What a split import is of: the header and compression every part must agree on.
#[derive(Debug, Clone)]
pub struct Identity {
    /// The volume's header.
    pub header: FileHeader,
    /// How the finished volume's bricks are compressed.
    pub compression: Compression,
    /// A hash of both, naming the import's row objects.
    pub fingerprint: String,
}

impl Identity {
    /// The identity of an import of `header` with `compression`.
    pub fn new(header: FileHeader, compression: Compression) -> Identity {
        let mut bytes = header.encode_page();
        bytes.extend_from_slice(compression_name(compression).as_bytes());
        let fingerprint = format!("{:016x}", xxhash_rust::xxh3::xxh3_64(&bytes));
        Identity {
            header,
            compression,
            fingerprint,
        }
    }

    fn row_key(&self, stream: usize, z: u32) -> String {
        format!("{PARTS_DIR}/{}/s{stream}-z{z:06}", self.fingerprint)
    }
}

/// The marker of a finished part (`parts/{I}-of-{N}.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Marker {
    /// [`MARKER_FORMAT`].
    pub format: String,
    /// I.
    pub part: u32,
    /// N.
    pub parts: u32,
    /// The brick rows it stored, `[start, end)`.
    pub rows: [u32; 2],
    /// The volume, for people (the same for every part of one import).
    pub volume: String,
    /// The compression of the finished volume.
    pub compression: String,
    /// The import's fingerprint ([`Identity`]).
    pub fingerprint: String,
    /// The header page of the volume, hex.
    pub header: String,
    /// Row objects it stored (those found stored by an earlier run included).
    pub row_objects: u64,
    /// Their bytes.
    pub stored_bytes: u64,
}

fn marker_key(part: u32, parts: u32) -> String {
    format!("{PARTS_DIR}/{part}-of-{parts}.json")
}

impl Marker {
    fn identity(&self, url: &str) -> Result<Identity, StoreError> {
        let bad = |what: &str| {
            StoreError::corrupt(
                0,
                format!("{url}/{}", marker_key(self.part, self.parts)),
                what.to_string(),
            )
        };
        if self.format != MARKER_FORMAT {
            return Err(bad(&format!(
                "format {:?}, {MARKER_FORMAT:?} expected",
                self.format
            )));
        }
        let page = from_hex(&self.header).ok_or_else(|| bad("its header is not hex"))?;
        let header = FileHeader::decode(&page)?;
        let compression = parse_compression(&self.compression)
            .ok_or_else(|| bad(&format!("unknown compression {:?}", self.compression)))?;
        let identity = Identity::new(header, compression);
        if identity.fingerprint != self.fingerprint {
            return Err(bad("its fingerprint does not match its header"));
        }
        Ok(identity)
    }
}

/// A row of bricks as stored: [`ROW_MAGIC`], then a zstd frame holding, per brick in row order,
/// a tag byte and its voxels: 0 and a u64 (little endian) for a constant brick, 1 and the
/// brick's bytes for the others.
pub fn encode_row(row: &[BrickVoxels]) -> Result<Vec<u8>, StoreError> {
    let mut plain = Vec::new();
    for brick in row {
        match brick {
            BrickVoxels::Constant(v) => {
                plain.push(0);
                plain.extend_from_slice(&v.to_le_bytes());
            }
            BrickVoxels::Data(d) => {
                plain.push(1);
                plain.extend_from_slice(d);
            }
        }
    }
    let packed = zstd::bulk::compress(&plain, ROW_ZSTD_LEVEL)
        .map_err(|e| StoreError::Internal(format!("cannot compress a brick row: {e}")))?;
    let mut out = ROW_MAGIC.to_vec();
    out.extend_from_slice(&packed);
    Ok(out)
}

/// The bricks of a row [`encode_row`] wrote, for a stream of `layout`; `what` names it in
/// errors.
///
/// # Errors
/// The object is not such a row, or not of this layout.
pub fn decode_row(
    bytes: &[u8],
    layout: &VolumeLayout,
    what: &str,
) -> Result<Vec<BrickVoxels>, StoreError> {
    let bad = |detail: String| StoreError::corrupt(0, what.to_string(), detail);
    let g = layout.grid(0);
    let count = g[0] as usize * g[1] as usize;
    let brick_bytes = layout.brick_bytes();
    let packed = bytes
        .strip_prefix(ROW_MAGIC.as_slice())
        .ok_or_else(|| bad("not a stored brick row (wrong magic)".into()))?;
    let plain = zstd::bulk::decompress(packed, count * (1 + brick_bytes))
        .map_err(|e| bad(format!("its zstd frame does not decode: {e}")))?;
    let mut row = Vec::with_capacity(count);
    let mut at = 0;
    while at < plain.len() {
        let tag = plain[at];
        let (brick, len) = match tag {
            0 => {
                let v = plain
                    .get(at + 1..at + 9)
                    .ok_or_else(|| bad("a constant brick is cut short".into()))?;
                let v = u64::from_le_bytes(v.try_into().expect("8 bytes"));
                if v > layout.voxel_type().max_value() {
                    return Err(bad(format!(
                        "a constant {v} past the largest {}",
                        layout.voxel_type()
                    )));
                }
                (BrickVoxels::Constant(v), 9)
            }
            1 => {
                let d = plain
                    .get(at + 1..at + 1 + brick_bytes)
                    .ok_or_else(|| bad("a brick's voxels are cut short".into()))?;
                (BrickVoxels::Data(d.to_vec()), 1 + brick_bytes)
            }
            t => return Err(bad(format!("brick {} has tag {t}", row.len()))),
        };
        row.push(brick);
        at += len;
    }
    if row.len() != count {
        return Err(bad(format!(
            "{} bricks, the row of a {} x {} grid has {count}",
            row.len(),
            g[0],
            g[1]
        )));
    }
    Ok(row)
}

/// For fault-injection tests: `ISOVOX_PART_PAUSE_AFTER_ROW_MS` makes a part wait that long
/// after each row it stores (so a test can kill it between two rows).
fn pause_after_row() {
    if let Some(ms) = std::env::var("ISOVOX_PART_PAUSE_AFTER_ROW_MS")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        std::thread::sleep(std::time::Duration::from_millis(ms));
    }
}

/// What [`write_part`] did.
#[derive(Debug, Clone)]
pub enum PartOutcome {
    /// The part's marker was there already: nothing was done.
    AlreadyDone(Marker),
    /// The part was written (`resumed`: rows found stored by an earlier run).
    Written {
        /// Its marker.
        marker: Marker,
        /// Rows an earlier, unfinished run had stored.
        resumed: u64,
    },
}

/// Writes part `part` of `parts` of a split import of the volume at `volume`
/// (`store.child(NAME)`): each brick row of the part, every stream, read from `sources`
/// (density first, then each channel of `identity.header`), then its marker. `say` is told
/// what happens, a line at a time (the rows as they are stored).
///
/// # Errors
/// The volume exists already, a marker of this part describes another volume, a source
/// fails, or the store fails.
pub fn write_part(
    volume: &Bucket,
    identity: &Identity,
    sources: &[&dyn BrickSource],
    part: u32,
    parts: u32,
    say: &mut dyn FnMut(&str),
) -> Result<PartOutcome, StoreError> {
    let header = &identity.header;
    if sources.len() != 1 + header.channels.len() {
        return Err(StoreError::Internal(format!(
            "{} sources for {} streams",
            sources.len(),
            1 + header.channels.len()
        )));
    }
    if read_head(volume).is_ok() {
        return Err(StoreError::BadInput(format!(
            "{} exists already (it has a head): a split import creates a new volume",
            volume.url()
        )));
    }
    let key = marker_key(part, parts);
    if let Some(bytes) = volume.get(&key)? {
        let marker: Marker = serde_json::from_slice(&bytes).map_err(|e| {
            StoreError::corrupt(0, format!("{}/{key}", volume.url()), e.to_string())
        })?;
        if marker.fingerprint != identity.fingerprint {
            return Err(StoreError::BadInput(format!(
                "part {part}/{parts} was finished for another volume ({}, compression {}); this run imports {} (compression {}). Delete {}/{key} to import it again",
                marker.volume,
                marker.compression,
                describe(header),
                compression_name(identity.compression),
                volume.url()
            )));
        }
        return Ok(PartOutcome::AlreadyDone(marker));
    }
    let rows = part_rows(&header.layout, part, parts);
    let streams: Vec<VolumeLayout> = (0..sources.len())
        .map(|s| {
            header
                .stream_layout(s)
                .ok_or_else(|| StoreError::Internal(format!("no stream {s}")))
        })
        .collect::<Result<_, _>>()?;
    let stored: HashSet<String> = volume
        .list(&format!("{PARTS_DIR}/{}", identity.fingerprint))?
        .into_iter()
        .map(|o| o.key)
        .collect();
    let total = u64::from(rows.end - rows.start) * sources.len() as u64;
    let resumed = (rows.clone())
        .flat_map(|z| (0..sources.len()).map(move |s| (s, z)))
        .filter(|&(s, z)| stored.contains(&identity.row_key(s, z)))
        .count() as u64;
    say(&format!(
        "part {part}/{parts}: brick rows {}..{} of {}, {} streams, {total} row objects{}",
        rows.start,
        rows.end,
        header.layout.grid(0)[2],
        sources.len(),
        if resumed > 0 {
            format!("; resuming: {resumed} stored by an earlier run")
        } else {
            String::new()
        }
    ));
    let (mut done, mut stored_bytes) = (0u64, 0u64);
    for z in rows.clone() {
        for (s, (layout, source)) in streams.iter().zip(sources).enumerate() {
            let row_key = identity.row_key(s, z);
            done += 1;
            if stored.contains(&row_key) {
                continue;
            }
            let row = level0_row(layout, *source, z);
            if source.failed() {
                return Err(StoreError::BadInput(format!(
                    "the input failed at brick row {z}; part {part}/{parts} stopped"
                )));
            }
            let bytes = encode_row(&row)?;
            stored_bytes += bytes.len() as u64;
            // A row of a wide volume can pass the multipart threshold (or 5 GB).
            volume.put_large(&row_key, Bytes::from(bytes))?;
            say(&format!(
                "part {part}/{parts}: stored row {z} of stream {s} ({done} of {total})"
            ));
            pause_after_row();
        }
    }
    let marker = Marker {
        format: MARKER_FORMAT.into(),
        part,
        parts,
        rows: [rows.start, rows.end],
        volume: describe(header),
        compression: compression_name(identity.compression),
        fingerprint: identity.fingerprint.clone(),
        header: to_hex(&header.encode_page()),
        row_objects: total,
        stored_bytes,
    };
    let json = serde_json::to_vec_pretty(&marker)
        .map_err(|e| StoreError::Internal(format!("cannot encode a marker: {e}")))?;
    volume.put(&key, Bytes::from(json))?;
    Ok(PartOutcome::Written { marker, resumed })
}

/// The level-0 bricks of one stream, read from the stored rows in row order: the row being
/// built is kept decoded, and the next one is fetched meanwhile.
struct RowSource<'a> {
    volume: &'a Bucket,
    identity: &'a Identity,
    stream: usize,
    layout: VolumeLayout,
    row: Mutex<RowCache>,
    error: FirstError,
    failed: AtomicBool,
}

/// A row's object being fetched on a thread of its own.
type Fetch = JoinHandle<Result<Option<Bytes>, StoreError>>;

#[derive(Default)]
struct RowCache {
    current: Option<(u32, Arc<Vec<BrickVoxels>>)>,
    next: Option<(u32, Fetch)>,
}

impl RowSource<'_> {
    fn fetch(&self, z: u32) -> Fetch {
        let (volume, key) = (self.volume.clone(), self.identity.row_key(self.stream, z));
        std::thread::spawn(move || volume.get(&key))
    }

    fn load(&self, z: u32) -> Result<Arc<Vec<BrickVoxels>>, StoreError> {
        let mut cache = self.row.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((at, row)) = &cache.current {
            if *at == z {
                return Ok(row.clone());
            }
        }
        let pending = match cache.next.take() {
            Some((at, handle)) if at == z => handle,
            _ => self.fetch(z),
        };
        if z + 1 < self.layout.grid(0)[2] {
            cache.next = Some((z + 1, self.fetch(z + 1)));
        }
        let key = self.identity.row_key(self.stream, z);
        let what = format!("{}/{key}", self.volume.url());
        let bytes = pending
            .join()
            .map_err(|_| StoreError::Internal("a row fetch panicked".into()))??
            .ok_or_else(|| {
                StoreError::Absent(format!(
                    "{what}: a finished part's row is missing (deleted?); run that part again after deleting its marker"
                ))
            })?;
        let row = Arc::new(decode_row(&bytes, &self.layout, &what)?);
        cache.current = Some((z, row.clone()));
        Ok(row)
    }

    fn brick(&self, key: BrickKey) -> Option<(Arc<Vec<BrickVoxels>>, usize)> {
        match self.load(key.z) {
            Ok(row) => Some((row, (key.y * self.layout.grid(0)[0] + key.x) as usize)),
            Err(e) => {
                self.failed.store(true, Ordering::Release);
                self.error.record(e);
                None
            }
        }
    }
}

impl BrickSource for RowSource<'_> {
    fn constant(&self, key: BrickKey) -> Option<u64> {
        let (row, i) = self.brick(key)?;
        match row.get(i)? {
            BrickVoxels::Constant(v) => Some(*v),
            BrickVoxels::Data(_) => None,
        }
    }

    fn fill(&self, key: BrickKey, out: &mut [u8]) {
        let Some((row, i)) = self.brick(key) else {
            return;
        };
        match row.get(i) {
            Some(BrickVoxels::Data(d)) if d.len() == out.len() => out.copy_from_slice(d),
            Some(BrickVoxels::Constant(v)) => {
                fill_constant(out, *v, self.layout.voxel_type());
            }
            _ => {}
        }
    }

    fn failed(&self) -> bool {
        self.failed.load(Ordering::Acquire)
    }
}

/// What [`finish`] did.
#[derive(Debug, Clone)]
pub struct Finished {
    /// The new volume's head.
    pub head: Head,
    /// How many parts were put together.
    pub parts: u32,
    /// How many parts the segment went up in (1: one PUT).
    pub upload_parts: u32,
    /// Objects of `parts/` deleted afterwards.
    pub deleted: usize,
}

/// The progress reports of [`finish`].
pub struct FinishProgress<'a> {
    /// Bricks built (every level).
    pub build: Arc<dyn Progress>,
    /// Bytes uploaded.
    pub upload: &'a dyn Progress,
    /// Lines for people.
    pub say: &'a mut dyn FnMut(&str),
}

impl std::fmt::Debug for FinishProgress<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FinishProgress").finish_non_exhaustive()
    }
}

/// Finishes the split import of the volume at `volume`: checks the markers of all parts
/// (`parts`: N, or `None` to take it from the markers), builds the volume in `tmp` (a local
/// file, removed afterwards) from the stored rows, uploads it and creates its head
/// (`If-None-Match: *`), then deletes the import's objects under `parts/`.
///
/// # Errors
/// A part is missing or was of another volume (the error names it), the volume exists, a row
/// is missing or damaged, the file cannot be written, or the store fails.
pub fn finish(
    volume: &Bucket,
    parts: Option<u32>,
    tmp: &Path,
    progress: FinishProgress<'_>,
) -> Result<Finished, StoreError> {
    let url = volume.url().to_string();
    if read_head(volume).is_ok() {
        return Err(StoreError::BadInput(format!(
            "{url} exists already (it has a head): nothing to finish"
        )));
    }
    // Every marker there is, by N and then I.
    let mut markers: BTreeMap<u32, BTreeMap<u32, String>> = BTreeMap::new();
    for object in volume.list(PARTS_DIR)? {
        let Some(name) = object
            .key
            .strip_prefix(&format!("{PARTS_DIR}/"))
            .and_then(|k| k.strip_suffix(".json"))
        else {
            continue;
        };
        let Some((i, n)) = name.split_once("-of-") else {
            continue;
        };
        if let (Ok(i), Ok(n)) = (i.parse::<u32>(), n.parse::<u32>()) {
            markers.entry(n).or_default().insert(i, object.key);
        }
    }
    let n = match parts {
        Some(n) => n,
        None => match markers.keys().collect::<Vec<_>>().as_slice() {
            [] => {
                return Err(StoreError::BadInput(format!(
                    "{url}: no part has finished (no marker under {url}/{PARTS_DIR}/); run `isovox import SRC -o {url} --part I/N` for each I first"
                )))
            }
            [n] => **n,
            several => {
                return Err(StoreError::BadInput(format!(
                    "{url}: markers of imports split {} ways are there; say which with --parts N",
                    several
                        .iter()
                        .map(|n| n.to_string())
                        .collect::<Vec<_>>()
                        .join(" and ")
                )))
            }
        },
    };
    if n == 0 || n > MAX_PARTS {
        return Err(StoreError::BadInput(format!(
            "--parts {n}: N must be 1 to {MAX_PARTS}"
        )));
    }
    let found = markers.remove(&n).unwrap_or_default();
    let missing: Vec<u32> = (0..n).filter(|i| !found.contains_key(i)).collect();
    if let Some(first) = missing.first() {
        let list: Vec<String> = missing.iter().map(|i| format!("{i}/{n}")).collect();
        return Err(StoreError::BadInput(format!(
            "{url}: part {first}/{n} has not finished (no marker {url}/{}); missing: {}. Run `isovox import SRC -o {url} --part I/{n}` for each",
            marker_key(*first, n),
            list.join(", ")
        )));
    }
    let mut identity: Option<(u32, Identity, String)> = None;
    for (i, key) in &found {
        let bytes = volume.get(key)?.ok_or_else(|| {
            StoreError::Absent(format!("{url}/{key}: the marker went away while read"))
        })?;
        let marker: Marker = serde_json::from_slice(&bytes)
            .map_err(|e| StoreError::corrupt(0, format!("{url}/{key}"), e.to_string()))?;
        if marker.part != *i || marker.parts != n {
            return Err(StoreError::corrupt(
                0,
                format!("{url}/{key}"),
                format!("it says part {}/{}", marker.part, marker.parts),
            ));
        }
        let this = marker.identity(&url)?;
        match &identity {
            None => identity = Some((*i, this, marker.volume.clone())),
            Some((first, id, volume_text)) => {
                if id.fingerprint != this.fingerprint {
                    return Err(StoreError::BadInput(format!(
                        "{url}: part {i}/{n} is of another volume than part {first}/{n}: {} (compression {}) against {volume_text} (compression {}); run part {i}/{n} again with the same input and options",
                        marker.volume,
                        marker.compression,
                        compression_name(id.compression)
                    )));
                }
            }
        }
    }
    let Some((_, identity, text)) = identity else {
        return Err(StoreError::Internal("no marker after the check".into()));
    };
    let header = identity.header.clone();
    (progress.say)(&format!(
        "{url}: all {n} parts there ({text}); building the levels above level 0"
    ));
    let sources: Vec<RowSource<'_>> = (0..1 + header.channels.len())
        .map(|s| {
            let layout = header
                .stream_layout(s)
                .ok_or_else(|| StoreError::Internal(format!("no stream {s}")))?;
            Ok(RowSource {
                volume,
                identity: &identity,
                stream: s,
                layout,
                row: Mutex::new(RowCache::default()),
                error: FirstError::default(),
                failed: AtomicBool::new(false),
            })
        })
        .collect::<Result<_, StoreError>>()?;
    let refs: Vec<&dyn BrickSource> = sources.iter().map(|s| s as &dyn BrickSource).collect();
    let options = BuildOptions {
        compression: identity.compression,
        progress: progress.build.clone(),
    };
    let built = build_streams(tmp, header, &refs, &options);
    drop(refs);
    // A row that could not be read stopped the build: its error says which.
    for source in sources {
        if let Err(e) = source.error.finish() {
            let _ = std::fs::remove_file(tmp);
            return Err(e);
        }
    }
    let report = match built {
        Ok(r) => r,
        Err(e) => {
            let _ = std::fs::remove_file(tmp);
            return Err(e);
        }
    };
    (progress.say)(&format!(
        "{url}: built {} bytes; uploading",
        report.file_bytes
    ));
    let uploaded = upload_with(volume, tmp, None, progress.upload);
    let _ = std::fs::remove_file(tmp);
    let (head, upload_parts) = match uploaded {
        Ok(done) => done,
        Err(StoreError::HeadMoved { .. }) => {
            return Err(StoreError::BadInput(format!(
                "{url} was created meanwhile by another writer; this finish changed nothing"
            )))
        }
        Err(e) => return Err(e),
    };
    // The volume is committed; the rows and markers are garbage now.
    let mut deleted = 0;
    for object in volume.list(PARTS_DIR)? {
        volume.delete(&object.key)?;
        deleted += 1;
    }
    Ok(Finished {
        head,
        parts: n,
        upload_parts,
        deleted,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use isovox_proto::VoxelType;

    #[test]
    fn parts_cover_every_row_once_in_pairs() {
        // 63 rows (brick 16 of 1000) and 16 rows (brick 32 of 512).
        for (dims, brick) in [([300, 200, 1000], 16), ([512, 512, 512], 32)] {
            let layout = VolumeLayout::new(dims, brick, VoxelType::U8).unwrap();
            let gz = layout.grid(0)[2];
            for n in [1, 2, 3, 4, 7, 64] {
                let mut next = 0;
                for i in 0..n {
                    let r = part_rows(&layout, i, n);
                    assert_eq!(r.start, next, "{dims:?} part {i}/{n}");
                    assert!(
                        r.start.is_multiple_of(2) || r.is_empty(),
                        "{dims:?} part {i}/{n}: {r:?}"
                    );
                    next = r.end;
                }
                assert_eq!(next, gz, "{dims:?} n {n}: every row belongs to a part");
            }
        }
        // 16 rows in 4 parts: 4 each.
        let layout = VolumeLayout::new([512, 512, 512], 32, VoxelType::U8).unwrap();
        assert_eq!(part_rows(&layout, 2, 4), 8..12);
    }

    #[test]
    fn part_arguments_are_checked() {
        assert_eq!(parse_part("0/4"), Ok((0, 4)));
        assert_eq!(parse_part("3/4"), Ok((3, 4)));
        for bad in ["4/4", "1", "a/4", "1/0", "-1/4", "0/10001"] {
            assert!(parse_part(bad).is_err(), "{bad}");
        }
        assert!(parse_part("4/4").unwrap_err().contains("0 to 3"));
    }

    #[test]
    fn rows_round_trip_and_damage_is_an_error() {
        let layout = VolumeLayout::new([8, 4, 4], 4, VoxelType::U16).unwrap();
        let data: Vec<u8> = (0..128u32).map(|i| (i * 7) as u8).collect();
        let row = vec![BrickVoxels::Constant(40000), BrickVoxels::Data(data)];
        let bytes = encode_row(&row).unwrap();
        assert_eq!(decode_row(&bytes, &layout, "row").unwrap(), row);
        let mut cut = bytes.clone();
        cut.truncate(cut.len() - 3);
        assert!(decode_row(&cut, &layout, "row").is_err());
        let wider = VolumeLayout::new([12, 4, 4], 4, VoxelType::U16).unwrap();
        let e = decode_row(&bytes, &wider, "row").unwrap_err().to_string();
        assert!(e.contains("2 bricks"), "{e}");
        assert!(decode_row(b"nonsense", &layout, "row").is_err());
    }

    #[test]
    fn compression_names_round_trip() {
        for c in [
            Compression::Zstd(3),
            Compression::Zstd(19),
            Compression::Lz4,
            Compression::None,
        ] {
            assert_eq!(parse_compression(&compression_name(c)), Some(c));
        }
        assert_eq!(parse_compression("zstd:x"), None);
    }
}
