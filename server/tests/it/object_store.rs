//! Volumes in an object store, tested as the deployment runs: a real S3 server on loopback
//! (moto's, served by `scripts/s3-server.py`; `.ci/run` installs it), `isovox serve --store`
//! replicas as processes, edits over HTTP, kill -9.
//!
//! - replicas answer byte for byte like the local-file server on the same volume, before and
//!   after the same edit;
//! - two replicas editing one volume concurrently lose no acknowledged edit and end at the same
//!   head, with the same history; a replica started later serves that head;
//! - a replica catching up with another's commits fetches the volume's manifest once, not at
//!   each commit (counted in the S3 server's request log);
//! - a writer killed between writing its segment and advancing the head leaves the volume at its
//!   last acknowledged version, and `isovox compact` collects the orphan;
//! - a stalled writer cannot overwrite a newer head: it re-applies its edit on top, or, asked
//!   with `If-Match`, is refused with 409;
//! - a store that stops answering (SIGSTOP) makes an edit a 503 with `Retry-After` once the
//!   edit timeout passes, not a 422, commits nothing, and edits succeed again once it answers.
//!
//! The S3 server's Python: `ISOVOX_S3_PYTHON`, else `target/s3-venv/bin/python` (what
//! `.ci/run` creates).

use crate::server_process;
use reqwest::blocking::Client;
use serde_json::{json, Value};

use server_process::ServerProcess;
use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

const TOKEN: &str = "object-store-7c1e94a0";
const KEY_ID: &str = "isovox";
const SECRET: &str = "isovox-secret";
const VOLUME: &str = "w";
/// The generated world: 96 x 64 x 96 voxels, bricks of 16 (levels 6x4x6, 3x2x3, 2x1x2, 1x1x1).
const DIMS: [u32; 3] = [96, 64, 96];
const BRICK: u32 = 16;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The S3 server, killed when dropped (also used by [`crate::split_import`]).
pub(crate) struct S3 {
    child: Child,
    pub(crate) endpoint: String,
    bucket: String,
    /// The server's request log (werkzeug's access log: one line per request).
    log: tempfile::NamedTempFile,
}

impl S3 {
    pub(crate) fn start(bucket: &str) -> S3 {
        let python = std::env::var("ISOVOX_S3_PYTHON")
            .map(PathBuf::from)
            .unwrap_or_else(|_| workspace().join("target/s3-venv/bin/python"));
        assert!(
            python.exists(),
            "no Python with moto at {} (run .ci/run, or set ISOVOX_S3_PYTHON)",
            python.display()
        );
        let port = free_port();
        let log = tempfile::NamedTempFile::new().unwrap();
        let mut child = Command::new(&python)
            .arg(workspace().join("scripts/s3-server.py"))
            .arg(port.to_string())
            .arg(bucket)
            .stdout(Stdio::piped())
            .stderr(log.reopen().unwrap())
            .spawn()
            .expect("the S3 server starts");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if line.trim() == "ready" {
                    let _ = tx.send(());
                }
            }
        });
        rx.recv_timeout(Duration::from_secs(60))
            .expect("the S3 server says ready");
        S3 {
            child,
            endpoint: format!("http://127.0.0.1:{port}"),
            bucket: bucket.to_string(),
            log,
        }
    }

    /// How many `method` requests the server has answered for objects of the volume whose key
    /// starts with `prefix` (below the volume's).
    fn requests(&self, method: &str, prefix: &str) -> usize {
        // The request line is quoted (and, for answers other than 200, coloured).
        let wanted = format!("{method} /{}/vols/{VOLUME}/{prefix}", self.bucket);
        std::fs::read_to_string(self.log.path())
            .unwrap()
            .lines()
            .filter(|line| line.contains(&wanted))
            .count()
    }

    pub(crate) fn url(&self) -> String {
        format!("s3://{}/vols", self.bucket)
    }

    pub(crate) fn env(&self, cmd: &mut Command) {
        cmd.env("AWS_ENDPOINT", &self.endpoint)
            .env("AWS_ACCESS_KEY_ID", KEY_ID)
            .env("AWS_SECRET_ACCESS_KEY", SECRET)
            .env("AWS_REGION", "us-east-1")
            .env("AWS_ALLOW_HTTP", "true");
    }

    /// The volume's objects, read in this process.
    fn volume_bucket(&self) -> isovox_server::store::remote::Bucket {
        // SAFETY of the environment: every test sets the same credentials.
        std::env::set_var("AWS_ACCESS_KEY_ID", KEY_ID);
        std::env::set_var("AWS_SECRET_ACCESS_KEY", SECRET);
        std::env::set_var("AWS_REGION", "us-east-1");
        isovox_server::store::remote::Bucket::from_url_at(&self.url(), Some(&self.endpoint))
            .unwrap()
            .child(VOLUME)
    }

    fn segments(&self) -> Vec<String> {
        self.volume_bucket()
            .list("seg")
            .unwrap()
            .into_iter()
            .map(|o| o.key)
            .collect()
    }

    fn head_version(&self) -> u64 {
        isovox_server::store::remote::read_head(&self.volume_bucket())
            .unwrap()
            .0
            .version
    }

    fn isovox(&self, args: &[&str]) -> String {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_isovox"));
        cmd.args(args);
        self.env(&mut cmd);
        let out = cmd.output().unwrap();
        assert!(
            out.status.success(),
            "isovox {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }
}

impl Drop for S3 {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An `isovox serve` process (a replica on the store, or the local-file server), killed with
/// SIGKILL when dropped.
struct Server {
    process: ServerProcess,
    base: String,
    _dir: tempfile::TempDir,
}

impl Server {
    fn replica(s3: &S3, pause_before_head_ms: Option<u64>) -> Server {
        Server::replica_with(s3, pause_before_head_ms, &[])
    }

    /// [`Server::replica`] whose every segment is an object of its own, none carried in the
    /// head (`--inline-kb 0`): a commit writes its segment, then the head, and a test sees the
    /// window between the two in the store.
    fn replica_of_objects(s3: &S3, pause_before_head_ms: Option<u64>) -> Server {
        Server::replica_with(s3, pause_before_head_ms, &["--inline-kb", "0"])
    }

    /// [`Server::replica`] with more arguments for `isovox serve` (polling the head every 50 ms
    /// unless they say otherwise).
    fn replica_with(s3: &S3, pause_before_head_ms: Option<u64>, more: &[&str]) -> Server {
        let store = s3.url();
        let pause = pause_before_head_ms.map(|ms| ms.to_string());
        let mut envs = vec![
            ("AWS_ENDPOINT", s3.endpoint.as_str()),
            ("AWS_ACCESS_KEY_ID", KEY_ID),
            ("AWS_SECRET_ACCESS_KEY", SECRET),
            ("AWS_REGION", "us-east-1"),
            ("AWS_ALLOW_HTTP", "true"),
        ];
        if let Some(ms) = &pause {
            envs.push(("ISOVOX_STORE_PAUSE_BEFORE_HEAD_MS", ms));
        }
        let mut args = vec!["--store", &store];
        if !more.contains(&"--follow-ms") {
            args.extend(["--follow-ms", "50"]);
        }
        args.extend_from_slice(more);
        Server::start(&args, &envs)
    }

    fn local(data: &Path) -> Server {
        Server::start(&["--data", data.to_str().unwrap()], &[])
    }

    fn start(args: &[&str], envs: &[(&str, &str)]) -> Server {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("tokens"), format!("t {TOKEN} write\n")).unwrap();
        let tokens = dir.path().join("tokens");
        let cache = dir.path().join("cache");
        let mut all: Vec<&std::ffi::OsStr> = args.iter().map(std::ffi::OsStr::new).collect();
        all.extend([
            std::ffi::OsStr::new("--token-file"),
            tokens.as_os_str(),
            std::ffi::OsStr::new("--cache-dir"),
            cache.as_os_str(),
        ]);
        let mut envs = envs.to_vec();
        envs.push(("ISOVOX_EDIT_RATE", "100000"));
        let process = ServerProcess::start(&all, &envs);
        Server {
            base: process.url(&format!("/v1/volumes/{VOLUME}")),
            process,
            _dir: dir,
        }
    }

    fn version(&self, http: &Client) -> u64 {
        let v: Value = http.get(&self.base).send().unwrap().json().unwrap();
        v["version"].as_u64().unwrap()
    }

    /// Waits until the served head is `version` (replicas follow every 50 ms).
    fn wait_for(&self, http: &Client, version: u64) {
        let deadline = Instant::now() + Duration::from_secs(30);
        while self.version(http) != version {
            assert!(
                Instant::now() < deadline,
                "{} stays at version {}, {version} expected",
                self.base,
                self.version(http)
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn get(&self, http: &Client, path: &str, encoding: Option<&str>) -> (u16, Vec<u8>, String) {
        let mut req = http.get(format!("{}/{path}", self.base));
        if let Some(e) = encoding {
            req = req.header("Accept-Encoding", e);
        }
        let resp = req.send().unwrap();
        let status = resp.status().as_u16();
        let etag = resp
            .headers()
            .get("etag")
            .map(|v| v.to_str().unwrap().to_string())
            .unwrap_or_default();
        (status, resp.bytes().unwrap().to_vec(), etag)
    }

    /// Posts an edit; the status and the answer.
    fn edit(&self, http: &Client, edit: &Value, if_match: Option<u64>) -> (u16, Value) {
        let mut req = http
            .post(format!("{}/edits", self.base))
            .bearer_auth(TOKEN)
            .json(edit);
        if let Some(v) = if_match {
            req = req.header("If-Match", v.to_string());
        }
        let resp = req.send().unwrap();
        let status = resp.status().as_u16();
        (status, resp.json().unwrap_or(Value::Null))
    }

    /// Posts `body` to the volume's `route` (undo, revert) with the write token.
    fn post(&self, http: &Client, route: &str, body: &Value) -> (u16, Value) {
        let resp = http
            .post(format!("{}/{route}", self.base))
            .bearer_auth(TOKEN)
            .json(body)
            .send()
            .unwrap();
        let status = resp.status().as_u16();
        (status, resp.json().unwrap_or(Value::Null))
    }

    fn kill(mut self) {
        self.process.stop();
    }
}

fn client() -> Client {
    isovox_server::client_tls::install_provider();
    Client::builder()
        .timeout(Duration::from_secs(60))
        .build()
        .unwrap()
}

/// Generates an `edge`^3 world in bricks of 16 into `dir/w.vod` (larger than [`world`]'s: its
/// index spans several chunks and pages) and imports it into the store as [`VOLUME`].
fn large_world(s3: &S3, dir: &Path, edge: u32) -> PathBuf {
    let file = dir.join("w.vod");
    let dims = format!("{edge},{edge},{edge}");
    let path = file.to_str().unwrap();
    s3.isovox(&[
        "generate", "world", "-o", path, "--dims", &dims, "--brick", "16",
    ]);
    s3.isovox(&["import", path, "-o", &format!("{}/{VOLUME}", s3.url())]);
    file
}

/// Generates the world into `dir/w.vod` and imports it into the store.
fn world(s3: &S3, dir: &Path) -> PathBuf {
    let file = dir.join(format!("{VOLUME}.vod"));
    let dims = format!("{},{},{}", DIMS[0], DIMS[1], DIMS[2]);
    s3.isovox(&[
        "generate",
        "world",
        "-o",
        file.to_str().unwrap(),
        "--dims",
        &dims,
        "--brick",
        &BRICK.to_string(),
    ]);
    let out = s3.isovox(&[
        "import",
        file.to_str().unwrap(),
        "-o",
        &format!("{}/{VOLUME}", s3.url()),
    ]);
    assert!(out.contains("version 1"), "{out}");
    file
}

/// Every brick of every level, as `level/x/y/z`.
fn all_bricks() -> Vec<String> {
    let mut out = Vec::new();
    let mut grid = DIMS.map(|d| d.div_ceil(BRICK));
    for level in 0.. {
        for z in 0..grid[2] {
            for y in 0..grid[1] {
                for x in 0..grid[0] {
                    out.push(format!("{level}/{x}/{y}/{z}"));
                }
            }
        }
        if grid == [1, 1, 1] {
            break;
        }
        grid = grid.map(|g| g.div_ceil(2));
    }
    out
}

/// A union with a cuboid at `origin` (size 8: H on its inner 4^3 voxels).
fn carve(origin: [u32; 3]) -> Value {
    json!({"op": "union", "term": {"cuboid": {"origin": origin, "size": [8, 8, 8]}}})
}

/// The level-0 voxel at `p` as a replica serves it (u8 world).
fn voxel(server: &Server, http: &Client, p: [u32; 3]) -> u8 {
    let b = p.map(|c| c / BRICK);
    let (status, body, _) = server.get(http, &format!("bricks/0/{}/{}/{}", b[0], b[1], b[2]), None);
    assert_eq!(status, 200);
    let l = p.map(|c| (c % BRICK) as usize);
    let b = BRICK as usize;
    body[l[0] + b * (l[1] + b * l[2])]
}

/// Asserts that `a` and `b` answer every brick (raw, and zstd for the level-0 ones), every
/// level grid and the metadata with the same bytes.
fn assert_same_answers(http: &Client, a: &Server, b: &Server) {
    assert_same_content(http, a, b, true);
}

/// [`assert_same_answers`], the stored (zstd) bricks only when `stored` (content that an older
/// version held too may be found in the file by one writer and stored again by another: the
/// same voxels in other frames).
fn assert_same_content(http: &Client, a: &Server, b: &Server, stored: bool) {
    for key in all_bricks() {
        let (sa, ba, ea) = a.get(http, &format!("bricks/{key}"), None);
        let (sb, bb, eb) = b.get(http, &format!("bricks/{key}"), None);
        assert_eq!((sa, &ea), (sb, &eb), "brick {key}: status and ETag");
        assert!(
            ba == bb,
            "brick {key}: raw bytes differ ({} vs {})",
            a.base,
            b.base
        );
        if key.starts_with("0/") {
            if stored {
                let (_, za, _) = a.get(http, &format!("bricks/{key}"), Some("zstd"));
                let (_, zb, _) = b.get(http, &format!("bricks/{key}"), Some("zstd"));
                assert!(za == zb, "brick {key}: stored zstd bytes differ");
            }
            let hash = ea.trim_matches('"');
            let (sh, bh, _) = b.get(http, &format!("blobs/{hash}"), None);
            assert_eq!(sh, 200, "blob {hash}");
            assert!(bh == ba, "blob {hash}: bytes differ from brick {key}");
        }
    }
    for level in 0..4 {
        let (_, ga, _) = a.get(http, &format!("levels/{level}"), None);
        let (_, gb, _) = b.get(http, &format!("levels/{level}"), None);
        assert!(ga == gb, "level {level} grid differs");
    }
    let ma: Value = http.get(&a.base).send().unwrap().json().unwrap();
    let mb: Value = http.get(&b.base).send().unwrap().json().unwrap();
    assert_eq!(ma, mb, "metadata");
}

#[test]
fn replicas_answer_byte_for_byte_like_the_local_file_server() {
    let s3 = S3::start("isovox-equal");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    let local = Server::local(data.path());
    let r1 = Server::replica(&s3, None);
    let r2 = Server::replica(&s3, None);
    assert_same_answers(&http, &local, &r1);
    assert_same_answers(&http, &local, &r2);

    // The same edit on the local server and on one replica: the other follows.
    let edit = json!({"op": "difference", "term": {"ellipsoid": {"center": [40, 40, 50], "radii": [18, 12, 14]}}});
    let (sl, al) = local.edit(&http, &edit, None);
    let (s1, a1) = r1.edit(&http, &edit, None);
    assert_eq!((sl, s1), (200, 200), "{al} {a1}");
    assert_eq!(al["version"], 2);
    assert_eq!(a1["version"], 2);
    assert_eq!(al["changed"], a1["changed"]);
    r2.wait_for(&http, 2);
    assert_same_answers(&http, &local, &r1);
    assert_same_answers(&http, &local, &r2);
    let (_, cl, _) = local.get(&http, "changes?since=0", None);
    let (_, c2, _) = r2.get(&http, "changes?since=0", None);
    let (cl, c2): (Value, Value) = (
        serde_json::from_slice(&cl).unwrap(),
        serde_json::from_slice(&c2).unwrap(),
    );
    assert_eq!(cl["changes"][0]["changed"], c2["changes"][0]["changed"]);
    assert_eq!(
        c2["changes"][1]["author"], "t",
        "the replica reads the commit's note: {c2}"
    );

    // Undo and revert commit on the store as edits do, and give what the local server gives.
    let over = json!({"op": "union", "term": {"ellipsoid": {"center": [48, 44, 50], "radii": [14, 14, 14]}}});
    assert_eq!(local.edit(&http, &over, None).0, 200);
    assert_eq!(r1.edit(&http, &over, None).0, 200);
    for (route, body) in [
        ("undo", json!({"version": 2})),
        ("revert", json!({"to": 1})),
    ] {
        let (sl, al) = local.post(&http, route, &body);
        let (s1, a1) = r1.post(&http, route, &body);
        assert_eq!((sl, s1), (200, 200), "{route}: {al} {a1}");
        assert_eq!(
            (&al["version"], &al["replayed"]),
            (&a1["version"], &a1["replayed"])
        );
        r2.wait_for(&http, a1["version"].as_u64().unwrap());
        assert_same_content(&http, &local, &r1, false);
        assert_same_content(&http, &local, &r2, false);
    }
}

#[test]
fn two_replicas_editing_concurrently_lose_no_acknowledged_edit_and_converge() {
    let s3 = S3::start("isovox-concurrent");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let r1 = Server::replica(&s3, None);
    let r2 = Server::replica(&s3, None);
    const PER_EDITOR: u32 = 6;
    // Cuboids above the terrain (its top is below y = 48 there): each union changes voxels.
    let origin = |editor: u32, i: u32| [2 + 10 * i, 50, 2 + 22 * editor];
    let centre = |editor: u32, i: u32| origin(editor, i).map(|c| c + 4);
    {
        let http = client();
        for editor in 0..4 {
            for i in 0..PER_EDITOR {
                assert_ne!(voxel(&r1, &http, centre(editor, i)), 255);
            }
        }
    }
    // Four editors, two per replica, each carving its own cuboids (none overlaps another).
    let acks: Vec<(u32, u32, Value)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..4u32)
            .map(|editor| {
                let server = if editor % 2 == 0 { &r1 } else { &r2 };
                scope.spawn(move || {
                    let http = client();
                    (0..PER_EDITOR)
                        .map(|i| {
                            let (status, answer) =
                                server.edit(&http, &carve(origin(editor, i)), None);
                            assert_eq!(status, 200, "editor {editor} edit {i}: {answer}");
                            (editor, i, answer)
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap())
            .collect()
    });
    let http = client();
    let total = acks.len() as u64;
    let mut versions: Vec<u64> = acks
        .iter()
        .map(|(_, _, a)| a["version"].as_u64().unwrap())
        .collect();
    versions.sort_unstable();
    versions.dedup();
    assert_eq!(
        versions.len() as u64,
        total,
        "two edits acknowledged as one version"
    );
    // Every acknowledged edit is a version of the one history: 1 (the import) plus each edit.
    assert_eq!(versions, (2..=total + 1).collect::<Vec<_>>());
    assert_eq!(s3.head_version(), total + 1);
    r1.wait_for(&http, total + 1);
    r2.wait_for(&http, total + 1);

    // The same history on both, each version as its editor was told.
    let (_, c1, _) = r1.get(&http, "changes?since=1", None);
    let (_, c2, _) = r2.get(&http, "changes?since=1", None);
    assert!(c1 == c2, "the replicas list different histories");
    let c1: Value = serde_json::from_slice(&c1).unwrap();
    for (editor, i, ack) in &acks {
        let v = ack["version"].as_u64().unwrap();
        let listed = &c1["changes"][(v - 2) as usize];
        assert_eq!(listed["version"], v);
        assert_eq!(
            listed["changed"], ack["changed"],
            "editor {editor} edit {i}"
        );
    }
    // Every cuboid is there (H at its centre), on both replicas.
    for (editor, i, _) in &acks {
        let c = centre(*editor, *i);
        assert_eq!(voxel(&r1, &http, c), 255, "editor {editor} edit {i} on r1");
        assert_eq!(voxel(&r2, &http, c), 255, "editor {editor} edit {i} on r2");
    }
    assert_same_answers(&http, &r1, &r2);
    // A replica started now serves the current head.
    let late = Server::replica(&s3, None);
    assert_eq!(late.version(&http), total + 1);
    assert_same_answers(&http, &r1, &late);
}

/// A replica following another's commits fetches the volume's manifest when the head names a
/// new one, not at every commit it catches up with: a manifest's key is unique and its content
/// never changes, and the head names the same one until the next 64 segments are folded.
#[test]
fn a_replica_catching_up_fetches_a_manifest_once_not_at_every_commit() {
    let s3 = S3::start("isovox-manifests");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    let writer = Server::replica(&s3, None);
    // Cuboids above the terrain, each a commit of its own: past 64 segments (the import's and
    // 64 edits') the head folds them into a manifest.
    let edit = |i: u32| {
        let origin = [2 + 10 * (i % 9), 50, 2 + 10 * (i / 9)];
        let (status, answer) = writer.edit(&http, &carve(origin), None);
        assert_eq!(status, 200, "edit {i}: {answer}");
        answer["version"].as_u64().unwrap()
    };
    let mut version = 0;
    for i in 0..66 {
        version = edit(i);
    }
    assert_eq!(
        s3.requests("PUT", "manifests/"),
        1,
        "the head names one manifest"
    );
    let follower = Server::replica(&s3, None);
    follower.wait_for(&http, version);
    let opened = s3.requests("GET", "manifests/");
    assert_eq!(
        opened, 1,
        "the follower reads the manifest when it opens the volume"
    );
    for i in 66..81 {
        let v = edit(i);
        follower.wait_for(&http, v);
    }
    assert_eq!(s3.requests("PUT", "manifests/"), 1);
    assert_eq!(
        s3.requests("GET", "manifests/"),
        opened,
        "the follower fetched the manifest again while catching up with 15 commits"
    );
    assert_same_answers(&http, &writer, &follower);
}

/// A small commit's segment rides in the head: the commit is one PUT (no segment object), and
/// a replica following reads it with the head, no segment GET. When the next would not fit,
/// the writer spills the inlined segments and its own into one object, which a replica that
/// opens later reads them from.
#[test]
fn small_commits_ride_in_the_head_and_spill_into_one_object() {
    let s3 = S3::start("isovox-inline");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    let writer = Server::replica(&s3, None);
    let follower = Server::replica(&s3, None);
    assert_eq!(follower.version(&http), 1);
    let imported = s3.segments();
    assert_eq!(imported.len(), 1, "{imported:?}");
    let origin = |i: u32| [2 + 10 * (i % 9), 50, 2 + 10 * (i / 9)];
    let centre = |i: u32| origin(i).map(|c| c + 4);
    let edit = |i: u32| {
        assert_ne!(voxel(&writer, &http, centre(i)), 255, "edit {i} before");
        let (status, answer) = writer.edit(&http, &carve(origin(i)), None);
        assert_eq!(status, 200, "edit {i}: {answer}");
        let version = answer["version"].as_u64().unwrap();
        follower.wait_for(&http, version);
        version
    };

    for i in 0..8 {
        edit(i);
    }
    assert_eq!(
        s3.segments(),
        imported,
        "a small commit wrote a segment object"
    );
    assert_eq!(s3.requests("PUT", "seg/"), 1, "the import's alone");
    assert_eq!(
        s3.requests("PUT", "head"),
        1 + 8,
        "the import's and one a commit"
    );
    let (head, _) = isovox_server::store::remote::read_head(&s3.volume_bucket()).unwrap();
    let carried: Vec<_> = head
        .segments
        .iter()
        .filter(|s| s.inline.is_some())
        .collect();
    assert_eq!(carried.len(), 8, "{head:?}");
    // The follower caught up with all eight from the head alone: its only segment reads are of
    // the import's (opening, and its index fetched ahead).
    let import_gets = s3.requests("GET", &imported[0]);
    assert_eq!(s3.requests("GET", "seg/"), import_gets);
    for i in 0..8 {
        assert_eq!(
            voxel(&follower, &http, centre(i)),
            255,
            "edit {i} on the follower"
        );
    }

    // Until a segment object appears: at the latest when the head would list 65 segments.
    let mut i = 8;
    while s3.segments().len() == 1 {
        assert!(i < 64, "no spill after {i} commits");
        edit(i);
        i += 1;
    }
    let spilled: Vec<String> = s3
        .segments()
        .into_iter()
        .filter(|k| !imported.contains(k))
        .collect();
    assert_eq!(
        spilled.len(),
        1,
        "one object for every inlined segment: {spilled:?}"
    );
    let (head, _) = isovox_server::store::remote::read_head(&s3.volume_bucket()).unwrap();
    let after_import: Vec<_> = head.segments.iter().skip(1).collect();
    assert_eq!(after_import.len() as u32, i, "{head:?}");
    let mut at = 0;
    for s in &after_import {
        let within = s.within.as_ref().expect("spilled");
        assert!(s.inline.is_none());
        assert_eq!((within.key.as_str(), within.at), (spilled[0].as_str(), at));
        at += s.len;
    }
    let object = s3.volume_bucket().get(&spilled[0]).unwrap().unwrap();
    assert_eq!(object.len() as u64, at, "the spilled segments end to end");

    // One more commit rides in the head again; a replica opened now reads the spilled ones
    // from their object and the last from the head.
    let last = edit(i);
    assert_eq!(s3.segments().len(), 2);
    let late = Server::replica(&s3, None);
    assert_eq!(late.version(&http), last);
    for e in 0..=i {
        assert_eq!(
            voxel(&late, &http, centre(e)),
            255,
            "edit {e} on a late replica"
        );
    }
    assert_same_answers(&http, &writer, &late);
    assert_same_answers(&http, &writer, &follower);
}

/// A replica that read segments from the head and then saw them spilled keeps where the store
/// says they are: a manifest it writes later names their object, and a replica that opens from
/// that manifest finds every one of them. (Its mirror's pages of those segments still say
/// "inline": they never need fetching, but a manifest written from them would be wrong.)
#[test]
fn a_manifest_names_where_segments_first_read_inline_were_spilled() {
    let s3 = S3::start("isovox-inline-manifest");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    let a = Server::replica(&s3, None);
    let b = Server::replica(&s3, None);
    // 81 places above the terrain: a cuboid added at each, then taken away again.
    const PLACES: u32 = 81;
    let origin = |i: u32| [2 + 10 * (i % 9), 50, 2 + 10 * ((i % PLACES) / 9)];
    let edit = |on: &Server, i: u32| {
        let op = if i < PLACES { "union" } else { "difference" };
        let term = json!({"op": op, "term": {"cuboid": {"origin": origin(i), "size": [8, 8, 8]}}});
        let (status, answer) = on.edit(&http, &term, None);
        assert_eq!(status, 200, "edit {i}: {answer}");
        let version = answer["version"].as_u64().unwrap();
        a.wait_for(&http, version);
        b.wait_for(&http, version);
    };
    let manifests = || s3.requests("PUT", "manifests/");
    // On a, with b following every commit (reading the small ones from the head), until a
    // folds the head's segments, spilled on the way, into a first manifest.
    let mut i = 0;
    while manifests() == 0 {
        assert!(i < 70, "no manifest after {i} commits");
        edit(&a, i);
        i += 1;
    }
    // On b, until it folds the next 64 into a second manifest, which lists the first's too.
    while manifests() == 1 {
        assert!(i < 2 * PLACES, "no second manifest after {i} commits");
        edit(&b, i);
        i += 1;
    }
    let bucket = s3.volume_bucket();
    let key = isovox_server::store::remote::read_head(&bucket)
        .unwrap()
        .0
        .manifest
        .unwrap()
        .key;
    let manifest: Value = serde_json::from_slice(&bucket.get(&key).unwrap().unwrap()).unwrap();
    let listed = manifest["segments"].as_array().unwrap();
    assert_eq!(listed.len() as u32, 1 + i, "the import's and one a commit");
    assert!(
        listed.iter().all(|s| s.get("inline").is_none()),
        "{manifest}"
    );
    assert!(listed.iter().filter(|s| s.get("within").is_some()).count() >= 2);

    let late = Server::replica(&s3, None);
    for e in 0..PLACES.min(i) {
        let centre = origin(e).map(|c| c + 4);
        let taken_away = e + PLACES < i;
        assert_eq!(
            voxel(&late, &http, centre) == 255,
            !taken_away,
            "place {e} on a late replica"
        );
    }
    assert_same_answers(&http, &a, &late);
    assert_same_answers(&http, &b, &late);
}

#[test]
fn a_writer_killed_before_the_head_leaves_the_last_acknowledged_version() {
    let s3 = S3::start("isovox-killed");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    let r1 = Server::replica_of_objects(&s3, None);
    let (status, ack) = r1.edit(&http, &carve([10, 10, 10]), None);
    assert_eq!((status, ack["version"].as_u64()), (200, Some(2)));
    let before = s3.segments();
    assert_eq!(before.len(), 2, "{before:?}");

    // A writer that stops between its segment and the head, killed there.
    let doomed = Server::replica_of_objects(&s3, Some(60_000));
    let base = doomed.base.clone();
    std::thread::spawn(move || {
        let _ = http_post_edit(&base, &carve([40, 50, 40]));
    });
    let deadline = Instant::now() + Duration::from_secs(30);
    while s3.segments().len() == before.len() {
        assert!(Instant::now() < deadline, "the writer wrote no segment");
        std::thread::sleep(Duration::from_millis(20));
    }
    doomed.kill();
    assert_eq!(s3.head_version(), 2, "the head moved without its writer");
    assert_eq!(
        s3.segments().len(),
        3,
        "the orphaned segment is in the store"
    );
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(r1.version(&http), 2);
    let before = voxel_in_file(&s3, data.path(), [44, 54, 44]);
    assert_ne!(before, 255, "the lost edit would have changed this voxel");
    assert_eq!(voxel(&r1, &http, [44, 54, 44]), before);
    let late = Server::replica(&s3, None);
    assert_eq!(late.version(&http), 2);
    assert_same_answers(&http, &r1, &late);

    // Compaction keeps version 2 as it is and collects the orphan (and the replaced segments).
    let out = s3.isovox(&[
        "compact",
        &format!("{}/{VOLUME}", s3.url()),
        "--grace-secs",
        "0",
    ]);
    assert!(out.contains("version 2 kept"), "{out}");
    assert_eq!(s3.segments().len(), 1, "{:?}", s3.segments());
    assert_eq!(s3.head_version(), 2);
    let fresh = Server::replica(&s3, None);
    assert_same_answers(&http, &late, &fresh);
    // r1 follows the compacted head: same version, same answers.
    std::thread::sleep(Duration::from_millis(300));
    assert_same_answers(&http, &r1, &fresh);
}

/// Group commit on the object store: 8 editors on each of 2 replicas edit one volume, and one
/// replica is killed with SIGKILL while its writer is busy (under this load it is always
/// staging a group, uploading its segment or racing for the head). Every edit either replica
/// acknowledged is in the history at the version it was told, with its own message; the
/// groups took fewer segments than versions; the survivor and a late replica serve one head.
#[test]
fn group_commits_on_the_store_lose_no_acknowledged_edit_when_a_replica_is_killed() {
    let s3 = S3::start("isovox-groups");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let survivor = Server::replica(&s3, None);
    let mut doomed = Server::replica(&s3, None);
    let bases = [survivor.base.clone(), doomed.base.clone()];
    let segments_before = s3.segments().len();
    const EDITORS: usize = 8;
    let stop = std::sync::atomic::AtomicBool::new(false);
    // (message, acknowledged version) of every 200.
    let acked = std::sync::Mutex::new(Vec::<(String, u64)>::new());
    let failed_on_doomed = std::sync::atomic::AtomicUsize::new(0);
    // Stops the editors however the scope ends (a failed assertion in it would otherwise wait
    // for them forever).
    struct StopOnDrop<'a>(&'a std::sync::atomic::AtomicBool);
    impl Drop for StopOnDrop<'_> {
        fn drop(&mut self) {
            self.0.store(true, std::sync::atomic::Ordering::Relaxed);
        }
    }
    let refused = std::sync::atomic::AtomicUsize::new(0);
    std::thread::scope(|scope| {
        let _stop = StopOnDrop(&stop);
        for (r, base) in bases.iter().enumerate() {
            for e in 0..EDITORS {
                let (stop, acked, failed, refused) = (&stop, &acked, &failed_on_doomed, &refused);
                scope.spawn(move || {
                    let http = client();
                    let mut i = 0u32;
                    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                        let message = format!("replica {r} editor {e} edit {i}");
                        // Cuboids above the terrain, each editor in its own column of x, z.
                        let slot = (r * EDITORS + e) as u32;
                        let mut edit =
                            carve([2 + 5 * (slot % 16), 50, 2 + 40 * (slot / 16) + (i % 8) * 5]);
                        edit["message"] = json!(message);
                        let sent = http
                            .post(format!("{base}/edits"))
                            .bearer_auth(TOKEN)
                            .json(&edit)
                            .send();
                        match sent.map(|resp| (resp.status().as_u16(), resp.json::<Value>())) {
                            Ok((200, Ok(answer))) => {
                                let v = answer["version"].as_u64().expect("a version");
                                acked.lock().unwrap().push((message, v));
                            }
                            // Lost the head race 16 times in a row: not acknowledged.
                            Ok((503, _)) => {
                                refused.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            }
                            Ok((status, answer)) => panic!("{message}: {status} {answer:?}"),
                            Err(_) if r == 1 => {
                                failed.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                                return;
                            }
                            Err(e) => panic!("{message}: {e}"),
                        }
                        i += 1;
                    }
                });
            }
        }
        let acked_by_doomed = |acked: &std::sync::Mutex<Vec<(String, u64)>>| {
            acked
                .lock()
                .unwrap()
                .iter()
                .filter(|(m, _)| m.starts_with("replica 1"))
                .count()
        };
        let deadline = Instant::now() + Duration::from_secs(60);
        while acked_by_doomed(&acked) < 10 {
            assert!(
                Instant::now() < deadline,
                "the doomed replica acknowledged {} edits in 60 s ({} acknowledged in all, {} refused 503)",
                acked_by_doomed(&acked),
                acked.lock().unwrap().len(),
                refused.load(std::sync::atomic::Ordering::Relaxed)
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        // SIGKILL, mid-group.
        doomed.process.stop();
        // The survivor goes on alone for a while, then everyone stops.
        std::thread::sleep(Duration::from_secs(1));
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
    });
    assert!(
        failed_on_doomed.load(std::sync::atomic::Ordering::Relaxed) > 0,
        "no edit was in flight on the killed replica"
    );
    let acked = acked.into_inner().unwrap();
    let http = client();
    let head = s3.head_version();
    survivor.wait_for(&http, head);
    // Every acknowledged version is distinct and holds the edit it was acknowledged for.
    let mut versions: Vec<u64> = acked.iter().map(|(_, v)| *v).collect();
    versions.sort_unstable();
    versions.dedup();
    assert_eq!(
        versions.len(),
        acked.len(),
        "two edits acknowledged as one version"
    );
    let mut messages = std::collections::HashMap::new();
    let mut before = head + 1;
    while before > 2 {
        let (status, body, _) =
            survivor.get(&http, &format!("history?before={before}&limit=1000"), None);
        assert_eq!(status, 200);
        let page: Value = serde_json::from_slice(&body).unwrap();
        for c in page["commits"].as_array().unwrap() {
            let v = c["version"].as_u64().unwrap();
            messages.insert(v, c["message"].as_str().unwrap_or_default().to_string());
            before = before.min(v);
        }
        if page["more"] != json!(true) {
            break;
        }
    }
    for (message, v) in &acked {
        assert_eq!(
            messages.get(v),
            Some(message),
            "acknowledged version {v} ({message}) is not in the history as acknowledged"
        );
    }
    // Groups: fewer segments than versions (each group is one segment for all its versions).
    let segments = s3.segments().len() - segments_before;
    let made = (head - 1) as usize;
    assert!(
        segments < made,
        "{made} versions took {segments} segments: no group of edits shared one"
    );
    // The survivor still edits, and a replica started now serves the same head.
    let (status, answer) = survivor.edit(&http, &carve([40, 50, 40]), None);
    assert_eq!(status, 200, "{answer}");
    let late = Server::replica(&s3, None);
    assert_eq!(late.version(&http), head + 1);
    assert_same_answers(&http, &survivor, &late);
}

/// The level-0 voxel at `p` of the imported world (before any edit), read from its file.
fn voxel_in_file(s3: &S3, dir: &Path, p: [u32; 3]) -> u8 {
    let out = dir.join("b.raw");
    let (bx, by, bz) = (
        (p[0] / BRICK).to_string(),
        (p[1] / BRICK).to_string(),
        (p[2] / BRICK).to_string(),
    );
    s3.isovox(&[
        "get",
        dir.join(format!("{VOLUME}.vod")).to_str().unwrap(),
        "0",
        &bx,
        &by,
        &bz,
        "-o",
        out.to_str().unwrap(),
    ]);
    let bytes = std::fs::read(out).unwrap();
    let b = BRICK as usize;
    let l = p.map(|c| (c % BRICK) as usize);
    bytes[l[0] + b * (l[1] + b * l[2])]
}

fn http_post_edit(base: &str, edit: &Value) -> Option<u16> {
    let resp = client()
        .post(format!("{base}/edits"))
        .bearer_auth(TOKEN)
        .json(edit)
        .send()
        .ok()?;
    Some(resp.status().as_u16())
}

#[test]
fn a_stalled_writer_cannot_overwrite_a_newer_head() {
    let s3 = S3::start("isovox-stalled");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    let r1 = Server::replica_of_objects(&s3, None);
    let slow = Server::replica_of_objects(&s3, Some(1500));
    // Both edits go above the terrain, where they change voxels.
    for p in [[14, 54, 14], [44, 54, 44], [74, 54, 74]] {
        assert_ne!(voxel(&r1, &http, p), 255);
    }

    // The slow writer starts on version 1 and stalls before the head; r1 commits meanwhile.
    // (The store's segments are counted before the edit is sent: it may write its segment
    // before this thread looks.)
    let segments = s3.segments().len();
    let slow_base = slow.base.clone();
    let stalled = std::thread::spawn(move || {
        let http = client();
        let resp = http
            .post(format!("{slow_base}/edits"))
            .bearer_auth(TOKEN)
            .json(&carve([10, 50, 10]))
            .send()
            .unwrap();
        (resp.status().as_u16(), resp.json::<Value>().unwrap())
    });
    let deadline = Instant::now() + Duration::from_secs(30);
    while s3.segments().len() == segments {
        assert!(
            Instant::now() < deadline,
            "the slow writer wrote no segment"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    let (status, fast) = r1.edit(&http, &carve([40, 50, 40]), None);
    assert_eq!((status, fast["version"].as_u64()), (200, Some(2)));
    // Its head PUT is refused; it re-applies its edit on version 2.
    let (status, late) = stalled.join().unwrap();
    assert_eq!(status, 200, "{late}");
    assert_eq!(late["version"], 3);
    assert_eq!(late["previous"], 2);
    r1.wait_for(&http, 3);
    assert_eq!(
        voxel(&r1, &http, [14, 14, 14]),
        255,
        "the stalled writer's edit"
    );
    assert_eq!(
        voxel(&r1, &http, [44, 14, 44]),
        255,
        "the newer edit survived"
    );

    // Asked with If-Match, a stalled writer whose version is overtaken is refused (409).
    let untouched = voxel(&r1, &http, [74, 54, 74]);
    assert_ne!(
        untouched, 255,
        "the world is not full where the refused edit would go"
    );
    let segments = s3.segments().len();
    let slow_base = slow.base.clone();
    let conditional = std::thread::spawn(move || {
        let resp = client()
            .post(format!("{slow_base}/edits"))
            .bearer_auth(TOKEN)
            .header("If-Match", "3")
            .json(&carve([70, 50, 70]))
            .send()
            .unwrap();
        (resp.status().as_u16(), resp.json::<Value>().unwrap())
    });
    while s3.segments().len() == segments {
        assert!(Instant::now() < deadline + Duration::from_secs(30));
        std::thread::sleep(Duration::from_millis(10));
    }
    let (status, _) = r1.edit(&http, &carve([40, 40, 40]), None);
    assert_eq!(status, 200);
    let (status, refused) = conditional.join().unwrap();
    assert_eq!(status, 409, "{refused}");
    assert_eq!(refused["version"], 4);
    assert_eq!(s3.head_version(), 4);
    r1.wait_for(&http, 4);
    assert_eq!(
        voxel(&r1, &http, [74, 54, 74]),
        untouched,
        "the refused edit is not there"
    );
}

/// nginx (Debian's) as a process, with a main configuration written for the test around
/// `docker/nginx/isovox-locations.conf`, included as it is. Stopped when dropped.
struct Nginx {
    child: Child,
    base: String,
    _dir: tempfile::TempDir,
}

impl Nginx {
    fn start(upstream: &str) -> Nginx {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path().display();
        let port = free_port();
        let rules = workspace().join("docker/nginx/isovox-locations.conf");
        let conf = format!(
            "daemon off;\nworker_processes 1;\npid {d}/nginx.pid;\nerror_log {d}/error.log;\n\
             events {{ worker_connections 512; }}\nhttp {{\n  access_log off;\n\
             client_body_temp_path {d}/body; proxy_temp_path {d}/proxy;\n\
             fastcgi_temp_path {d}/fcgi; uwsgi_temp_path {d}/uwsgi; scgi_temp_path {d}/scgi;\n\
             proxy_cache_path {d}/cache levels=1:2 keys_zone=isovox:8m max_size=1g inactive=30d use_temp_path=off;\n\
             upstream isovox {{ server {upstream}; keepalive 16; }}\n\
             server {{ listen 127.0.0.1:{port}; include {}; }}\n}}\n",
            rules.display()
        );
        std::fs::write(dir.path().join("nginx.conf"), conf).unwrap();
        let nginx = ["/usr/sbin/nginx", "/usr/bin/nginx"]
            .into_iter()
            .find(|p| Path::new(p).exists())
            .expect("nginx is installed (.ci/run installs Debian's)");
        let child = Command::new(nginx)
            .arg("-c")
            .arg(dir.path().join("nginx.conf"))
            .arg("-p")
            .arg(dir.path())
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(20);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "nginx does not listen");
            std::thread::sleep(Duration::from_millis(20));
        }
        Nginx {
            child,
            base: format!("http://127.0.0.1:{port}/v1/volumes/{VOLUME}"),
            _dir: dir,
        }
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        // TERM first: nginx's master stops its worker and cache manager before it exits.
        // Killed outright, it would leave them running (holding the port) after the test.
        let _ = Command::new("kill")
            .args(["-s", "TERM", &self.child.id().to_string()])
            .status();
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The cache deployment: the world in the S3 server, one replica on it, nginx in front.
/// (Fields drop in order: nginx, the replica, then the store.)
struct Cached {
    nginx: Nginx,
    replica: Server,
    _data: tempfile::TempDir,
    _s3: S3,
}

impl Cached {
    fn start(bucket: &str) -> Cached {
        let s3 = S3::start(bucket);
        let data = tempfile::tempdir().unwrap();
        world(&s3, data.path());
        let replica = Server::replica(&s3, None);
        let upstream = &replica.base["http://".len()..replica.base.find("/v1/").unwrap()];
        Cached {
            nginx: Nginx::start(upstream),
            replica,
            _data: data,
            _s3: s3,
        }
    }
}

/// Requests the replica answered on `route` with `status` (every status when `None`), from its
/// Prometheus counter.
fn answered(http: &Client, replica: &Server, route: &str, status: Option<u16>) -> u64 {
    let root = &replica.base[..replica.base.find("/v1/").unwrap()];
    let text = http
        .get(format!("{root}/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    text.lines()
        .filter(|l| {
            l.starts_with("isovox_requests_total{")
                && l.contains(&format!("route=\"{route}\""))
                && status.is_none_or(|s| l.contains(&format!("status=\"{s}\"")))
        })
        .filter_map(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
        .sum()
}

#[test]
fn nginx_in_front_of_a_replica_caches_blobs_for_good_and_revalidates_bricks() {
    let Cached { nginx, replica, .. } = &Cached::start("isovox-nginx");
    let http = client();
    let blobs = "/v1/volumes/{name}/blobs/{hash}";

    // A stampede of 16 concurrent misses for one blob makes one request to the replica.
    let (_, direct, etag) = replica.get(&http, "bricks/0/2/2/2", None);
    let hash = etag.trim_matches('"').to_string();
    let before = answered(&http, replica, blobs, None);
    let bodies = stampede(nginx, &format!("blobs/{hash}"), 16);
    assert!(
        bodies.iter().all(|b| *b == direct),
        "a cached blob differs from the replica's"
    );
    assert_eq!(
        answered(&http, replica, blobs, None) - before,
        1,
        "proxy_cache_lock"
    );
    let resp = http
        .get(format!("{}/blobs/{hash}", nginx.base))
        .send()
        .unwrap();
    assert_eq!(resp.headers()["x-cache"], "HIT");
    assert!(resp.headers()["cache-control"]
        .to_str()
        .unwrap()
        .contains("immutable"));

    // Bricks by position: served through the cache, then revalidated by ETag after an edit.
    let bricks = "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}";
    let through = http
        .get(format!("{}/bricks/0/4/3/4", nginx.base))
        .send()
        .unwrap()
        .bytes()
        .unwrap();
    let (_, at_replica, _) = replica.get(&http, "bricks/0/4/3/4", None);
    assert!(through.as_ref() == at_replica.as_slice());
    let (status, _) = replica.edit(&http, &carve([66, 50, 66]), None);
    assert_eq!(status, 200);
    std::thread::sleep(Duration::from_millis(2100));
    let n = answered(&http, replica, bricks, None);
    let resp = http
        .get(format!("{}/bricks/0/4/3/4", nginx.base))
        .send()
        .unwrap();
    let status = resp.headers()["x-cache"].to_str().unwrap().to_string();
    let fresh = resp.bytes().unwrap();
    let (_, edited, _) = replica.get(&http, "bricks/0/4/3/4", None);
    assert!(
        fresh.as_ref() == edited.as_slice(),
        "nginx served a stale brick ({status})"
    );
    assert!(
        answered(&http, replica, bricks, None) > n,
        "nginx did not ask the replica again"
    );
    // An unchanged brick revalidates with a 304 from the replica: nginx says REVALIDATED.
    let _ = http
        .get(format!("{}/bricks/0/0/0/0", nginx.base))
        .send()
        .unwrap();
    std::thread::sleep(Duration::from_millis(2100));
    let resp = http
        .get(format!("{}/bricks/0/0/0/0", nginx.base))
        .send()
        .unwrap();
    assert_eq!(resp.headers()["x-cache"], "REVALIDATED");

    // The change feed passes through unbuffered: an edit's event arrives while the stream is open.
    let feed = client()
        .get(format!("{}/events", nginx.base))
        .send()
        .unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(feed).lines() {
            let Ok(line) = line else { break };
            if line.contains("\"version\":3") {
                let _ = tx.send(line);
                break;
            }
        }
    });
    std::thread::sleep(Duration::from_millis(200));
    let (status, _) = replica.edit(&http, &carve([10, 50, 70]), None);
    assert_eq!(status, 200);
    let event = rx
        .recv_timeout(Duration::from_secs(10))
        .expect("the commit event through nginx");
    assert!(event.contains("changed"), "{event}");
}

/// `path` (under the volume) asked by `n` clients at once through `nginx`: their bodies.
fn stampede(nginx: &Nginx, path: &str, n: usize) -> Vec<Vec<u8>> {
    std::thread::scope(|scope| {
        let handles: Vec<_> = (0..n)
            .map(|_| {
                let url = format!("{}/{path}", nginx.base);
                scope.spawn(move || {
                    let resp = client().get(url).send().unwrap();
                    assert_eq!(resp.status(), 200);
                    resp.bytes().unwrap().to_vec()
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

/// Level grids and mesh tiles are CPU work on a replica (a bounded queue, 503 beyond it) that
/// every viewer asks first: through nginx a stampede for one answer makes it once on the
/// replica, and after an edit nginx asks again with the ETag and serves the new answer.
#[test]
fn nginx_in_front_of_a_replica_makes_each_level_and_tile_once_and_revalidates_them() {
    let Cached { nginx, replica, .. } = &Cached::start("isovox-nginx-levels");
    let http = client();
    let levels = "/v1/volumes/{name}/levels/{level}";
    let meshes = "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}";

    // The replica names levels and tiles with a strong ETag and answers If-None-Match with 304;
    // the newest version's answers are no-cache, a pinned version's immutable.
    // (A region of a grid is answered on the store-read threads, the others by CPU jobs.)
    for path in [
        "levels/1",
        "levels/0?region=0,0,0,6,4,6",
        "levels/0?format=voxels",
        "meshes/0/2/2/2",
    ] {
        let (status, _, etag) = replica.get(&http, path, None);
        assert_eq!(status, 200, "{path}");
        assert!(
            etag.len() > 2 && etag.starts_with('"') && etag.ends_with('"'),
            "{path}: a strong ETag, not {etag:?}"
        );
        let again = http
            .get(format!("{}/{path}", replica.base))
            .header("If-None-Match", &etag)
            .send()
            .unwrap();
        assert_eq!(again.status(), 304, "{path}");
        assert_eq!(again.headers()["cache-control"], "no-cache", "{path}");
        let sep = if path.contains('?') { '&' } else { '?' };
        let pinned = http
            .get(format!("{}/{path}{sep}version=1", replica.base))
            .send()
            .unwrap();
        assert_eq!(pinned.headers()["etag"].to_str().unwrap(), etag, "{path}");
        assert_eq!(
            pinned.headers()["cache-control"],
            "public, max-age=31536000, immutable",
            "{path}"
        );
    }

    // A stampede of 16 concurrent misses for one answer makes it once on the replica (the
    // 200s it answered; proxy_cache_lock), and every viewer gets the replica's bytes.
    for (route, path) in [
        (levels, "levels/1"),
        (levels, "levels/0?region=0,0,0,6,4,6&version=1"),
        (meshes, "meshes/0/2/2/2?version=1"),
    ] {
        let (_, direct, _) = replica.get(&http, path, None);
        let before = answered(&http, replica, route, Some(200));
        let bodies = stampede(nginx, path, 16);
        assert!(
            bodies.iter().all(|b| *b == direct),
            "{path}: a cached answer differs from the replica's"
        );
        assert_eq!(
            answered(&http, replica, route, Some(200)) - before,
            1,
            "{path}: answers made on the replica for 16 concurrent requests through nginx"
        );
    }

    // After an edit nginx asks the replica again (the second it keeps an answer has passed)
    // with the old ETag, and serves the new grid, not the one it cached above.
    let (_, old, _) = replica.get(&http, "levels/1", None);
    let (status, _) = replica.edit(&http, &carve([66, 50, 66]), None);
    assert_eq!(status, 200);
    std::thread::sleep(Duration::from_millis(2100));
    let resp = http.get(format!("{}/levels/1", nginx.base)).send().unwrap();
    let cache = resp.headers()["x-cache"].to_str().unwrap().to_string();
    let fresh = resp.bytes().unwrap();
    let (_, edited, _) = replica.get(&http, "levels/1", None);
    assert_ne!(old, edited, "the edit changed level 1's grid");
    assert!(
        fresh.as_ref() == edited.as_slice(),
        "nginx served a stale level ({cache})"
    );
    // Unchanged since: nginx revalidates with a 304 from the replica.
    std::thread::sleep(Duration::from_millis(2100));
    let resp = http.get(format!("{}/levels/1", nginx.base)).send().unwrap();
    assert_eq!(resp.headers()["x-cache"], "REVALIDATED");
    assert!(resp.bytes().unwrap().as_ref() == edited.as_slice());

    // A pinned answer is kept as the server says (immutable): seconds later nginx serves it
    // without asking the replica, not even for a revalidation. The pinned version is the one
    // the stampede above cached.
    let pinned = "levels/0?region=0,0,0,6,4,6&version=1";
    let (_, direct, _) = replica.get(&http, pinned, None);
    let asked = |status| answered(&http, replica, levels, Some(status));
    let before = (asked(200), asked(304));
    let resp = http.get(format!("{}/{pinned}", nginx.base)).send().unwrap();
    assert_eq!(resp.headers()["x-cache"], "HIT", "{pinned}");
    assert!(resp.bytes().unwrap().as_ref() == direct.as_slice());
    assert_eq!(
        (asked(200), asked(304)),
        before,
        "{pinned} reached the replica"
    );
}

/// Sends `signal` (`-STOP`, `-CONT`) to the S3 server.
fn signal(s3: &S3, signal: &str) {
    let status = Command::new("kill")
        .args([signal, &s3.child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success(), "kill {signal}");
}

#[test]
fn a_stalled_store_makes_an_edit_a_503_with_retry_after_and_commits_nothing() {
    let s3 = S3::start("isovox-frozen");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    // Polling the head all the time, the replica is most likely in a poll when the store
    // stops: the poll holds the writer the edit waits for, and must give up in time too.
    let server = Server::replica_with(&s3, None, &["--edit-timeout", "1", "--follow-ms", "1"]);
    assert_eq!(server.version(&http), 1);

    // The store stops answering; the edit (a few bricks: its own evaluation takes
    // milliseconds) waits on it past its 1 s timeout.
    signal(&s3, "-STOP");
    let sent = Instant::now();
    let resp = http
        .post(format!("{}/edits", server.base))
        .bearer_auth(TOKEN)
        .json(&carve([10, 50, 10]))
        .send()
        .unwrap();
    let took = sent.elapsed();
    let status = resp.status().as_u16();
    let retry_after = resp
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().to_string());
    let media = resp.headers()["content-type"].to_str().unwrap().to_string();
    let problem: Value = resp.json().unwrap();
    signal(&s3, "-CONT");
    assert_eq!(status, 503, "{problem}");
    // The limit was 1 s: retry after 1 s.
    assert_eq!(retry_after.as_deref(), Some("1"), "{problem}");
    assert_eq!(media, "application/problem+json");
    assert_eq!(problem["status"], 503);
    let detail = problem["detail"].as_str().unwrap();
    assert!(
        detail.contains("object store did not answer") && detail.contains("nothing was committed"),
        "{detail}"
    );
    // Answered at the deadline, not after the store client's own retries (30 s and more).
    assert!(took < Duration::from_secs(15), "answered after {took:?}");
    let log = server.process.log();
    assert!(
        log.contains("the store stalled") && log.contains("did not answer within"),
        "the log says why: {log}"
    );

    // The store answers again: the next edit is version 2 (the stalled one made none).
    let (status, answer) = server.edit(&http, &carve([40, 50, 40]), None);
    assert_eq!(
        (status, answer["version"].as_u64()),
        (200, Some(2)),
        "{answer}"
    );
    assert_eq!(s3.head_version(), 2);
    assert_eq!(voxel(&server, &http, [44, 54, 44]), 255, "the edit after");
    assert_ne!(voxel(&server, &http, [14, 54, 14]), 255, "the stalled edit");
}

#[test]
fn a_replica_whose_store_reads_are_all_busy_still_takes_feed_subscriptions_and_reads_what_it_holds()
{
    let s3 = S3::start("isovox-busy-reads");
    let data = tempfile::tempdir().unwrap();
    world(&s3, data.path());
    let http = client();
    // Page by page: with blocks of 64 KiB, opening the volume fetches most of this small world.
    let server = Server::replica_with(&s3, None, &["--read-ahead-kb", "4"]);
    assert_eq!(server.version(&http), 1);
    // A brick read once: its pages are in the replica's mirror from then on.
    let warm = format!("{}/bricks/0/2/2/2", server.base);
    let warm_body = http.get(&warm).send().unwrap().bytes().unwrap();

    // The store stops answering; cold brick reads pile up on the replica's store-read threads
    // and places (16 and 128 on two cores) until it refuses more with 503.
    signal(&s3, "-STOP");
    let (done_tx, done_rx) = mpsc::channel();
    let bricks = all_bricks();
    let readers: Vec<_> = (0..600)
        .map(|i| {
            let url = format!("{}/bricks/{}", server.base, bricks[i % bricks.len()]);
            let done = done_tx.clone();
            std::thread::spawn(move || {
                let status = Client::new().get(url).send().map(|r| r.status().as_u16());
                let _ = done.send(status.ok());
            })
        })
        .collect();
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut refused = 0;
    while refused == 0 {
        assert!(Instant::now() < deadline, "the store reads never filled up");
        if let Ok(Some(503)) = done_rx.recv_timeout(Duration::from_millis(100)) {
            refused += 1;
        }
    }

    // The brick read before is answered from the mirror, in place: not refused, and not
    // queued behind the reads waiting for the store.
    let resp = http.get(&warm).send().unwrap();
    let warm_status = resp.status().as_u16();
    let warm_again = resp.bytes().unwrap();

    // A new viewer subscribes to the change feed: taken, and told the head at once.
    let mut feed = Client::builder()
        .timeout(Duration::from_secs(5))
        .build()
        .unwrap()
        .get(format!("{}/events", server.base))
        .send()
        .unwrap();
    let status = feed.status().as_u16();
    let mut first = [0u8; 64];
    let n = if status == 200 {
        std::io::Read::read(&mut feed, &mut first).unwrap()
    } else {
        0
    };
    signal(&s3, "-CONT");
    for r in readers {
        r.join().unwrap();
    }
    assert_eq!(
        status, 200,
        "the feed subscription while store reads were full"
    );
    assert_eq!(
        warm_status, 200,
        "a read of mirrored pages while store reads were full"
    );
    assert_eq!(warm_again, warm_body);
    let hello = String::from_utf8_lossy(&first[..n]);
    assert!(
        hello.contains("event: hello") && hello.contains("\"version\":1"),
        "{hello}"
    );
}

/// Range requests the replica's volumes made of the store so far, and the bytes they fetched
/// (its Prometheus counters).
fn store_fetches(http: &Client, replica: &Server) -> (u64, u64) {
    let root = &replica.base[..replica.base.find("/v1/").unwrap()];
    let text = http
        .get(format!("{root}/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap();
    let counter = |name: &str| {
        text.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
            .unwrap_or_else(|| panic!("no {name} in the metrics"))
    };
    (
        counter("isovox_store_fetches_total "),
        counter("isovox_store_fetched_bytes_total "),
    )
}

#[test]
fn a_cold_replica_lists_a_level_grid_from_index_chunks_not_brick_records() {
    // A world larger than the other tests': 256^3 in bricks of 16 is 4,096 level-0 bricks, in
    // 8 index chunks of 512 entries. `ISOVOX_GRID_EDGE=512` measures the 512^3 world of
    // docs/scaling.md (32,768 bricks, 64 chunks) with the same code.
    let edge: u32 = std::env::var("ISOVOX_GRID_EDGE")
        .ok()
        .and_then(|e| e.parse().ok())
        .unwrap_or(256);
    let s3 = S3::start("isovox-grids");
    let dir = tempfile::tempdir().unwrap();
    let file = large_world(&s3, dir.path(), edge);
    // The same volume as a writer before revision 5 wrote it: no summaries in its index.
    let old = dir.path().join("w4.vod");
    crate::grid_summaries::revision4_copy(&file, &old);
    let old = old.to_str().unwrap();
    s3.isovox(&["import", old, "-o", &format!("{}/w4", s3.url())]);

    // Page by page (no read-ahead) and without the index prefetched at open, so the requests
    // count the records the grid reads, not the blocks around them.
    let replica = Server::replica_with(
        &s3,
        None,
        &["--read-ahead-kb", "4", "--prefetch-index-mb", "0"],
    );
    let http = client();
    let root = replica.base[..replica.base.find("/v1/").unwrap()].to_string();
    let grid_cost = |volume: &str| {
        let (requests, bytes) = store_fetches(&http, &replica);
        let url = format!("{root}/v1/volumes/{volume}/levels/0");
        let resp = http.get(&url).send().unwrap();
        assert_eq!(resp.status().as_u16(), 200, "{url}");
        let grid: Value = resp.json().unwrap();
        let (after, after_bytes) = store_fetches(&http, &replica);
        (grid, after - requests, after_bytes - bytes)
    };
    let (grid, requests, bytes) = grid_cost(VOLUME);
    let (old_grid, old_requests, old_bytes) = grid_cost("w4");
    let stored = grid["bricks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|b| b["min"] != b["max"])
        .count();
    let bricks = (edge / 16).pow(3) as usize;
    let chunks = bricks.div_ceil(512) as u64;
    eprintln!(
        "level-0 grid of {edge}^3 ({bricks} bricks, {stored} not constant, {chunks} index \
         chunks) on a cold replica: revision 5 {requests} range requests, {bytes} bytes; \
         revision 4 {old_requests} requests, {old_bytes} bytes"
    );
    // What the summaries cost: the head checkpoint's bytes per index entry, both files.
    let index_bytes = |path: &Path| {
        let vod = isovox_server::store::Vod2::open(path).unwrap();
        let (_, len) = vod.head().checkpoint_span().unwrap();
        (len, vod.header().node_count())
    };
    let ((new_len, nodes), (old_len, _)) = (index_bytes(&file), index_bytes(Path::new(old)));
    eprintln!(
        "index of {nodes} entries: revision 5 {new_len} bytes ({:.2} a entry), revision 4 \
         {old_len} bytes ({:.2} a entry)",
        new_len as f64 / nodes as f64,
        old_len as f64 / nodes as f64
    );
    assert_eq!(
        grid["bricks"], old_grid["bricks"],
        "both files list the same grid"
    );
    assert!(
        stored > bricks / 20,
        "{stored} of {bricks} bricks are not constant"
    );
    // One request per index chunk (its entries and summaries lie in a row), one per page of
    // 128 chunk references, and a few to spare; nothing per brick.
    assert!(
        requests <= chunks + chunks.div_ceil(128) + 2,
        "{requests} range requests for {chunks} chunks"
    );
    // Without summaries the same grid reads the brick headers, pages spread over the file.
    assert!(old_requests > 4 * requests, "{old_requests} vs {requests}");
}

#[test]
fn a_cold_replica_reads_ahead_in_blocks_and_fetches_each_block_once_for_many_readers() {
    let s3 = S3::start("isovox-read-ahead");
    let dir = tempfile::tempdir().unwrap();
    let file = large_world(&s3, dir.path(), 256);
    let http = client();
    let root = |replica: &Server| replica.base[..replica.base.find("/v1/").unwrap()].to_string();
    // The voxels of level 1 (512 bricks, read in the file's order on the CPU threads) and the
    // grids of levels 0, 2 and 3 (read on the store-read threads), on a cold replica; what the store was asked for meanwhile. With several readers the store is
    // stopped while they send their requests, so that all of them miss the same pages at once.
    let cost = |replica: &Server, readers: usize| {
        let (requests, bytes) = store_fetches(&http, replica);
        let base = root(replica);
        let bodies: Vec<Vec<u8>> = std::thread::scope(|scope| {
            if readers > 1 {
                signal(&s3, "-STOP");
            }
            let readers: Vec<_> = (0..readers)
                .map(|_| {
                    let base = &base;
                    scope.spawn(move || {
                        let http = client();
                        let mut body = Vec::new();
                        for route in [
                            "levels/1?format=voxels",
                            "levels/0?region=0,0,0,16,16,16",
                            "levels/2",
                            "levels/3",
                        ] {
                            let url = format!("{base}/v1/volumes/{VOLUME}/{route}");
                            let resp = http.get(&url).send().unwrap();
                            assert_eq!(resp.status().as_u16(), 200, "{url}");
                            body.extend_from_slice(&resp.bytes().unwrap());
                        }
                        body
                    })
                })
                .collect();
            if readers.len() > 1 {
                std::thread::sleep(Duration::from_millis(500));
                signal(&s3, "-CONT");
            }
            readers.into_iter().map(|r| r.join().unwrap()).collect()
        });
        assert!(bodies.iter().all(|b| *b == bodies[0]), "readers disagree");
        let (after, after_bytes) = store_fetches(&http, replica);
        (bodies[0].clone(), after - requests, after_bytes - bytes)
    };
    let no_prefetch = ["--prefetch-index-mb", "0"];
    let paged = Server::replica_with(&s3, None, &["--read-ahead-kb", "4", no_prefetch[0], "0"]);
    let (paged_body, paged_requests, paged_bytes) = cost(&paged, 1);
    let ahead = Server::replica_with(&s3, None, &no_prefetch);
    let (ahead_body, ahead_requests, ahead_bytes) = cost(&ahead, 1);
    // Sixteen readers at once on a third cold replica: each block is fetched by one of them
    // while the others wait for it.
    let many = Server::replica_with(&s3, None, &no_prefetch);
    let (many_body, many_requests, many_bytes) = cost(&many, 16);
    eprintln!(
        "level-1 voxels + grids of 256^3 on a cold replica: page by page \
         {paged_requests} range requests, {paged_bytes} bytes; 64 KiB read-ahead \
         {ahead_requests} requests, {ahead_bytes} bytes; 16 readers at once {many_requests} \
         requests, {many_bytes} bytes"
    );
    assert_eq!(paged_body, ahead_body);
    assert_eq!(paged_body, many_body);
    assert!(
        2 * ahead_requests <= paged_requests,
        "read-ahead {ahead_requests} requests vs page by page {paged_requests}"
    );
    // No byte of the volume's one segment (the imported file) is fetched twice, however many
    // readers miss it at once: a level read by several threads, sixteen readers.
    let segment = std::fs::metadata(&file).unwrap().len();
    assert!(
        ahead_bytes <= segment && many_bytes <= segment,
        "{ahead_bytes} bytes (one reader) and {many_bytes} (16 readers) fetched of a \
         {segment}-byte segment"
    );
}

#[test]
fn a_replica_prefetches_the_index_so_its_first_grids_wait_for_no_store_read() {
    let s3 = S3::start("isovox-prefetch");
    let data = tempfile::tempdir().unwrap();
    large_world(&s3, data.path(), 256);
    let http = client();
    // Every level's grid on a replica once its open has settled (no fetch for half a second):
    // the range requests they cost.
    let grids_cost = |replica: &Server| {
        let mut last = store_fetches(&http, replica);
        let mut quiet_since = Instant::now();
        let deadline = Instant::now() + Duration::from_secs(30);
        while quiet_since.elapsed() < Duration::from_millis(500) {
            assert!(Instant::now() < deadline, "the replica keeps fetching");
            std::thread::sleep(Duration::from_millis(50));
            let now = store_fetches(&http, replica);
            if now != last {
                (last, quiet_since) = (now, Instant::now());
            }
        }
        let info: Value = http.get(&replica.base).send().unwrap().json().unwrap();
        let levels = info["levels"].as_array().unwrap().len();
        let grids: Vec<Vec<u8>> = (0..levels)
            .map(|l| {
                let (status, body, _) = replica.get(&http, &format!("levels/{l}"), None);
                assert_eq!(status, 200, "levels/{l}");
                body
            })
            .collect();
        (grids, store_fetches(&http, replica).0 - last.0)
    };
    // Page by page, so that the reads at open fetch no more of the index than they parse.
    let cold = Server::replica_with(
        &s3,
        None,
        &["--read-ahead-kb", "4", "--prefetch-index-mb", "0"],
    );
    let (cold_grids, cold_requests) = grids_cost(&cold);
    let prefetched = Server::replica_with(&s3, None, &["--read-ahead-kb", "4"]);
    let (grids, requests) = grids_cost(&prefetched);
    eprintln!(
        "every level's grid after the open settled: {cold_requests} range requests without \
         the prefetch, {requests} with it"
    );
    assert_eq!(grids, cold_grids);
    assert!(
        cold_requests > 0,
        "without the prefetch the grids read the store"
    );
    assert_eq!(
        requests, 0,
        "the grids read index pages the prefetch did not fetch"
    );
}
