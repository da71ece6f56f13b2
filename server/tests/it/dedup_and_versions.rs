//! Deduplication, versions and crash safety of VOD 2 files.
//!
//! Proves that a volume made of one repeated brick stores that content once (and the file's
//! size accounts for exactly the distinct records); that appending versions with
//! `Vod2Writer::open_append` + `commit` gives a head with the new content while `version(n)` still
//! reads every older one, also after reopening; that `inspect` counts the replaced bricks as
//! garbage; and that a crash at any byte of a commit (file cut anywhere in the appended tail, the
//! slot never written, or the slot torn) opens as the old version with the old content, or as the
//! new one once its slot is complete, and that appending after such a crash works.

// unwrap is how a test says "this must work"; clippy exempts only #[test] functions.

use isovox_proto::vod2::{
    HeaderSlot, NodeEntry, BRICK_HEADER_LEN, CHECKPOINT_FIXED_LEN, CHUNK_REF_LEN, DATA_START,
    PAYLOAD_CHECK_LEN, SLOT_LEN, SLOT_OFFSETS,
};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::progress::Silent;
use isovox_server::store::codec::Compression;
use isovox_server::store::inspect::inspect;
use isovox_server::store::{
    build_vod2, BrickVoxels, BuildOptions, DenseGrid, StoredBrick, Vod2, Vod2Writer,
};
use std::collections::{HashMap, HashSet};
use std::path::Path;

use crate::common;
use common::{brick_count, mixed_volume, pyramid, Grid, XorShift};

/// The new content of a brick in an appended version.
enum Content {
    /// Voxels, stored through the writer (deduplicated, compressed).
    Data(Vec<u8>),
    /// One value everywhere, committed directly as `NodeEntry::Constant`.
    Constant(u16),
}
use Content::{Constant, Data};

/// Expected decoded content of every node, in node order.
type Contents = Vec<Vec<u8>>;

fn build(
    path: &Path,
    volume: &Grid,
    voxel_type: VoxelType,
    brick: u32,
    compression: Compression,
) -> VolumeLayout {
    let dims = volume.dims_u32();
    let bytes = volume.to_bytes(voxel_type);
    let layout = VolumeLayout::new(dims, brick, voxel_type).unwrap();
    let grid = DenseGrid::new(dims, voxel_type, brick, &bytes);
    let options = BuildOptions {
        compression,
        progress: std::sync::Arc::new(Silent),
    };
    build_vod2(path, &layout, [1.0; 3], &grid, &options).unwrap();
    layout
}

/// The content of every node of `layout`, from the independent pyramid.
fn pyramid_contents(layout: &VolumeLayout, volume: &Grid) -> Contents {
    let levels = pyramid(volume, layout.brick());
    let b = layout.brick() as usize;
    (0..layout.node_count())
        .map(|node| {
            let key = layout.key_of(node).unwrap();
            levels[key.level as usize].brick(
                [key.x, key.y, key.z].map(|c| c as usize),
                b,
                layout.voxel_type(),
            )
        })
        .collect()
}

fn assert_version_reads(vod: &Vod2, version: u64, expected: &Contents, what: &str) {
    let snap = vod.version(version).unwrap();
    assert_eq!(snap.version, version, "{what}");
    let layout = vod.layout();
    for (node, content) in expected.iter().enumerate() {
        let key = layout.key_of(node as u64).unwrap();
        let got = snap.read(key).unwrap();
        assert!(
            got == *content,
            "{what}: version {version} brick {key} differs from its expected content"
        );
    }
}

fn noise_brick(layout: &VolumeLayout, seed: u64) -> Vec<u8> {
    let mut rng = XorShift(seed);
    (0..layout.brick_bytes())
        .map(|_| rng.next() as u8)
        .collect()
}

/// Stores `changes` (node, new content; a constant is committed directly) as one
/// commit, with a full checkpoint when asked, and applies them to `model`.
fn append_version(
    path: &Path,
    layout: &VolumeLayout,
    model: &mut Contents,
    changes: Vec<(u64, Content)>,
    checkpoint: bool,
) {
    let mut w = Vod2Writer::open_append(path, Compression::Zstd(5)).unwrap();
    let mut entries = Vec::new();
    for (node, content) in changes {
        let entry = match content {
            Data(bytes) => {
                let v = BrickVoxels::Data(bytes.clone());
                let p = w.prepare(&v);
                let e = w.store(&v, p).unwrap();
                model[node as usize] = bytes;
                e
            }
            Constant(value) => {
                model[node as usize] = vec![value as u8; layout.brick_bytes()];
                NodeEntry::Constant(value.into())
            }
        };
        entries.push((node, entry));
    }
    if checkpoint {
        let vod = Vod2::open(path).unwrap();
        let head = vod.head();
        let mut full: Vec<u64> = (0..layout.node_count())
            .map(|n| head.entry_at(n).unwrap().encode())
            .collect();
        for (node, e) in &entries {
            full[*node as usize] = e.encode();
        }
        drop(head);
        drop(vod);
        w.commit(&entries, Some(&full)).unwrap();
    } else {
        w.commit(&entries, None).unwrap();
    }
}

/// 64^3 u8, brick 8: every level-0 brick below z = 48 holds the same 8^3 noise tile, except the
/// last column of bricks (x >= 56), which is constant 200; above z = 48 everything is L.
fn tiled_volume() -> (Grid, Vec<u16>) {
    let mut rng = XorShift(0x5EED);
    let tile: Vec<u16> = (0..512).map(|_| (rng.next() % 256) as u16).collect();
    let mut values = Vec::with_capacity(64 * 64 * 64);
    for z in 0..64 {
        for y in 0..64 {
            for x in 0..64 {
                values.push(match (x, z) {
                    (_, z) if z >= 48 => 0,
                    (x, _) if x >= 56 => 200,
                    _ => tile[(z % 8 * 8 + y % 8) * 8 + x % 8],
                });
            }
        }
    }
    (
        Grid {
            dims: [64; 3],
            values,
        },
        tile,
    )
}

#[test]
fn repeated_brick_content_is_stored_once() {
    let (volume, _) = tiled_volume();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiled.vod");
    let layout = build(&path, &volume, VoxelType::U8, 8, Compression::None);
    let expected = pyramid_contents(&layout, &volume);

    // Independent count of distinct contents, and of those that are not one value throughout.
    let distinct: HashSet<&Vec<u8>> = expected.iter().collect();
    let constant = |c: &Vec<u8>| c.iter().all(|&v| v == c[0]);
    let distinct_records = distinct.iter().filter(|c| !constant(c)).count() as u64;
    let constant_nodes = expected.iter().filter(|c| constant(c)).count() as u64;
    // 512 + 64 + 8 + 1 nodes; yet only a handful of distinct contents.
    assert_eq!(brick_count([64; 3], 8), 585);
    assert!(
        distinct.len() < 20,
        "the test volume is meant to repeat ({} distinct)",
        distinct.len()
    );

    let vod = Vod2::open(&path).unwrap();
    let i = inspect(&vod).unwrap();
    assert_eq!(i.bricks_total, 585);
    assert_eq!(i.bricks_unique, distinct.len() as u64);
    assert_eq!(
        i.codecs.raw_records, distinct_records,
        "one record per distinct non-constant content"
    );
    assert_eq!(i.codecs.raw_bytes, distinct_records * 512);
    assert_eq!((i.codecs.lz4_records, i.codecs.zstd_records), (0, 0));
    assert_eq!(i.codecs.constant_bricks, constant_nodes);
    assert_eq!(
        i.garbage_bytes, 0,
        "a fresh build references every byte it wrote"
    );

    // The 6 * 7 * 8 = 336 tiled level-0 bricks all point at one record.
    let snap = vod.head();
    let mut offsets = HashSet::new();
    for z in 0..6 {
        for y in 0..8 {
            for x in 0..7 {
                match snap.stored(layout.key(0, x, y, z).unwrap()).unwrap() {
                    StoredBrick::Record { offset, .. } => offsets.insert(offset),
                    StoredBrick::Constant(v) => panic!("tiled brick ({x},{y},{z}) is constant {v}"),
                };
            }
        }
    }
    assert_eq!(offsets.len(), 1, "the repeated tile is stored once");

    // The file is the header pages, the distinct records, the index and one empty commit.
    // The index is at most its fixed part, two chunk references, 585 uncompressed entries and
    // their 12-byte summaries in two blocks, each with its 16-byte header (revision 5).
    let index_bound =
        (CHECKPOINT_FIXED_LEN + 2 * CHUNK_REF_LEN + 585 * 8 + 2 * 16 + 585 * 12) as u64;
    assert!(
        i.index_bytes <= index_bound,
        "index of {} bytes",
        i.index_bytes
    );
    // Each record: its 24-byte header, 512 payload bytes, the payload's 4-byte checksum.
    let records = distinct_records * (BRICK_HEADER_LEN as u64 + 512 + PAYLOAD_CHECK_LEN as u64);
    assert_eq!(vod.file_len(), DATA_START + records + i.index_bytes + 56);
    assert_version_reads(&vod, 1, &expected, "tiled");
}

#[test]
fn appending_content_already_stored_shares_the_record() {
    let (volume, tile) = tiled_volume();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiled.vod");
    let layout = build(&path, &volume, VoxelType::U8, 8, Compression::Zstd(3));
    let mut model = pyramid_contents(&layout, &volume);
    let old_model = model.clone();
    let vod = Vod2::open(&path).unwrap();
    let tile_offset = match vod.head().stored(layout.key(0, 0, 0, 0).unwrap()).unwrap() {
        StoredBrick::Record { offset, .. } => offset,
        StoredBrick::Constant(_) => panic!("the tile is not constant"),
    };
    let len_before = vod.file_len();
    drop(vod);

    // Brick (7, 0, 0) is constant 200; give it the tile's content.
    let node = layout.node_index(layout.key(0, 7, 0, 0).unwrap());
    let tile_bytes: Vec<u8> = tile.iter().map(|&v| v as u8).collect();
    let mut w = Vod2Writer::open_append(&path, Compression::Zstd(3)).unwrap();
    let v = BrickVoxels::Data(tile_bytes.clone());
    let p = w.prepare(&v);
    let entry = w.store(&v, p).unwrap();
    assert_eq!(
        entry,
        NodeEntry::Stored(tile_offset),
        "the writer found the stored copy"
    );
    w.commit(&[(node, entry)], None).unwrap();
    model[node as usize] = tile_bytes;

    let vod = Vod2::open(&path).unwrap();
    // Only the commit record was appended: 56 bytes plus one 16-byte change, then (revision 5)
    // the change's 12-byte summary and the section's 8-byte checksum.
    assert_eq!(vod.file_len(), len_before + 56 + 16 + 12 + 8);
    assert_version_reads(&vod, 2, &model, "after sharing");
    assert_version_reads(&vod, 1, &old_model, "before sharing");
}

#[test]
fn appended_versions_keep_older_versions_readable() {
    let volume = mixed_volume([40, 24, 16], VoxelType::U8, 31);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.vod");
    let layout = build(&path, &volume, VoxelType::U8, 8, Compression::Zstd(3));
    let v1 = pyramid_contents(&layout, &volume);
    let node = |l, x, y, z| layout.node_index(layout.key(l, x, y, z).unwrap());
    // Brick (4, 1, 1) is noise: stored once, referenced once.
    let noisy = node(0, 4, 1, 1);
    let vod = Vod2::open(&path).unwrap();
    let noisy_record = match vod.head().entry_at(noisy).unwrap() {
        NodeEntry::Stored(off) => off,
        NodeEntry::Constant(v) => panic!("noise brick is constant {v}"),
    };
    let references = (0..layout.node_count())
        .filter(|&n| vod.head().entry_at(n).unwrap() == NodeEntry::Stored(noisy_record))
        .count();
    assert_eq!(references, 1);
    drop(vod);

    let mut v2 = v1.clone();
    append_version(
        &path,
        &layout,
        &mut v2,
        vec![
            (noisy, Data(noise_brick(&layout, 1))),
            (node(0, 0, 0, 0), Constant(77)),
            (node(0, 2, 1, 0), Data(noise_brick(&layout, 2))),
        ],
        false,
    );
    let check_v2 = |vod: &Vod2| {
        assert_eq!(vod.head().version, 2);
        assert_version_reads(vod, 2, &v2, "v2");
        assert_version_reads(vod, 1, &v1, "v1 after v2");
        let i = inspect(vod).unwrap();
        assert_eq!((i.version, i.commits), (2, 2));
        // Garbage: exactly the version-1 records the head no longer references.
        let head = vod.head();
        let old = vod.version(1).unwrap();
        let live: HashSet<u64> = (0..layout.node_count())
            .filter_map(|n| match head.entry_at(n).unwrap() {
                NodeEntry::Stored(o) => Some(o),
                NodeEntry::Constant(_) => None,
            })
            .collect();
        let mut dropped = HashMap::new();
        for n in 0..layout.node_count() {
            if let StoredBrick::Record { offset, header, .. } =
                old.stored_entry(old.entry_at(n).unwrap()).unwrap()
            {
                if !live.contains(&offset) {
                    dropped.insert(
                        offset,
                        (BRICK_HEADER_LEN + PAYLOAD_CHECK_LEN) as u64 + header.stored_len as u64,
                    );
                }
            }
        }
        assert!(
            dropped.contains_key(&noisy_record),
            "the replaced noise brick is unreferenced"
        );
        assert!(i.garbage_bytes > 0);
        assert_eq!(i.garbage_bytes, dropped.values().sum::<u64>());
        i.garbage_bytes
    };
    let garbage_v2 = check_v2(&Vod2::open(&path).unwrap());
    // Reopening gives the same again.
    assert_eq!(check_v2(&Vod2::open(&path).unwrap()), garbage_v2);

    // Version 3 writes a full index checkpoint and also changes a level-1 brick.
    let mut v3 = v2.clone();
    append_version(
        &path,
        &layout,
        &mut v3,
        vec![
            (noisy, Data(noise_brick(&layout, 3))),
            (node(1, 1, 0, 0), Constant(5)),
        ],
        true,
    );
    let vod = Vod2::open(&path).unwrap();
    assert_eq!(vod.head().version, 3);
    assert_version_reads(&vod, 3, &v3, "v3");
    assert_version_reads(&vod, 2, &v2, "v2 after v3");
    assert_version_reads(&vod, 1, &v1, "v1 after v3");
    let i = inspect(&vod).unwrap();
    assert_eq!((i.version, i.commits), (3, 3));
    assert!(
        i.garbage_bytes > garbage_v2,
        "older index and records are garbage too"
    );
    for missing in [0, 4, 1000] {
        let e = vod.version(missing).expect_err("no such version");
        assert!(!e.to_string().is_empty());
    }
}

/// What the crash tests start from: a file at version 2 (both slots used) and the new bytes of
/// version 3 appended to a copy of it.
struct Crash {
    layout: VolumeLayout,
    old: Vec<u8>,
    new: Vec<u8>,
    old_model: Contents,
    new_model: Contents,
}

fn crash_setup(dir: &Path, checkpoint: bool) -> Crash {
    let volume = mixed_volume([20, 12, 9], VoxelType::U8, 41);
    let path = dir.join("base.vod");
    let layout = build(&path, &volume, VoxelType::U8, 4, Compression::Zstd(3));
    let mut old_model = pyramid_contents(&layout, &volume);
    let node = |x, y, z| layout.node_index(layout.key(0, x, y, z).unwrap());
    append_version(
        &path,
        &layout,
        &mut old_model,
        vec![(node(4, 2, 2), Data(noise_brick(&layout, 10)))],
        false,
    );
    let old = std::fs::read(&path).unwrap();

    let copy = dir.join("copy.vod");
    std::fs::write(&copy, &old).unwrap();
    let mut new_model = old_model.clone();
    let changes = vec![
        (node(4, 0, 0), Data(noise_brick(&layout, 11))),
        (node(3, 1, 1), Data(noise_brick(&layout, 12))),
        (node(0, 0, 0), Constant(9)),
        (node(1, 2, 2), Data(noise_brick(&layout, 13))),
    ];
    append_version(&copy, &layout, &mut new_model, changes, checkpoint);
    let new = std::fs::read(&copy).unwrap();
    assert!(
        new.len() > old.len() + 3 * 64,
        "the commit appended its bricks"
    );
    assert!(
        new[old.len()..].len() < 8192,
        "keep the tail short: one open per byte"
    );
    Crash {
        layout,
        old,
        new,
        old_model,
        new_model,
    }
}

fn open_bytes(path: &Path, bytes: &[u8]) -> Vod2 {
    std::fs::write(path, bytes).unwrap();
    Vod2::open(path)
        .unwrap_or_else(|e| panic!("a crashed file of {} bytes does not open: {e}", bytes.len()))
}

fn check_crash(c: &Crash, bytes: &[u8], expect_new: bool, path: &Path, what: &str) {
    let vod = open_bytes(path, bytes);
    let (version, model) = if expect_new {
        (3, &c.new_model)
    } else {
        (2, &c.old_model)
    };
    assert_eq!(vod.head().version, version, "{what}");
    let head = vod.head();
    for (n, content) in model.iter().enumerate() {
        let key = c.layout.key_of(n as u64).unwrap();
        let got = head
            .read(key)
            .unwrap_or_else(|e| panic!("{what}: brick {key}: {e}"));
        assert!(
            got == *content,
            "{what}: brick {key} is not version {version}'s"
        );
    }
}

fn crash_at_every_byte(checkpoint: bool) {
    let dir = tempfile::tempdir().unwrap();
    let c = crash_setup(dir.path(), checkpoint);
    let crashed = dir.path().join("crashed.vod");
    let (old_len, new_len) = (c.old.len(), c.new.len());
    // Exactly one header slot changed: the one the new commit switched to.
    let slot_changed: Vec<usize> = SLOT_OFFSETS
        .iter()
        .map(|&s| s as usize)
        .filter(|&s| c.old[s..s + SLOT_LEN] != c.new[s..s + SLOT_LEN])
        .collect();
    assert_eq!(slot_changed.len(), 1);
    let slot = slot_changed[0];
    let mut expected_prefix = c.old.clone();
    expected_prefix[slot..slot + SLOT_LEN].copy_from_slice(&c.new[slot..slot + SLOT_LEN]);
    assert!(
        c.new[..old_len] == expected_prefix[..],
        "the commit changed nothing below the old length but its slot"
    );

    // 1. The slot was written, but the file lost part of its tail.
    for len in old_len..=new_len {
        check_crash(
            &c,
            &c.new[..len],
            len == new_len,
            &crashed,
            &format!("slot written, cut at {len}"),
        );
    }
    // 2. The tail was (partly) written, the slot never was.
    let mut no_slot = c.new.clone();
    no_slot[slot..slot + SLOT_LEN].copy_from_slice(&c.old[slot..slot + SLOT_LEN]);
    for len in old_len..=new_len {
        check_crash(
            &c,
            &no_slot[..len],
            false,
            &crashed,
            &format!("slot not written, cut at {len}"),
        );
    }
    // 3. The tail is durable and the slot write tore after `k` bytes.
    for k in 0..=SLOT_LEN {
        let mut torn = c.new.clone();
        torn[slot + k..slot + SLOT_LEN].copy_from_slice(&c.old[slot + k..slot + SLOT_LEN]);
        check_crash(
            &c,
            &torn,
            k == SLOT_LEN,
            &crashed,
            &format!("slot torn after {k} bytes"),
        );
    }
    // 4. The slot and the file's new length reached the disk, but not every byte of the tail:
    // the slot and the tail are made durable by one sync, so nothing orders them. The slot
    // carries the tail's checksum, and a tail that does not match it leaves the old version.
    let written = HeaderSlot::decode(&c.new[slot..slot + SLOT_LEN], slot as u64).unwrap();
    assert_eq!(
        written.appended.map(|a| a.from),
        Some(old_len as u64),
        "the slot checks the bytes appended since the old one"
    );
    for at in old_len..new_len {
        let mut lost = c.new.clone();
        lost[at] ^= 0x01;
        check_crash(
            &c,
            &lost,
            false,
            &crashed,
            &format!("byte {at} of the tail lost"),
        );
    }
    let sector_zeroed = |at: usize| {
        let mut lost = c.new.clone();
        lost[at..(at + 512).min(new_len)].fill(0);
        lost
    };
    // A sector that was all zeros reads the same whether or not it was written: no lost write.
    // The tail holds the commit's timestamp, so which sectors (and bytes) are zero varies by run.
    let written_nonzero = |at: usize| c.new[at..(at + 512).min(new_len)].iter().any(|&b| b != 0);
    for at in (old_len..new_len)
        .step_by(512)
        .filter(|&at| written_nonzero(at))
    {
        check_crash(
            &c,
            &sector_zeroed(at),
            false,
            &crashed,
            &format!("512 bytes at {at} of the tail never written"),
        );
    }
    // After a crash, appending cuts the unfinished tail and commits on top of the old version:
    // the tail cut short, or whole in length with a sector of it never written (the stale slot
    // is overwritten by the next commit's).
    let cut_states =
        [old_len, (old_len + new_len) / 2, new_len - 1].map(|len| c.new[..len].to_vec());
    let last_nonzero = (old_len..new_len).rev().find(|&at| c.new[at] != 0).unwrap();
    let lost_states = [old_len, last_nonzero].map(sector_zeroed);
    for state in &lost_states {
        assert_ne!(*state, c.new, "a lost sector changes the tail");
    }
    for state in cut_states.iter().chain(&lost_states) {
        let len = state.len();
        std::fs::write(&crashed, state).unwrap();
        let mut model = c.old_model.clone();
        let node = c.layout.node_index(c.layout.key(0, 2, 1, 1).unwrap());
        let mut w = Vod2Writer::open_append(&crashed, Compression::Lz4).unwrap();
        assert_eq!(
            std::fs::metadata(&crashed).unwrap().len(),
            old_len as u64,
            "the unfinished tail is cut"
        );
        let bytes = noise_brick(&c.layout, 99);
        let v = BrickVoxels::Data(bytes.clone());
        let p = w.prepare(&v);
        let e = w.store(&v, p).unwrap();
        w.commit(&[(node, e)], None).unwrap();
        drop(w);
        model[node as usize] = bytes;
        let vod = Vod2::open(&crashed).unwrap();
        assert_eq!(vod.head().version, 3, "recovered after a cut at {len}");
        assert_version_reads(&vod, 3, &model, "recovered");
        assert_version_reads(&vod, 2, &c.old_model, "recovered, old");
    }
}

#[test]
fn crash_during_a_delta_commit_leaves_the_old_version() {
    crash_at_every_byte(false);
}

#[test]
fn crash_during_a_checkpoint_commit_leaves_the_old_version() {
    crash_at_every_byte(true);
}

#[test]
fn a_reader_keeps_its_snapshot_while_a_writer_commits() {
    let volume = mixed_volume([20, 12, 9], VoxelType::U8, 71);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("live.vod");
    let layout = build(&path, &volume, VoxelType::U8, 4, Compression::Zstd(3));
    let v1 = pyramid_contents(&layout, &volume);
    let reader = Vod2::open(&path).unwrap();
    let old = reader.head();
    let mut v2 = v1.clone();
    let node = layout.node_index(layout.key(0, 4, 2, 2).unwrap());
    append_version(
        &path,
        &layout,
        &mut v2,
        vec![(node, Data(noise_brick(&layout, 7)))],
        true,
    );
    // The reader opened before the commit still sees version 1, brick for brick.
    assert_eq!(old.version, 1);
    assert_eq!(reader.head().version, 1);
    for (n, content) in v1.iter().enumerate() {
        let key = layout.key_of(n as u64).unwrap();
        assert!(
            old.read(key).unwrap() == *content,
            "old snapshot brick {key}"
        );
    }
    // A new reader sees version 2.
    let fresh = Vod2::open(&path).unwrap();
    assert_version_reads(&fresh, 2, &v2, "fresh reader");
}
