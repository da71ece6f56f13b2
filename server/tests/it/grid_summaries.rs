//! Level grids from the index alone (VOD 2 revision 5): each brick's content hash and value
//! range are stored beside its index entry, so a grid, a change event and a tile's inputs read
//! no brick record.
//!
//! - a local file's grids say what its bricks hold (hash and range computed here from the
//!   decoded voxels the server sends), before and after edits, an undo and a revert, and after
//!   the server reopens it (an older version's grid too);
//! - a grid reads no brick record: with every record's header damaged, grids still answer,
//!   while brick reads fail;
//! - a checkpoint written after edits keeps the summaries (library writer, checkpoint on every
//!   commit);
//! - a revision-4 file (written without summaries) opens and answers the same grids from its
//!   brick headers; a revision-5 writer appending to it upgrades what it writes, and so do
//!   `isovox compact` and `isovox salvage`; a commit without summaries (an older writer's) on
//!   a revision-5 checkpoint is summarized from its records;
//! - a damaged summary is an error naming it (500, cause logged), never a wrong grid.
//!
//! The object-store figure (a cold replica's range requests for a grid) is in
//! `object_store.rs`.

use crate::channel_volumes::{post_ok, serve};
use crate::server_process::{run_isovox, ServerProcess};
use isovox_proto::vod2::{Checkpoint, NodeEntry};
use isovox_proto::BrickKey;
use isovox_server::store::codec::Compression;
use isovox_server::store::{BrickVoxels, CheckpointPolicy, Transaction, Vod2, Vod2Writer};
use serde_json::{json, Value};
use std::collections::HashMap;
use std::path::Path;

/// `isovox generate world` of 96 x 64 x 96 voxels in bricks of 16 as `dir/world.vod`: 144
/// level-0 bricks (6 x 4 x 6), most of them neither empty nor full.
fn generate_world(dir: &Path) {
    let out = dir.join("world.vod");
    let out = out.to_str().unwrap();
    run_isovox(&[
        "generate", "world", "-o", out, "--dims", "96,64,96", "--brick", "16",
    ]);
}

/// A brick as a grid lists it: content hash, smallest and largest value.
type Listed = (u64, u16, u16);

/// Copies `src`'s head into `dst` as a writer before revision 5 wrote files: the same records
/// (copied as they are) and entries, no summaries in its checkpoint or commit record.
pub(crate) fn revision4_copy(src: &Path, dst: &Path) {
    let vod = Vod2::open(src).unwrap();
    let snap = vod.head();
    let mut w = Vod2Writer::create(dst, vod.header().clone(), Compression::for_edits()).unwrap();
    w.omit_summaries();
    let mut copied: HashMap<u64, NodeEntry> = HashMap::new();
    let mut entries = Vec::new();
    for view in snap.streams() {
        for node in 0..view.layout().node_count() {
            let entry = match view.entry_at(node).unwrap() {
                e @ NodeEntry::Stored(offset) => match copied.get(&offset) {
                    Some(&c) => c,
                    None => {
                        let c = w.copy_record(&view.stored_entry(e).unwrap()).unwrap();
                        copied.insert(offset, c);
                        c
                    }
                },
                constant => constant,
            };
            entries.push(entry.encode());
        }
    }
    w.commit(&[], Some(&entries)).unwrap();
}

/// Whether the head checkpoint of `path` stores summaries beside its first chunk.
pub(crate) fn checkpoint_has_summaries(path: &Path) -> bool {
    let vod = Vod2::open(path).unwrap();
    let (at, _) = vod.head().checkpoint_span().unwrap();
    let bytes = std::fs::read(path).unwrap();
    let nodes = vod.header().node_count();
    let cp = Checkpoint::decode(&bytes[at as usize..], at, nodes).unwrap();
    let (r, _) = cp.chunk(0).unwrap();
    cp.summaries(&r).unwrap().is_some()
}

fn get(server: &ServerProcess, path: &str) -> (u16, Vec<u8>) {
    let r = reqwest::blocking::get(server.url(path)).unwrap();
    let status = r.status().as_u16();
    (status, r.bytes().unwrap().to_vec())
}

/// The grid of `level` (the whole level) as the server lists it, x fastest, and the grid's
/// size; `Err` with the status and body when it is not a 200.
fn grid(server: &ServerProcess, level: u8) -> Result<([u32; 3], Vec<Listed>), (u16, String)> {
    let (status, body) = get(server, &format!("/v1/volumes/world/levels/{level}"));
    if status != 200 {
        return Err((status, String::from_utf8_lossy(&body).into_owned()));
    }
    let v: Value = serde_json::from_slice(&body).unwrap();
    let dims: Vec<u32> = v["grid"]
        .as_array()
        .unwrap()
        .iter()
        .map(|g| g.as_u64().unwrap() as u32)
        .collect();
    Ok(([dims[0], dims[1], dims[2]], listed(&v)))
}

/// The bricks a grid answer lists.
fn listed(grid: &Value) -> Vec<Listed> {
    grid["bricks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| {
            (
                u64::from_str_radix(b["hash"].as_str().unwrap(), 16).unwrap(),
                b["min"].as_u64().unwrap() as u16,
                b["max"].as_u64().unwrap() as u16,
            )
        })
        .collect()
}

/// What each brick of `level` holds, computed here from the decoded voxels the server sends
/// (a u8 world: one byte a voxel): xxh3-64 of the bytes, their least and greatest value.
fn truth(server: &ServerProcess, level: u8, dims: [u32; 3]) -> Vec<Listed> {
    let mut out = Vec::new();
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let (status, voxels) = get(
                    server,
                    &format!("/v1/volumes/world/bricks/{level}/{x}/{y}/{z}"),
                );
                assert_eq!(status, 200, "brick {level}/{x}/{y}/{z}");
                let min = *voxels.iter().min().unwrap() as u16;
                let max = *voxels.iter().max().unwrap() as u16;
                out.push((xxhash_rust::xxh3::xxh3_64(&voxels), min, max));
            }
        }
    }
    out
}

/// Every level's grid of `server`, checked against [`truth`]; returns them.
fn assert_grids_tell_the_truth(server: &ServerProcess, what: &str) -> Vec<Vec<Listed>> {
    let mut grids = Vec::new();
    for level in 0u8.. {
        let (dims, listed) = grid(server, level).unwrap_or_else(|e| panic!("{what}: {e:?}"));
        assert_eq!(listed, truth(server, level, dims), "{what}: level {level}");
        grids.push(listed);
        if dims == [1, 1, 1] {
            break;
        }
    }
    grids
}

/// A union with a cuboid at `origin` (size 8).
fn carve(origin: [u32; 3]) -> Value {
    json!({"op": "union", "term": {"cuboid": {"origin": origin, "size": [8, 8, 8]}}})
}

/// Sets the header checksum of every brick record `path`'s head points at to a wrong value:
/// any read of a record's header then fails. Records among the bytes the head's slot was synced
/// with are left alone: damage there is a crash before that sync, and the previous version
/// would open instead.
fn damage_every_brick_header(path: &Path) -> usize {
    let offsets: std::collections::BTreeSet<u64> = {
        let vod = Vod2::open(path).unwrap();
        let synced_from = vod.head_slot().appended.map_or(u64::MAX, |a| a.from);
        let snap = vod.head();
        (0..snap.layout().node_count())
            .filter_map(|n| match snap.entry_at(n).unwrap() {
                NodeEntry::Stored(o) if o < synced_from => Some(o),
                _ => None,
            })
            .collect()
    };
    let mut bytes = std::fs::read(path).unwrap();
    for &o in &offsets {
        bytes[o as usize + 20] ^= 0xff;
    }
    std::fs::write(path, bytes).unwrap();
    offsets.len()
}

#[test]
fn grids_say_what_the_bricks_hold_before_and_after_edits_and_after_reopening() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path());
    assert!(checkpoint_has_summaries(&dir.path().join("world.vod")));
    let server = serve(dir.path(), &[]);
    let before = assert_grids_tell_the_truth(&server, "as generated");
    for origin in [[4, 4, 4], [40, 20, 60], [90, 56, 90]] {
        post_ok(&server, "/v1/volumes/world/edits", carve(origin));
    }
    let after = assert_grids_tell_the_truth(&server, "after three edits");
    assert_ne!(before[0], after[0], "the edits changed level 0");
    // An undo, then a revert: entries pointing at records of older versions again, whose
    // summaries the writer reads from those versions.
    post_ok(&server, "/v1/volumes/world/undo", json!({"version": 3}));
    let undone = assert_grids_tell_the_truth(&server, "after an undo");
    assert_ne!(undone[0], after[0], "the undo changed level 0");
    post_ok(&server, "/v1/volumes/world/revert", json!({"to": 1}));
    let reverted = assert_grids_tell_the_truth(&server, "after a revert");
    assert_eq!(reverted, before, "version 1's grids again");
    drop(server);
    let server = serve(dir.path(), &[]);
    let reopened = assert_grids_tell_the_truth(&server, "reopened");
    assert_eq!(reopened, reverted);
    // An older version's grid, read through the commits' summaries after reopening.
    let (status, body) = get(&server, "/v1/volumes/world/levels/0?version=4");
    assert_eq!(status, 200);
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(listed(&v), after[0], "version 4 as it was listed then");
}

#[test]
fn a_grid_reads_no_brick_record() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path());
    let server = serve(dir.path(), &[]);
    // The first edit's bricks are then listed from its commit record's summaries; the
    // second's records are left whole (see `damage_every_brick_header`).
    post_ok(&server, "/v1/volumes/world/edits", carve([40, 20, 60]));
    post_ok(&server, "/v1/volumes/world/edits", carve([4, 4, 4]));
    let healthy = assert_grids_tell_the_truth(&server, "healthy");
    drop(server);
    let path = dir.path().join("world.vod");
    let damaged = damage_every_brick_header(&path);
    assert!(damaged > 20, "{damaged} records");
    let server = serve(dir.path(), &[]);
    // Every grid answers as before, from the checkpoint's and the commit's summaries...
    for (level, want) in healthy.iter().enumerate() {
        let (_, got) = grid(&server, level as u8).unwrap();
        assert_eq!(&got, want, "level {level}");
    }
    // ...while reading a stored brick does need its record, and fails.
    let stored = healthy[0].iter().rposition(|b| b.1 != b.2).unwrap();
    let dims = grid(&server, 0).unwrap().0;
    let (x, y, z) = (
        stored as u32 % dims[0],
        stored as u32 / dims[0] % dims[1],
        stored as u32 / (dims[0] * dims[1]),
    );
    let (status, _) = get(&server, &format!("/v1/volumes/world/bricks/0/{x}/{y}/{z}"));
    assert_eq!(status, 500);
}

/// Each brick's summary of `vod`'s head, against its decoded voxels (hash and range computed
/// here).
fn assert_summaries_match_voxels(vod: &Vod2, what: &str) -> usize {
    let snap = vod.head();
    let layout = snap.layout().clone();
    let mut stored = 0;
    for node in 0..layout.node_count() {
        let key: BrickKey = layout.key_of(node).unwrap();
        let voxels = snap.read(key).unwrap();
        let s = snap.summary(key).unwrap();
        let want = (
            xxhash_rust::xxh3::xxh3_64(&voxels),
            u64::from(*voxels.iter().min().unwrap()),
            u64::from(*voxels.iter().max().unwrap()),
        );
        assert_eq!((s.hash, s.min, s.max), want, "{what}: brick {key}");
        stored += usize::from(matches!(snap.entry(key).unwrap(), NodeEntry::Stored(_)));
    }
    stored
}

/// Writes new noise into the level-0 brick at `key` of the file's head with a revision-5
/// writer, a full checkpoint with the commit.
fn edit_with_checkpoint(path: &Path, key: BrickKey, seed: u8) {
    let policy = CheckpointPolicy {
        max_overlay: 0,
        max_chain: 0,
    };
    assert!(crate::checkpoints::edit(
        path,
        [key.x, key.y, key.z],
        seed,
        policy
    ));
}

#[test]
fn a_checkpoint_written_after_edits_keeps_the_summaries() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path());
    let path = dir.path().join("world.vod");
    for (i, key) in [[0, 0, 0], [2, 1, 3], [5, 3, 5]].into_iter().enumerate() {
        let key = BrickKey {
            level: 0,
            x: key[0],
            y: key[1],
            z: key[2],
        };
        edit_with_checkpoint(&path, key, i as u8 * 7);
    }
    assert!(checkpoint_has_summaries(&path));
    let stored = assert_summaries_match_voxels(&Vod2::open(&path).unwrap(), "after edits");
    assert!(stored > 20, "{stored} stored bricks");
}

#[test]
fn a_revision_4_file_answers_the_same_grids_and_a_revision_5_writer_upgrades_it() {
    let dir = tempfile::tempdir().unwrap();
    let new_dir = dir.path().join("new");
    let old_dir = dir.path().join("old");
    std::fs::create_dir_all(&new_dir).unwrap();
    std::fs::create_dir_all(&old_dir).unwrap();
    generate_world(&new_dir);
    let old = old_dir.join("world.vod");
    revision4_copy(&new_dir.join("world.vod"), &old);
    assert!(!checkpoint_has_summaries(&old));
    assert_summaries_match_voxels(&Vod2::open(&old).unwrap(), "revision 4");

    // The same grids from both files, and an edit on each gives the same grids again.
    let new_server = serve(&new_dir, &[]);
    let old_server = serve(&old_dir, &[]);
    let from_new = assert_grids_tell_the_truth(&new_server, "revision 5");
    let from_old = assert_grids_tell_the_truth(&old_server, "revision 4");
    assert_eq!(from_new, from_old);
    for server in [&new_server, &old_server] {
        post_ok(server, "/v1/volumes/world/edits", carve([40, 20, 60]));
    }
    let from_new = assert_grids_tell_the_truth(&new_server, "revision 5 edited");
    let from_old = assert_grids_tell_the_truth(&old_server, "revision 4 edited");
    assert_eq!(from_new, from_old);
    drop((new_server, old_server));

    // Without summaries its grids need the brick headers: damaged, the grid fails...
    let damaged = dir.path().join("damaged");
    std::fs::create_dir_all(&damaged).unwrap();
    std::fs::copy(&old, damaged.join("world.vod")).unwrap();
    damage_every_brick_header(&damaged.join("world.vod"));
    let server = serve(&damaged, &[]);
    assert_eq!(grid(&server, 0).unwrap_err().0, 500);
    drop(server);

    // ...and once a revision-5 writer wrote a checkpoint into it, they need none.
    let key = BrickKey {
        level: 0,
        x: 1,
        y: 1,
        z: 1,
    };
    edit_with_checkpoint(&old, key, 3);
    assert!(checkpoint_has_summaries(&old));
    assert_summaries_match_voxels(&Vod2::open(&old).unwrap(), "upgraded");
    let server = serve(&old_dir, &[]);
    let upgraded = assert_grids_tell_the_truth(&server, "upgraded");
    drop(server);
    damage_every_brick_header(&old);
    let server = serve(&old_dir, &[]);
    for (level, want) in upgraded.iter().enumerate() {
        assert_eq!(
            &grid(&server, level as u8).unwrap().1,
            want,
            "level {level}"
        );
    }
}

#[test]
fn a_damaged_summary_is_an_error_naming_it_never_a_wrong_grid() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path());
    let path = dir.path().join("world.vod");
    let server = serve(dir.path(), &[]);
    let healthy = assert_grids_tell_the_truth(&server, "healthy");
    drop(server);

    // One byte of the first chunk's summaries, inside their compressed payload.
    let vod = Vod2::open(&path).unwrap();
    let (at, _) = vod.head().checkpoint_span().unwrap();
    let nodes = vod.header().node_count();
    drop(vod);
    let mut bytes = std::fs::read(&path).unwrap();
    let block = {
        let cp = Checkpoint::decode(&bytes[at as usize..], at, nodes).unwrap();
        let (r, _) = cp.chunk(0).unwrap();
        let block = cp.summaries(&r).unwrap().unwrap();
        (block.offset as usize + 16, block.payload.len())
    };
    bytes[block.0 + block.1 / 2] ^= 0x04;
    std::fs::write(&path, &bytes).unwrap();

    let mut server = serve(dir.path(), &[]);
    let (status, body) = grid(&server, 0).unwrap_err();
    assert_eq!(status, 500, "{body}");
    // The bricks themselves still read: their entries are intact, and checked on their own.
    let (dims, first) = (healthy[0].len(), healthy[0][0]);
    assert!(dims > 1);
    let (status, voxels) = get(&server, "/v1/volumes/world/bricks/0/0/0/0");
    assert_eq!(status, 200);
    assert_eq!(xxhash_rust::xxh3::xxh3_64(&voxels), first.0);
    let log = server.stop();
    assert!(
        log.contains("index chunk summaries"),
        "the log names the damaged summaries: {log}"
    );

    // A damaged summary in a commit record makes that record damaged: the versions that need
    // it do not load, and the error says why. (The first of two edits: damage among the bytes
    // the newest slot was synced with would pass for a crash before that sync.)
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path());
    let server = serve(dir.path(), &[]);
    post_ok(&server, "/v1/volumes/world/edits", carve([40, 20, 60]));
    post_ok(&server, "/v1/volumes/world/edits", carve([4, 4, 4]));
    drop(server);
    let path = dir.path().join("world.vod");
    let vod = Vod2::open(&path).unwrap();
    let (head, _) = vod.commit_at(vod.head().commit_offset()).unwrap();
    let (first, _) = vod.commit_at(head.parent).unwrap();
    assert!(first.summaries && first.n_changes > 0);
    let end = head.parent + first.total_len();
    drop(vod);
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[end as usize - 12] ^= 0x01; // inside the last summary
    std::fs::write(&path, &bytes).unwrap();
    let err = Vod2::open(&path).unwrap_err();
    let why = isovox_server::store::error_chain(&err);
    assert!(why.contains("commit summaries"), "{why}");
}

#[test]
fn compaction_and_salvage_give_a_revision_4_file_its_summaries() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path());
    let old = dir.path().join("old.vod");
    revision4_copy(&dir.path().join("world.vod"), &old);
    assert!(!checkpoint_has_summaries(&old));
    let old_path = old.to_str().unwrap();

    let salvaged = dir.path().join("salvaged.vod");
    run_isovox(&["salvage", old_path, "-o", salvaged.to_str().unwrap()]);
    assert!(checkpoint_has_summaries(&salvaged));
    assert_summaries_match_voxels(&Vod2::open(&salvaged).unwrap(), "salvaged");

    run_isovox(&["compact", old_path]);
    assert!(checkpoint_has_summaries(&old));
    let stored = assert_summaries_match_voxels(&Vod2::open(&old).unwrap(), "compacted");
    assert!(stored > 20, "{stored} stored bricks");
}

#[test]
fn a_commit_by_an_older_writer_in_a_revision_5_file_is_summarized_from_its_records() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path());
    let path = dir.path().join("world.vod");
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    let layout = snap.layout().clone();
    let mut w = Vod2Writer::open_append(&path, Compression::for_edits()).unwrap();
    w.omit_summaries();
    let key = BrickKey {
        level: 0,
        x: 2,
        y: 1,
        z: 3,
    };
    let voxels: Vec<u8> = (0..layout.brick_bytes())
        .map(|i| (i as u8).wrapping_mul(13) % 150)
        .collect();
    let mut t = Transaction::on(&mut w, &snap);
    t.update_level0(
        vec![(key, BrickVoxels::Data(voxels))],
        &isovox_proto::geometry::Box3::of_volume(&layout),
    )
    .unwrap();
    let committed = t.commit(CheckpointPolicy::default()).unwrap();
    assert!(!committed.checkpoint);
    drop((w, snap, vod));

    let vod = Vod2::open(&path).unwrap();
    let (h, _) = vod.commit_at(vod.head().commit_offset()).unwrap();
    assert!(
        !h.summaries && h.n_changes > 0,
        "the commit is as an older writer wrote it"
    );
    assert!(checkpoint_has_summaries(&path));
    assert_summaries_match_voxels(&vod, "a summary-less commit on a revision-5 checkpoint");
}
