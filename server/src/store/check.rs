//! Checking a whole VOD 2 file: every record of every version it holds, and which versions are
//! intact.
//!
//! Opening a file reads only what its newest version needs, lazily; this reads everything,
//! eagerly. Commit records are found by scanning the committed region for their magic and
//! checksum rather than by walking parent offsets from the head, so that versions older than a
//! damaged commit record (whose parent offset cannot be trusted) are still found. Then:
//! - every commit record a valid one (or a header slot) names as its parent (or head) must be
//!   valid, with the version before it;
//! - every index checkpoint a commit names is read whole: its directory, every chunk (decoded
//!   and checked against its hash) and every entry (a constant in range, or a brick record
//!   inside the committed region);
//! - every brick record an entry points at (from a checkpoint or a commit's changes) has a
//!   valid header, a payload matching its checksum, and decodes to its content hash.
//!
//! A version is *readable* when its commit chain back to its checkpoint and that checkpoint are
//! intact (its index can be loaded), and *intact* when, besides, every brick it points at is.
//! A server serves the newest readable version of a file whose head does not open (read-only;
//! a damaged brick is a 500 for that brick, as always); `isovox salvage` copies the newest
//! intact one.
//!
//! Cost: one pass over the committed region for the scan, one decode of each checkpoint, and
//! (at [`Depth::Everything`]) one decode of each distinct brick record, in parallel.

use super::vod2::{decode_stored, SlotState, Vod2File};
use super::{error_chain, StoreError, StoredBrick, Vod2};
use crate::progress::Progress;
use isovox_proto::vod2::{
    CommitHeader, NodeEntry, CHUNK_ENTRIES, COMMIT_FIXED_LEN, DATA_START, SLOT_OFFSETS,
};
use isovox_proto::VoxelType;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::Path;

/// How deep [`check`] reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Depth {
    /// Header, slots, commit records, index checkpoints: which versions can be loaded.
    Index,
    /// Also every brick record any version points at: which versions are intact.
    Everything,
}

/// One damaged structure of a file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Damage {
    /// Where it starts in the file.
    pub offset: u64,
    /// What it is: a header slot, commit record, index checkpoint or brick record.
    pub record: &'static str,
    /// What is wrong with it.
    pub detail: String,
}

/// One version of a checked file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct VersionCheck {
    /// The version.
    pub version: u64,
    /// Offset of its commit record.
    pub commit: u64,
    /// Why its index cannot be loaded (a damaged commit on its chain, a damaged checkpoint),
    /// or `None`.
    pub index_damage: Option<String>,
    /// Index entries that point at damaged brick records (0 unless bricks were checked).
    pub damaged_bricks: u64,
}

impl VersionCheck {
    /// Whether its index can be loaded.
    pub fn readable(&self) -> bool {
        self.index_damage.is_none()
    }

    /// Whether every record it needs is intact (bricks included, when they were checked).
    pub fn intact(&self) -> bool {
        self.readable() && self.damaged_bricks == 0
    }
}

/// What [`check`] found.
#[derive(Debug, Clone, Serialize)]
pub struct CheckReport {
    /// The file's length.
    pub file_bytes: u64,
    /// The committed length the newest valid header slot names (the whole file when none is
    /// valid); bytes past it are an unfinished commit, not damage.
    pub committed_bytes: u64,
    /// The version the header slots name as the newest durable one (`None`: no valid slot).
    pub head: Option<u64>,
    /// Every version whose commit record was found, oldest first.
    pub versions: Vec<VersionCheck>,
    /// Everything damaged, by offset.
    pub damage: Vec<Damage>,
    /// Distinct brick records checked (0 at [`Depth::Index`]).
    pub bricks: u64,
    /// Of them, records written before payload checksums (verified by decoding only).
    pub bricks_without_checksum: u64,
}

impl CheckReport {
    /// Whether anything is damaged.
    pub fn is_damaged(&self) -> bool {
        !self.damage.is_empty()
    }

    /// The newest version whose index can be loaded.
    pub fn newest_readable(&self) -> Option<&VersionCheck> {
        self.versions.iter().rev().find(|v| v.readable())
    }

    /// The newest version every record of which is intact.
    pub fn newest_intact(&self) -> Option<&VersionCheck> {
        self.versions.iter().rev().find(|v| v.intact())
    }

    /// The check of `version`, if its commit record was found.
    pub fn version(&self, version: u64) -> Option<&VersionCheck> {
        self.versions.iter().find(|v| v.version == version)
    }

    /// One line on what is damaged first (by offset), for logs and error messages.
    pub fn summary(&self) -> String {
        match self.damage.first() {
            None => "nothing is damaged".into(),
            Some(d) => format!(
                "{} damaged record(s), the first a {} at offset {}: {}",
                self.damage.len(),
                d.record,
                d.offset,
                d.detail
            ),
        }
    }
}

/// Checks the file at `path` to `depth` (see the module's documentation).
///
/// # Errors
/// The file cannot be read, or its file header is damaged (nothing else can be read without
/// the volume's shape). Damage anywhere else is reported, not an error.
pub fn check(
    path: &Path,
    depth: Depth,
    progress: &dyn Progress,
) -> Result<CheckReport, StoreError> {
    let file = Vod2File::open(path)?;
    let mut damage = Vec::new();
    for (state, at) in file.slots().iter().zip(SLOT_OFFSETS) {
        if let SlotState::Invalid(why) = state {
            damage.push(Damage {
                offset: at,
                record: "header slot",
                detail: why.clone(),
            });
        }
    }
    let commits = scan_commits(file.mapped());
    check_chain(&file, &commits, &mut damage);

    // Every checkpoint, whole; then the state of every version, oldest first.
    let mut checkpoints: HashMap<u64, Result<HashMap<u64, VoxelType>, String>> = HashMap::new();
    for h in commits.values() {
        if h.checkpoint != 0 && !checkpoints.contains_key(&h.checkpoint) {
            let read = read_checkpoint(&file, &commits, h.checkpoint);
            if let Err(why) = &read {
                damage.push(Damage {
                    offset: h.checkpoint,
                    record: "index checkpoint",
                    detail: why.clone(),
                });
            }
            checkpoints.insert(h.checkpoint, read);
        }
    }
    let mut versions = version_states(&file, &commits, &checkpoints, &mut damage);

    let (mut bricks, mut without_checksum) = (0, 0);
    if depth == Depth::Everything {
        let mut referenced: HashMap<u64, VoxelType> = HashMap::new();
        for offsets in checkpoints.values().flatten() {
            referenced.extend(offsets);
        }
        for &at in commits.keys() {
            referenced.extend(stored_changes(&file, at));
        }
        let mut offsets: Vec<(u64, VoxelType)> = referenced.into_iter().collect();
        offsets.sort_unstable_by_key(|&(offset, _)| offset);
        progress.start(offsets.len() as u64);
        let checked: Vec<(u64, Result<bool, StoreError>)> = offsets
            .par_iter()
            .map(|&(offset, voxel_type)| {
                let r = check_brick(&file, offset, voxel_type);
                progress.advance(1);
                (offset, r)
            })
            .collect();
        progress.finish();
        let mut damaged = HashSet::new();
        for (offset, r) in checked {
            bricks += 1;
            match r {
                Ok(had_checksum) => without_checksum += u64::from(!had_checksum),
                Err(e) => {
                    damaged.insert(offset);
                    damage.push(Damage {
                        offset,
                        record: "brick record",
                        detail: error_chain(&e),
                    });
                }
            }
        }
        if !damaged.is_empty() {
            count_damaged_bricks(&file, &commits, &mut versions, &damaged);
        }
    }
    damage.sort_by_key(|d| d.offset);
    damage.dedup();
    Ok(CheckReport {
        file_bytes: file.file_len(),
        committed_bytes: file.mapped().len() as u64,
        head: file.head_slot().map(|s| s.version),
        versions,
        damage,
        bricks,
        bricks_without_checksum: without_checksum,
    })
}

/// Opens `path` at its newest readable version when its newest durable one does not open:
/// what a server serves, read-only, from a damaged file. Returns the file and the check that
/// chose the version.
///
/// # Errors
/// No version of the file can be loaded, or the file cannot be read at all.
pub fn open_newest_readable(path: &Path) -> Result<(Vod2, CheckReport), StoreError> {
    let report = check(path, Depth::Index, &crate::progress::Silent)?;
    let Some(newest) = report.newest_readable() else {
        return Err(isovox_proto::FormatError::invalid(
            "VOD 2 file",
            format!("no version can be read: {}", report.summary()),
        )
        .into());
    };
    let vod = Vod2File::open(path)?.into_version(newest.commit)?;
    Ok((vod, report))
}

/// Every valid commit record of the committed region, by offset: wherever its magic is
/// followed by a record whose checksum holds (a record's bytes are checked, so a stray
/// magic inside other data is not taken for one).
fn scan_commits(mapped: &[u8]) -> BTreeMap<u64, CommitHeader> {
    const MAGIC: &[u8; 4] = b"VCMT";
    let mut found = BTreeMap::new();
    let start = DATA_START as usize;
    if mapped.len() < start + COMMIT_FIXED_LEN {
        return found;
    }
    let mut at = start;
    while let Some(i) = mapped[at..].windows(4).position(|w| w == MAGIC) {
        let offset = at + i;
        if let Ok((h, _)) = CommitHeader::decode(&mapped[offset..], offset as u64) {
            found.insert(offset as u64, h);
        }
        at = offset + 1;
    }
    found
}

/// Why the commit record at `at` does not read.
fn commit_error(mapped: &[u8], at: u64) -> String {
    match mapped.get(at as usize..) {
        None => format!("offset {at} is past the committed length {}", mapped.len()),
        Some(region) => match CommitHeader::decode(region, at) {
            Err(e) => e.to_string(),
            Ok(_) => "it reads".into(),
        },
    }
}

/// Damage on the commit chain: a head or parent named but not valid, a parent of another
/// version than the one before.
fn check_chain(file: &Vod2File, commits: &BTreeMap<u64, CommitHeader>, damage: &mut Vec<Damage>) {
    let mapped = file.mapped();
    if let Some(slot) = file.head_slot() {
        if !commits.contains_key(&slot.commit) {
            damage.push(Damage {
                offset: slot.commit,
                record: "commit record",
                detail: format!(
                    "the head (version {}, named by the header slot): {}",
                    slot.version,
                    commit_error(mapped, slot.commit)
                ),
            });
        }
    }
    for (&at, h) in commits {
        if h.parent == 0 {
            continue;
        }
        match commits.get(&h.parent) {
            None => damage.push(Damage {
                offset: h.parent,
                record: "commit record",
                detail: format!(
                    "the parent of version {} (expected version {}): {}",
                    h.version,
                    h.version.wrapping_sub(1),
                    commit_error(mapped, h.parent)
                ),
            }),
            Some(p) if p.version.checked_add(1) != Some(h.version) => damage.push(Damage {
                offset: at,
                record: "commit record",
                detail: format!(
                    "version {} names a parent of version {} at {}",
                    h.version, p.version, h.parent
                ),
            }),
            Some(_) => {}
        }
    }
}

/// Reads the checkpoint at `at` whole (directory, chunks, entries) through the commit that
/// names it; returns the brick records its entries point at, or why it does not read.
fn read_checkpoint(
    file: &Vod2File,
    commits: &BTreeMap<u64, CommitHeader>,
    at: u64,
) -> Result<HashMap<u64, VoxelType>, String> {
    let (&commit, _) = commits
        .iter()
        .find(|(_, h)| h.checkpoint == at)
        .ok_or_else(|| "no commit names it".to_string())?;
    let snap = file.snapshot_at(commit).map_err(|e| error_chain(&e))?;
    let mut bricks = HashMap::new();
    let mut problems = Vec::new();
    // The checkpoint commit's own state is the checkpoint's (its changes are already in it),
    // so every entry read here comes from the checkpoint itself.
    let nodes = snap.layout().node_count();
    for view in snap.streams() {
        let base = view.stream() as u64 * nodes;
        let mut node = 0;
        while node < nodes {
            match view.entry_at(node) {
                Ok(entry @ NodeEntry::Stored(offset)) => {
                    bricks.insert(offset, view.layout().voxel_type());
                    // Revision 5: the summary stored beside the entry (its block's hash and
                    // ranges checked) must say what the record's header says. A damaged
                    // header is the brick check's to report.
                    match (view.summary_at(node), view.entry_summary(entry)) {
                        (Err(e), _) => problems.push(format!(
                            "summary of entry {}: {}",
                            base + node,
                            error_chain(&e)
                        )),
                        (Ok(indexed), Ok(header)) if indexed != header => problems.push(format!(
                            "summary of entry {} is {indexed:?}, its brick record's header \
                                 says {header:?}",
                            base + node
                        )),
                        _ => {}
                    }
                }
                Ok(NodeEntry::Constant(_)) => {}
                Err(e) => {
                    let at = base + node;
                    let chunk = at / CHUNK_ENTRIES;
                    problems.push(format!("chunk {chunk}, entry {at}: {}", error_chain(&e)));
                    // A chunk that does not decode fails for each of its entries: say it once.
                    node = (chunk + 1) * CHUNK_ENTRIES - base;
                    continue;
                }
            }
            node += 1;
        }
    }
    if problems.is_empty() {
        Ok(bricks)
    } else {
        Err(problems.join("; "))
    }
}

/// Whether each version's index can be loaded, oldest first; damage in commit changes is
/// added to `damage`.
fn version_states(
    file: &Vod2File,
    commits: &BTreeMap<u64, CommitHeader>,
    checkpoints: &HashMap<u64, Result<HashMap<u64, VoxelType>, String>>,
    damage: &mut Vec<Damage>,
) -> Vec<VersionCheck> {
    let mut order: Vec<(u64, &CommitHeader)> = commits.iter().map(|(&at, h)| (at, h)).collect();
    order.sort_by_key(|(at, h)| (h.version, *at));
    let mut states: HashMap<u64, Option<String>> = HashMap::new();
    let mut out = Vec::with_capacity(order.len());
    for (at, h) in order {
        let mut why = if let Err(e) = changes_valid(file, at) {
            damage.push(Damage {
                offset: at,
                record: "commit record",
                detail: e.clone(),
            });
            Some(e)
        } else {
            None
        };
        if why.is_none() {
            why = if h.checkpoint != 0 {
                match checkpoints.get(&h.checkpoint) {
                    Some(Ok(_)) => None,
                    Some(Err(e)) => Some(format!("its index checkpoint at {}: {e}", h.checkpoint)),
                    None => Some(format!(
                        "its index checkpoint at {} was not read",
                        h.checkpoint
                    )),
                }
            } else {
                match (commits.get(&h.parent), states.get(&h.parent)) {
                    (Some(p), Some(None)) if p.version.checked_add(1) == Some(h.version) => None,
                    (Some(p), Some(Some(e))) if p.version.checked_add(1) == Some(h.version) => {
                        Some(format!("its parent, version {}: {e}", p.version))
                    }
                    _ => Some(format!(
                        "its parent commit record at {} (version {}) is damaged",
                        h.parent,
                        h.version.wrapping_sub(1)
                    )),
                }
            };
        }
        states.insert(at, why.clone());
        out.push(VersionCheck {
            version: h.version,
            commit: at,
            index_damage: why,
            damaged_bricks: 0,
        });
    }
    out
}

/// Checks a commit record's changes: nodes inside the volume, entries valid.
fn changes_valid(file: &Vod2File, at: u64) -> Result<(), String> {
    let header = file.header();
    let mapped = file.mapped();
    let (_, record) =
        CommitHeader::decode(&mapped[at as usize..], at).map_err(|e| e.to_string())?;
    for (node, raw) in CommitHeader::changes(record) {
        let (_, voxel_type) = header.stream_of(node).ok_or_else(|| {
            format!(
                "a change to node {node}; the file has {}",
                header.node_count()
            )
        })?;
        NodeEntry::decode(raw, voxel_type, mapped.len() as u64)
            .map_err(|e| format!("the change to node {node}: {e}"))?;
    }
    Ok(())
}

/// The entry of node `node` (file-wide) as its stream's type reads it.
fn decode_change(file: &Vod2File, node: u64, raw: u64) -> Option<NodeEntry> {
    let (_, voxel_type) = file.header().stream_of(node)?;
    NodeEntry::decode(raw, voxel_type, file.mapped().len() as u64).ok()
}

/// The brick records a commit record's changes point at, with their streams' value types.
fn stored_changes(file: &Vod2File, at: u64) -> Vec<(u64, VoxelType)> {
    let mapped = file.mapped();
    let Ok((_, record)) = CommitHeader::decode(&mapped[at as usize..], at) else {
        return Vec::new();
    };
    CommitHeader::changes(record)
        .filter_map(|(node, raw)| match decode_change(file, node, raw)? {
            NodeEntry::Stored(offset) => Some((offset, file.header().stream_of(node)?.1)),
            NodeEntry::Constant(_) => None,
        })
        .collect()
}

/// Checks one brick record (of a stream of `voxel_type`) whole: header, payload checksum,
/// decoded content hash. Returns whether it has a payload checksum.
fn check_brick(file: &Vod2File, offset: u64, voxel_type: VoxelType) -> Result<bool, StoreError> {
    let layout = file.header().layout.with_voxel_type(voxel_type);
    let stored = file.stored_as(offset, &layout)?;
    let had_checksum = matches!(
        stored,
        StoredBrick::Record {
            checksum: Some(_),
            ..
        }
    );
    stored.check_payload()?;
    let mut out = vec![0u8; layout.brick_bytes()];
    decode_stored(&stored, &layout, &mut out)?;
    Ok(had_checksum)
}

/// Counts, for every readable version, the index entries that point at a damaged brick
/// record: from its checkpoint's entries, then through the changes of each commit after it.
fn count_damaged_bricks(
    file: &Vod2File,
    commits: &BTreeMap<u64, CommitHeader>,
    versions: &mut [VersionCheck],
    damaged: &HashSet<u64>,
) {
    // Nodes pointing at damaged records, per commit offset, built oldest first.
    let mut bad: HashMap<u64, HashSet<u64>> = HashMap::new();
    for v in versions.iter_mut().filter(|v| v.readable()) {
        let Some(h) = commits.get(&v.commit) else {
            continue;
        };
        let nodes = if h.checkpoint != 0 {
            let Ok(snap) = file.snapshot_at(v.commit) else {
                continue;
            };
            let n = snap.layout().node_count();
            snap.streams()
                .flat_map(|view| {
                    (0..n)
                        .filter(|&node| {
                            matches!(view.entry_at(node), Ok(NodeEntry::Stored(o)) if damaged.contains(&o))
                        })
                        .map(move |node| view.stream() as u64 * n + node)
                })
                .collect()
        } else {
            // A version is the only child of the one before it: its set moves on.
            let mut nodes = bad.remove(&h.parent).unwrap_or_default();
            let mapped = file.mapped();
            if let Ok((_, record)) = CommitHeader::decode(&mapped[v.commit as usize..], v.commit) {
                for (node, raw) in CommitHeader::changes(record) {
                    match decode_change(file, node, raw) {
                        Some(NodeEntry::Stored(o)) if damaged.contains(&o) => nodes.insert(node),
                        _ => nodes.remove(&node),
                    };
                }
            }
            nodes
        };
        v.damaged_bricks = nodes.len() as u64;
        bad.insert(v.commit, nodes);
    }
}
