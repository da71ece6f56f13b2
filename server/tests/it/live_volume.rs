//! A served volume across edits and compaction, at the library level.
//!
//! The server never reopens a file after an edit: `Vod2::advance` builds the next head from the
//! current one (overlay, decoded index chunks, blob index carried over). These tests check that
//! head against an independent reading of the same file (`Vod2::open` from scratch) after every
//! edit, through checkpoints, for every node and every content hash; that older versions read
//! through the live history equal those read by walking the file; that the change list equals
//! what the edits answered; and that compaction keeps the head's content and number. Then group
//! commit: a group's versions equal the same edits applied one at a time, take one slot write,
//! see each other's versions in If-Match; an edit withdrawn or rolled back leaves no trace; a
//! group cut short by a crash is invisible.

use isovox_proto::api::ChangeEvent;
use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::vod2::{HeaderSlot, NodeEntry, SLOT_LEN, SLOT_OFFSETS};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::cancel::CancelToken;
use isovox_server::generate::WorldSource;
use isovox_server::icvg::edit::{stage_edit, Edit};
use isovox_server::icvg::term::{NoVolumes, TermLimits};
use isovox_server::store::codec::Compression;
use isovox_server::store::CheckpointPolicy;
use isovox_server::store::{build_vod2, BuildOptions, Snapshot, StoredBrick, Vod2, Vod2Writer};
use isovox_server::volume::group::{EditAnswer, Work};
use isovox_server::volume::{LiveVolume, PendingEdit, VolumeError, WriterSlot};
use std::path::{Path, PathBuf};
use tokio::sync::oneshot::Receiver;

use crate::common;
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
        message: None,
        channel: None,
        overwrite: None,
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
        let answer = vol.apply(&mut slot, edit, None, policy).unwrap();
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
            edit(&mut rng),
            Some(v1),
            CheckpointPolicy::default(),
        )
        .unwrap();
    assert_eq!(a.version, v1 + 1);
    let len = std::fs::metadata(&path).unwrap().len();
    let refused = vol.apply(
        &mut slot,
        edit(&mut rng),
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
        vol.apply(&mut slot, edit, None, CheckpointPolicy::default())
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
        .apply(&mut slot, edit, None, CheckpointPolicy::default())
        .unwrap();
    assert_eq!(a.version, before.version + 1);
    assert_eq!(
        entries(&vol.head()),
        entries(&Vod2::open(&path).unwrap().head())
    );
}

// ---------------------------------------------------------------------------------------------
// Group commit: several edits staged, one pair of syncs, one version each
// ---------------------------------------------------------------------------------------------

fn compiled(request: &EditRequest) -> Edit {
    Edit::from_request(request, VoxelType::U8, &TermLimits::default(), &NoVolumes).unwrap()
}

/// `request` compiled, as the writer's queue takes it.
fn work(request: &EditRequest) -> Work {
    Work::edit(compiled(request), false)
}

/// Both header slots as the file holds them now (read with pread, as a reader opening it).
/// Two copies of the same world in `dir`: the file under test and a reference.
fn two_worlds(dir: &Path) -> (PathBuf, PathBuf) {
    let (path, reference) = (dir.join("w.vod"), dir.join("r.vod"));
    world(&path);
    world(&reference);
    (path, reference)
}

/// The world at `reference` with `requests` applied one at a time (each a group of its own).
fn one_at_a_time(reference: &Path, requests: &[&EditRequest]) -> LiveVolume {
    let vol = LiveVolume::new("r", Vod2::open(reference).unwrap()).unwrap();
    let mut slot = WriterSlot::default();
    for request in requests {
        vol.apply(
            &mut slot,
            compiled(request),
            None,
            CheckpointPolicy::default(),
        )
        .unwrap();
    }
    vol
}

fn header_slots(path: &Path) -> Vec<HeaderSlot> {
    use std::os::unix::fs::FileExt;
    let file = std::fs::File::open(path).unwrap();
    SLOT_OFFSETS
        .iter()
        .filter_map(|&at| {
            let mut bytes = vec![0u8; SLOT_LEN];
            file.read_exact_at(&mut bytes, at).unwrap();
            HeaderSlot::decode(&bytes, at).ok()
        })
        .collect()
}

fn answer_of(receiver: &mut Receiver<EditAnswer>) -> EditAnswer {
    receiver
        .try_recv()
        .expect("commit_group answers every edit it was given before it returns")
}

#[test]
fn a_group_is_consecutive_versions_made_durable_by_one_slot_write() {
    let dir = tempfile::tempdir().unwrap();
    let (grouped, single) = (dir.path().join("g.vod"), dir.path().join("s.vod"));
    world(&grouped);
    world(&single);
    let vol = LiveVolume::new("g", Vod2::open(&grouped).unwrap()).unwrap();
    let one_by_one = LiveVolume::new("s", Vod2::open(&single).unwrap()).unwrap();
    assert_eq!(contents(&vol.head()), contents(&one_by_one.head()));
    // A short chain, so the group writes a checkpoint in its middle.
    let policy = CheckpointPolicy {
        max_overlay: 40,
        max_chain: 3,
    };
    let mut rng = XorShift(0x6209);
    let requests: Vec<EditRequest> = (0..8).map(|_| random_edit(&mut rng)).collect();
    let first = vol.head().version;
    let seq_before = header_slots(&grouped).iter().map(|s| s.seq).max().unwrap();
    let mut feed = vol.subscribe();

    let (group, mut receivers): (Vec<_>, Vec<_>) = requests
        .iter()
        .map(|r| PendingEdit::new(work(r), None, CancelToken::never()))
        .unzip();
    let mut slot = WriterSlot::default();
    vol.commit_group(&mut slot, group, policy);

    // Every edit is its own version, in the order given, each answered.
    let answers: Vec<_> = receivers
        .iter_mut()
        .map(|r| answer_of(r).unwrap())
        .collect();
    let versions: Vec<u64> = answers.iter().map(|a| a.version).collect();
    assert_eq!(versions, (first + 1..=first + 8).collect::<Vec<_>>());
    for a in &answers {
        assert_eq!(a.previous + 1, a.version);
    }
    assert!(
        answers.iter().any(|a| a.checkpoint),
        "the policy puts a checkpoint inside the group"
    );
    // One slot write for the whole group: the sequence moved by one, and the new slot names
    // the group's last version; the other slot still names the version before the group.
    let slots = header_slots(&grouped);
    assert_eq!(slots.len(), 2);
    let newest = slots.iter().max_by_key(|s| s.seq).unwrap();
    let older = slots.iter().min_by_key(|s| s.seq).unwrap();
    assert_eq!(newest.seq, seq_before + 1);
    assert_eq!(newest.version, first + 8);
    assert_eq!(older.version, first);
    // One event per version, in order, each saying what its answer said.
    for a in &answers {
        let item = feed.try_recv().unwrap();
        assert_eq!(item.version, a.version);
        let event: ChangeEvent = serde_json::from_str(&item.json).unwrap();
        assert_eq!(event.changed, a.changed);
    }
    assert!(feed.try_recv().is_err(), "one event per version, no more");

    // The same edits one at a time give the same versions, brick for brick, and the same
    // changes; the file read from scratch agrees with the served versions.
    for request in &requests {
        one_by_one
            .apply(&mut WriterSlot::default(), compiled(request), None, policy)
            .unwrap();
    }
    let file = Vod2::open(&grouped).unwrap();
    assert_eq!(file.head().version, first + 8);
    assert_eq!(entries(&file.head()), entries(&vol.head()));
    for (v, a) in (first + 1..).zip(&answers) {
        let served = contents(&vol.version(v).unwrap());
        assert_eq!(
            served,
            contents(&one_by_one.version(v).unwrap()),
            "version {v}"
        );
        assert_eq!(served, contents(&file.version(v).unwrap()), "version {v}");
        let listed = &vol.changes(v - 1, 1).unwrap().0[0];
        assert_eq!((listed.version, &listed.changed), (v, &a.changed));
    }
}

#[test]
fn if_match_inside_a_group_sees_the_versions_made_before_it_in_the_group() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    world(&path);
    let vol = LiveVolume::new("w", Vod2::open(&path).unwrap()).unwrap();
    let v = vol.head().version;
    let mut rng = XorShift(31);
    // A (no condition) makes v+1; B asks for v: conflict, v+1 is current; C asks for v+1: it
    // makes v+2; D asks for v+1 again: conflict, v+2 is current; E asks for v+2: v+3.
    let conditions = [None, Some(v), Some(v + 1), Some(v + 1), Some(v + 2)];
    let (group, mut receivers): (Vec<_>, Vec<_>) = conditions
        .iter()
        .map(|&c| PendingEdit::new(work(&random_edit(&mut rng)), c, CancelToken::never()))
        .unzip();
    vol.commit_group(
        &mut WriterSlot::default(),
        group,
        CheckpointPolicy::default(),
    );
    let answers: Vec<_> = receivers.iter_mut().map(answer_of).collect();
    let made = |a: &EditAnswer| a.as_ref().ok().map(|r| r.version);
    let conflict = |a: &EditAnswer| match a {
        Err(VolumeError::Conflict { expected, current }) => Some((*expected, *current)),
        _ => None,
    };
    assert_eq!(made(&answers[0]), Some(v + 1));
    assert_eq!(conflict(&answers[1]), Some((v, v + 1)));
    assert_eq!(made(&answers[2]), Some(v + 2));
    assert_eq!(conflict(&answers[3]), Some((v + 1, v + 2)));
    assert_eq!(made(&answers[4]), Some(v + 3));
    assert_eq!(vol.head().version, v + 3);
    assert_eq!(Vod2::open(&path).unwrap().head().version, v + 3);
}

#[test]
fn an_edit_withdrawn_before_the_writer_reaches_it_is_never_applied() {
    let dir = tempfile::tempdir().unwrap();
    let (path, reference) = two_worlds(dir.path());
    let vol = LiveVolume::new("w", Vod2::open(&path).unwrap()).unwrap();
    let v = vol.head().version;
    let mut rng = XorShift(4242);
    let requests: Vec<EditRequest> = (0..3).map(|_| random_edit(&mut rng)).collect();
    let (a, mut a_answer) = PendingEdit::new(work(&requests[0]), None, CancelToken::never());
    let (b, b_answer) = PendingEdit::new(work(&requests[1]), None, CancelToken::never());
    let (c, mut c_answer) = PendingEdit::new(work(&requests[2]), None, CancelToken::never());
    // B's client left while B waited.
    drop(b_answer);
    vol.commit_group(
        &mut WriterSlot::default(),
        vec![a, b, c],
        CheckpointPolicy::default(),
    );
    assert_eq!(answer_of(&mut a_answer).unwrap().version, v + 1);
    assert_eq!(answer_of(&mut c_answer).unwrap().version, v + 2);
    let expected = one_at_a_time(&reference, &[&requests[0], &requests[2]]);
    assert_eq!(contents(&vol.head()), contents(&expected.head()));
}

/// A cuboid union through the whole height of the world: it changes bricks for sure (the air
/// above the terrain fills), so it stores new brick records.
fn column(x: i64, z: i64) -> EditRequest {
    EditRequest {
        op: "union".into(),
        term: Some(Term::Cuboid {
            origin: [x, -4, z],
            size: [20, 72, 20],
        }),
        s_l: None,
        k: None,
        region: None,
        message: None,
        channel: None,
        overwrite: None,
    }
}

#[test]
fn a_rolled_back_edit_leaves_the_group_as_if_it_had_never_come() {
    let dir = tempfile::tempdir().unwrap();
    let (path, reference) = two_worlds(dir.path());
    let (a, b, c) = (column(4, 4), column(60, 10), column(30, 50));
    let base = Vod2::open(&path).unwrap();
    let v = base.head().version;
    let mut writer = Vod2Writer::open_append(&path, Compression::for_edits()).unwrap();
    let policy = CheckpointPolicy::default();

    stage_edit(
        &mut writer,
        base.head_ref(),
        &mut compiled(&a),
        policy,
        &CancelToken::never(),
    )
    .unwrap();
    let after_a = base.advance(writer.tip().unwrap()).unwrap();
    let end_after_a = writer.end();
    // B is staged, then given up (as a cancelled edit would be): its bricks and its commit
    // record go, A stays.
    let savepoint = writer.savepoint();
    let given_up = stage_edit(
        &mut writer,
        after_a.head_ref(),
        &mut compiled(&b),
        policy,
        &CancelToken::never(),
    )
    .unwrap();
    assert!(given_up.new_records > 0, "B stores bricks");
    writer.rollback(savepoint).unwrap();
    assert_eq!(writer.end(), end_after_a);
    assert_eq!(writer.tip().unwrap().version, v + 1);
    assert_eq!(std::fs::metadata(&path).unwrap().len(), end_after_a);
    // The writer forgot B's bricks as well: B staged again stores every one of them again
    // (none is taken for a duplicate of a record that is gone).
    let again = stage_edit(
        &mut writer,
        after_a.head_ref(),
        &mut compiled(&b),
        policy,
        &CancelToken::never(),
    )
    .unwrap();
    assert_eq!(again.new_records, given_up.new_records);
    assert_eq!(again.version, v + 2);
    let after_b = after_a.advance(writer.tip().unwrap()).unwrap();
    stage_edit(
        &mut writer,
        after_b.head_ref(),
        &mut compiled(&c),
        policy,
        &CancelToken::never(),
    )
    .unwrap();
    let after_c = after_b.advance(writer.tip().unwrap()).unwrap();
    // Nothing is durable yet: a reader opening the file finds the version before the group.
    assert_eq!(Vod2::open(&path).unwrap().head().version, v);
    writer.sync().unwrap();

    // The reference: A, B and C applied one at a time to a copy of the same world.
    let expected = one_at_a_time(&reference, &[&a, &b, &c]);
    let file = Vod2::open(&path).unwrap();
    assert_eq!(file.head().version, v + 3);
    assert_eq!(entries(&file.head()), entries(&after_c.head()));
    for version in v + 1..=v + 3 {
        assert_eq!(
            contents(&file.version(version).unwrap()),
            contents(&expected.version(version).unwrap()),
            "version {version}"
        );
    }
    // Not a byte of the first B is left: both files grew by the same records (only the
    // commits' timestamps differ).
    assert_eq!(
        std::fs::metadata(&path).unwrap().len(),
        std::fs::metadata(&reference).unwrap().len()
    );
}

#[test]
fn a_group_cut_short_by_a_crash_is_invisible_and_the_next_writer_cuts_it_off() {
    let dir = tempfile::tempdir().unwrap();
    let (path, reference) = two_worlds(dir.path());
    let mut rng = XorShift(0xc0ffee);
    let [a, b, c] = [0; 3].map(|_| random_edit(&mut rng));
    let policy = CheckpointPolicy::default();
    let base = Vod2::open(&path).unwrap();
    let v = base.head().version;
    let committed = base.head_slot().committed_len;
    {
        let mut writer = Vod2Writer::open_append(&path, Compression::for_edits()).unwrap();
        stage_edit(
            &mut writer,
            base.head_ref(),
            &mut compiled(&a),
            policy,
            &CancelToken::never(),
        )
        .unwrap();
        let after_a = base.advance(writer.tip().unwrap()).unwrap();
        stage_edit(
            &mut writer,
            after_a.head_ref(),
            &mut compiled(&b),
            policy,
            &CancelToken::never(),
        )
        .unwrap();
        // The process dies here: two versions' records are in the file, no slot names them.
    }
    let crashed = Vod2::open(&path).unwrap();
    assert_eq!(crashed.head().version, v);
    assert!(crashed.file_len() > committed);
    assert_eq!(contents(&crashed.head()), contents(&base.head()));
    // The next writer cuts the unfinished group off and goes on from the durable head.
    let vol = LiveVolume::new("w", crashed).unwrap();
    let answer = vol
        .apply(&mut WriterSlot::default(), compiled(&c), None, policy)
        .unwrap();
    assert_eq!(answer.version, v + 1);
    let expected = one_at_a_time(&reference, &[&c]);
    assert_eq!(
        contents(&Vod2::open(&path).unwrap().head()),
        contents(&expected.head())
    );
    assert_eq!(
        std::fs::metadata(&path).unwrap().len(),
        std::fs::metadata(&reference).unwrap().len()
    );
}

#[test]
fn a_volume_behind_its_file_catches_up_before_building_on_it() {
    // The served head falls behind the file when a group stops after its sync and before
    // publishing; here the file is moved on directly (as `isovox edit` would) to get there.
    let dir = tempfile::tempdir().unwrap();
    let (path, reference) = two_worlds(dir.path());
    let vol = LiveVolume::new("w", Vod2::open(&path).unwrap()).unwrap();
    let v = vol.head().version;
    let (a, b) = (column(4, 4), column(60, 10));
    vol.apply(
        &mut WriterSlot::default(),
        compiled(&column(30, 50)),
        None,
        CheckpointPolicy::default(),
    )
    .unwrap();
    // One writer at a time: the volume's is closed while the file moves on.
    isovox_server::volume::edit_file(&path, &a).unwrap();
    let answer = vol
        .apply(
            &mut WriterSlot::default(),
            compiled(&b),
            None,
            CheckpointPolicy::default(),
        )
        .unwrap();
    assert_eq!((answer.previous, answer.version), (v + 2, v + 3));
    // Nothing is lost: the volume is the world with the three edits, in order.
    let expected = one_at_a_time(&reference, &[&column(30, 50), &a, &b]);
    assert_eq!(contents(&vol.head()), contents(&expected.head()));
    assert_eq!(
        contents(&Vod2::open(&path).unwrap().head()),
        contents(&expected.head())
    );
    let (listed, _) = vol.changes(v, 10).unwrap();
    assert_eq!(
        listed.iter().map(|c| c.version).collect::<Vec<_>>(),
        vec![v + 1, v + 2, v + 3]
    );
}
