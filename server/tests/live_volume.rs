//! A served volume across edits and compaction, at the library level.
//!
//! The server never reopens a file after an edit: `Vod2::advance` builds the next head from the
//! current one (overlay, decoded index chunks, blob index carried over). These tests check that
//! head against an independent reading of the same file (`Vod2::open` from scratch) after every
//! edit, through checkpoints, for every node and every content hash; that older versions read
//! through the live history equal those read by walking the file; that the change list equals
//! what the edits answered; and that compaction keeps the head's content and number.

#![allow(clippy::unwrap_used)]

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::vod2::NodeEntry;
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::icvg::edit::Edit;
use isovox_server::icvg::term::{NoVolumes, TermLimits};
use isovox_server::store::CheckpointPolicy;
use isovox_server::store::{build_vod2, BuildOptions, Snapshot, StoredBrick, Vod2};
use isovox_server::volume::{LiveVolume, WriterSlot};
use std::path::Path;

mod common;
use common::XorShift;

fn world(path: &Path) -> VolumeLayout {
    let layout = VolumeLayout::new([96, 64, 80], 16, VoxelType::U8).unwrap();
    build_vod2(
        path,
        &layout,
        [1.0; 3],
        &WorldSource::new(layout.clone(), 5),
        &BuildOptions::default(),
    )
    .unwrap();
    layout
}

fn random_edit(rng: &mut XorShift) -> EditRequest {
    let op = if rng.below(2) == 0 {
        "union"
    } else {
        "difference"
    };
    let term = if rng.below(2) == 0 {
        Term::Ellipsoid {
            center: [
                rng.below(96) as i64,
                rng.below(64) as i64,
                rng.below(80) as i64,
            ],
            radii: [
                2 + rng.below(12) as u32,
                2 + rng.below(12) as u32,
                2 + rng.below(12) as u32,
            ],
        }
    } else {
        Term::Cuboid {
            origin: [
                rng.below(96) as i64 - 8,
                rng.below(64) as i64 - 8,
                rng.below(80) as i64 - 8,
            ],
            size: [
                3 + rng.below(30) as u32,
                3 + rng.below(30) as u32,
                3 + rng.below(30) as u32,
            ],
        }
    };
    EditRequest {
        op: op.into(),
        term: Some(term),
        s_l: None,
        k: None,
        region: None,
    }
}

/// Every node's entry resolved to (content hash, decoded bytes), so two snapshots compare by
/// content whatever offsets they use.
fn contents(snap: &Snapshot) -> Vec<(u64, Vec<u8>)> {
    (0..snap.layout().node_count())
        .map(|node| {
            let key = snap.layout().key_of(node).unwrap();
            (snap.hash(key).unwrap(), snap.read(key).unwrap())
        })
        .collect()
}

fn entries(snap: &Snapshot) -> Vec<NodeEntry> {
    (0..snap.layout().node_count())
        .map(|n| snap.entry_at(n).unwrap())
        .collect()
}

#[test]
fn advanced_heads_equal_freshly_opened_ones_through_checkpoints() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    world(&path);
    let vol = LiveVolume::new("w", Vod2::open(&path).unwrap()).unwrap();
    // A small policy, so the run crosses several checkpoints.
    let policy = CheckpointPolicy {
        max_overlay: 40,
        max_chain: 5,
    };
    let mut slot = WriterSlot::default();
    let mut rng = XorShift(0x5eed_1234);
    let mut answers = Vec::new();
    let first = vol.head().version;
    // Warm the blob index so that advancing has to carry it over.
    assert!(vol.head().find_by_hash(0).unwrap().is_none());
    for _ in 0..24 {
        let req = random_edit(&mut rng);
        let edit =
            Edit::from_request(&req, VoxelType::U8, &TermLimits::default(), &NoVolumes).unwrap();
        let answer = vol.apply(&mut slot, &edit, None, policy).unwrap();
        assert_eq!(answer.previous + 1, answer.version);
        let live = vol.head();
        assert_eq!(live.version, answer.version);
        let fresh = Vod2::open(&path).unwrap().head();
        assert_eq!(fresh.version, live.version);
        assert_eq!(entries(&live), entries(&fresh), "version {}", live.version);
        // The carried-over blob index finds every brick of the version by its hash, and what
        // it finds has that hash.
        for node in 0..live.layout().node_count() {
            let key = live.layout().key_of(node).unwrap();
            let hash = live.hash(key).unwrap();
            let found = live.find_by_hash(hash).unwrap().unwrap();
            let got = match live.stored_entry(found).unwrap() {
                StoredBrick::Record { header, .. } => header.hash,
                StoredBrick::Constant(_) => hash_of_constant(&live, found),
            };
            assert_eq!(got, hash);
        }
        answers.push(answer);
    }
    // Bricks replaced by edits stay findable by hash from the head, across checkpoint commits
    // too (a client one version behind asks for them), and what is found has that content:
    // from the live head, whose table was carried over commit by commit, and from the head of
    // the file opened afresh (a restarted server), whose table is built from the file alone.
    let file = Vod2::open(&path).unwrap();
    for (head, which) in [(vol.head(), "live"), (file.head(), "reopened")] {
        for v in first..=head.version {
            let old = file.version(v).unwrap();
            for node in 0..old.layout().node_count() {
                let key = old.layout().key_of(node).unwrap();
                let hash = old.hash(key).unwrap();
                let found = head.find_by_hash(hash).unwrap().unwrap_or_else(|| {
                    panic!("hash {hash:016x} of version {v} not found from the {which} head")
                });
                let mut bytes = vec![0u8; head.layout().brick_bytes()];
                isovox_server::store::vod2::decode_stored(
                    &head.stored_entry(found).unwrap(),
                    head.layout(),
                    &mut bytes,
                )
                .unwrap();
                assert_eq!(bytes, old.read(key).unwrap());
            }
        }
    }
    // Older versions through the live history equal those found by walking the file.
    let file = Vod2::open(&path).unwrap();
    for v in first..=vol.head().version {
        assert_eq!(
            contents(&vol.version(v).unwrap()),
            contents(&file.version(v).unwrap()),
            "version {v}"
        );
    }
    // The change list says what the edits answered.
    let (listed, more) = vol.changes(first, 1000).unwrap();
    assert!(!more);
    assert_eq!(listed.len(), answers.len());
    for (l, a) in listed.iter().zip(&answers) {
        assert_eq!((l.version, &l.changed), (a.version, &a.changed));
    }
    // And each listed change is exactly the set of bricks whose content differs from the
    // previous version (computed here by comparing whole versions).
    for l in &listed {
        let before = contents(&file.version(l.version - 1).unwrap());
        let after = contents(&file.version(l.version).unwrap());
        let layout = file.layout();
        let mut differing: Vec<Vec<[u32; 3]>> = vec![Vec::new(); layout.levels() as usize];
        for node in 0..layout.node_count() {
            if before[node as usize].0 != after[node as usize].0 {
                let k = layout.key_of(node).unwrap();
                differing[k.level as usize].push([k.x, k.y, k.z]);
            }
        }
        for level in &mut differing {
            level.sort_by_key(|k| (k[2], k[1], k[0]));
        }
        assert_eq!(l.changed, differing, "version {}", l.version);
    }
}

fn hash_of_constant(snap: &Snapshot, entry: NodeEntry) -> u64 {
    let NodeEntry::Constant(v) = entry else {
        unreachable!()
    };
    let bytes = vec![v as u8; snap.layout().brick_bytes()];
    isovox_proto::vod2::content_hash(&bytes)
}

#[test]
fn if_match_refuses_a_moved_head_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    world(&path);
    let vol = LiveVolume::new("w", Vod2::open(&path).unwrap()).unwrap();
    let mut slot = WriterSlot::default();
    let mut rng = XorShift(7);
    let edit = |rng: &mut XorShift| {
        Edit::from_request(
            &random_edit(rng),
            VoxelType::U8,
            &TermLimits::default(),
            &NoVolumes,
        )
        .unwrap()
    };
    let v1 = vol.head().version;
    let a = vol
        .apply(
            &mut slot,
            &edit(&mut rng),
            Some(v1),
            CheckpointPolicy::default(),
        )
        .unwrap();
    assert_eq!(a.version, v1 + 1);
    let len = std::fs::metadata(&path).unwrap().len();
    let refused = vol.apply(
        &mut slot,
        &edit(&mut rng),
        Some(v1),
        CheckpointPolicy::default(),
    );
    match refused {
        Err(isovox_server::volume::VolumeError::Conflict { expected, current }) => {
            assert_eq!((expected, current), (v1, v1 + 1));
        }
        other => panic!("expected a conflict, got {other:?}"),
    }
    assert_eq!(vol.head().version, v1 + 1);
    assert_eq!(std::fs::metadata(&path).unwrap().len(), len);
}

#[test]
fn compaction_keeps_the_head_and_its_number_and_edits_continue() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    world(&path);
    let vol = LiveVolume::new("w", Vod2::open(&path).unwrap()).unwrap();
    let mut slot = WriterSlot::default();
    let mut rng = XorShift(99);
    for _ in 0..10 {
        let edit = Edit::from_request(
            &random_edit(&mut rng),
            VoxelType::U8,
            &TermLimits::default(),
            &NoVolumes,
        )
        .unwrap();
        vol.apply(&mut slot, &edit, None, CheckpointPolicy::default())
            .unwrap();
    }
    let before = vol.head();
    let expected = contents(&before);
    let size_before = std::fs::metadata(&path).unwrap().len();
    // A reader holding the old head keeps reading it across the swap.
    let held = vol.head();
    let report = vol.compact(&mut slot).unwrap();
    assert_eq!(report.version, before.version);
    assert_eq!(report.bytes_before, size_before);
    assert!(report.bytes_after < size_before);
    assert_eq!(std::fs::metadata(&path).unwrap().len(), report.bytes_after);
    assert_eq!(contents(&held), expected);
    let after = vol.head();
    assert_eq!(after.version, before.version);
    assert_eq!(contents(&after), expected);
    assert_eq!(vol.oldest(), before.version);
    assert!(vol.version(before.version - 1).is_err());
    // A fresh open agrees, and no temporary is left.
    let reopened = Vod2::open(&path).unwrap();
    assert_eq!(contents(&reopened.head()), expected);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    // Edits continue from the same number.
    let edit = Edit::from_request(
        &random_edit(&mut rng),
        VoxelType::U8,
        &TermLimits::default(),
        &NoVolumes,
    )
    .unwrap();
    let a = vol
        .apply(&mut slot, &edit, None, CheckpointPolicy::default())
        .unwrap();
    assert_eq!(a.version, before.version + 1);
    assert_eq!(
        entries(&vol.head()),
        entries(&Vod2::open(&path).unwrap().head())
    );
}
