//! Editing together, as people, against the real `isovox serve`: alice signs in with a JWT
//! (the test is her issuer, as in `oidc.rs`), bob, carol and dave with tokens of a token file.
//! Who did what reaches the feed, `changes` and `history`; undo takes back one edit and keeps
//! the later ones (checked against an independent copy of the volume edited once); redo,
//! revert, tags, dry runs, who may undo what; and presence between two subscribers.

use crate::oidc::{claims, Issuer, Key, AUDIENCE};
use crate::server_process::ServerProcess;
use crate::shared_editing::{Sse, SseEvent};
use jsonwebtoken::Algorithm;
use reqwest::blocking::{Client, Response};
use reqwest::header::{AUTHORIZATION, CONTENT_TYPE};
use reqwest::StatusCode;
use serde_json::{json, Value};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

const BOB: &str = "bob-0123456789abcdef";
const CAROL: &str = "carol-0123456789abcdef";
const DAVE: &str = "dave-0123456789abcdef";

/// alice's ball (added) and bob's (carved): they overlap in several bricks.
fn alice_edit() -> Value {
    json!({"op": "union", "message": "alice's hill",
           "term": {"ellipsoid": {"center": [24, 24, 32], "radii": [12, 12, 12]}}})
}

fn bob_edit() -> Value {
    json!({"op": "difference", "message": "bob's tunnel",
           "term": {"ellipsoid": {"center": [34, 30, 32], "radii": [11, 11, 11]}}})
}

/// A data directory with the world `w` (64^3, bricks of 16) and `copy`, the same file.
fn data_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_isovox"))
        .args(["generate", "world", "-o"])
        .arg(dir.path().join("w.vod"))
        .args(["--dims", "64,64,64", "--brick", "16"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    std::fs::copy(dir.path().join("w.vod"), dir.path().join("copy.vod")).unwrap();
    std::fs::write(
        dir.path().join("tokens"),
        format!("bob {BOB} write\ncarol {CAROL} write other\ndave {DAVE} admin\n"),
    )
    .unwrap();
    dir
}

struct World {
    _dir: tempfile::TempDir,
    _issuer: Issuer,
    server: ServerProcess,
    http: Client,
    alice: String,
}

fn world() -> World {
    let dir = data_dir();
    let keys = tempfile::tempdir().unwrap();
    let key = Key::new(keys.path(), "k1", Algorithm::ES256);
    let issuer = Issuer::start(&[&key]);
    let alice = key.sign(&claims(&issuer.url, "alice", &["write:*"]));
    let server = serve(dir.path(), &issuer.url);
    isovox_server::client_tls::install_provider();
    World {
        _dir: dir,
        _issuer: issuer,
        server,
        http: Client::builder()
            .timeout(Duration::from_secs(30))
            .build()
            .unwrap(),
        alice,
    }
}

fn serve(dir: &Path, issuer: &str) -> ServerProcess {
    let tokens = dir.join("tokens");
    ServerProcess::start(
        &[
            "--data".as_ref(),
            dir.as_os_str(),
            "--token-file".as_ref(),
            tokens.as_os_str(),
            "--oidc-issuer".as_ref(),
            issuer.as_ref(),
            "--oidc-audience".as_ref(),
            AUDIENCE.as_ref(),
        ],
        &[],
    )
}

impl World {
    fn send(&self, method: &str, path: &str, token: Option<&str>, body: Option<Value>) -> Response {
        let url = self.server.url(path);
        let mut request = match method {
            "GET" => self.http.get(url),
            "PUT" => self.http.put(url),
            _ => self.http.post(url),
        };
        if let Some(t) = token {
            request = request.header(AUTHORIZATION, format!("Bearer {t}"));
        }
        if let Some(b) = body {
            request = request
                .header(CONTENT_TYPE, "application/json")
                .body(b.to_string());
        }
        request.send().unwrap()
    }

    /// A JSON answer with the status `expected`.
    #[track_caller]
    fn json(
        &self,
        method: &str,
        path: &str,
        token: Option<&str>,
        body: Option<Value>,
        expected: StatusCode,
    ) -> Value {
        let response = self.send(method, path, token, body);
        let status = response.status();
        let text = response.text().unwrap();
        assert_eq!(status, expected, "{method} {path}: {text}");
        serde_json::from_str(&text).unwrap_or(Value::Null)
    }

    fn ok(&self, method: &str, path: &str, token: Option<&str>, body: Option<Value>) -> Value {
        self.json(method, path, token, body, StatusCode::OK)
    }

    /// Every level's brick grid of `volume` (hashes, min, max), at `version` when given.
    fn grids(&self, volume: &str, version: Option<&str>) -> Vec<Value> {
        let info = self.ok("GET", &format!("/v1/volumes/{volume}"), None, None);
        let levels = info["levels"].as_array().unwrap().len();
        (0..levels)
            .map(|level| {
                let query = version.map_or(String::new(), |v| format!("?version={v}"));
                let grid = self.ok(
                    "GET",
                    &format!("/v1/volumes/{volume}/levels/{level}{query}"),
                    None,
                    None,
                );
                grid["bricks"].clone()
            })
            .collect()
    }

    /// The raw bytes of every level-0 brick of `volume` at `version`.
    fn level0_bytes(&self, volume: &str, version: &str) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        for z in 0..4 {
            for y in 0..4 {
                for x in 0..4 {
                    let r = self.send(
                        "GET",
                        &format!("/v1/volumes/{volume}/bricks/0/{x}/{y}/{z}?version={version}"),
                        None,
                        None,
                    );
                    assert_eq!(r.status(), StatusCode::OK);
                    out.push(r.bytes().unwrap().to_vec());
                }
            }
        }
        out
    }

    fn subscribe(&self, volume: &str) -> Sse<Response> {
        let r = self
            .http
            .get(self.server.url(&format!("/v1/volumes/{volume}/events")))
            .timeout(Duration::from_secs(60))
            .send()
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        let mut sse = Sse::new(r);
        assert_eq!(sse.next_event().unwrap().event, "hello");
        sse
    }
}

/// The next event named `name` (others skipped), within `limit`.
fn next_named(sse: &mut Sse<Response>, name: &str, limit: Duration) -> SseEvent {
    let start = Instant::now();
    loop {
        assert!(start.elapsed() < limit, "no {name} event within {limit:?}");
        let e = sse.next_event().unwrap();
        if e.event == name {
            return e;
        }
    }
}

#[test]
fn undo_takes_back_one_edit_and_keeps_the_later_ones() {
    let w = world();
    let mut feed = w.subscribe("w");
    let v1 = w.ok("GET", "/v1/volumes/w", None, None)["version"]
        .as_u64()
        .unwrap();

    // alice (JWT) then bob (token) edit the same place; each commit names its author.
    let a = w.ok(
        "POST",
        "/v1/volumes/w/edits",
        Some(&w.alice),
        Some(alice_edit()),
    );
    let b = w.ok("POST", "/v1/volumes/w/edits", Some(BOB), Some(bob_edit()));
    let (va, vb) = (
        a["version"].as_u64().unwrap(),
        b["version"].as_u64().unwrap(),
    );
    assert_eq!((va, vb), (v1 + 1, v1 + 2));
    let ea: Value =
        serde_json::from_str(&next_named(&mut feed, "commit", Duration::from_secs(10)).data)
            .unwrap();
    let eb: Value =
        serde_json::from_str(&next_named(&mut feed, "commit", Duration::from_secs(10)).data)
            .unwrap();
    assert_eq!(
        (ea["author"].as_str(), ea["message"].as_str()),
        (Some("alice"), Some("alice's hill"))
    );
    assert_eq!(
        (eb["author"].as_str(), eb["kind"].as_str()),
        (Some("bob"), Some("edit"))
    );
    assert_eq!(eb["op"]["op"], "difference");
    assert_eq!(eb["op"]["leaves"], json!(["ellipsoid"]));
    // bob's box: his ball's voxels, centre +- radius (the extension space is 2R + 1).
    assert_eq!(
        eb["op"]["box"],
        json!({"min": [23, 19, 21], "max": [46, 42, 44]})
    );
    let changes = w.ok(
        "GET",
        &format!("/v1/volumes/w/changes?since={v1}"),
        None,
        None,
    );
    assert_eq!(changes["changes"][0]["author"], "alice");
    assert_eq!(changes["changes"][1]["message"], "bob's tunnel");

    // The independent answer: the copy, edited once, by bob's edit alone.
    w.ok(
        "POST",
        "/v1/volumes/copy/edits",
        Some(BOB),
        Some(bob_edit()),
    );
    assert_ne!(
        w.grids("w", None),
        w.grids("copy", None),
        "alice's hill must show"
    );

    // bob may not undo alice's edit; an edit undone twice, or a version that is no edit, is
    // a conflict.
    let refused = w.json(
        "POST",
        "/v1/volumes/w/undo",
        Some(BOB),
        Some(json!({"version": va})),
        StatusCode::FORBIDDEN,
    );
    assert!(
        refused["detail"].as_str().unwrap().contains("alice"),
        "{refused}"
    );
    let undo = w.ok(
        "POST",
        "/v1/volumes/w/undo",
        Some(&w.alice),
        Some(json!({"version": va, "message": "oops"})),
    );
    assert_eq!(undo["replayed"], 1, "bob's edit is applied again: {undo}");
    let vu = undo["version"].as_u64().unwrap();
    assert_eq!(vu, vb + 1);
    assert_eq!(
        w.grids("w", None),
        w.grids("copy", None),
        "the volume is the copy with bob's edit only, at every level"
    );
    let again = w.json(
        "POST",
        "/v1/volumes/w/undo",
        Some(&w.alice),
        Some(json!({"version": va})),
        StatusCode::CONFLICT,
    );
    assert!(
        again["detail"].as_str().unwrap().contains("undone already"),
        "{again}"
    );
    let eu: Value =
        serde_json::from_str(&next_named(&mut feed, "commit", Duration::from_secs(10)).data)
            .unwrap();
    assert_eq!(
        (
            eu["kind"].as_str(),
            eu["target"].as_u64(),
            eu["author"].as_str()
        ),
        (Some("undo"), Some(va), Some("alice"))
    );

    // Redo (undo of the undo): the volume after both edits again, byte for byte.
    let redo = w.ok(
        "POST",
        "/v1/volumes/w/undo",
        Some(&w.alice),
        Some(json!({"version": vu})),
    );
    assert_eq!(redo["replayed"], 1);
    assert_eq!(w.grids("w", None), w.grids("w", Some(&vb.to_string())));
    assert_eq!(
        w.level0_bytes("w", &redo["version"].to_string()),
        w.level0_bytes("w", &vb.to_string())
    );

    // A tag names a version; ?version=TAG reads it.
    w.ok(
        "PUT",
        "/v1/volumes/w/tags/start",
        Some(&w.alice),
        Some(json!({"version": v1})),
    );
    let tags = w.ok("GET", "/v1/volumes/w/tags", None, None);
    assert_eq!(tags["tags"][0]["tag"], "start");
    assert_eq!(tags["tags"][0]["version"], v1);
    assert_eq!(
        w.grids("w", Some("start")),
        w.grids("w", Some(&v1.to_string()))
    );
    w.json(
        "GET",
        "/v1/volumes/w/levels/0?version=nonesuch",
        None,
        None,
        StatusCode::NOT_FOUND,
    );
    w.json(
        "PUT",
        "/v1/volumes/w/tags/123",
        Some(&w.alice),
        Some(json!({"version": v1})),
        StatusCode::BAD_REQUEST,
    );
    let tag_version = w.ok("GET", "/v1/volumes/w", None, None)["version"]
        .as_u64()
        .unwrap();
    w.json(
        "POST",
        "/v1/volumes/w/undo",
        Some(&w.alice),
        Some(json!({"version": tag_version})),
        StatusCode::CONFLICT,
    );

    // A dry run says what would change and commits nothing.
    let dry = w.ok(
        "POST",
        "/v1/volumes/w/edits?dry_run=true",
        Some(BOB),
        Some(alice_edit()),
    );
    assert_eq!(dry["dry_run"], true);
    assert!(!dry["changed"][0].as_array().unwrap().is_empty(), "{dry}");
    assert_eq!(
        w.ok("GET", "/v1/volumes/w", None, None)["version"],
        tag_version
    );

    // Revert to the start: every brick as it was, byte for byte; dave (admin) may then undo
    // alice's edit even so... it is reverted away already.
    let revert = w.ok(
        "POST",
        "/v1/volumes/w/revert",
        Some(BOB),
        Some(json!({"to": v1, "message": "start over"})),
    );
    let vr = revert["version"].to_string();
    assert_eq!(
        w.level0_bytes("w", &vr),
        w.level0_bytes("w", &v1.to_string())
    );
    assert_eq!(w.grids("w", None), w.grids("w", Some(&v1.to_string())));
    let gone = w.json(
        "POST",
        "/v1/volumes/w/undo",
        Some(DAVE),
        Some(json!({"version": vb})),
        StatusCode::CONFLICT,
    );
    assert!(
        gone["detail"].as_str().unwrap().contains("reverted"),
        "{gone}"
    );

    // The history, newest first, tells it all.
    let history = w.ok("GET", "/v1/volumes/w/history?limit=10", None, None);
    let commits = history["commits"].as_array().unwrap();
    let kinds: Vec<&str> = commits.iter().filter_map(|c| c["kind"].as_str()).collect();
    assert_eq!(kinds, ["revert", "tag", "redo", "undo", "edit", "edit"]);
    assert_eq!(commits[0]["message"], "start over");
    let alices = commits.iter().find(|c| c["version"] == va).unwrap();
    assert_eq!(
        (alices["author"].as_str(), alices["undone"].as_bool()),
        (Some("alice"), Some(true))
    );
    let page = w.ok(
        "GET",
        &format!("/v1/volumes/w/history?before={vb}&limit=1"),
        None,
        None,
    );
    assert_eq!(page["commits"][0]["version"], va);
    assert_eq!(page["more"], true);
}

#[test]
fn only_authors_and_admins_undo_and_tokens_keep_to_their_volumes() {
    let w = world();
    let v1 = w.ok("GET", "/v1/volumes/w", None, None)["version"].to_string();
    let a = w.ok(
        "POST",
        "/v1/volumes/w/edits",
        Some(&w.alice),
        Some(alice_edit()),
    );
    // carol's token is for the volume `other` only.
    let carol = w.json(
        "POST",
        "/v1/volumes/w/edits",
        Some(CAROL),
        Some(bob_edit()),
        StatusCode::FORBIDDEN,
    );
    assert!(
        carol["detail"].as_str().unwrap().contains("carol"),
        "{carol}"
    );
    w.json(
        "POST",
        "/v1/volumes/w/undo",
        Some(CAROL),
        Some(json!({"version": a["version"]})),
        StatusCode::FORBIDDEN,
    );
    // dave, an admin, may undo alice's edit: the volume is as before it.
    let undo = w.ok(
        "POST",
        "/v1/volumes/w/undo",
        Some(DAVE),
        Some(json!({"version": a["version"]})),
    );
    assert_eq!(undo["replayed"], 0);
    assert_eq!(w.grids("w", None), w.grids("w", Some(&v1)));
    // Messages are short; versions must exist; a JWT for another audience is refused.
    let long = json!({"op": "union", "message": "x".repeat(201),
                      "term": {"cuboid": {"origin": [0, 0, 0], "size": [4, 4, 4]}}});
    w.json(
        "POST",
        "/v1/volumes/w/edits",
        Some(BOB),
        Some(long),
        StatusCode::BAD_REQUEST,
    );
    w.json(
        "POST",
        "/v1/volumes/w/undo",
        Some(BOB),
        Some(json!({"version": 999})),
        StatusCode::NOT_FOUND,
    );
    w.json(
        "POST",
        "/v1/volumes/w/revert",
        Some(BOB),
        Some(json!({"to": 999})),
        StatusCode::BAD_REQUEST,
    );
}

#[test]
fn presence_reaches_the_others_and_expires() {
    let w = world();
    let mut bobs_feed = w.subscribe("w");
    let here = json!({"position": [10.5, 20.0, 30.0], "looking": [32, 32, 32], "label": "alice"});
    let r = w.send("POST", "/v1/volumes/w/presence", Some(&w.alice), Some(here));
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    let seen: Value =
        serde_json::from_str(&next_named(&mut bobs_feed, "presence", Duration::from_secs(10)).data)
            .unwrap();
    assert_eq!(
        (seen["user"].as_str(), seen["position"][0].as_f64()),
        (Some("alice"), Some(10.5))
    );
    let list = w.ok("GET", "/v1/volumes/w/presence", None, None);
    assert_eq!(list["present"][0]["user"], "alice");
    // No token: 401; bursts beyond a few a second: 429; NaN is no position.
    let anonymous = w.send(
        "POST",
        "/v1/volumes/w/presence",
        None,
        Some(json!({"position": [0, 0, 0]})),
    );
    assert_eq!(anonymous.status(), StatusCode::UNAUTHORIZED);
    let bad = w.send(
        "POST",
        "/v1/volumes/w/presence",
        Some(BOB),
        Some(json!({"position": [0, 0, "x"]})),
    );
    assert_eq!(bad.status(), StatusCode::BAD_REQUEST);
    let statuses: Vec<StatusCode> = (0..12)
        .map(|i| {
            w.send(
                "POST",
                "/v1/volumes/w/presence",
                Some(BOB),
                Some(json!({"position": [i, 0, 0]})),
            )
            .status()
        })
        .collect();
    assert!(
        statuses.contains(&StatusCode::TOO_MANY_REQUESTS),
        "{statuses:?}"
    );
    // Silent for 10 s: announced gone, and no longer listed.
    let gone: Value = loop {
        let e: Value = serde_json::from_str(
            &next_named(&mut bobs_feed, "presence", Duration::from_secs(30)).data,
        )
        .unwrap();
        if e["user"] == "alice" && e["gone"] == true {
            break e;
        }
    };
    assert_eq!(gone["label"], "alice");
    let list = w.ok("GET", "/v1/volumes/w/presence", None, None);
    assert!(
        list["present"]
            .as_array()
            .unwrap()
            .iter()
            .all(|p| p["user"] != "alice"),
        "{list}"
    );
}
