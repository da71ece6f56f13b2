//! Shared editing over HTTP (`docs/editing.md`), tested against the real `isovox serve` binary:
//! concurrent editors and change-feed subscribers, `If-Match`, token access control, the
//! edit errors, compaction, and a subscriber that never reads.
//!
//! The expected voxels come from an independent evaluator written here from `docs/icvg.md`
//! (the cuboid primitive, `union` and `difference`); nothing here calls the server's library.

use crate::common::XorShift;
use crate::server_process;

use reqwest::blocking::{Client, Response};
use reqwest::header::{HeaderMap, AUTHORIZATION, CONTENT_TYPE};
use reqwest::StatusCode;
use serde_json::{json, Value};
use server_process::ServerProcess;
use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader, Read};
use std::path::PathBuf;
use std::process::Command;
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::Duration;

/// Tokens written to the server's token file (the server refuses secrets under 16 characters).
const SECRET1: &str = "SECRET1-4f0c9a7e21d8b36c";
const SECRET2: &str = "SECRET2-b71e5d03a9c2f648";
const VIEWSECRET: &str = "VIEWSECRET-2d9e6f1a0c84";
/// An unknown token with a distinctive spelling, to look for in the logs.
const UNKNOWN_TOKEN: &str = "NOTATOKENq7Zx9";

const VOLUME_DIMS: [usize; 3] = [64, 48, 64];

// ---------------------------------------------------------------------------------------------
// The server under test
// ---------------------------------------------------------------------------------------------

/// A running `isovox serve` on an ephemeral port over a fresh data directory holding `w.vod`.
/// Dropping it kills the child.
struct Server {
    process: ServerProcess,
    base: String,
    // Dropped after the process is killed (fields drop in declaration order).
    dir: tempfile::TempDir,
}

impl Server {
    /// Generates the volume and the token file, starts the server with `--edit-rate edit_rate`
    /// and waits for it to announce its address.
    fn start(edit_rate: u32) -> Server {
        Server::start_on("127.0.0.1:0", edit_rate)
    }

    /// [`Server::start`], listening on `addr` (`HOST:PORT`).
    fn start_on(addr: &str, edit_rate: u32) -> Server {
        Server::start_with(addr, edit_rate, &[])
    }

    /// [`Server::start_on`] with more options for `isovox serve`.
    fn start_with(addr: &str, edit_rate: u32, options: &[&str]) -> Server {
        let dir = tempfile::tempdir().unwrap();
        let vod = dir.path().join("w.vod");
        let out = Command::new(env!("CARGO_BIN_EXE_isovox"))
            .args(["generate", "world", "-o"])
            .arg(&vod)
            .args(["--dims", "64,48,64", "--brick", "16"])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "isovox generate failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let tokens = dir.path().join("tokens");
        std::fs::write(
            &tokens,
            format!(
                "# NAME TOKEN [SCOPE]\nwriter1 {SECRET1} write\nwriter2 {SECRET2}\nviewer {VIEWSECRET} read\n"
            ),
        )
        .unwrap();
        let edit_rate = edit_rate.to_string();
        let process = ServerProcess::start_on(
            addr,
            &[
                "--data".as_ref(),
                dir.path().as_os_str(),
                "--token-file".as_ref(),
                tokens.as_os_str(),
                "--edit-rate".as_ref(),
                edit_rate.as_ref(),
            ]
            .into_iter()
            .chain(options.iter().map(|o| o.as_ref()))
            .collect::<Vec<&std::ffi::OsStr>>(),
            &[("RUST_LOG", "debug"), ("ISOVOX_LOG", "debug")],
        );
        let base = process.url("");
        Server { process, base, dir }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    fn vod_path(&self) -> PathBuf {
        self.dir.path().join("w.vod")
    }

    /// Kills the server and returns everything it wrote to stderr.
    fn stop(mut self) -> String {
        self.process.stop()
    }
}

fn client() -> Client {
    isovox_server::client_tls::install_provider();
    Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap()
}

// ---------------------------------------------------------------------------------------------
// Requests
// ---------------------------------------------------------------------------------------------

/// An answer read whole: status, headers, body.
struct Answer {
    status: StatusCode,
    headers: HeaderMap,
    body: Vec<u8>,
}

impl Answer {
    fn read(r: Response) -> Answer {
        let status = r.status();
        let headers = r.headers().clone();
        let body = r.bytes().unwrap().to_vec();
        Answer {
            status,
            headers,
            body,
        }
    }

    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "{} answered a body that is not JSON ({e}): {}",
                self.status,
                String::from_utf8_lossy(&self.body)
            )
        })
    }

    fn header(&self, name: &str) -> Option<String> {
        self.headers
            .get(name)
            .map(|v| v.to_str().unwrap().to_string())
    }

    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }

    /// Asserts an RFC 9457 problem-details answer with `status` and returns its body.
    fn expect_problem(&self, status: u16, what: &str) -> Value {
        assert_eq!(
            self.status.as_u16(),
            status,
            "{what}: expected {status}, got {} with body {}",
            self.status,
            self.text()
        );
        let ct = self.header("content-type").unwrap_or_default();
        assert!(
            ct.starts_with("application/problem+json"),
            "{what}: content type {ct:?}, not application/problem+json; body {}",
            self.text()
        );
        let body = self.json();
        assert!(body.is_object(), "{what}: problem body {body}");
        body
    }
}

/// `POST /v1/volumes/{volume}/edits` with a JSON body and an optional bearer token.
fn post_edit(
    c: &Client,
    s: &Server,
    volume: &str,
    token: Option<&str>,
    body: &Value,
    if_match: Option<&str>,
) -> Answer {
    let mut req = c
        .post(s.url(&format!("/v1/volumes/{volume}/edits")))
        .header(CONTENT_TYPE, "application/json")
        .body(serde_json::to_vec(body).unwrap());
    if let Some(t) = token {
        req = req.header(AUTHORIZATION, format!("Bearer {t}"));
    }
    if let Some(m) = if_match {
        req = req.header("If-Match", m);
    }
    Answer::read(req.send().unwrap())
}

/// An edit that must succeed: returns the response JSON after checking its shape.
fn edit_ok(c: &Client, s: &Server, token: &str, body: &Value) -> Value {
    let a = post_edit(c, s, "w", Some(token), body, None);
    assert_eq!(
        a.status,
        StatusCode::OK,
        "edit {body} answered {}",
        a.text()
    );
    let v = a.json();
    check_edit_response(&v);
    v
}

fn check_edit_response(v: &Value) {
    let version = v["version"].as_u64().unwrap_or_else(|| panic!("{v}"));
    assert_eq!(v["previous"].as_u64(), Some(version - 1), "{v}");
    assert!(v["changed"].is_array(), "{v}");
}

fn info(c: &Client, s: &Server) -> Value {
    let a = Answer::read(c.get(s.url("/v1/volumes/w")).send().unwrap());
    assert_eq!(a.status, StatusCode::OK, "{}", a.text());
    a.json()
}

fn head_version(c: &Client, s: &Server) -> u64 {
    info(c, s)["version"].as_u64().unwrap()
}

/// Level 0 as voxel values (`?format=voxels`, x fastest), optionally of an older version.
fn level0(c: &Client, s: &Server, bytes_per_voxel: usize, version: Option<u64>) -> Vec<u16> {
    let mut url = s.url("/v1/volumes/w/levels/0?format=voxels");
    if let Some(v) = version {
        url.push_str(&format!("&version={v}"));
    }
    let a = Answer::read(c.get(url).send().unwrap());
    assert_eq!(a.status, StatusCode::OK, "level 0: {}", a.text());
    let n: usize = VOLUME_DIMS.iter().product();
    assert_eq!(a.body.len(), n * bytes_per_voxel, "level 0 size");
    if bytes_per_voxel == 1 {
        a.body.iter().map(|&b| b as u16).collect()
    } else {
        a.body
            .chunks_exact(2)
            .map(|p| u16::from_le_bytes([p[0], p[1]]))
            .collect()
    }
}

fn changes_since(c: &Client, s: &Server, since: u64) -> Answer {
    Answer::read(
        c.get(s.url(&format!("/v1/volumes/w/changes?since={since}")))
            .send()
            .unwrap(),
    )
}

// ---------------------------------------------------------------------------------------------
// Server-sent events
// ---------------------------------------------------------------------------------------------

#[derive(Debug, Clone)]
pub(crate) struct SseEvent {
    pub(crate) event: String,
    pub(crate) id: Option<String>,
    pub(crate) data: String,
}

/// A minimal `text/event-stream` parser over any reader.
pub(crate) struct Sse<R: Read> {
    reader: BufReader<R>,
}

impl<R: Read> Sse<R> {
    pub(crate) fn new(r: R) -> Self {
        Sse {
            reader: BufReader::new(r),
        }
    }

    /// The next event, or the error or end of stream that came first.
    pub(crate) fn next_event(&mut self) -> Result<SseEvent, String> {
        let mut event = String::new();
        let mut id = None;
        let mut data: Option<String> = None;
        let mut line = String::new();
        loop {
            line.clear();
            match self.reader.read_line(&mut line) {
                Ok(0) => return Err("end of stream".to_string()),
                Ok(_) => {}
                Err(e) => return Err(format!("read error: {e}")),
            }
            let l = line.trim_end_matches(['\n', '\r']);
            if l.is_empty() {
                if data.is_some() || !event.is_empty() {
                    return Ok(SseEvent {
                        event: if event.is_empty() {
                            "message".to_string()
                        } else {
                            event
                        },
                        id,
                        data: data.unwrap_or_default(),
                    });
                }
                continue;
            }
            if l.starts_with(':') {
                continue; // comment (keep-alive)
            }
            let (field, value) = match l.find(':') {
                Some(i) => {
                    let v = &l[i + 1..];
                    (&l[..i], v.strip_prefix(' ').unwrap_or(v))
                }
                None => (l, ""),
            };
            match field {
                "event" => event = value.to_string(),
                "id" => id = Some(value.to_string()),
                "data" => match &mut data {
                    Some(d) => {
                        d.push('\n');
                        d.push_str(value);
                    }
                    None => data = Some(value.to_string()),
                },
                _ => {}
            }
        }
    }
}

/// Opens `GET /v1/volumes/w/events` and checks the status and content type.
fn subscribe(c: &Client, s: &Server) -> Response {
    let r = c.get(s.url("/v1/volumes/w/events")).send().unwrap();
    assert_eq!(r.status(), StatusCode::OK, "events");
    let ct = r
        .headers()
        .get(CONTENT_TYPE)
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    assert!(
        ct.starts_with("text/event-stream"),
        "events content type {ct:?}"
    );
    r
}

/// What one subscriber saw: the hello version, every commit (version, its `changed`) in arrival
/// order, every other event, and why it stopped if it stopped early.
#[derive(Debug, Default)]
struct Seen {
    hello: u64,
    commits: Vec<(u64, Value)>,
    others: Vec<SseEvent>,
    stopped: Option<String>,
}

/// Reads the first event, which must be `hello`, and returns its version.
fn read_hello<R: Read>(sse: &mut Sse<R>) -> u64 {
    let hello = sse.next_event().unwrap();
    assert_eq!(hello.event, "hello", "first event {hello:?}");
    let hv: Value = serde_json::from_str(&hello.data).unwrap();
    hv["version"]
        .as_u64()
        .unwrap_or_else(|| panic!("{hello:?}"))
}

/// Reads events into `seen` until a commit with version `last` or later (or an error).
fn read_commits<R: Read>(sse: &mut Sse<R>, seen: &mut Seen, last: u64) {
    loop {
        match sse.next_event() {
            Err(e) => {
                seen.stopped = Some(e);
                return;
            }
            Ok(e) if e.event == "commit" => {
                let d: Value = serde_json::from_str(&e.data).unwrap();
                let v = d["version"].as_u64().unwrap_or_else(|| panic!("{e:?}"));
                assert_eq!(
                    e.id.as_deref(),
                    Some(v.to_string().as_str()),
                    "commit event id {e:?}"
                );
                seen.commits.push((v, d["changed"].clone()));
                if v >= last {
                    return;
                }
            }
            Ok(e) => seen.others.push(e),
        }
    }
}

/// Starts a thread that subscribes, reports the hello version on `ready`, then reads commit
/// events until one with version `last` (or an error).
fn spawn_subscriber(
    c: Client,
    url: String,
    last: u64,
    ready: mpsc::Sender<u64>,
) -> JoinHandle<Seen> {
    std::thread::spawn(move || {
        let r = c.get(url).send().unwrap();
        assert_eq!(r.status(), StatusCode::OK, "events");
        let mut sse = Sse::new(r);
        let mut seen = Seen {
            hello: read_hello(&mut sse),
            ..Seen::default()
        };
        ready.send(seen.hello).unwrap();
        if seen.hello < last {
            read_commits(&mut sse, &mut seen, last);
        }
        seen
    })
}

/// Asserts that a subscriber saw exactly the versions `first..=last`, in order, once each, with
/// the `changed` lists the editors were answered.
fn check_seen(who: &str, seen: &Seen, first: u64, last: u64, acked: &BTreeMap<u64, Value>) {
    assert!(
        seen.others.is_empty(),
        "{who}: unexpected events {:?}",
        seen.others
    );
    let versions: Vec<u64> = seen.commits.iter().map(|(v, _)| *v).collect();
    let expected: Vec<u64> = (first..=last).collect();
    assert_eq!(
        versions, expected,
        "{who}: commit versions (stopped: {:?})",
        seen.stopped
    );
    for (v, changed) in &seen.commits {
        assert_eq!(
            Some(changed),
            acked.get(v).map(|r| &r["changed"]),
            "{who}: `changed` of version {v} differs from the edit response"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// The independent evaluator (docs/icvg.md)
// ---------------------------------------------------------------------------------------------

/// L, S, H of the volume as `GET /v1/volumes/w` reports them, and its voxel width.
#[derive(Debug, Clone, Copy)]
struct Range {
    low: i64,
    surface: i64,
    high: i64,
    bytes: usize,
}

fn range_of(info: &Value) -> Range {
    let r = Range {
        low: info["low"].as_i64().unwrap(),
        surface: info["surface"].as_i64().unwrap(),
        high: info["high"].as_i64().unwrap(),
        bytes: if info["high"].as_u64().unwrap() > 255 {
            2
        } else {
            1
        },
    };
    assert_eq!(
        info["dims"],
        json!(VOLUME_DIMS),
        "the generated volume's dims"
    );
    r
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Op {
    Union,
    Difference,
}

#[derive(Debug, Clone, Copy)]
struct CuboidEdit {
    op: Op,
    origin: [i64; 3],
    size: [i64; 3],
}

impl CuboidEdit {
    fn json(&self) -> Value {
        let op = match self.op {
            Op::Union => "union",
            Op::Difference => "difference",
        };
        json!({"op": op, "term": {"cuboid": {"origin": self.origin, "size": self.size}}})
    }

    /// The cuboid's value at world voxel `p`: L outside its extension space and on its outer
    /// layer, S on the next layer, H inside.
    fn density(&self, p: [i64; 3], r: Range) -> i64 {
        let mut on_surface = false;
        for ((&pa, &oa), &b) in p.iter().zip(&self.origin).zip(&self.size) {
            let v = pa - oa;
            if v <= 0 || v >= b - 1 {
                return r.low;
            }
            if v == 1 || v == b - 2 {
                on_surface = true;
            }
        }
        if on_surface {
            r.surface
        } else {
            r.high
        }
    }

    /// Applies `op(volume, cuboid)` to `grid` (x fastest) and returns the level-0 bricks (of
    /// edge `brick`) where a voxel changed, as `[x, y, z]` sorted by z, then y, then x. Outside
    /// the cuboid the operand is L, which leaves both operators' results equal to D1, so only
    /// the box is visited.
    fn apply(&self, grid: &mut [u16], r: Range, brick: i64) -> Vec<[i64; 3]> {
        let mut changed = BTreeSet::new();
        let d = VOLUME_DIMS.map(|v| v as i64);
        let lo: Vec<i64> = (0..3).map(|a| self.origin[a].max(0)).collect();
        let hi: Vec<i64> = (0..3)
            .map(|a| (self.origin[a] + self.size[a]).min(d[a]))
            .collect();
        for z in lo[2]..hi[2] {
            for y in lo[1]..hi[1] {
                for x in lo[0]..hi[0] {
                    let i = ((z * d[1] + y) * d[0] + x) as usize;
                    let d1 = grid[i] as i64;
                    let d2 = self.density([x, y, z], r);
                    let v = match self.op {
                        Op::Union => d1.max(d2),
                        // docs/icvg.md, "Resolved (difference)": the S bound applies where the
                        // source is visible and the operand is not.
                        Op::Difference => {
                            if d1 >= r.surface && d2 < r.surface {
                                (d1 - d2).max(r.surface)
                            } else {
                                (d1 - d2).max(r.low)
                            }
                        }
                    };
                    let v = v.clamp(r.low, r.high) as u16;
                    if grid[i] != v {
                        changed.insert([z / brick, y / brick, x / brick]);
                    }
                    grid[i] = v;
                }
            }
        }
        changed.into_iter().map(|[z, y, x]| [x, y, z]).collect()
    }
}

/// A random cuboid edit in the middle of the volume (origins crowd a 40-voxel region so that
/// edits overlap and their order matters; some stick out of the volume, none lies wholly
/// outside it).
fn random_edit(rng: &mut XorShift, sizes: (i64, i64)) -> CuboidEdit {
    let op = if rng.next() & 1 == 0 {
        Op::Union
    } else {
        Op::Difference
    };
    let origin = [
        rng.between(-4, 44),
        rng.between(-4, 34),
        rng.between(-4, 44),
    ];
    let mut size = [
        rng.between(sizes.0, sizes.1),
        rng.between(sizes.0, sizes.1),
        rng.between(sizes.0, sizes.1),
    ];
    // The cuboid's inner voxels (origin + 1 ..= origin + size - 2) must meet the volume: an edit
    // wholly outside it commits no version (`an_edit_outside_the_volume_commits_nothing`), and
    // these tests count one version per edit. Grown after drawing, so the draws stay the same.
    for (s, o) in size.iter_mut().zip(origin) {
        *s = (*s).max(2 - o);
    }
    CuboidEdit { op, origin, size }
}

fn mismatch_report(got: &[u16], want: &[u16]) -> String {
    let d = VOLUME_DIMS;
    let diffs: Vec<usize> = (0..got.len()).filter(|&i| got[i] != want[i]).collect();
    let first: Vec<String> = diffs
        .iter()
        .take(8)
        .map(|&i| {
            let x = i % d[0];
            let y = (i / d[0]) % d[1];
            let z = i / (d[0] * d[1]);
            format!("({x},{y},{z}): server {} expected {}", got[i], want[i])
        })
        .collect();
    format!("{} voxels differ; first: {}", diffs.len(), first.join("; "))
}

// ---------------------------------------------------------------------------------------------
// The tests
// ---------------------------------------------------------------------------------------------

/// K editors in parallel, S subscribers: every edit gets its own version, every subscriber sees
/// every version once and in order, the final voxels are the edits applied in version order, and
/// the change list agrees with the feed.
#[test]
fn no_lost_updates() {
    const K: usize = 4;
    const M: usize = 15;
    const S: usize = 3;
    let s = Server::start(1000);
    let c = client();
    let vinfo = info(&c, &s);
    let r = range_of(&vinfo);
    let start = vinfo["version"].as_u64().unwrap();
    let last = start + (K * M) as u64;
    let before = level0(&c, &s, r.bytes, None);

    // Subscribers first; wait for each one's hello.
    let (ready_tx, ready_rx) = mpsc::channel();
    let subs: Vec<JoinHandle<Seen>> = (0..S)
        .map(|_| {
            spawn_subscriber(
                c.clone(),
                s.url("/v1/volumes/w/events"),
                last,
                ready_tx.clone(),
            )
        })
        .collect();
    for _ in 0..S {
        let hello = ready_rx.recv_timeout(Duration::from_secs(20)).unwrap();
        assert_eq!(hello, start, "hello version before any edit");
    }

    // K editors, M edits each, two tokens.
    let mut rng = XorShift(0x9e37_79b9_7f4a_7c15);
    let plans: Vec<Vec<CuboidEdit>> = (0..K)
        .map(|_| (0..M).map(|_| random_edit(&mut rng, (3, 20))).collect())
        .collect();
    let results: Vec<Vec<(CuboidEdit, Value)>> = std::thread::scope(|scope| {
        let handles: Vec<_> = plans
            .iter()
            .enumerate()
            .map(|(k, plan)| {
                let c = c.clone();
                let s = &s;
                scope.spawn(move || {
                    let token = if k % 2 == 0 { SECRET1 } else { SECRET2 };
                    plan.iter()
                        .map(|e| (*e, edit_ok(&c, s, token, &e.json())))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });

    // (a) the acknowledged versions are exactly start+1..=start+K*M.
    let mut acked: BTreeMap<u64, Value> = BTreeMap::new();
    let mut edit_of: BTreeMap<u64, CuboidEdit> = BTreeMap::new();
    for (e, resp) in results.iter().flatten() {
        let v = resp["version"].as_u64().unwrap();
        assert!(
            acked.insert(v, resp.clone()).is_none(),
            "version {v} acknowledged twice"
        );
        edit_of.insert(v, *e);
    }
    let versions: Vec<u64> = acked.keys().copied().collect();
    assert_eq!(versions, (start + 1..=last).collect::<Vec<_>>());
    let levels = vinfo["levels"].as_array().unwrap().len();
    for (v, resp) in &acked {
        assert_eq!(
            resp["changed"].as_array().unwrap().len(),
            levels,
            "version {v}: one `changed` list per level"
        );
    }
    assert_eq!(head_version(&c, &s), last);

    // (b) every subscriber saw every version once, in order, with the same `changed`.
    for (i, h) in subs.into_iter().enumerate() {
        let seen = h.join().unwrap();
        check_seen(&format!("subscriber {i}"), &seen, start + 1, last, &acked);
    }

    // (c) the final level 0 is the initial one with the edits applied in version order, and
    // each version's `changed[0]` lists exactly the level-0 bricks where that edit changed a
    // voxel.
    let brick = vinfo["brick"].as_i64().unwrap();
    let mut want = before.clone();
    for (v, e) in &edit_of {
        let bricks = e.apply(&mut want, r, brick);
        assert_eq!(
            acked[v]["changed"][0],
            json!(bricks),
            "version {v} ({e:?}): changed level-0 bricks"
        );
    }
    assert_ne!(want, before, "the edits should change something");
    let got = level0(&c, &s, r.bytes, None);
    assert!(
        got == want,
        "final level 0: {}",
        mismatch_report(&got, &want)
    );

    // (d) the change list agrees with the feed.
    let a = changes_since(&c, &s, start);
    assert_eq!(a.status, StatusCode::OK, "{}", a.text());
    let ch = a.json();
    assert_eq!(ch["since"].as_u64(), Some(start), "{ch}");
    assert_eq!(ch["head"].as_u64(), Some(last), "{ch}");
    assert_eq!(ch["more"].as_bool(), Some(false), "{ch}");
    let listed: Vec<(u64, Value)> = ch["changes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|item| (item["version"].as_u64().unwrap(), item["changed"].clone()))
        .collect();
    assert_eq!(
        listed.iter().map(|(v, _)| *v).collect::<Vec<_>>(),
        (start + 1..=last).collect::<Vec<_>>()
    );
    for (v, changed) in &listed {
        assert_eq!(Some(changed), acked.get(v).map(|r| &r["changed"]), "v{v}");
    }

    // (e) a late subscriber resumes from `?since=` or `Last-Event-ID` out of the file.
    let mid = start + (K * M / 2) as u64;
    for (how, req) in [
        (
            "?since",
            c.get(s.url(&format!("/v1/volumes/w/events?since={start}"))),
        ),
        (
            "Last-Event-ID",
            c.get(s.url("/v1/volumes/w/events"))
                .header("Last-Event-ID", mid.to_string()),
        ),
    ] {
        let r = req.send().unwrap();
        assert_eq!(r.status(), StatusCode::OK, "{how}");
        let from = if how == "?since" { start } else { mid };
        let mut sse = Sse::new(r);
        let mut seen = Seen {
            hello: read_hello(&mut sse),
            ..Seen::default()
        };
        assert_eq!(seen.hello, last, "{how}: hello");
        read_commits(&mut sse, &mut seen, last);
        check_seen(
            &format!("resuming with {how}"),
            &seen,
            from + 1,
            last,
            &acked,
        );
    }
}

/// `If-Match` applies an edit only on the named version, plain or quoted; a stale one gets 409
/// with the current version in the problem body and commits nothing.
#[test]
fn if_match() {
    let s = Server::start(1000);
    let c = client();
    let v0 = head_version(&c, &s);
    let body = json!({"op": "union", "term": {"cuboid": {"origin": [4, 4, 4], "size": [8, 8, 8]}}});

    let a = post_edit(&c, &s, "w", Some(SECRET1), &body, Some(&v0.to_string()));
    assert_eq!(a.status, StatusCode::OK, "{}", a.text());
    assert_eq!(a.json()["version"].as_u64(), Some(v0 + 1));

    let a = post_edit(&c, &s, "w", Some(SECRET1), &body, Some(&v0.to_string()));
    let p = a.expect_problem(409, "stale If-Match");
    assert_eq!(p["version"].as_u64(), Some(v0 + 1), "409 body {p}");
    assert_eq!(
        head_version(&c, &s),
        v0 + 1,
        "a refused edit commits nothing"
    );

    let quoted = format!("\"{}\"", v0 + 1);
    let a = post_edit(&c, &s, "w", Some(SECRET1), &body, Some(&quoted));
    assert_eq!(a.status, StatusCode::OK, "quoted If-Match: {}", a.text());
    assert_eq!(a.json()["version"].as_u64(), Some(v0 + 2));

    let a = post_edit(&c, &s, "w", Some(SECRET1), &body, Some(&quoted));
    let p = a.expect_problem(409, "stale quoted If-Match");
    assert_eq!(p["version"].as_u64(), Some(v0 + 2), "409 body {p}");
    assert_eq!(head_version(&c, &s), v0 + 2);

    // `*` matches whatever version is current (RFC 9110): the edit applies.
    let a = post_edit(&c, &s, "w", Some(SECRET1), &body, Some("*"));
    assert_eq!(a.status, StatusCode::OK, "If-Match: *: {}", a.text());
    assert_eq!(a.json()["version"].as_u64(), Some(v0 + 3));
    // A weak tag of the current version, and a number no version reaches (past u64): the
    // first applies, the second names another version (409), neither is malformed.
    let weak = format!("W/\"{}\"", v0 + 3);
    let a = post_edit(&c, &s, "w", Some(SECRET1), &body, Some(&weak));
    assert_eq!(a.status, StatusCode::OK, "weak If-Match: {}", a.text());
    let a = post_edit(
        &c,
        &s,
        "w",
        Some(SECRET1),
        &body,
        Some("99999999999999999999"),
    );
    let p = a.expect_problem(409, "If-Match past u64");
    assert_eq!(p["version"].as_u64(), Some(v0 + 4), "409 body {p}");
    // Neither `*` nor a version: 400, and nothing is committed.
    for bad in [
        "",
        "**",
        "abc",
        "\"5",
        "5\"",
        "W/5",
        "-1",
        "1, 2",
        "+5",
        "123456789012345678901",
    ] {
        let a = post_edit(&c, &s, "w", Some(SECRET1), &body, Some(bad));
        let p = a.expect_problem(400, &format!("If-Match {bad:?}"));
        assert!(
            p["detail"].as_str().unwrap().contains("If-Match"),
            "{bad:?}: {p}"
        );
    }
    assert_eq!(head_version(&c, &s), v0 + 4);
}

/// A `since` after the head names a version this volume does not have (its file was replaced
/// by an older copy, say): 409 with the current version, on the list and on the feed alike, so
/// a client knows to reload; it is well-formed, not a 400.
#[test]
fn since_after_the_head_is_a_conflict() {
    let s = Server::start(1000);
    let c = client();
    let h = head_version(&c, &s);
    let a = changes_since(&c, &s, h);
    assert_eq!(
        a.status,
        StatusCode::OK,
        "changes since the head: {}",
        a.text()
    );
    for since in [h + 1, u64::MAX] {
        let p = changes_since(&c, &s, since).expect_problem(409, "changes since past the head");
        assert_eq!(p["version"].as_u64(), Some(h), "{p}");
        let a = Answer::read(
            c.get(s.url(&format!("/v1/volumes/w/events?since={since}")))
                .send()
                .unwrap(),
        );
        let p = a.expect_problem(409, "events since past the head");
        assert_eq!(p["version"].as_u64(), Some(h), "{p}");
    }
    // Last-Event-ID the same, a number past u64 too; an empty one is no event seen yet (what
    // a browser means by it): the feed opens.
    for id in [(h + 1).to_string(), "99999999999999999999".to_string()] {
        let a = Answer::read(
            c.get(s.url("/v1/volumes/w/events"))
                .header("Last-Event-ID", &id)
                .send()
                .unwrap(),
        );
        a.expect_problem(409, &format!("Last-Event-ID {id}"));
    }
    let r = c
        .get(s.url("/v1/volumes/w/events"))
        .header("Last-Event-ID", "")
        .send()
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(
        r.headers()["content-type"].to_str().unwrap(),
        "text/event-stream"
    );
    let a = Answer::read(
        c.get(s.url("/v1/volumes/w/events"))
            .header("Last-Event-ID", "x1")
            .send()
            .unwrap(),
    );
    a.expect_problem(400, "Last-Event-ID x1");
}

/// A commit's event lists, for each brick it changed, the hash and value range the level grid
/// gives that brick at the commit's version (asked brick by brick with `?region=&version=`),
/// so a streamer refreshes its grid from the event alone; an undo's event too.
#[test]
fn change_events_list_what_each_changed_brick_holds_as_the_grid_does() {
    let s = Server::start(1000);
    let c = client();
    let h = head_version(&c, &s);
    let edits = [
        json!({"op": "union", "term": {"cuboid": {"origin": [10, 20, 12], "size": [20, 12, 9]}}}),
        json!({"op": "difference", "term": {"ellipsoid": {"center": [40, 15, 40], "radii": [9, 7, 9]}}}),
    ];
    let mut last = 0;
    for body in &edits {
        last = edit_ok(&c, &s, SECRET1, body)["version"].as_u64().unwrap();
    }
    let undo = Answer::read(
        c.post(s.url("/v1/volumes/w/undo"))
            .header(AUTHORIZATION, format!("Bearer {SECRET1}"))
            .header(CONTENT_TYPE, "application/json")
            .body(json!({ "version": last }).to_string())
            .send()
            .unwrap(),
    );
    assert_eq!(undo.status, StatusCode::OK, "undo: {}", undo.text());
    let a = changes_since(&c, &s, h);
    assert_eq!(a.status, StatusCode::OK, "{}", a.text());
    let list = a.json();
    let events = list["changes"].as_array().unwrap();
    assert_eq!(events.len(), 3, "{list}");
    let mut checked = 0;
    for ev in events {
        let version = ev["version"].as_u64().unwrap();
        let changed = ev["changed"].as_array().unwrap();
        let bricks = ev["bricks"]
            .as_array()
            .unwrap_or_else(|| panic!("no bricks: {ev}"));
        assert_eq!(bricks.len(), changed.len(), "{ev}");
        for (level, (keys, now)) in changed.iter().zip(bricks).enumerate() {
            let (keys, now) = (keys.as_array().unwrap(), now.as_array().unwrap());
            assert_eq!(keys.len(), now.len(), "level {level} of {ev}");
            for (k, listed) in keys.iter().zip(now) {
                let [x, y, z] = [0, 1, 2].map(|a| k[a].as_u64().unwrap());
                let url = format!(
                    "/v1/volumes/w/levels/{level}?region={x},{y},{z},{},{},{}&version={version}",
                    x + 1,
                    y + 1,
                    z + 1
                );
                let g = Answer::read(c.get(s.url(&url)).send().unwrap());
                assert_eq!(g.status, StatusCode::OK, "{url}: {}", g.text());
                let grid = g.json();
                assert_eq!(&grid["bricks"][0], listed, "{url}");
                checked += 1;
            }
        }
    }
    assert!(checked > 10, "{checked} bricks checked");
}

/// A log written to a pipe or a file carries no ANSI colour codes (they are for terminals), and
/// `--addr` takes a host name, as every server does.
#[test]
fn logs_to_a_pipe_are_plain_and_addr_takes_a_host_name() {
    let s = Server::start_on("localhost:0", 1000);
    let c = client();
    assert!(
        s.base.starts_with("http://127.0.0.1:") || s.base.starts_with("http://[::1]:"),
        "localhost is a loopback address: {}",
        s.base
    );
    let r = c.get(s.url("/healthz")).send().unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    edit_ok(
        &c,
        &s,
        SECRET1,
        &json!({"op": "union", "term": {"cuboid": {"origin": [4, 4, 4], "size": [8, 8, 8]}}}),
    );
    let log = s.stop();
    assert!(
        log.contains("edit committed"),
        "the debug log has the edit: {log}"
    );
    assert!(
        !log.contains('\u{1b}'),
        "colour codes in a piped log: {log:?}"
    );
}

/// Write routes: 401 (with `WWW-Authenticate`) without a token, with an unknown one or another
/// scheme; 403 with a read token; 200 with a write token. No token ever reaches the log.
#[test]
fn access_control() {
    let s = Server::start(1000);
    let c = client();
    let body = json!({"op": "union", "term": {"cuboid": {"origin": [4, 4, 4], "size": [6, 6, 6]}}});
    let send = |route: &str, auth: Option<&str>| -> Answer {
        let mut req = c.post(s.url(&format!("/v1/volumes/w/{route}")));
        if route == "edits" {
            req = req
                .header(CONTENT_TYPE, "application/json")
                .body(serde_json::to_vec(&body).unwrap());
        }
        if let Some(a) = auth {
            req = req.header(AUTHORIZATION, a);
        }
        Answer::read(req.send().unwrap())
    };

    for route in ["edits", "compact"] {
        let a = send(route, None);
        a.expect_problem(401, &format!("{route} without a token"));
        let www = a
            .header("www-authenticate")
            .unwrap_or_else(|| panic!("{route}: 401 without WWW-Authenticate: {:?}", a.headers));
        assert!(
            www.to_ascii_lowercase().starts_with("bearer"),
            "{route}: WWW-Authenticate {www:?}"
        );

        for bad in [
            "Bearer wrong".to_string(),
            format!("Bearer {UNKNOWN_TOKEN}"),
            "Basic xyz".to_string(),
            format!("Basic {SECRET1}"),
            "Bearer".to_string(),
        ] {
            let a = send(route, Some(&bad));
            a.expect_problem(401, &format!("{route} with {bad:?}"));
            assert!(
                a.header("www-authenticate").is_some(),
                "{route} with {bad:?}: 401 without WWW-Authenticate"
            );
        }

        let a = send(route, Some(&format!("Bearer {VIEWSECRET}")));
        a.expect_problem(403, &format!("{route} with a read token"));

        let v = head_version(&c, &s);
        let a = send(route, Some(&format!("Bearer {SECRET1}")));
        assert_eq!(a.status, StatusCode::OK, "{route}: {}", a.text());
        let j = a.json();
        let expected = if route == "edits" { v + 1 } else { v };
        assert_eq!(j["version"].as_u64(), Some(expected), "{route}: {j}");

        // The default scope is write.
        let v = head_version(&c, &s);
        let a = send(route, Some(&format!("Bearer {SECRET2}")));
        assert_eq!(
            a.status,
            StatusCode::OK,
            "{route} (default scope): {}",
            a.text()
        );
        let expected = if route == "edits" { v + 1 } else { v };
        assert_eq!(a.json()["version"].as_u64(), Some(expected));
    }

    // Reads stay open without --private-reads.
    let a = Answer::read(c.get(s.url("/v1/volumes/w")).send().unwrap());
    assert_eq!(a.status, StatusCode::OK);

    let log = s.stop();
    // The log is not empty (debug logging took effect) and names the token, not its secret.
    assert!(
        log.contains("writer1"),
        "the log does not name the token that edited:\n{log}"
    );
    for secret in [SECRET1, SECRET2, VIEWSECRET, UNKNOWN_TOKEN] {
        assert!(
            !log.contains(secret),
            "the server's log contains the token {secret:?}:\n{log}"
        );
    }
}

/// The edit route's error statuses, and rate limiting per token.
#[test]
fn edit_errors() {
    let s = Server::start(1000);
    let c = client();
    let v0 = head_version(&c, &s);
    let raw = |body: &str, content_type: Option<&str>, volume: &str| -> Answer {
        let mut req = c
            .post(s.url(&format!("/v1/volumes/{volume}/edits")))
            .header(AUTHORIZATION, format!("Bearer {SECRET1}"))
            .body(body.to_string());
        if let Some(ct) = content_type {
            req = req.header(CONTENT_TYPE, ct);
        }
        Answer::read(req.send().unwrap())
    };
    let json_ct = Some("application/json");
    let good = r#"{"op":"union","term":{"cuboid":{"origin":[4,4,4],"size":[6,6,6]}}}"#;

    raw(r#"{"op":"union","term":{"cuboid":"#, json_ct, "w").expect_problem(400, "truncated JSON");
    raw("not json at all", json_ct, "w").expect_problem(400, "not JSON");
    raw(
        r#"{"op":"union","term":{"cuboid":{"origin":[4,4,4],"size":[6,6,6]}},"bogus":1}"#,
        json_ct,
        "w",
    )
    .expect_problem(400, "unknown field");
    raw(
        r#"{"op":"union","term":{"cuboid":{"origin":"here","size":[6,6,6]}}}"#,
        json_ct,
        "w",
    )
    .expect_problem(400, "wrong type");

    raw(
        r#"{"op":"frobnicate","term":{"cuboid":{"origin":[4,4,4],"size":[6,6,6]}}}"#,
        json_ct,
        "w",
    )
    .expect_problem(422, "unknown op");
    raw(
        r#"{"op":"union","term":{"cuboid":{"origin":[0,0,0],"size":[100000,100000,100000]}}}"#,
        json_ct,
        "w",
    )
    .expect_problem(422, "cuboid of 100000 per axis");
    raw(
        r#"{"op":"union","term":{"cuboid":{"origin":[4,4,4],"size":[2,6,6]}}}"#,
        json_ct,
        "w",
    )
    .expect_problem(422, "cuboid side 2");
    // 40 nested unions (depth over 32, 81 nodes: under the node limit).
    let leaf = json!({"cuboid": {"origin": [4, 4, 4], "size": [6, 6, 6]}});
    let mut deep = leaf.clone();
    for _ in 0..40 {
        deep = json!({"union": [deep, leaf]});
    }
    raw(
        &json!({"op": "union", "term": deep}).to_string(),
        json_ct,
        "w",
    )
    .expect_problem(422, "nesting deeper than 32");

    raw(good, Some("text/plain"), "w").expect_problem(415, "text/plain");
    raw(good, None, "w").expect_problem(415, "no content type");
    raw(good, json_ct, "nope").expect_problem(404, "unknown volume");

    assert_eq!(head_version(&c, &s), v0, "refused edits commit nothing");
    let a = raw(good, json_ct, "w");
    assert_eq!(a.status, StatusCode::OK, "{}", a.text());
    assert_eq!(a.json()["version"].as_u64(), Some(v0 + 1));
    drop(s);

    // Rate limiting: 2 edits per second per token.
    let s = Server::start(2);
    let body: Value = serde_json::from_str(good).unwrap();
    let answers: Vec<Answer> = (0..10)
        .map(|_| post_edit(&c, &s, "w", Some(SECRET1), &body, None))
        .collect();
    let ok = answers
        .iter()
        .filter(|a| a.status == StatusCode::OK)
        .count();
    let limited: Vec<&Answer> = answers
        .iter()
        .filter(|a| a.status == StatusCode::TOO_MANY_REQUESTS)
        .collect();
    assert_eq!(
        ok + limited.len(),
        10,
        "statuses: {:?}",
        answers.iter().map(|a| a.status).collect::<Vec<_>>()
    );
    assert!(ok >= 1, "the first edit is within the burst");
    assert!(
        !limited.is_empty(),
        "10 edits back to back at --edit-rate 2: none limited"
    );
    for a in &limited {
        a.expect_problem(429, "rate limited");
        let retry = a.header("retry-after").expect("429 without Retry-After");
        assert!(!retry.trim().is_empty(), "empty Retry-After");
    }
    // The limit is per token: another write token still gets through.
    let a = post_edit(&c, &s, "w", Some(SECRET2), &body, None);
    assert_eq!(a.status, StatusCode::OK, "other token: {}", a.text());
}

/// A body over 1 MiB gets 413 as problem details, like every other edit error.
#[test]
fn edit_body_too_large() {
    let s = Server::start(1000);
    let c = client();
    let v0 = head_version(&c, &s);
    // A valid edit padded with whitespace to just over 1 MiB.
    let mut body =
        r#"{"op":"union","term":{"cuboid":{"origin":[4,4,4],"size":[6,6,6]}}}"#.to_string();
    body.push_str(&" ".repeat((1 << 20) + 64 - body.len()));
    let a = Answer::read(
        c.post(s.url("/v1/volumes/w/edits"))
            .header(AUTHORIZATION, format!("Bearer {SECRET1}"))
            .header(CONTENT_TYPE, "application/json")
            .body(body)
            .send()
            .unwrap(),
    );
    a.expect_problem(413, "a body over 1 MiB");
    // The server read the rest of that body before answering, so the client heard its 413
    // (not a reset) and the same client edits on.
    edit_ok(
        &c,
        &s,
        SECRET1,
        &json!({"op":"union","term":{"cuboid":{"origin":[4,4,4],"size":[6,6,6]}}}),
    );
    let v1 = head_version(&c, &s);
    assert_eq!(v1, v0 + 1);

    // Without a token the body is not even read: the 401 comes back before the client has
    // sent a byte of the megabyte it announced.
    let (status, text) = headers_only(&s, None, (1 << 20) + 64);
    assert_eq!(status, 401, "a big body without a token: {text}");
    assert!(text.contains("application/problem+json"), "{text}");
    // With a token, a body announced far over the limit is refused before it is sent.
    let (status, text) = headers_only(&s, Some(SECRET1), 100 << 20);
    assert_eq!(status, 413, "a body announced at 100 MiB: {text}");
    assert!(text.contains("application/problem+json"), "{text}");
    assert_eq!(head_version(&c, &s), v1);
}

/// Sends an edit request's head with `Content-Length: length` and no body, and reads the
/// answer until the server closes the connection or 5 s pass: the status and the whole text.
fn headers_only(s: &Server, token: Option<&str>, length: u64) -> (u16, String) {
    let addr = s.process.addr.clone();
    let mut tcp = std::net::TcpStream::connect(&addr).unwrap();
    tcp.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
    let head = format!(
        "POST /v1/volumes/w/edits HTTP/1.1\r\nHost: {addr}\r\n{auth}\
         Content-Type: application/json\r\nContent-Length: {length}\r\n\r\n"
    );
    std::io::Write::write_all(&mut tcp, head.as_bytes()).unwrap();
    let mut text = Vec::new();
    // A read timeout after the answer is fine: the server may keep the connection open.
    let _ = tcp.read_to_end(&mut text);
    let text = String::from_utf8_lossy(&text).into_owned();
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    (status, text)
}

/// Compaction keeps the head's version and voxels, drops the history, does not grow the file,
/// and editing goes on.
#[test]
fn compact_keeps_content() {
    let s = Server::start(1000);
    let c = client();
    let vinfo = info(&c, &s);
    let r = range_of(&vinfo);
    let start = vinfo["version"].as_u64().unwrap();
    let mut rng = XorShift(0x1234_5678_9abc_def1);
    for _ in 0..6 {
        edit_ok(&c, &s, SECRET1, &random_edit(&mut rng, (3, 20)).json());
    }
    let h = head_version(&c, &s);
    assert_eq!(h, start + 6);
    let head_voxels = level0(&c, &s, r.bytes, None);
    let older = level0(&c, &s, r.bytes, Some(h - 2));
    assert_eq!(older.len(), head_voxels.len());
    let a = changes_since(&c, &s, start);
    assert_eq!(a.status, StatusCode::OK, "before compaction: {}", a.text());
    let size_before = std::fs::metadata(s.vod_path()).unwrap().len();

    let a = Answer::read(
        c.post(s.url("/v1/volumes/w/compact"))
            .header(AUTHORIZATION, format!("Bearer {SECRET1}"))
            .send()
            .unwrap(),
    );
    assert_eq!(a.status, StatusCode::OK, "compact: {}", a.text());
    let j = a.json();
    assert_eq!(j["version"].as_u64(), Some(h), "{j}");
    let bytes_before = j["bytes_before"].as_u64().unwrap();
    let bytes_after = j["bytes_after"].as_u64().unwrap();
    assert!(bytes_after <= bytes_before, "{j}");
    let size_after = std::fs::metadata(s.vod_path()).unwrap().len();
    assert!(
        size_after <= size_before,
        "file grew from {size_before} to {size_after}"
    );
    assert_eq!(size_after, bytes_after, "{j}");

    assert_eq!(head_version(&c, &s), h);
    let after = level0(&c, &s, r.bytes, None);
    assert!(
        after == head_voxels,
        "level 0 after compaction: {}",
        mismatch_report(&after, &head_voxels)
    );
    let a = Answer::read(
        c.get(s.url(&format!(
            "/v1/volumes/w/levels/0?format=voxels&version={}",
            h - 2
        )))
        .send()
        .unwrap(),
    );
    a.expect_problem(404, "an older version after compaction");
    let a = Answer::read(
        c.get(s.url(&format!("/v1/volumes/w/bricks/0/0/0/0?version={}", h - 2)))
            .send()
            .unwrap(),
    );
    a.expect_problem(404, "an older brick after compaction");
    changes_since(&c, &s, start).expect_problem(410, "changes since a compacted version");
    changes_since(&c, &s, h - 3).expect_problem(410, "changes since H - 3");
    let a = changes_since(&c, &s, h);
    assert_eq!(
        a.status,
        StatusCode::OK,
        "changes since the head: {}",
        a.text()
    );
    let j = a.json();
    assert_eq!(j["changes"].as_array().map(Vec::len), Some(0), "{j}");
    assert_eq!(j["head"].as_u64(), Some(h), "{j}");

    // Editing goes on from the same version number.
    let e = random_edit(&mut rng, (3, 20));
    let resp = edit_ok(&c, &s, SECRET1, &e.json());
    assert_eq!(resp["version"].as_u64(), Some(h + 1));
    let mut want = head_voxels.clone();
    let bricks = e.apply(&mut want, r, vinfo["brick"].as_i64().unwrap());
    assert_eq!(resp["changed"][0], json!(bricks), "{resp}");
    let got = level0(&c, &s, r.bytes, None);
    assert!(
        got == want,
        "level 0 after an edit on the compacted file: {}",
        mismatch_report(&got, &want)
    );
    let a = changes_since(&c, &s, h);
    assert_eq!(a.status, StatusCode::OK, "{}", a.text());
    let j = a.json();
    let listed: Vec<u64> = j["changes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["version"].as_u64().unwrap())
        .collect();
    assert_eq!(listed, vec![h + 1], "{j}");
}

/// A compaction asked for while editors keep the writer's queue full is served between two
/// groups (the writer does not keep it waiting until the editors stop), every edit before and
/// after it is answered, and the versions stay consecutive across it.
#[test]
fn compaction_is_served_while_editors_keep_the_writer_busy() {
    // One edit a group: while the writer commits one, the other editors' edits wait, so the
    // queue is never empty while they edit.
    let s = Server::start_with("127.0.0.1:0", 1000, &["--edit-group", "1"]);
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    // Each editor stops after this many edits at most, so that a writer that kept the
    // compaction waiting until the queue is empty fails the test instead of hanging it.
    const EDITS_EACH: usize = 400;
    let (stop, done) = (AtomicBool::new(false), AtomicUsize::new(0));
    let versions = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for seed in 0..4u64 {
            let (s, stop, done, versions) = (&s, &stop, &done, &versions);
            scope.spawn(move || {
                let c = client();
                let mut rng = XorShift(0x5eed_0000 + seed);
                for _ in 0..EDITS_EACH {
                    if stop.load(Ordering::Acquire) {
                        break;
                    }
                    let v = edit_ok(&c, s, SECRET1, &random_edit(&mut rng, (3, 12)).json());
                    versions
                        .lock()
                        .unwrap()
                        .push(v["version"].as_u64().unwrap());
                }
                done.fetch_add(1, Ordering::AcqRel);
            });
        }
        // Let the editors fill the queue, then compact while they go on.
        while versions.lock().unwrap().len() < 20 {
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        let c = client();
        let a = Answer::read(
            c.post(s.url("/v1/volumes/w/compact"))
                .header(AUTHORIZATION, format!("Bearer {SECRET1}"))
                .send()
                .unwrap(),
        );
        let edits_before_the_answer = versions.lock().unwrap().len();
        assert_eq!(a.status, StatusCode::OK, "compact: {}", a.text());
        let compacted = a.json()["version"].as_u64().unwrap();
        // Editing goes on after the compaction.
        while versions.lock().unwrap().len() < edits_before_the_answer + 20
            && done.load(Ordering::Acquire) < 4
        {
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        stop.store(true, Ordering::Release);
        // Edits in flight at the stop are answered and recorded before the versions are read:
        // an answer still on its way would look like a gap.
        while done.load(Ordering::Acquire) < 4 {
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        let mut got = versions.lock().unwrap().clone();
        got.sort_unstable();
        // Every answered edit has its own version, with no gap: the compaction kept the
        // numbering, and it saw a version some edit had made.
        assert!(got.windows(2).all(|w| w[1] == w[0] + 1), "{got:?}");
        assert!(
            got.contains(&compacted),
            "compacted {compacted}, edits {got:?}"
        );
        assert!(
            got.iter().any(|&v| v > compacted),
            "no edit after the compaction"
        );
    });
}

/// A subscriber that never reads does not hold up the writer; a reading one sees everything.
#[test]
fn slow_subscriber_does_not_block() {
    const N: u64 = 300;
    let s = Server::start(1000);
    let c = client();
    let vinfo = info(&c, &s);
    let start = vinfo["version"].as_u64().unwrap();
    let last = start + N;

    // Never read from this one (kept alive until the end).
    let slow = subscribe(&c, &s);
    let (ready_tx, ready_rx) = mpsc::channel();
    let reader = spawn_subscriber(c.clone(), s.url("/v1/volumes/w/events"), last, ready_tx);
    assert_eq!(
        ready_rx.recv_timeout(Duration::from_secs(20)).unwrap(),
        start
    );

    let mut rng = XorShift(0x0bad_cafe_f00d_d00d);
    let mut acked: BTreeMap<u64, Value> = BTreeMap::new();
    for i in 0..N {
        let mut e = random_edit(&mut rng, (3, 4));
        e.op = if i % 2 == 0 {
            Op::Union
        } else {
            Op::Difference
        };
        let resp = edit_ok(&c, &s, SECRET1, &e.json());
        let v = resp["version"].as_u64().unwrap();
        assert_eq!(v, start + 1 + i);
        acked.insert(v, resp);
    }
    assert_eq!(head_version(&c, &s), last);

    let seen = reader.join().unwrap();
    check_seen("reading subscriber", &seen, start + 1, last, &acked);
    let distinct: BTreeSet<u64> = seen.commits.iter().map(|(v, _)| *v).collect();
    assert_eq!(distinct.len() as u64, N);

    // The silent one is 300 versions behind, well within the 1024 it may lag: it gets them all.
    let mut sse = Sse::new(slow);
    let mut seen = Seen {
        hello: read_hello(&mut sse),
        ..Seen::default()
    };
    assert_eq!(seen.hello, start);
    read_commits(&mut sse, &mut seen, last);
    check_seen(
        "silent subscriber, read late",
        &seen,
        start + 1,
        last,
        &acked,
    );
}

/// An edit that reaches no voxel of the volume (a term wholly outside it, or a region outside
/// it) commits nothing: 200 naming the current version with `"committed": false` and no
/// changed bricks, no new version in the history, no event on the change feed. (It used to
/// commit an empty version, announced to every follower.)
#[test]
fn an_edit_outside_the_volume_commits_nothing() {
    let s = Server::start(1000);
    let c = client();
    let h = head_version(&c, &s);
    let mut sse = Sse::new(subscribe(&c, &s));
    assert_eq!(read_hello(&mut sse), h);
    // The volume is 64 x 48 x 64: x from 64 on, and a region past y = 48, are outside it.
    let outside = [
        json!({"op": "union", "term": {"cuboid": {"origin": [70, 0, 0], "size": [8, 8, 8]}}}),
        json!({"op": "inverse", "region": {"min": [0, 50, 0], "max": [64, 60, 64]}}),
    ];
    for body in &outside {
        let a = post_edit(&c, &s, "w", Some(SECRET1), body, None);
        assert_eq!(a.status, StatusCode::OK, "{body}: {}", a.text());
        let v = a.json();
        assert_eq!(v["committed"], json!(false), "{v}");
        assert_eq!(v["version"].as_u64(), Some(h), "{v}");
        assert_eq!(v["previous"].as_u64(), Some(h), "{v}");
        assert_eq!(v["evaluated"].as_u64(), Some(0), "{v}");
        let changed = v["changed"].as_array().unwrap();
        assert!(!changed.is_empty(), "one list per level: {v}");
        assert!(
            changed.iter().all(|l| l.as_array().unwrap().is_empty()),
            "{v}"
        );
    }
    assert_eq!(head_version(&c, &s), h, "no version was made");
    let j = changes_since(&c, &s, h).json();
    assert_eq!(j["changes"].as_array().map(Vec::len), Some(0), "{j}");
    // The next real edit is h + 1, and it is the feed's first commit event.
    let body =
        json!({"op": "union", "term": {"cuboid": {"origin": [8, 40, 8], "size": [8, 8, 8]}}});
    let v = edit_ok(&c, &s, SECRET1, &body);
    assert_eq!(v["version"].as_u64(), Some(h + 1), "{v}");
    assert_eq!(v["committed"], json!(true), "{v}");
    let mut seen = Seen::default();
    read_commits(&mut sse, &mut seen, h + 1);
    assert_eq!(seen.stopped, None);
    let versions: Vec<u64> = seen.commits.iter().map(|(v, _)| *v).collect();
    assert_eq!(versions, [h + 1], "the feed announced only the real edit");
}
