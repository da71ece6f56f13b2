//! Truncated, corrupted and hostile files.
//!
//! Proves that for a small valid VOD 2 file with four versions, and for VOD 1 files (lz4 and
//! uncompressed), every truncation point and thousands of seeded single-byte flips never make
//! opening or reading panic: each attempt gives an error with a message, or bricks exactly equal
//! to the expected content of the version the file reports (where the outcome is fully
//! determined - a flip in unused padding, in a header, in a slot - the exact outcome is checked).
//! A counting global allocator shows that no single allocation made while opening or reading a
//! hostile file exceeds the file's length plus 1 MiB. Property tests feed arbitrary bytes, and
//! records with valid checksums but arbitrary fields, to every decoder of `isovox_proto::vod2`
//! and to `Vod1::parse`. Crafted files with valid checksums probe the arithmetic on versions and
//! sequence numbers.

// unwrap is how a test says "this must work"; clippy exempts only #[test] functions.

use isovox_proto::layout::MAX_NODES;
use isovox_proto::vod2::{
    content_hash, BrickHeader, Checkpoint, CommitHeader, FileHeader, HeaderSlot, NodeEntry,
    CHECKPOINT_FIXED_LEN, CHUNK_REF_LEN, DATA_START, HEADER_LEN, SLOT_LEN, SLOT_OFFSETS,
};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::progress::Silent;
use isovox_server::store::codec::Compression;
use isovox_server::store::inspect::inspect;
use isovox_server::store::vod1::{write_vod1, Vod1};
use isovox_server::store::{build_vod2, BrickVoxels, BuildOptions, DenseGrid, Vod2, Vod2Writer};
use proptest::prelude::*;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard, OnceLock};

use crate::common;
use common::{mixed_volume, pyramid, XorShift};

/// The new content of a brick in an appended version.
enum Content {
    /// Voxels, stored through the writer (deduplicated, compressed).
    Data(Vec<u8>),
    /// One value everywhere, committed directly as `NodeEntry::Constant`.
    Constant(u16),
}
use Content::{Constant, Data};

// ---------------------------------------------------------------------------------------------
// The counting allocator.

/// Wraps the system allocator and, on threads that are measuring, records the largest single
/// allocation (or reallocation) size.
struct LargestAllocation;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    static MEASURING: Cell<bool> = const { Cell::new(false) };
}

fn note(size: usize) {
    if MEASURING.try_with(Cell::get).unwrap_or(false) {
        LARGEST.fetch_max(size, Ordering::Relaxed);
    }
}

// SAFETY: every call is forwarded unchanged to `System`; the bookkeeping neither allocates nor
// touches the memory.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for LargestAllocation {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: LargestAllocation = LargestAllocation;

/// `LARGEST` is global: tests that measure take turns.
fn measuring_lock() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// Runs `f` on this thread while recording allocations, and checks the largest against the
/// hostile file's length plus 1 MiB. The caller holds `measuring_lock()`.
fn within_allocation_bound<R>(file_len: usize, what: &str, f: impl FnOnce() -> R) -> R {
    LARGEST.store(0, Ordering::SeqCst);
    MEASURING.with(|m| m.set(true));
    let r = f();
    MEASURING.with(|m| m.set(false));
    let largest = LARGEST.load(Ordering::SeqCst);
    assert!(
        largest <= file_len + (1 << 20),
        "{what}: an allocation of {largest} bytes for a file of {file_len} bytes"
    );
    r
}

#[test]
fn the_allocator_sees_allocations_while_measuring() {
    let _lock = measuring_lock();
    let v = within_allocation_bound(1 << 20, "self-test", || vec![0u8; 12345]);
    assert_eq!(LARGEST.load(Ordering::SeqCst), 12345);
    drop(v);
}

// ---------------------------------------------------------------------------------------------
// The valid files and what they hold.

type Contents = Vec<Vec<u8>>;

struct Fixture {
    layout: VolumeLayout,
    /// The VOD 2 file's bytes (head: version 4).
    vod2: Vec<u8>,
    /// Expected content of every node, per version (index 0 is version 1).
    versions: Vec<Contents>,
    /// The file's committed length after each version's commit.
    committed: Vec<usize>,
    /// VOD 1 files of version 4: lz4-compressed and uncompressed.
    vod1_lz4: Vec<u8>,
    vod1_plain: Vec<u8>,
}

fn noise(len: usize, seed: u64) -> Vec<u8> {
    let mut rng = XorShift(seed);
    (0..len).map(|_| rng.next() as u8).collect()
}

fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("valid.vod");
        let volume = mixed_volume([20, 12, 9], VoxelType::U8, 51);
        let layout = VolumeLayout::new([20, 12, 9], 4, VoxelType::U8).unwrap();
        let bytes = volume.to_bytes(VoxelType::U8);
        let grid = DenseGrid::new([20, 12, 9], VoxelType::U8, 4, &bytes);
        let options = BuildOptions {
            compression: Compression::Zstd(3),
            progress: std::sync::Arc::new(Silent),
        };
        build_vod2(&path, &layout, [1.0; 3], &grid, &options).unwrap();
        let levels = pyramid(&volume, 4);
        let v1: Contents = (0..layout.node_count())
            .map(|n| {
                let k = layout.key_of(n).unwrap();
                levels[k.level as usize].brick(
                    [k.x, k.y, k.z].map(|c| c as usize),
                    4,
                    VoxelType::U8,
                )
            })
            .collect();
        let mut versions = vec![v1];
        let mut committed = vec![std::fs::metadata(&path).unwrap().len() as usize];
        let node = |l, x, y, z| layout.node_index(layout.key(l, x, y, z).unwrap());
        let two_runs: Vec<u8> = (0..64).map(|i| if i < 32 { 1 } else { 2 }).collect();
        let commits: Vec<(Vec<(u64, Content)>, bool)> = vec![
            (
                vec![
                    (node(0, 4, 2, 2), Data(noise(64, 1))),
                    (node(0, 0, 0, 0), Constant(200)),
                    (node(1, 1, 1, 1), Data(two_runs)),
                ],
                false,
            ),
            (
                vec![
                    (node(0, 4, 2, 2), Data(noise(64, 2))),
                    (node(0, 1, 1, 1), Data(noise(64, 3))),
                ],
                true,
            ),
            (
                vec![
                    (node(0, 2, 0, 2), Constant(0)),
                    (node(2, 0, 0, 0), Data(noise(64, 4))),
                    (node(0, 3, 2, 0), Data(noise(64, 3))),
                ],
                false,
            ),
        ];
        for (changes, checkpoint) in commits {
            let mut model = versions[versions.len() - 1].clone();
            let mut w = Vod2Writer::open_append(&path, Compression::Zstd(3)).unwrap();
            let mut entries = Vec::new();
            for (n, content) in changes {
                let entry = match content {
                    Data(bytes) => {
                        let v = BrickVoxels::Data(bytes.clone());
                        let p = w.prepare(&v);
                        model[n as usize] = bytes;
                        w.store(&v, p).unwrap()
                    }
                    Constant(value) => {
                        model[n as usize] = vec![value as u8; 64];
                        NodeEntry::Constant(value.into())
                    }
                };
                entries.push((n, entry));
            }
            if checkpoint {
                let vod = Vod2::open(&path).unwrap();
                let head = vod.head();
                let mut full: Vec<u64> = (0..layout.node_count())
                    .map(|n| head.entry_at(n).unwrap().encode())
                    .collect();
                for (n, e) in &entries {
                    full[*n as usize] = e.encode();
                }
                w.commit(&entries, Some(&full)).unwrap();
            } else {
                w.commit(&entries, None).unwrap();
            }
            versions.push(model);
            committed.push(std::fs::metadata(&path).unwrap().len() as usize);
        }
        let vod = Vod2::open(&path).unwrap();
        assert_eq!(vod.head().version, 4);
        let mut vod1_lz4 = Vec::new();
        write_vod1(&vod.head(), true, &mut vod1_lz4).unwrap();
        let mut vod1_plain = Vec::new();
        write_vod1(&vod.head(), false, &mut vod1_plain).unwrap();
        Fixture {
            layout,
            vod2: std::fs::read(&path).unwrap(),
            versions,
            committed,
            vod1_lz4,
            vod1_plain,
        }
    })
}

#[test]
fn the_fixture_reads_back_every_version() {
    let fx = fixture();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f.vod");
    let _lock = measuring_lock();
    let outcome = check_vod2(fx, &fx.vod2, &path, "the valid file");
    assert_eq!(
        outcome,
        Outcome::Opened {
            version: 4,
            all_read: true
        }
    );
    assert_eq!(fx.committed.len(), 4);
    assert_eq!(*fx.committed.last().unwrap(), fx.vod2.len());
    for bytes in [&fx.vod1_lz4, &fx.vod1_plain] {
        assert_eq!(
            check_vod1(fx, bytes, None, "valid VOD 1"),
            Outcome::Opened {
                version: 1,
                all_read: true
            }
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Checking one (possibly damaged) file.

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Outcome {
    /// Opening failed with a message.
    Rejected,
    /// The file opened at this head version; `all_read` is false if any brick gave an error.
    Opened { version: u64, all_read: bool },
}

fn error_has_message(e: &dyn std::fmt::Display, what: &str) {
    assert!(
        !e.to_string().trim().is_empty(),
        "{what}: an error without a message"
    );
}

/// Opens `bytes` as a VOD 2 file and reads every brick of every level of every version from the
/// head down; each read is an error with a message or exactly that version's content.
fn check_vod2(fx: &Fixture, bytes: &[u8], path: &Path, what: &str) -> Outcome {
    std::fs::write(path, bytes).unwrap();
    within_allocation_bound(bytes.len(), what, || {
        let vod = match Vod2::open(path) {
            Ok(vod) => vod,
            Err(e) => {
                error_has_message(&e, what);
                return Outcome::Rejected;
            }
        };
        assert_eq!(
            *vod.layout(),
            fx.layout,
            "{what}: the layout is checksummed"
        );
        let head = vod.head().version;
        assert!(
            (1..=4).contains(&head),
            "{what}: version {head} was never written"
        );
        let mut all_read = true;
        for version in (1..=head).rev() {
            let snap = match vod.version(version) {
                Ok(s) => s,
                Err(e) => {
                    error_has_message(&e, what);
                    all_read = false;
                    continue;
                }
            };
            assert_eq!(snap.version, version, "{what}");
            let expected = &fx.versions[version as usize - 1];
            for (node, content) in expected.iter().enumerate() {
                let key = fx.layout.key_of(node as u64).unwrap();
                match snap.read(key) {
                    Ok(got) => assert!(
                        got == *content,
                        "{what}: version {version} brick {key} read without error but wrong"
                    ),
                    Err(e) => {
                        error_has_message(&e, what);
                        all_read = false;
                    }
                }
            }
        }
        if let Err(e) = inspect(&vod) {
            error_has_message(&e, what);
        }
        Outcome::Opened {
            version: head,
            all_read,
        }
    })
}

/// Preorder position of every key of the complete octree of `height` levels (children x
/// fastest, then y, then z), written from the spec's wording.
fn preorder_positions(height: u32) -> HashMap<BrickKey, usize> {
    fn visit(key: BrickKey, out: &mut HashMap<BrickKey, usize>) {
        let n = out.len();
        out.insert(key, n);
        if key.level == 0 {
            return;
        }
        for (cx, cy, cz) in (0..8).map(|o| (o & 1, o >> 1 & 1, o >> 2)) {
            let child = BrickKey {
                level: key.level - 1,
                x: 2 * key.x + cx,
                y: 2 * key.y + cy,
                z: 2 * key.z + cz,
            };
            visit(child, out);
        }
    }
    let mut out = HashMap::new();
    visit(
        BrickKey {
            level: height as u8 - 1,
            x: 0,
            y: 0,
            z: 0,
        },
        &mut out,
    );
    out
}

/// The content a VOD 1 file of the head version holds at `key`: the head's brick inside the
/// volume, all L elsewhere in the complete octree.
fn vod1_expected(fx: &Fixture, key: BrickKey) -> Vec<u8> {
    if fx.layout.contains(key) {
        fx.versions[3][fx.layout.node_index(key) as usize].clone()
    } else {
        vec![0u8; fx.layout.brick_bytes()]
    }
}

/// What a node of a VOD 1 file whose brick ID was changed to `id` must read as: all L for ID 0
/// (the thesis's empty node), the content of brick `id` if the file has it, an error otherwise.
fn vod1_content_of_id(fx: &Fixture, original: &[u8], id: u32) -> Option<Vec<u8>> {
    if id == 0 {
        return Some(vec![0u8; fx.layout.brick_bytes()]);
    }
    let height = fx.layout.levels() as u32;
    preorder_positions(height)
        .into_iter()
        .find(|&(_, n)| {
            u32::from_le_bytes(original[64 + 4 * n..68 + 4 * n].try_into().unwrap()) == id
        })
        .map(|(key, _)| vod1_expected(fx, key))
}

/// Parses `bytes` as VOD 1 and reads every brick of every level; each read is an error with a
/// message or the expected content. `node_flip` is (preorder node, its new brick ID) when the
/// damage is in the node array, which the thesis's layout stores without any checksum: that
/// node must then read exactly as the brick it now names.
fn check_vod1(
    fx: &Fixture,
    bytes: &[u8],
    node_flip: Option<(usize, Option<Vec<u8>>)>,
    what: &str,
) -> Outcome {
    within_allocation_bound(bytes.len(), what, || {
        let vod1 = match Vod1::parse(bytes) {
            Ok(v) => v,
            Err(e) => {
                error_has_message(&e, what);
                return Outcome::Rejected;
            }
        };
        let layout = &vod1.layout;
        let positions = preorder_positions(vod1.height);
        let mut all_read = true;
        let mut out = vec![0u8; layout.brick_bytes()];
        for level in 0..layout.levels() {
            let g = layout.grid(level);
            for z in 0..g[2] {
                for y in 0..g[1] {
                    for x in 0..g[0] {
                        let key = BrickKey { level, x, y, z };
                        let expected = match &node_flip {
                            Some((n, named)) if positions[&key] == *n => named.clone(),
                            _ => Some(vod1_expected(fx, key)),
                        };
                        match (vod1.read_into(key, &mut out), expected) {
                            (Ok(()), Some(expected)) => assert!(
                                out == expected,
                                "{what}: brick {key} read without error but wrong"
                            ),
                            (Ok(()), None) => panic!(
                                "{what}: brick {key} names a brick the file lacks, yet reads"
                            ),
                            (Err(e), _) => {
                                error_has_message(&e, what);
                                all_read = false;
                            }
                        }
                    }
                }
            }
        }
        Outcome::Opened {
            version: 1,
            all_read,
        }
    })
}

// ---------------------------------------------------------------------------------------------
// (a) Every truncation point.

#[test]
fn vod2_every_truncation_opens_as_an_older_version_or_fails() {
    let fx = fixture();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cut.vod");
    let _lock = measuring_lock();
    for len in 0..fx.vod2.len() {
        let outcome = check_vod2(fx, &fx.vod2[..len], &path, &format!("VOD 2 cut at {len}"));
        // Both slots name more bytes than the file has until version 3's length is reached;
        // from there on version 3's slot is the valid one with the highest sequence number.
        let expected = if len < fx.committed[2] {
            Outcome::Rejected
        } else {
            Outcome::Opened {
                version: 3,
                all_read: true,
            }
        };
        assert_eq!(outcome, expected, "VOD 2 cut at {len}");
    }
}

#[test]
fn vod1_every_truncation_fails() {
    let fx = fixture();
    let _lock = measuring_lock();
    for bytes in [&fx.vod1_lz4, &fx.vod1_plain] {
        for len in 0..bytes.len() {
            // The last brick's payload ends the file, and parsing checks every payload's bounds.
            let outcome = check_vod1(fx, &bytes[..len], None, &format!("VOD 1 cut at {len}"));
            assert_eq!(outcome, Outcome::Rejected, "VOD 1 cut at {len}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// (b) Seeded single-byte flips.

/// Flips `pos` to a different value drawn from `rng`.
fn flip(bytes: &mut [u8], pos: usize, rng: &mut XorShift) -> u8 {
    let old = bytes[pos];
    bytes[pos] = old ^ (1 + rng.below(255)) as u8;
    assert_ne!(bytes[pos], old);
    old
}

/// Which slot names version 4 (the head) and which version 3.
fn slots_by_version(fx: &Fixture) -> (usize, usize) {
    let decode =
        |at: u64| HeaderSlot::decode(&fx.vod2[at as usize..at as usize + SLOT_LEN], at).unwrap();
    let (a, b) = (decode(SLOT_OFFSETS[0]), decode(SLOT_OFFSETS[1]));
    assert_eq!([a.version.min(b.version), a.version.max(b.version)], [3, 4]);
    if a.version == 4 {
        (SLOT_OFFSETS[0] as usize, SLOT_OFFSETS[1] as usize)
    } else {
        (SLOT_OFFSETS[1] as usize, SLOT_OFFSETS[0] as usize)
    }
}

#[test]
fn vod2_random_byte_flips_never_give_wrong_voxels() {
    let fx = fixture();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("flipped.vod");
    let (head_slot, other_slot) = slots_by_version(fx);
    let len = fx.vod2.len();
    // The bytes version 4 appended, which its slot checks.
    let head_group = {
        let slot = HeaderSlot::decode(&fx.vod2[head_slot..head_slot + SLOT_LEN], 0).unwrap();
        let check = slot.appended.expect("version 4 was synced with its slot");
        check.from..slot.committed_len
    };
    // Half the flips anywhere; half in the bytes that hold records (header, slots, data).
    let structured: Vec<usize> = (0..HEADER_LEN)
        .chain(head_slot..head_slot + SLOT_LEN)
        .chain(other_slot..other_slot + SLOT_LEN)
        .chain(DATA_START as usize..len)
        .collect();
    let mut rng = XorShift(0x0BAD_F11E);
    let mut bytes = fx.vod2.clone();
    let mut seen = HashMap::new();
    let _lock = measuring_lock();
    for i in 0..6000 {
        let pos = if i % 2 == 0 {
            rng.below(len as u64) as usize
        } else {
            structured[rng.below(structured.len() as u64) as usize]
        };
        let old = flip(&mut bytes, pos, &mut rng);
        let what = format!("flip {i}: byte {pos} {old:#04x} -> {:#04x}", bytes[pos]);
        let outcome = check_vod2(fx, &bytes, &path, &what);
        *seen.entry(outcome).or_insert(0u32) += 1;
        // Where the outcome is determined, it is checked exactly.
        let in_slot = |s: usize| (s..s + SLOT_LEN).contains(&pos);
        if pos < HEADER_LEN {
            assert_eq!(
                outcome,
                Outcome::Rejected,
                "{what}: the file header is checksummed"
            );
        } else if in_slot(head_slot) {
            assert_eq!(
                outcome,
                Outcome::Opened {
                    version: 3,
                    all_read: true
                },
                "{what}: a damaged head slot falls back"
            );
        } else if in_slot(other_slot) {
            assert_eq!(
                outcome,
                Outcome::Opened {
                    version: 4,
                    all_read: true
                },
                "{what}: the older slot is not needed"
            );
        } else if pos < DATA_START as usize {
            assert_eq!(
                outcome,
                Outcome::Opened {
                    version: 4,
                    all_read: true
                },
                "{what}: padding is never read"
            );
        } else if head_group.contains(&(pos as u64)) {
            assert_eq!(
                outcome,
                Outcome::Opened {
                    version: 3,
                    all_read: true
                },
                "{what}: bytes synced with the head slot fail its check, which falls back"
            );
        } else {
            assert!(
                matches!(
                    outcome,
                    Outcome::Opened { version: 4, .. } | Outcome::Rejected
                ),
                "{what}: {outcome:?}"
            );
        }
        bytes[pos] = old;
    }
    // The flips reached both outcomes, and damaged bricks.
    assert!(seen.contains_key(&Outcome::Rejected), "{seen:?}");
    assert!(
        seen.contains_key(&Outcome::Opened {
            version: 4,
            all_read: false
        }),
        "{seen:?}"
    );
}

#[test]
fn vod1_random_byte_flips_never_give_wrong_voxels() {
    let fx = fixture();
    let height = fx.layout.levels() as usize;
    let n_nodes = (8usize.pow(height as u32) - 1) / 7;
    let mut rng = XorShift(0xF1_1FF1);
    let _lock = measuring_lock();
    for original in [&fx.vod1_lz4, &fx.vod1_plain] {
        let mut bytes = original.clone();
        let mut seen = HashMap::new();
        for i in 0..3000 {
            let pos = rng.below(bytes.len() as u64) as usize;
            let old = flip(&mut bytes, pos, &mut rng);
            let what = format!(
                "VOD 1 flip {i}: byte {pos} {old:#04x} -> {:#04x}",
                bytes[pos]
            );
            let node_flip = (64..64 + 4 * n_nodes).contains(&pos).then(|| {
                let n = (pos - 64) / 4;
                let id = u32::from_le_bytes(bytes[64 + 4 * n..68 + 4 * n].try_into().unwrap());
                (n, vod1_content_of_id(fx, original, id))
            });
            let outcome = check_vod1(fx, &bytes, node_flip, &what);
            *seen.entry(outcome).or_insert(0u32) += 1;
            bytes[pos] = old;
        }
        assert!(seen.contains_key(&Outcome::Rejected), "{seen:?}");
        assert!(
            seen.contains_key(&Outcome::Opened {
                version: 1,
                all_read: false
            }),
            "{seen:?}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Crafted files: records with valid checksums and extreme values.

/// Rewrites the commit record at `at` with `edit` applied to its header, resealing it.
fn reseal_commit(bytes: &mut [u8], at: usize, edit: impl FnOnce(&mut CommitHeader)) {
    let (mut h, record) = CommitHeader::decode(&bytes[at..], at as u64).unwrap();
    let len = h.total_len() as usize;
    let changes: Vec<(u64, NodeEntry)> = CommitHeader::changes(record)
        .map(|(n, raw)| (n, NodeEntry::decode(raw, VoxelType::U8, u64::MAX).unwrap()))
        .collect();
    let note = h.note(&bytes[at..]).to_vec();
    let summaries = h.summaries_in(&bytes[at..]);
    edit(&mut h);
    let encoded = h.encode(&changes, &note, summaries.as_deref());
    assert_eq!(encoded.len(), len);
    bytes[at..at + len].copy_from_slice(&encoded);
}

fn head_slot(bytes: &[u8]) -> (usize, HeaderSlot) {
    SLOT_OFFSETS
        .iter()
        .map(|&at| {
            (
                at as usize,
                HeaderSlot::decode(&bytes[at as usize..at as usize + SLOT_LEN], at).unwrap(),
            )
        })
        .max_by_key(|(_, s)| s.seq)
        .unwrap()
}

#[test]
fn parent_commit_claiming_the_largest_version_is_an_error() {
    // Version 4 is a delta on version 3. Give version 3's record (checksum resealed) the version
    // u64::MAX: opening must report a broken chain, not overflow computing "parent + 1".
    let fx = fixture();
    let mut bytes = fx.vod2.clone();
    let (_, slot) = head_slot(&bytes);
    let (head, _) = CommitHeader::decode(&bytes[slot.commit as usize..], slot.commit).unwrap();
    assert_eq!((head.version, head.checkpoint), (4, 0));
    reseal_commit(&mut bytes, head.parent as usize, |h| h.version = u64::MAX);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("crafted.vod");
    std::fs::write(&path, &bytes).unwrap();
    let _lock = measuring_lock();
    let result = std::panic::catch_unwind(|| Vod2::open(&path).map(|v| v.head().version));
    match result {
        Ok(Err(e)) => error_has_message(&e, "crafted parent version"),
        Ok(Ok(v)) => panic!("a commit chain 4 -> u64::MAX opened as version {v}"),
        Err(_) => panic!("Vod2::open panicked on a commit whose parent claims version u64::MAX"),
    }
}

#[test]
fn appending_to_a_file_whose_slot_sequence_is_exhausted_never_loses_the_commit() {
    // A head slot (checksum resealed) with sequence number u64::MAX: the next commit either fails
    // or becomes the head. Wrapping to 0 would write a slot that loses to the old one.
    let fx = fixture();
    let mut bytes = fx.vod2.clone();
    let (at, slot) = head_slot(&bytes);
    let exhausted = HeaderSlot {
        seq: u64::MAX,
        ..slot
    };
    bytes[at..at + SLOT_LEN].copy_from_slice(&exhausted.encode());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("crafted.vod");
    std::fs::write(&path, &bytes).unwrap();
    assert_eq!(
        Vod2::open(&path).unwrap().head().version,
        4,
        "the crafted slot is valid"
    );
    let node = fx.layout.node_index(fx.layout.key(0, 1, 1, 1).unwrap());
    let result = std::panic::catch_unwind(|| {
        let mut w = Vod2Writer::open_append(&path, Compression::None)?;
        w.commit(&[(node, NodeEntry::Constant(42))], None)
    });
    match result {
        Err(_) => panic!("committing after a slot with sequence u64::MAX panicked"),
        Ok(Err(e)) => error_has_message(&e, "exhausted sequence"),
        Ok(Ok(_)) => {
            let vod = Vod2::open(&path).unwrap();
            assert_eq!(
                vod.head().version,
                5,
                "the commit that succeeded is not the head"
            );
            assert_eq!(
                vod.head().read(fx.layout.key(0, 1, 1, 1).unwrap()).unwrap(),
                vec![42u8; 64]
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// (c) Property tests: decoders never panic.

fn layouts() -> Vec<VolumeLayout> {
    vec![
        VolumeLayout::new([20, 12, 9], 4, VoxelType::U8).unwrap(),
        VolumeLayout::new([1, 1, 1], 2, VoxelType::U16).unwrap(),
        VolumeLayout::new([200, 160, 160], 256, VoxelType::U16).unwrap(),
    ]
}

/// A record of `len` bytes with `fields` written at their offsets and an xxh3 seal over
/// `[0, len - 8)` stored at `len - 8`.
fn sealed(len: usize, fields: &[(usize, &[u8])]) -> Vec<u8> {
    let mut b = vec![0u8; len];
    for (at, f) in fields {
        b[*at..*at + f.len()].copy_from_slice(f);
    }
    let sum = content_hash(&b[..len - 8]);
    b[len - 8..].copy_from_slice(&sum.to_le_bytes());
    b
}

/// Mostly small values, some anywhere in the type's range.
fn small_or_any() -> impl Strategy<Value = u32> {
    prop_oneof![0u32..600, Just(u32::MAX), any::<u32>()]
}

fn offset() -> impl Strategy<Value = u64> {
    prop_oneof![
        0u64..(DATA_START * 4),
        Just(u64::MAX),
        Just(u64::MAX - 40),
        any::<u64>()
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn file_header_decode_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
        let _ = FileHeader::decode(&bytes);
    }

    #[test]
    fn sealed_file_header_with_any_fields_never_panics(
        version in prop_oneof![Just(2u32), any::<u32>()],
        dims in [small_or_any(), small_or_any(), small_or_any()],
        brick in prop_oneof![(1u32..10).prop_map(|s| 1 << s), any::<u32>()],
        bits in prop_oneof![Just(8u32), Just(16u32), any::<u32>()],
        levels in prop_oneof![0u32..40, any::<u32>()],
        scale in [any::<u32>(), any::<u32>(), any::<u32>()],
        channels in prop_oneof![Just(1u32), any::<u32>()],
    ) {
        let mut fields: Vec<(usize, Vec<u8>)> = vec![
            (0, b".VOD".to_vec()),
            (4, version.to_le_bytes().to_vec()),
            (8, (HEADER_LEN as u32).to_le_bytes().to_vec()),
            (28, brick.to_le_bytes().to_vec()),
            (32, bits.to_le_bytes().to_vec()),
            (36, levels.to_le_bytes().to_vec()),
            (52, b"XH64".to_vec()),
            (56, channels.to_le_bytes().to_vec()),
        ];
        for a in 0..3 {
            fields.push((16 + 4 * a, dims[a].to_le_bytes().to_vec()));
            fields.push((40 + 4 * a, scale[a].to_le_bytes().to_vec()));
        }
        let refs: Vec<(usize, &[u8])> = fields.iter().map(|(at, f)| (*at, f.as_slice())).collect();
        let b = sealed(HEADER_LEN, &refs);
        if let Ok(h) = FileHeader::decode(&b) {
            prop_assert_eq!(h.layout.dims(), dims);
            prop_assert_eq!(FileHeader::decode(&h.encode()), Ok(h));
        }
    }

    #[test]
    fn header_slot_decode_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..100), base in 0u64..(1 << 40)) {
        let _ = HeaderSlot::decode(&bytes, base);
    }

    #[test]
    fn sealed_header_slot_with_any_fields_never_panics(seq in any::<u64>(), commit in offset(), committed_len in offset(), version in any::<u64>(), flags in prop_oneof![Just(0u32), Just(1u32), any::<u32>()], from in offset(), checksum in any::<u64>()) {
        // The fields every reader checks, sealed at 40; then the appended-bytes check, sealed
        // over the whole record at 64.
        let base = sealed(48, &[(0, b"VSLT"), (4, &flags.to_le_bytes()), (8, &seq.to_le_bytes()), (16, &commit.to_le_bytes()), (24, &committed_len.to_le_bytes()), (32, &version.to_le_bytes())]);
        let b = sealed(SLOT_LEN, &[(0, &base), (48, &from.to_le_bytes()), (56, &checksum.to_le_bytes())]);
        if let Ok(s) = HeaderSlot::decode(&b, 4096) {
            prop_assert!(s.commit >= DATA_START && s.commit + 56 <= s.committed_len);
            prop_assert_eq!(flags, u32::from(s.appended.is_some()));
            if let Some(check) = s.appended {
                prop_assert!(check.from >= DATA_START && check.from <= s.commit);
            }
        }
    }

    #[test]
    fn commit_decode_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..400), base in DATA_START..(1 << 40)) {
        if let Ok((_, record)) = CommitHeader::decode(&bytes, base) {
            let _ = CommitHeader::changes(record).count();
        }
    }

    #[test]
    fn sealed_commit_with_any_fields_never_panics(
        version in any::<u64>(),
        parent in offset(),
        checkpoint in offset(),
        n_changes in prop_oneof![0u64..8, any::<u64>()],
        changes in proptest::collection::vec(any::<(u64, u64)>(), 0..8),
        trailing in proptest::collection::vec(any::<u8>(), 0..64),
        base in DATA_START..(1 << 40),
    ) {
        let len = 56 + 16 * changes.len();
        let mut fields: Vec<(usize, Vec<u8>)> = vec![
            (0, b"VCMT".to_vec()),
            (8, version.to_le_bytes().to_vec()),
            (16, parent.to_le_bytes().to_vec()),
            (24, 0u64.to_le_bytes().to_vec()),
            (32, checkpoint.to_le_bytes().to_vec()),
            (40, n_changes.to_le_bytes().to_vec()),
        ];
        for (i, (n, e)) in changes.iter().enumerate() {
            fields.push((48 + 16 * i, n.to_le_bytes().to_vec()));
            fields.push((56 + 16 * i, e.to_le_bytes().to_vec()));
        }
        let refs: Vec<(usize, &[u8])> = fields.iter().map(|(at, f)| (*at, f.as_slice())).collect();
        let mut b = sealed(len, &refs);
        b.extend_from_slice(&trailing);
        if let Ok((h, record)) = CommitHeader::decode(&b, base) {
            prop_assert_eq!(CommitHeader::changes(record).count() as u64, h.n_changes);
            for (_, raw) in CommitHeader::changes(record) {
                let _ = NodeEntry::decode(raw, VoxelType::U16, base);
            }
        }
    }

    #[test]
    fn checkpoint_decode_never_panics(
        bytes in proptest::collection::vec(any::<u8>(), 0..600),
        nodes in prop_oneof![0u64..3000, Just(MAX_NODES), 0..=MAX_NODES],
        base in DATA_START..(1 << 40),
    ) {
        if let Ok(cp) = Checkpoint::decode(&bytes, base, nodes) {
            for c in 0..Checkpoint::n_chunks(nodes) {
                if cp.chunk(c).is_ok() {
                    prop_assert!(cp.chunk_entries(c) <= 512);
                }
            }
            let _ = cp.total_len();
        }
    }

    #[test]
    fn sealed_checkpoint_with_any_chunk_refs_never_panics(
        nodes in 1u64..2000,
        refs in proptest::collection::vec((offset(), any::<u32>(), prop_oneof![Just(0u8), Just(2u8), any::<u8>()], any::<u64>()), 4),
        payload in proptest::collection::vec(any::<u8>(), 0..256),
        base in DATA_START..(1 << 40),
    ) {
        // The fixed part and every chunk reference carry their own seal (docs/vod2.md).
        let n_chunks = Checkpoint::n_chunks(nodes) as usize;
        let mut b = sealed(CHECKPOINT_FIXED_LEN, &[(0, b"VIDX"), (4, &512u32.to_le_bytes()), (8, &nodes.to_le_bytes())]);
        for (off, len, codec, hash) in refs.iter().take(n_chunks) {
            b.extend_from_slice(&sealed(CHUNK_REF_LEN, &[(0, &off.to_le_bytes()), (8, &len.to_le_bytes()), (12, &[*codec]), (16, &hash.to_le_bytes())]));
        }
        prop_assert_eq!(b.len() as u64, Checkpoint::directory_len(nodes));
        b.extend_from_slice(&payload);
        let cp = Checkpoint::decode(&b, base, nodes);
        prop_assert!(cp.is_ok(), "a sealed checkpoint decodes: {:?}", cp.err());
        let cp = cp.unwrap();
        for c in 0..n_chunks as u64 {
            if let Ok((r, p)) = cp.chunk(c) {
                prop_assert_eq!(p.len() as u64, r.stored_len as u64);
                prop_assert!(r.offset + r.stored_len as u64 <= b.len() as u64);
                prop_assert!(cp.chunk_entries(c) <= 512);
            }
        }
        let _ = cp.total_len();
    }

    #[test]
    fn brick_header_decode_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..40), base in 0u64..(1 << 40)) {
        for layout in layouts() {
            let _ = BrickHeader::decode(&bytes, base, &layout);
        }
    }

    #[test]
    fn sealed_brick_header_with_any_fields_never_panics(hash in any::<u64>(), stored_len in any::<u32>(), codec in any::<u8>(), min in any::<u16>(), max in any::<u16>()) {
        let mut b = [0u8; 24];
        b[0..8].copy_from_slice(&hash.to_le_bytes());
        b[8..12].copy_from_slice(&stored_len.to_le_bytes());
        b[12] = codec;
        b[14..16].copy_from_slice(&min.to_le_bytes());
        b[16..18].copy_from_slice(&max.to_le_bytes());
        let check = content_hash(&b[..20]) as u32;
        b[20..24].copy_from_slice(&check.to_le_bytes());
        for layout in layouts() {
            if let Ok(h) = BrickHeader::decode(&b, DATA_START, &layout) {
                prop_assert!(h.min <= h.max && h.max <= layout.voxel_type().max_value());
                prop_assert!(h.stored_len as usize <= layout.brick_bytes());
            }
        }
    }

    #[test]
    fn vod1_parse_never_panics_on_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        let _ = Vod1::parse(&bytes);
    }

    #[test]
    fn vod1_header_with_any_fields_never_panics(
        dims in [small_or_any(), small_or_any(), small_or_any()],
        brick in prop_oneof![(1u32..10).prop_map(|s| 1 << s), any::<u32>()],
        height in prop_oneof![0u32..25, any::<u32>()],
        bits in prop_oneof![Just(8u32), Just(16u32), any::<u32>()],
        hash in prop_oneof![Just(*b"XH64"), Just(*b"XH32"), any::<[u8; 4]>()],
        comp in prop_oneof![Just(*b"LZ4B"), Just(*b"NONE"), any::<[u8; 4]>()],
        flags in any::<u32>(),
        tail in proptest::collection::vec(any::<u8>(), 0..3000),
    ) {
        let mut b = Vec::with_capacity(64 + tail.len());
        b.extend_from_slice(b".VOD");
        b.extend_from_slice(&1u32.to_le_bytes());
        for d in dims {
            b.extend_from_slice(&d.to_le_bytes());
        }
        for _ in 0..3 {
            b.extend_from_slice(&brick.to_le_bytes());
        }
        for _ in 0..3 {
            b.extend_from_slice(&1.0f32.to_le_bytes());
        }
        b.extend_from_slice(&height.to_le_bytes());
        b.extend_from_slice(&bits.to_le_bytes());
        b.extend_from_slice(&hash);
        b.extend_from_slice(&comp);
        b.extend_from_slice(&flags.to_le_bytes());
        b.extend_from_slice(&tail);
        read_all_vod1(&b);
    }

    #[test]
    fn vod1_with_overwritten_bytes_never_panics(
        edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..12),
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
        compressed in any::<bool>(),
    ) {
        let fx = fixture();
        let mut b = if compressed { fx.vod1_lz4.clone() } else { fx.vod1_plain.clone() };
        for (at, v) in edits {
            let i = at.index(b.len());
            b[i] = v;
        }
        if truncate {
            b.truncate(cut.index(b.len()));
        }
        read_all_vod1(&b);
    }
}

/// Parses `b` and, if that works, reads every brick of every level (errors are fine).
fn read_all_vod1(b: &[u8]) {
    if let Ok(v) = Vod1::parse(b) {
        let mut out = vec![0u8; v.layout.brick_bytes()];
        for level in 0..v.layout.levels() {
            let g = v.layout.grid(level);
            for z in 0..g[2] {
                for y in 0..g[1] {
                    for x in 0..g[0] {
                        let _ = v.read_into(BrickKey { level, x, y, z }, &mut out);
                    }
                }
            }
        }
    }
}
