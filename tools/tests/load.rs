//! The load tester against a real server on an ephemeral port: short runs with viewers and an
//! editor have no error, every acknowledged edit is announced to every subscriber and reaches
//! every streamer, and the per-route counts and bytes it reports agree with what the server's
//! own `/metrics` counted: exactly for a still camera; with moving cameras and edits the
//! streamers abort requests nobody needs any more, which the server may have counted and the
//! client never saw answered, so there the report's counts are bounded by the server's, and the
//! server's by the requests the streamers started.

#![allow(clippy::unwrap_used)] // tests fail loudly on purpose

use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::auth::Tokens;
use isovox_server::http::{spawn, AppState, ServerConfig, Spawned};
use isovox_server::store::{build_vod2, BuildOptions};
use isovox_tools::load::{run, LoadConfig, LoadReport, PathSpec, RecordedPath, Tiles};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

const TOKEN: &str = "0123456789abcdef0123";

struct Server {
    base: String,
    _server: Spawned,
    _dir: tempfile::TempDir,
}

/// A 128x64x128 u8 terrain, brick 16, served as "terrain" with a write token.
async fn start() -> Server {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("terrain.vod");
    let layout = VolumeLayout::new([128, 64, 128], 16, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &WorldSource::new(layout.clone(), 3),
        &BuildOptions::default(),
    )
    .unwrap();
    let catalog = Catalog::open_dir(dir.path()).unwrap();
    let state = AppState::with_config(
        catalog,
        ServerConfig {
            tokens: Tokens::parse(&format!(
                "t {TOKEN} write\n{}",
                (0..3)
                    .map(|i| format!("p{i} {} read", presence_token(i)))
                    .collect::<Vec<_>>()
                    .join("\n")
            ))
            .unwrap(),
            edit_rate: 1000.0,
            // Room for every request the streamers can have in flight (16 each, up to four
            // users here): these tests check what is counted, not shedding (the server's
            // overload tests do), and the default of eight per core sheds on a busy machine.
            cpu_queue: 64,
            ..Default::default()
        },
    );
    let server = spawn("127.0.0.1:0", state).await.unwrap();
    Server {
        base: server.base(),
        _server: server,
        _dir: dir,
    }
}

/// The read token of presence user `p{i}`.
fn presence_token(i: usize) -> String {
    format!("presence-user-token-{i:04}")
}

/// The server's route template for the client's route name.
fn template(route: &str) -> &'static str {
    match route {
        "volumes" => "/v1/volumes",
        "volume" => "/v1/volumes/{name}",
        "brick" => "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}",
        "blob" => "/v1/volumes/{name}/blobs/{hash}",
        "batch" => "/v1/volumes/{name}/batch",
        "level" => "/v1/volumes/{name}/levels/{level}",
        "mesh" => "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}",
        "strip" => "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}/strips/{face}",
        "edit" => "/v1/volumes/{name}/edits",
        "changes" => "/v1/volumes/{name}/changes",
        "events" => "/v1/volumes/{name}/events",
        other => panic!("a route the test does not know: {other}"),
    }
}

/// `/metrics`: requests by (route template, status), and the response bytes counted.
async fn server_metrics(base: &str) -> (BTreeMap<(String, String), u64>, u64) {
    isovox_server::client_tls::install_provider();
    let text = reqwest::get(format!("{base}/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let mut requests = BTreeMap::new();
    let mut bytes = None;
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("isovox_requests_total{route=\"") {
            let (route, rest) = rest.split_once("\",status=\"").unwrap();
            let (status, n) = rest.split_once("\"} ").unwrap();
            requests.insert((route.to_string(), status.to_string()), n.parse().unwrap());
        } else if let Some(n) = line.strip_prefix("isovox_response_bytes_total ") {
            bytes = Some(n.parse().unwrap());
        }
    }
    (requests, bytes.unwrap())
}

/// The routes a streamer requests (and may abort).
const STREAMER_ROUTES: [&str; 4] = ["level", "blob", "mesh", "strip"];

/// Everything a clean run must show, and the report's numbers against the server's.
async fn check(s: &Server, report: &LoadReport, users: usize) {
    check_run(report, users);

    // Edits: acknowledged, each its own version, each announced to every subscriber.
    let e = &report.edits;
    assert!(e.acknowledged > 0, "{e:?}");
    assert_eq!(e.failed, 0);
    assert_eq!(e.attempted, e.acknowledged);
    assert_eq!(e.carves + e.additions, e.attempted);
    assert_eq!(report.version_end - report.version_start, e.acknowledged);
    let n = &report.notifications;
    assert!(n.subscribers >= 1);
    assert_eq!(n.expected, e.acknowledged * n.subscribers as u64);
    assert_eq!(n.seen, n.expected, "{n:?}");
    assert_eq!(n.missing, 0);
    assert_eq!(n.latency_ms.samples, n.seen);
    assert!(n.latency_ms.max < 5000.0, "{n:?}");
    assert_eq!(n.from_send_ms.samples, n.seen);
    // Every streamer caught up with the last edit.
    let st = &report.streamers;
    assert_eq!(st.max_version, report.version_end, "{st:?}");
    assert_eq!(st.min_version, report.version_end, "{st:?}");
    assert!(st.version_events >= users as u64 * e.acknowledged);

    let edits = report.routes.iter().find(|r| r.route == "edit").unwrap();
    assert_eq!(edits.ok, e.acknowledged);

    // What the server counted: exactly the report's requests on the routes nothing cancels;
    // on the streamers' routes at least what the report saw answered, at most what the
    // streamers started, and never an error.
    let (counted, bytes) = server_metrics(&s.base).await;
    let reported = reported(report);
    let streamer_route = |t: &str| STREAMER_ROUTES.iter().any(|r| template(r) == t);
    let exact = |m: &BTreeMap<(String, String), u64>| -> BTreeMap<(String, String), u64> {
        m.iter()
            .filter(|((t, _), _)| !streamer_route(t))
            .map(|(k, v)| (k.clone(), *v))
            .collect()
    };
    assert_eq!(exact(&reported), exact(&counted));
    let mut started_seen = 0;
    for ((t, status), n) in &counted {
        if streamer_route(t) {
            assert!(status == "200" || status == "304", "{t} {status}");
            assert!(
                reported
                    .get(&(t.clone(), status.clone()))
                    .copied()
                    .unwrap_or(0)
                    <= *n
            );
            started_seen += n;
        }
    }
    for (k, n) in &reported {
        assert!(counted.get(k).is_some_and(|c| n <= c), "{k:?}");
    }
    assert!(
        started_seen <= st.requests,
        "{started_seen} > {}",
        st.requests
    );
    assert!(report.total.bytes <= bytes);
}

/// A clean run: no error, users streaming, figures that add up.
fn check_run(report: &LoadReport, users: usize) {
    println!("{}", report.to_markdown());
    assert_eq!(report.errors_total, 0, "{:?}", report.errors);
    assert!(report.errors.is_empty());
    let st = &report.streamers;
    assert_eq!(st.streamers, users);
    assert_eq!(st.failed_to_start, 0);
    assert_eq!(st.error_events, 0, "{:?}", st.error_samples);
    assert!(st.tiles_ready > 0);
    assert!(st.ready_bytes > 0);
    assert_eq!(st.ready_by_level.iter().sum::<u64>(), st.tiles_ready);
    assert!(st.cache_misses > 0);
    assert_eq!(report.radii, vec![24.0, 48.0, 96.0]);
    // Every viewer is counted once in each first-tile figure, and the tiles of the world's
    // surface within the radii are drawn by every viewer; a tile that draws is a tile, so
    // each viewer's first drawn tile comes no sooner than its first tile (and so does every
    // quantile over the viewers).
    let (tile, drawn) = (&st.first_tile_ms, &st.first_drawn_ms);
    assert_eq!(tile.samples + st.without_tile, users as u64);
    assert_eq!(drawn.samples + st.without_drawn, users as u64);
    assert_eq!(st.without_drawn, 0, "a viewer never drew the surface");
    assert!(drawn.p50 >= tile.p50 && drawn.p99 >= tile.p99 && drawn.max >= tile.max);

    // The report's figures add up.
    let sum =
        |f: fn(&isovox_tools::load::RouteReport) -> u64| report.routes.iter().map(f).sum::<u64>();
    assert_eq!(report.total.requests, sum(|r| r.requests));
    assert_eq!(report.total.bytes, sum(|r| r.bytes));
    assert_eq!(report.total.retried, sum(|r| r.retried));
    for r in report.routes.iter().chain([&report.total]) {
        assert_eq!(
            r.requests,
            r.ok + r.not_modified + r.retried + r.errors,
            "{r:?}"
        );
        assert_eq!(r.latency_ms.samples, r.requests);
        assert!(r.latency_ms.p50 <= r.latency_ms.p90);
        assert!(r.latency_ms.p90 <= r.latency_ms.p99);
        assert!(r.latency_ms.p99 <= r.latency_ms.max);
    }
}

/// The report's exchanges by (server route template, status).
fn reported(report: &LoadReport) -> BTreeMap<(String, String), u64> {
    let mut m = BTreeMap::new();
    for r in &report.routes {
        for (status, n) in &r.outcomes {
            m.insert((template(&r.route).to_string(), status.clone()), *n);
        }
    }
    m
}

fn config(s: &Server, viewers: usize, editors: usize, tiles: Tiles) -> LoadConfig {
    let mut c = LoadConfig::new(&s.base, "terrain");
    c.viewers = viewers;
    c.editors = editors;
    c.duration = Duration::from_millis(2500);
    c.token = Some(TOKEN.into());
    c.tiles = tiles;
    c.path = PathSpec::Orbit {
        radius: Some(40.0),
        height: Some(60.0),
        period_s: 3.0,
    };
    c.radii = Some(vec![24.0, 48.0, 96.0]);
    c.edit_rate = 8.0;
    c.seed = 11;
    c.drain = Duration::from_secs(10);
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_and_an_editor_on_bricks() {
    let s = start().await;
    let report = run(config(&s, 3, 1, Tiles::Bricks)).await.unwrap();
    check(&s, &report, 4).await;
    let bricks = report.routes.iter().find(|r| r.route == "blob").unwrap();
    assert!(bricks.requests > 0);
    // The JSON report has the same figures.
    let json: serde_json::Value = serde_json::to_value(&report).unwrap();
    assert_eq!(json["errors_total"], 0);
    assert_eq!(json["edits"]["acknowledged"], report.edits.acknowledged);
    assert_eq!(json["total"]["requests"], report.total.requests);
    assert!(json["total"]["latency_ms"]["p99"].as_f64().unwrap() > 0.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn random_walks_on_mesh_tiles() {
    let s = start().await;
    let mut c = config(&s, 2, 1, Tiles::Meshes { iso: None });
    c.path = PathSpec::RandomWalk {
        speed: Some(60.0),
        low: None,
        high: None,
    };
    c.ramp_up = Duration::from_secs(1);
    let report = run(c).await.unwrap();
    check(&s, &report, 3).await;
    let meshes = report.routes.iter().find(|r| r.route == "mesh").unwrap();
    assert!(meshes.requests > 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_still_camera_is_counted_exactly() {
    let s = start().await;
    let mut c = config(&s, 3, 0, Tiles::Bricks);
    c.path = PathSpec::Recorded(Arc::new(RecordedPath::parse("0 70 40 50").unwrap()));
    // Without the descent: it may cancel grid regions a coarser answer made unneeded (with it,
    // the server's counts and the report's differed here), and this test counts a run in which
    // no request is aborted.
    c.descent = false;
    let report = run(c).await.unwrap();
    check_run(&report, 3);
    // Nothing moves and nobody edits, so no request is ever aborted: what the server counted,
    // route by route and status by status, is what the report says (its requests are the only
    // ones this server saw), and so are the bytes; the streamers' own counts agree.
    let (counted, bytes) = server_metrics(&s.base).await;
    assert_eq!(reported(&report), counted);
    assert_eq!(report.total.bytes, bytes);
    let route = |name: &str| report.routes.iter().find(|r| r.route == name).unwrap();
    let st = &report.streamers;
    assert_eq!(
        st.requests,
        route("level").requests + route("blob").requests
    );
    assert_eq!(st.bytes, route("blob").bytes);
    assert_eq!(st.cache_misses, route("blob").requests);
    // Three streamers at one camera fetch the same tiles.
    assert_eq!(st.tiles_ready % 3, 0);
    assert_eq!(st.resident_at_end, st.tiles_ready);
    assert_eq!(report.version_end, report.version_start);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_budget_stops_the_run_early() {
    let s = start().await;
    let mut c = config(&s, 2, 0, Tiles::Bricks);
    c.duration = Duration::from_secs(60);
    c.max_requests = Some(50);
    // The second viewer would start after 15 s: the run ends before.
    c.ramp_up = Duration::from_secs(30);
    let started = std::time::Instant::now();
    let report = run(c).await.unwrap();
    assert!(started.elapsed() < Duration::from_secs(15));
    assert_eq!(report.errors_total, 0, "{:?}", report.errors);
    assert_eq!(report.streamers.streamers, 2);
    assert_eq!(report.streamers.failed_to_start, 0);
    assert_eq!(report.streamers.never_started, 1);
    assert!(report.total.requests >= 50);
    assert_eq!(report.edits.acknowledged, 0);
    assert_eq!(report.notifications.subscribers, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_say_where_they_are_and_subscribers_hear_it() {
    let s = start().await;
    let mut c = config(&s, 3, 1, Tiles::Bricks);
    // Three users, two messages a second each: under the server's five per user.
    c.presence_hz = 2.0;
    c.presence_tokens = (0..3).map(presence_token).collect();
    let report = run(c).await.unwrap();
    let p = report.presence.clone().expect("a presence report");
    let subscribers = 3; // min(viewers, 8) with an editor
    assert!(p.accepted >= 3, "{p:?}");
    assert_eq!((p.limited, p.failed), (0, 0), "{p:?}");
    assert_eq!(p.sent, p.accepted, "{p:?}");
    // Each subscriber hears each message once at most; they heard some.
    assert!(
        p.delivered > 0 && p.delivered <= p.accepted * subscribers,
        "{p:?}"
    );
    assert!(
        p.delay_p99_ms >= p.delay_p50_ms && p.delay_p50_ms > 0.0,
        "{p:?}"
    );
    assert!(report.to_markdown().contains("### Presence"));
    // One user for all three viewers at 10 a second each, three times the server's five a
    // second (bursts of five): it refuses some (429), and the report counts them (presence is
    // never retried, so a refusal is not hidden behind a later success).
    let mut c = config(&s, 3, 1, Tiles::Bricks);
    c.presence_hz = 10.0;
    c.seed = 12;
    let report = run(c).await.unwrap();
    let p = report.presence.unwrap();
    assert!(p.limited > 0, "{p:?}");
    assert_eq!(p.sent, p.accepted + p.limited + p.failed, "{p:?}");
}
