//! Damage to a file's history, recovered with the real `isovox` binary: `isovox check` lists the
//! damaged record with its offset and exits non-zero; `isovox salvage` writes the newest intact
//! version to a new file, whose every brick of every level is checked here against the voxels
//! the test wrote (and an independent downsampling for the coarser levels); `isovox serve`
//! starts on a file whose newest version is damaged and serves the newest one that reads,
//! read-only.
//!
//! The history: version 1 is built from a mixed volume; versions 2 to 8 each write two level-0
//! bricks (one of noise, one constant), with a checkpoint policy that puts full index
//! checkpoints at some of them. The damage is one flipped byte, written by the test.

// unwrap is how a test says "this must work"; clippy exempts only #[test] functions.

use crate::common;
use crate::server_process;
use common::{mixed_volume, pyramid, Grid, XorShift};

use isovox_proto::vod2::{Checkpoint, CommitHeader, HeaderSlot, NodeEntry, SLOT_LEN, SLOT_OFFSETS};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::store::codec::Compression;
use isovox_server::store::{
    build_vod2, BrickVoxels, BuildOptions, CheckpointPolicy, DenseGrid, Transaction, Vod2,
    Vod2Writer,
};
use serde_json::Value;
use server_process::ServerProcess;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const DIMS: [u32; 3] = [64, 32, 64];
const BRICK: u32 = 16;
const HEAD: u64 = 8;
const T: VoxelType = VoxelType::U8;

fn layout() -> VolumeLayout {
    VolumeLayout::new(DIMS, BRICK, T).unwrap()
}

/// A file with versions 1..=HEAD and what each holds.
struct History {
    path: PathBuf,
    /// Level 0 of version v at `models[v - 1]`.
    models: Vec<Grid>,
    /// Commit record offset and header of each version, oldest first.
    commits: Vec<(u64, CommitHeader)>,
    /// Offset of the noise brick record each version from 2 on wrote, at
    /// `noise_records[v - 2]`. Version v's is at a place no later version writes: it stays
    /// referenced by every version from v on.
    noise_records: Vec<u64>,
}

impl History {
    fn commit(&self, version: u64) -> (u64, CommitHeader) {
        self.commits[version as usize - 1]
    }

    /// The offset of the header slot that names `version`. Each slot was synced together
    /// with the bytes its version's commit appended, and checks them: damage there is read as
    /// a crash before that sync, so the slot is reported too.
    fn slot_naming(&self, version: u64) -> u64 {
        let bytes = std::fs::read(&self.path).unwrap();
        SLOT_OFFSETS
            .into_iter()
            .find(|&at| {
                let at_usize = at as usize;
                HeaderSlot::decode(&bytes[at_usize..at_usize + SLOT_LEN], at)
                    .is_ok_and(|slot| slot.version == version && slot.appended.is_some())
            })
            .unwrap_or_else(|| panic!("no slot names version {version}"))
    }

    /// The versions whose commit wrote a full index checkpoint.
    fn checkpoints(&self) -> Vec<u64> {
        self.commits
            .iter()
            .filter(|(_, h)| h.checkpoint != 0)
            .map(|(_, h)| h.version)
            .collect()
    }
}

/// Writes the history into `dir/w.vod`.
fn write_history(dir: &Path) -> History {
    let path = dir.join("w.vod");
    let layout = layout();
    let v1 = mixed_volume(DIMS, T, 5);
    let bytes = v1.to_bytes(T);
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &DenseGrid::new(DIMS, T, BRICK, &bytes),
        &BuildOptions::default(),
    )
    .unwrap();
    let mut models = vec![v1];
    // A checkpoint every fourth commit or so, so that the history has deltas after one.
    let policy = CheckpointPolicy {
        max_overlay: 1 << 20,
        max_chain: 3,
    };
    let mut rng = XorShift(0xdead_beef);
    let b = BRICK as usize;
    let mut noise_records = Vec::new();
    for version in 2..=HEAD {
        let v = version as usize;
        let mut model = models.last().unwrap().clone();
        let mut level0 = Vec::new();
        let positions = [[v % 4, 0, (v / 4) % 4], [(v + 1) % 4, 1, (v * 3) % 4]];
        for (i, pos) in positions.into_iter().enumerate() {
            for z in 0..b {
                for y in 0..b {
                    for x in 0..b {
                        let at = ((pos[2] * b + z) * model.dims[1] + pos[1] * b + y)
                            * model.dims[0]
                            + pos[0] * b
                            + x;
                        model.values[at] = match i {
                            0 => (rng.next() & 0xff) as u16,
                            _ => 20 * v as u16,
                        };
                    }
                }
            }
            let key = layout
                .key(0, pos[0] as u32, pos[1] as u32, pos[2] as u32)
                .unwrap();
            level0.push((key, BrickVoxels::from_bytes(model.brick(pos, b, T), T)));
        }
        let vod = Vod2::open(&path).unwrap();
        let snap = vod.head();
        let mut writer = Vod2Writer::open_append(&path, Compression::default()).unwrap();
        let mut t = Transaction::on(&mut writer, &snap);
        t.update_level0(
            level0.clone(),
            &isovox_proto::geometry::Box3::of_volume(snap.layout()),
        )
        .unwrap();
        t.commit(policy).unwrap();
        let head = Vod2::open(&path).unwrap().head();
        let NodeEntry::Stored(offset) = head.entry(level0[0].0).unwrap() else {
            panic!("a noise brick is stored as a record");
        };
        noise_records.push(offset);
        models.push(model);
    }
    let mut commits = Vod2::open(&path).unwrap().commits().unwrap();
    commits.reverse();
    let history = History {
        path,
        models,
        commits,
        noise_records,
    };
    // The set-up this file is about: a checkpoint after the first, with two deltas after it.
    let checkpoints = history.checkpoints();
    assert!(checkpoints.len() >= 2, "checkpoints at {checkpoints:?}");
    assert!(
        *checkpoints.last().unwrap() + 2 < HEAD,
        "checkpoints at {checkpoints:?}"
    );
    history
}

fn flip(path: &Path, offset: u64) {
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .unwrap();
    let mut b = [0u8; 1];
    f.read_exact_at(&mut b, offset).unwrap();
    f.write_all_at(&[b[0] ^ 0x20], offset).unwrap();
    f.sync_all().unwrap();
}

fn isovox(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_isovox"))
        .args(args)
        .env_remove("ISOVOX_LOG")
        .output()
        .unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `isovox check --json`: the report and whether it exited with success.
fn check(path: &Path) -> (Value, bool) {
    let o = isovox(&["check", "--json", s(path)]);
    let stderr = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!stderr.contains("panicked"), "{stderr}");
    let report: Value = serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|e| panic!("check printed no JSON ({e}): {stderr}"));
    if !o.status.success() {
        assert!(
            stderr.starts_with("error:") && stderr.contains("damaged"),
            "{stderr}"
        );
    }
    (report, o.status.success())
}

/// The damage a report lists, as (offset, record).
fn damage(report: &Value) -> Vec<(u64, String)> {
    report["damage"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            (
                d["offset"].as_u64().unwrap(),
                d["record"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

/// The versions a report calls intact.
fn intact(report: &Value) -> Vec<u64> {
    report["versions"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|v| v["index_damage"].is_null() && v["damaged_bricks"] == 0)
        .map(|v| v["version"].as_u64().unwrap())
        .collect()
}

/// Checks that the file at `path` is exactly version `version` of the history: its only
/// version, and every brick of every level as the model and its downsampling say.
fn assert_is_version(path: &Path, h: &History, version: u64) {
    let vod = Vod2::open(path).unwrap();
    let head = vod.head();
    assert_eq!(head.version, version, "{}", path.display());
    assert_eq!(
        vod.commits().unwrap().len(),
        1,
        "one version in a salvaged file"
    );
    let levels = pyramid(&h.models[version as usize - 1], BRICK);
    let layout = layout();
    for (level, grid) in levels.iter().enumerate() {
        let g = layout.grid(level as u8);
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    let key = layout.key(level as u8, x, y, z).unwrap();
                    let want = grid.brick([x as usize, y as usize, z as usize], BRICK as usize, T);
                    assert_eq!(head.read(key).unwrap(), want, "version {version}, {key}");
                }
            }
        }
    }
}

/// Salvages `h`'s file into `dir/out.vod` and checks the result is version `expected`.
fn salvage_gives(h: &History, dir: &Path, expected: u64) {
    let before = std::fs::read(&h.path).unwrap();
    let out = dir.join("out.vod");
    let o = isovox(&["salvage", s(&h.path), "-o", s(&out)]);
    let stdout = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(
        o.status.success(),
        "salvage failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        stdout.contains(&format!("version {expected} written")),
        "{stdout}"
    );
    assert_is_version(&out, h, expected);
    let (report, clean) = check(&out);
    assert!(clean, "the salvaged file checks clean: {report}");
    assert_eq!(intact(&report), vec![expected]);
    assert_eq!(
        std::fs::read(&h.path).unwrap(),
        before,
        "salvage never writes to the damaged file"
    );
}

#[test]
fn an_intact_file_checks_clean() {
    let dir = tempfile::tempdir().unwrap();
    let h = write_history(dir.path());
    let (report, clean) = check(&h.path);
    assert!(clean, "{report}");
    assert!(damage(&report).is_empty());
    assert_eq!(intact(&report), (1..=HEAD).collect::<Vec<_>>());
    assert_eq!(report["head"], HEAD);
    // Every record this build wrote has a payload checksum.
    assert!(report["bricks"].as_u64().unwrap() > 0);
    assert_eq!(report["bricks_without_checksum"], 0);
    // And every version of it reads as written (the history's own set-up is right).
    let vod = Vod2::open(&h.path).unwrap();
    let layout = layout();
    for version in 1..=HEAD {
        let snap = vod.version(version).unwrap();
        let model = &h.models[version as usize - 1];
        for node in 0..layout.grid(0).iter().product::<u32>() as u64 {
            let k = layout.key_of(node).unwrap();
            let want = model.brick([k.x as usize, k.y as usize, k.z as usize], 16, T);
            assert_eq!(snap.read(k).unwrap(), want, "version {version} {k}");
        }
    }
}

#[test]
fn a_damaged_commit_record_is_salvaged_to_the_version_before_it() {
    let dir = tempfile::tempdir().unwrap();
    let h = write_history(dir.path());
    // Version HEAD - 1: a delta after the last checkpoint, on the head's chain.
    let (at, header) = h.commit(HEAD - 1);
    assert_eq!(header.checkpoint, 0);
    let older_slot = h.slot_naming(HEAD - 1);
    flip(&h.path, at + 20);
    assert!(Vod2::open(&h.path).is_err(), "the head no longer opens");

    let (report, clean) = check(&h.path);
    assert!(!clean);
    assert_eq!(
        damage(&report),
        vec![
            (older_slot, "header slot".to_string()),
            (at, "commit record".to_string())
        ]
    );
    assert_eq!(intact(&report), (1..HEAD - 1).collect::<Vec<_>>());
    assert_eq!(report["head"], HEAD);
    // The text report names the offset too.
    let text = isovox(&["check", s(&h.path)]);
    assert!(!text.status.success());
    assert!(String::from_utf8_lossy(&text.stdout).contains(&at.to_string()));

    salvage_gives(&h, dir.path(), HEAD - 2);
}

#[test]
fn a_damaged_head_commit_record_is_salvaged_to_its_parent() {
    let dir = tempfile::tempdir().unwrap();
    let h = write_history(dir.path());
    let (at, _) = h.commit(HEAD);
    let head_slot = h.slot_naming(HEAD);
    flip(&h.path, at + 9);
    // The record is among the bytes the head's slot was synced with: the slot fails its
    // check, as after a crash before that sync, and the version before is the head.
    assert_eq!(Vod2::open(&h.path).unwrap().head().version, HEAD - 1);
    let (report, clean) = check(&h.path);
    assert!(!clean);
    // What the failing slot named lies past the head's committed length, which is all a
    // check reads: the slot is the damage it finds.
    assert_eq!(
        damage(&report),
        vec![(head_slot, "header slot".to_string())]
    );
    assert_eq!(report["head"], HEAD - 1);
    assert_eq!(intact(&report), (1..HEAD).collect::<Vec<_>>());
    salvage_gives(&h, dir.path(), HEAD - 1);
}

#[test]
fn a_damaged_checkpoint_is_salvaged_to_the_version_before_it() {
    for part in ["fixed part", "chunk"] {
        let dir = tempfile::tempdir().unwrap();
        let h = write_history(dir.path());
        let last = *h.checkpoints().last().unwrap();
        let cp_at = h.commit(last).1.checkpoint;
        let offset = match part {
            // The node count, inside the fixed part's checksum: the version no longer opens.
            "fixed part" => cp_at + 9,
            // The middle of chunk 0's payload: found when the chunk is first used.
            _ => {
                let bytes = std::fs::read(&h.path).unwrap();
                let nodes = layout().node_count();
                let cp = Checkpoint::decode(&bytes[cp_at as usize..], cp_at, nodes).unwrap();
                let (r, payload) = cp.chunk(0).unwrap();
                cp_at + r.offset + payload.len() as u64 / 2
            }
        };
        flip(&h.path, offset);
        let (report, clean) = check(&h.path);
        assert!(!clean, "{part}");
        assert_eq!(
            damage(&report),
            vec![(cp_at, "index checkpoint".to_string())],
            "{part}"
        );
        // Every version from the checkpoint's on builds on it.
        assert_eq!(intact(&report), (1..last).collect::<Vec<_>>(), "{part}");
        salvage_gives(&h, dir.path(), last - 1);
    }
}

#[test]
fn a_damaged_brick_is_never_copied() {
    let dir = tempfile::tempdir().unwrap();
    let h = write_history(dir.path());
    // The noise brick version HEAD - 1 wrote, which the head points at too: its payload, past
    // the 24-byte header. It is among the bytes the slot naming HEAD - 1 was synced with, so
    // that slot is damaged too (the head's slot is not: it checks only what HEAD appended).
    let record = h.noise_records[HEAD as usize - 3];
    let older_slot = h.slot_naming(HEAD - 1);
    flip(&h.path, record + 24 + 100);
    let (report, clean) = check(&h.path);
    assert!(!clean);
    assert_eq!(
        damage(&report),
        vec![
            (older_slot, "header slot".to_string()),
            (record, "brick record".to_string())
        ]
    );
    let head = &report["versions"][HEAD as usize - 1];
    assert!(
        head["index_damage"].is_null(),
        "the head's index reads: {head}"
    );
    assert_eq!(head["damaged_bricks"], 1);
    assert_eq!(intact(&report), (1..HEAD - 1).collect::<Vec<_>>());
    // Asked for the head, salvage refuses: it would copy the damage.
    let out = dir.path().join("head.vod");
    let o = isovox(&[
        "salvage",
        s(&h.path),
        "-o",
        s(&out),
        "--version",
        &HEAD.to_string(),
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && stderr.contains("not intact"),
        "{stderr}"
    );
    assert!(!out.exists());
    salvage_gives(&h, dir.path(), HEAD - 2);
}

/// `isovox serve` on `dir` (killed when dropped), its address, and everything it logged up to
/// the line saying it serves.
struct Server {
    _process: ServerProcess,
    base: String,
    log: String,
}

fn serve(dir: &Path) -> Server {
    let process = ServerProcess::start(&["--data".as_ref(), dir.as_os_str()], &[]);
    Server {
        base: process.url(""),
        log: format!("{}\n{}", process.log(), process.announced),
        _process: process,
    }
}

/// A small edit, with the write token the server made in `dir`.
fn post_edit(c: &reqwest::blocking::Client, url: &str, dir: &Path) -> reqwest::blocking::Response {
    c.post(url)
        .bearer_auth(token(dir))
        .header("content-type", "application/json")
        .body(r#"{"op":"union","term":{"ellipsoid":{"center":[8,8,8],"radii":[4,4,4]}}}"#)
        .send()
        .unwrap()
}

fn token(dir: &Path) -> String {
    let text = std::fs::read_to_string(dir.join("tokens")).unwrap();
    let line = text.lines().find(|l| !l.starts_with('#')).unwrap();
    line.split_whitespace().nth(1).unwrap().to_string()
}

/// The volume at `volume_url` is at `version`, and every level-0 brick is that version's.
fn assert_serves(c: &reqwest::blocking::Client, volume_url: &str, h: &History, version: u64) {
    let info: Value = c.get(volume_url).send().unwrap().json().unwrap();
    assert_eq!(info["version"], version);
    let layout = layout();
    let model = &h.models[version as usize - 1];
    let g = layout.grid(0);
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                let r = c
                    .get(format!("{volume_url}/bricks/0/{x}/{y}/{z}"))
                    .send()
                    .unwrap();
                assert_eq!(r.status(), 200);
                let want = model.brick([x as usize, y as usize, z as usize], 16, T);
                assert_eq!(r.bytes().unwrap().to_vec(), want, "brick {x} {y} {z}");
            }
        }
    }
}

#[test]
fn damage_among_the_bytes_synced_with_the_head_slot_reads_as_a_crash_before_that_sync() {
    // One fdatasync makes the newest commit durable together with its slot, so damage among
    // the bytes it appended cannot be told from a crash that kept the slot and lost some of
    // them: the version before it opens, read-write, with a warning naming the slot, and the
    // next edit takes the failed commit's place.
    let dir = tempfile::tempdir().unwrap();
    let h = write_history(dir.path());
    let head_slot = h.slot_naming(HEAD);
    flip(&h.path, h.noise_records[HEAD as usize - 2] + 24 + 100);

    let server = serve(dir.path());
    assert!(!server.log.contains("READ-ONLY"), "{}", server.log);
    assert!(
        server.log.contains("header slot is not valid")
            && server.log.contains(&format!("slot={head_slot}"))
            && server.log.contains(&format!("version {HEAD}")),
        "a warning naming the slot and the version it named: {}",
        server.log
    );
    isovox_server::client_tls::install_provider();
    let c = reqwest::blocking::Client::new();
    let url = |p: &str| format!("{}/v1/volumes/w{p}", server.base);
    assert_serves(&c, &url(""), &h, HEAD - 1);
    let edit = post_edit(&c, &url("/edits"), dir.path());
    assert_eq!(edit.status(), 200);
    let answer: Value = edit.json().unwrap();
    assert_eq!(
        (answer["previous"].as_u64(), answer["version"].as_u64()),
        (Some(HEAD - 1), Some(HEAD))
    );
    let (report, clean) = check(&h.path);
    assert!(clean, "the edit's slot replaced the failed one: {report}");
    assert_eq!(intact(&report), (1..=HEAD).collect::<Vec<_>>());
}

#[test]
fn a_server_serves_the_newest_readable_version_read_only() {
    let dir = tempfile::tempdir().unwrap();
    let h = write_history(dir.path());
    let (at, _) = h.commit(HEAD - 1);
    flip(&h.path, at + 20);
    let served = HEAD - 2;

    let server = serve(dir.path());
    assert!(
        server.log.contains("READ-ONLY") && server.log.contains(&format!("version {served}")),
        "a loud warning: {}",
        server.log
    );
    isovox_server::client_tls::install_provider();
    let c = reqwest::blocking::Client::new();
    let url = |p: &str| format!("{}/v1/volumes/w{p}", server.base);
    assert_serves(&c, &url(""), &h, served);
    // Edits and compaction are refused, naming the cause; nothing is written.
    let len_before = std::fs::metadata(&h.path).unwrap().len();
    let edit = post_edit(&c, &url("/edits"), dir.path());
    assert_eq!(edit.status(), 409);
    let problem: Value = edit.json().unwrap();
    let detail = problem["detail"].as_str().unwrap();
    assert!(
        detail.contains("read-only")
            && detail.contains(&format!("version {HEAD}"))
            && detail.contains("salvage"),
        "{detail}"
    );
    assert!(
        problem.get("version").is_none_or(Value::is_null),
        "{problem}"
    );
    let compact = c
        .post(url("/compact"))
        .bearer_auth(token(dir.path()))
        .send()
        .unwrap();
    assert_eq!(compact.status(), 409);
    assert_eq!(std::fs::metadata(&h.path).unwrap().len(), len_before);
}

#[test]
fn damage_before_the_last_checkpoint_costs_only_the_history_before_it() {
    let dir = tempfile::tempdir().unwrap();
    let h = write_history(dir.path());
    let last = *h.checkpoints().last().unwrap();
    let (at, header) = h.commit(last - 1);
    assert_eq!(header.checkpoint, 0, "a delta before the last checkpoint");
    flip(&h.path, at + 20);
    // The head does not need it: it opens, and the server takes edits.
    assert_eq!(Vod2::open(&h.path).unwrap().head().version, HEAD);
    let server = serve(dir.path());
    assert!(!server.log.contains("READ-ONLY"), "{}", server.log);
    isovox_server::client_tls::install_provider();
    let c = reqwest::blocking::Client::new();
    let url = |p: &str| format!("{}/v1/volumes/w{p}", server.base);
    let edit = post_edit(&c, &url("/edits"), dir.path());
    assert_eq!(edit.status(), 200, "{}", edit.text().unwrap());
    // The versions after the damage are listed; asking for those before it is a server error,
    // not a 404 or a 410.
    let ok = c
        .get(url(&format!("/changes?since={}", last - 1)))
        .send()
        .unwrap();
    assert_eq!(ok.status(), 200);
    for bad in [
        url("/changes?since=0"),
        url(&format!("/changes?since={}", last - 3)),
        url(&format!("/bricks/0/0/0/0?version={}", last - 2)),
    ] {
        assert_eq!(c.get(&bad).send().unwrap().status(), 500, "{bad}");
    }
    // `check` finds it; only the version whose chain needs the record is not intact (the
    // edit's version, HEAD + 1, builds on the head).
    let (report, clean) = check(&h.path);
    assert!(!clean);
    assert_eq!(damage(&report), vec![(at, "commit record".to_string())]);
    let all_but: Vec<u64> = (1..=HEAD + 1).filter(|&v| v != last - 1).collect();
    assert_eq!(intact(&report), all_but);
}
