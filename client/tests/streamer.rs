#![allow(clippy::unwrap_used)] // tests fail loudly on purpose
//! The camera-distance streamer against a real server (the server's library, run in its own
//! runtime on a real socket): its selection against an independent computation, camera moves,
//! content deduplication, live updates from another client's edits (bricks and mesh tiles), and
//! catching up after the server went away and came back with new versions.
//!
//! Golden values come from elsewhere than the code under test: the selection from a brute force
//! over every tile of every level written here from the rule's statement; brick content and
//! hashes from the VOD 2 file itself; mesh tiles from the server's offline mesher on the file;
//! what an edit changed from the server's answer (or the offline edit's outcome); the balanced
//! selection and the face masks from a raster of level-0 bricks; closedness of the streamed,
//! stitched meshes from the welded assembly.

use isovox_client::proto::api::VolumeInfo;
use isovox_client::proto::icvg::{EditRequest, Term};
use isovox_client::proto::mesh::{
    decode_strip, decode_tile, encode_compact, encode_tile, stitch, Mesh, TileMesh,
};
use isovox_client::proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_client::{
    select_stitched_tiles, select_tiles, Client, Observer, StreamEvent, Streamer, StreamerConfig,
    TileData, TileKind,
};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::auth::Tokens;
use isovox_server::http::{run, AppState, ServerConfig};
use isovox_server::store::{build_vod2, BuildOptions, Snapshot, Vod2};
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc::Receiver;

const TOKEN: &str = "0123456789abcdef0123";
const NAME: &str = "w";

// ---------------------------------------------------------------------------------------------
// The server
// ---------------------------------------------------------------------------------------------

/// A world volume `w.vod` in a fresh directory.
struct World {
    dir: tempfile::TempDir,
    path: PathBuf,
    source: WorldSource,
}

fn world(dims: [u32; 3], brick: u32, scale: [f32; 3]) -> World {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(format!("{NAME}.vod"));
    let layout = VolumeLayout::new(dims, brick, VoxelType::U8).unwrap();
    let source = WorldSource::new(layout.clone(), 3);
    build_vod2(&path, &layout, scale, &source, &BuildOptions::default()).unwrap();
    World { dir, path, source }
}

/// `isovox serve` in-process: the server's library in its own runtime (its own threads), on a
/// real socket. Stopping it shuts that runtime down, which closes every connection at once, as
/// a killed process would.
struct TestServer {
    base: String,
    addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl TestServer {
    /// Serves every volume of `dir` on `addr` (an ephemeral port when `None`), with one write
    /// token.
    fn start(dir: &Path, addr: Option<SocketAddr>) -> TestServer {
        TestServer::start_with(dir, addr, ServerConfig::default())
    }

    /// [`TestServer::start`] with `config` (its tokens replaced by the one write token).
    fn start_with(dir: &Path, addr: Option<SocketAddr>, config: ServerConfig) -> TestServer {
        let dir = dir.to_path_buf();
        let (addr_tx, addr_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .unwrap();
            rt.block_on(async move {
                let socket = tokio::net::TcpSocket::new_v4().unwrap();
                socket.set_reuseaddr(true).unwrap();
                socket
                    .bind(addr.unwrap_or_else(|| "127.0.0.1:0".parse().unwrap()))
                    .unwrap();
                let listener = socket.listen(1024).unwrap();
                addr_tx.send(listener.local_addr().unwrap()).unwrap();
                let config = ServerConfig {
                    tokens: Tokens::parse(&format!("t {TOKEN} write")).unwrap(),
                    ..config
                };
                let state = AppState::with_config(Catalog::open_dir(&dir).unwrap(), config);
                tokio::select! {
                    r = run(listener, state, std::future::pending()) => r.unwrap(),
                    _ = stop_rx => {}
                }
            });
            rt.shutdown_timeout(Duration::from_secs(10));
        });
        let addr = addr_rx.recv().unwrap();
        TestServer {
            base: format!("http://{addr}"),
            addr,
            stop: Some(stop_tx),
            thread: Some(thread),
        }
    }

    fn stop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            t.join().unwrap();
        }
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Counts a client's HTTP exchanges by route.
#[derive(Debug, Default)]
struct Counter(Mutex<HashMap<&'static str, u64>>);

impl Observer for Counter {
    fn exchange(&self, route: &'static str, _: Result<u16, &str>, _: Duration, _: u64, _: bool) {
        *self.0.lock().unwrap().entry(route).or_default() += 1;
    }
}

impl Counter {
    fn snapshot(&self) -> HashMap<&'static str, u64> {
        self.0.lock().unwrap().clone()
    }

    /// Exchanges of `route` since `before`.
    fn since(&self, before: &HashMap<&'static str, u64>, route: &str) -> u64 {
        let now = self.snapshot();
        now.get(route).copied().unwrap_or(0) - before.get(route).copied().unwrap_or(0)
    }
}

/// A streamer of `kind` tiles within `radii` that fetches every tile of its desired set (the
/// descent and the skipping of empty mesh tiles have their own tests) and follows no edits.
fn every_tile(kind: TileKind, radii: &[f32]) -> StreamerConfig {
    StreamerConfig {
        kind,
        radii: radii.to_vec(),
        follow_edits: false,
        descent: false,
        skip_empty: false,
        ..StreamerConfig::default()
    }
}

fn counted_client(base: &str) -> (Client, Arc<Counter>) {
    let counter = Arc::new(Counter::default());
    isovox_server::client_tls::install_provider();
    let client = Client::new(base).unwrap().with_observer(counter.clone());
    (client, counter)
}

/// Drains events until the streamer is idle at `version` or later (for the current camera).
async fn settle(s: &Streamer, rx: &mut Receiver<StreamEvent>, version: u64) -> Vec<StreamEvent> {
    let mut out = Vec::new();
    let wait = s.wait_version(version);
    tokio::pin!(wait);
    let deadline = tokio::time::sleep(Duration::from_secs(120));
    tokio::pin!(deadline);
    loop {
        tokio::select! {
            biased;
            Some(e) = rx.recv() => out.push(e),
            () = &mut wait => break,
            () = &mut deadline => panic!(
                "the streamer did not settle at version {version} within 120 s; stats {:?}, last events {:?}",
                s.stats(),
                out.iter().rev().take(5).collect::<Vec<_>>()
            ),
        }
    }
    while let Ok(e) = rx.try_recv() {
        out.push(e);
    }
    out
}

/// Asserts that no event of `events` is an error.
fn assert_no_errors(events: &[StreamEvent]) {
    assert!(events
        .iter()
        .all(|e| !matches!(e, StreamEvent::Error { .. })));
}

fn ready_keys(events: &[StreamEvent]) -> Vec<BrickKey> {
    events
        .iter()
        .filter_map(|e| match e {
            StreamEvent::Ready { key, .. } => Some(*key),
            _ => None,
        })
        .collect()
}

fn dropped_keys(events: &[StreamEvent]) -> Vec<BrickKey> {
    events
        .iter()
        .filter_map(|e| match e {
            StreamEvent::Dropped { key } => Some(*key),
            _ => None,
        })
        .collect()
}

fn stale_keys(events: &[StreamEvent]) -> Vec<BrickKey> {
    events
        .iter()
        .filter_map(|e| match e {
            StreamEvent::Stale { key, .. } => Some(*key),
            _ => None,
        })
        .collect()
}

/// The keys as a set, asserting none appears twice.
fn once(keys: &[BrickKey], what: &str) -> BTreeSet<BrickKey> {
    let set: BTreeSet<BrickKey> = keys.iter().copied().collect();
    assert_eq!(set.len(), keys.len(), "a key {what} twice");
    set
}

// ---------------------------------------------------------------------------------------------
// The selection, computed independently
// ---------------------------------------------------------------------------------------------

/// Distance (f64) from `camera` to the box of tile (level, p): the brick's cell, `brick * 2^level`
/// level-0 voxels per side, times the voxel scale.
fn box_distance(info: &VolumeInfo, level: usize, p: [u32; 3], camera: [f32; 3]) -> f64 {
    let span = info.brick as f64 * (1u64 << level) as f64;
    let mut d2 = 0.0;
    for a in 0..3 {
        let s = info.voxel_scale[a] as f64;
        let lo = p[a] as f64 * span * s;
        let hi = (p[a] as f64 + 1.0) * span * s;
        let c = camera[a] as f64;
        let d = (lo - c).max(0.0).max(c - hi);
        d2 += d * d;
    }
    d2.sqrt()
}

/// The spherical detail bias by brute force over every tile of every level: with radii
/// r0 < ... < r(n-1), a tile of level j > 0 is refined (replaced by its children) when j > n or
/// its box lies within r(j-1) of the camera; a tile is selected when it is not refined and every
/// tile above it (its ancestors, up to the single root) is.
fn expected_set(info: &VolumeInfo, camera: [f32; 3], radii: &[f32]) -> BTreeSet<BrickKey> {
    let n = radii.len();
    let top = info.levels.len() - 1;
    let refined = |level: usize, p: [u32; 3]| {
        level > n || (level > 0 && box_distance(info, level, p, camera) <= radii[level - 1] as f64)
    };
    let mut out = BTreeSet::new();
    for level in 0..=top {
        let g = info.levels[level].grid;
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    let p = [x, y, z];
                    let ancestors_refined =
                        (level + 1..=top).all(|j| refined(j, p.map(|c| c >> (j - level))));
                    if !refined(level, p) && ancestors_refined {
                        out.insert(BrickKey {
                            level: level as u8,
                            x,
                            y,
                            z,
                        });
                    }
                }
            }
        }
    }
    out
}

/// Every level-0 brick is covered by exactly one selected tile.
fn assert_covers_once(info: &VolumeInfo, set: &BTreeSet<BrickKey>) {
    let g = info.levels[0].grid;
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                let covering = (0..info.levels.len())
                    .filter(|&l| {
                        set.contains(&BrickKey {
                            level: l as u8,
                            x: x >> l,
                            y: y >> l,
                            z: z >> l,
                        })
                    })
                    .count();
                assert_eq!(
                    covering, 1,
                    "level-0 brick {x},{y},{z} covered {covering} times"
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 1. The selected set, and the streamed bricks
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn selection_matches_independent_computation_and_streams_the_file_bricks() {
    // Extents in world units: 64 x 48 x 96; grids 16x8x12, 8x4x6, 4x2x3, 2x1x2, 1x1x1.
    let w = world([128, 64, 96], 8, [0.5, 0.75, 1.0]);
    let server = TestServer::start(w.dir.path(), None);
    let (client, counter) = counted_client(&server.base);
    let info = client.volume(NAME).await.unwrap();
    assert_eq!(info.levels.len(), 5);

    let cases: Vec<([f32; 3], Vec<f32>)> = vec![
        ([10.3, 20.1, 30.7], vec![9.5, 21.3, 40.2, 80.9]),
        ([-20.2, 5.5, 50.1], vec![12.1, 30.3]),
        ([61.7, 47.1, 3.3], vec![4.1, 17.9, 33.3]),
        ([33.3, 100.7, 48.9], vec![]),
        ([200.0, -50.0, 400.0], vec![5.0, 10.0, 20.0, 40.0]),
    ];
    for (camera, radii) in &cases {
        let expected = expected_set(&info, *camera, radii);
        let got: Vec<BrickKey> = select_tiles(&info, *camera, radii);
        assert!(got.windows(2).all(|w| w[0] < w[1]), "sorted, no duplicates");
        assert_eq!(
            got.iter().copied().collect::<BTreeSet<_>>(),
            expected,
            "camera {camera:?} radii {radii:?}"
        );
        assert_covers_once(&info, &expected);
    }
    // The shapes the cases were chosen for.
    assert_eq!(
        select_tiles(&info, cases[3].0, &cases[3].1).len(),
        16 * 8 * 12
    );
    assert_eq!(
        select_tiles(&info, cases[4].0, &cases[4].1),
        vec![BrickKey {
            level: 4,
            x: 0,
            y: 0,
            z: 0
        }]
    );
    let levels_used: BTreeSet<u8> = select_tiles(&info, cases[0].0, &cases[0].1)
        .iter()
        .map(|k| k.level)
        .collect();
    assert!(
        levels_used.len() >= 3,
        "the first case mixes levels: {levels_used:?}"
    );

    // Radii from a screen-space error: r_k = 2^(k+1) s H / (2 tan(fov/2) e), s the largest
    // voxel-scale component; one per level but the coarsest.
    let fov = 50f32.to_radians();
    let radii = StreamerConfig::radii_for_screen_error(&info, fov, 720.0, 8.0);
    assert_eq!(radii.len(), info.levels.len() - 1);
    for (k, r) in radii.iter().enumerate() {
        let want = 2f64.powi(k as i32 + 1) * 1.0 * 720.0 / (2.0 * (25f64.to_radians()).tan() * 8.0);
        assert!(
            ((*r as f64) - want).abs() < 1e-3 * want,
            "r_{k} = {r}, want {want}"
        );
    }
    let expected = expected_set(&info, [5.0, 30.0, 5.0], &radii);
    assert_eq!(
        select_tiles(&info, [5.0, 30.0, 5.0], &radii),
        expected.iter().copied().collect::<Vec<_>>()
    );
    // Radii from a screen-space error double per level, so their selection needs no balancing
    // (`lod::radii_keep_balance`: each exceeds the one before by 1.01 tile diagonals) while
    // H / (2 tan(fov/2) e) > 1.01 * 8 sqrt(0.5^2 + 0.75^2 + 1^2) = 10.878, that is for a
    // 1080-pixel, 60-degree view while the error e is under 85.98 pixels.
    let layout = VolumeLayout::new(info.dims, info.brick, info.voxel_type).unwrap();
    let balanced_for = |error_px: f32| {
        let radii =
            StreamerConfig::radii_for_screen_error(&info, 60f32.to_radians(), 1080.0, error_px);
        isovox_client::proto::lod::radii_keep_balance(&layout, info.voxel_scale, [0.0; 3], &radii)
    };
    assert!(balanced_for(1.0) && balanced_for(16.0) && balanced_for(85.0));
    assert!(!balanced_for(87.0));
    let defaults = StreamerConfig::default();
    assert_eq!(defaults.kind, TileKind::Bricks);
    assert!(defaults.radii.is_empty());
    assert_eq!(
        (defaults.max_in_flight, defaults.cache_bytes),
        (16, 256 << 20)
    );
    assert!(defaults.follow_edits);
    // The descent is on unless asked otherwise, and without it empty mesh tiles are skipped
    // (see `StreamerConfig::descent` and `skip_empty`).
    assert!(defaults.descent && defaults.skip_empty);

    // The streamer's resident set for the first case, and every delivered brick is the file's.
    let (camera, radii) = &cases[0];
    let expected = expected_set(&info, *camera, radii);
    let (streamer, mut rx) = Streamer::start(
        client.clone(),
        NAME,
        StreamerConfig {
            radii: radii.clone(),
            max_in_flight: 4,
            // The whole desired set, every tile fetched (the descent has its own tests).
            descent: false,
            ..StreamerConfig::default()
        },
    )
    .await
    .unwrap();
    assert_eq!(streamer.info(), &info);
    // A viewer can wait from a spawned task.
    fn is_send<T: Send>(_: &T) {}
    is_send(&streamer.wait_idle());
    is_send(&streamer);
    streamer.set_camera(*camera);
    let start = Instant::now();
    let events = settle(&streamer, &mut rx, 1).await;
    let elapsed = start.elapsed();
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        expected
    );
    assert_eq!(once(&ready_keys(&events), "was ready"), expected);
    assert!(dropped_keys(&events).is_empty() && stale_keys(&events).is_empty());
    assert_no_errors(&events);
    let vod = Vod2::open(&w.path).unwrap();
    let snap = vod.head();
    assert_bricks_match_file(&events, &snap);
    for e in &events {
        if let StreamEvent::Ready { version, .. } = e {
            assert_eq!(*version, 1);
        }
    }
    let stats = streamer.stats();
    assert_eq!(stats.resident, expected.len());
    assert_eq!(stats.in_flight, 0);
    assert_eq!(stats.version, 1);
    // Every blob fetched was needed: one per distinct hash of the set.
    let distinct: HashSet<u64> = expected.iter().map(|&k| snap.hash(k).unwrap()).collect();
    assert_eq!(
        counter.snapshot().get("blob").copied(),
        Some(distinct.len() as u64)
    );
    assert_eq!(counter.snapshot().get("brick"), None);
    eprintln!(
        "streamed {} tiles ({} distinct) in {elapsed:?}: {stats:?}",
        expected.len(),
        distinct.len()
    );
    streamer.shutdown().await;
}

// ---------------------------------------------------------------------------------------------
// 2. Moving the camera
// ---------------------------------------------------------------------------------------------

/// The camera tests' streamer: a 128 x 64 x 96 world of anisotropic voxels, radii 6.5 to 61.1,
/// the whole desired set fetched (the descent has its own tests). Returns the world and server
/// to keep them alive, and the radii.
async fn camera_test_streamer() -> (World, TestServer, Streamer, Receiver<StreamEvent>, Vec<f32>) {
    let w = world([128, 64, 96], 8, [0.5, 0.75, 1.0]);
    let server = TestServer::start(w.dir.path(), None);
    let (client, _) = counted_client(&server.base);
    let radii = vec![6.5, 14.3, 29.9, 61.1];
    let config = StreamerConfig {
        radii: radii.clone(),
        descent: false,
        ..StreamerConfig::default()
    };
    let (streamer, rx) = Streamer::start(client, NAME, config).await.unwrap();
    (w, server, streamer, rx, radii)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn moving_the_camera_drops_and_adds_the_right_tiles() {
    let (_w, _server, streamer, mut rx, radii) = camera_test_streamer().await;
    let info = streamer.info().clone();
    let a = [8.2, 20.3, 12.7];
    let b = [50.9, 30.1, 70.3];
    streamer.set_camera(a);
    settle(&streamer, &mut rx, 1).await;
    let set_a = expected_set(&info, a, &radii);
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        set_a
    );

    streamer.set_camera(b);
    let events = settle(&streamer, &mut rx, 1).await;
    let set_b = expected_set(&info, b, &radii);
    let old_minus_new: BTreeSet<BrickKey> = set_a.difference(&set_b).copied().collect();
    let new_minus_old: BTreeSet<BrickKey> = set_b.difference(&set_a).copied().collect();
    assert!(!old_minus_new.is_empty() && !new_minus_old.is_empty());
    assert!(set_a.intersection(&set_b).count() > 0, "some tiles stay");
    assert_eq!(once(&dropped_keys(&events), "was dropped"), old_minus_new);
    assert_eq!(once(&ready_keys(&events), "was ready"), new_minus_old);
    assert!(stale_keys(&events).is_empty());
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        set_b
    );

    // Quick moves without waiting: requests for tiles that left the set are cancelled and never
    // delivered after they left; the end state is the last camera's set.
    let path: Vec<[f32; 3]> = (0..12)
        .map(|i| {
            let t = i as f32 / 11.0;
            [50.9 - 45.0 * t, 30.1 - 10.0 * t, 70.3 - 60.0 * t]
        })
        .collect();
    let mut events = Vec::new();
    for c in &path {
        streamer.set_camera(*c);
        tokio::time::sleep(Duration::from_millis(3)).await;
        while let Ok(e) = rx.try_recv() {
            events.push(e);
        }
    }
    events.extend(settle(&streamer, &mut rx, 1).await);
    let last = expected_set(&info, path[path.len() - 1], &radii);
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        last
    );
    // Per key, events alternate Ready / Dropped starting from the state at camera b, and end
    // resident exactly for the last set.
    let mut shown: BTreeSet<BrickKey> = set_b.clone();
    for e in &events {
        match e {
            StreamEvent::Ready { key, .. } => assert!(shown.insert(*key), "{key} ready twice"),
            StreamEvent::Dropped { key } => assert!(shown.remove(key), "{key} dropped unshown"),
            StreamEvent::Stale { .. } => panic!("nothing was edited"),
            _ => {}
        }
    }
    assert_eq!(shown, last);
    streamer.shutdown().await;
}

/// Moves shorter than an eighth of the finest radius are selected once the camera rests (a
/// streamer selects them late, not never): the resident set ends exactly the one of the
/// camera's last position, after one small move that changes the set and after many that
/// each stay short but add up.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn small_camera_moves_are_selected_once_the_camera_rests() {
    let (_w, _server, streamer, mut rx, radii) = camera_test_streamer().await;
    let info = streamer.info().clone();
    // Two points a twentieth of a unit apart (an eighth of the finest radius is 0.8) whose
    // sets differ: the first along x from (8.2, 20.3, 12.7) where the set changes.
    let at = |i: u32| [8.2 + 0.05 * i as f32, 20.3, 12.7];
    let i = (0..400)
        .find(|&i| expected_set(&info, at(i), &radii) != expected_set(&info, at(i + 1), &radii))
        .expect("the set never changes along x");
    let (a, small) = (at(i), at(i + 1));
    streamer.set_camera(a);
    settle(&streamer, &mut rx, 1).await;
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        expected_set(&info, a, &radii)
    );
    streamer.set_camera(small);
    settle(&streamer, &mut rx, 1).await;
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        expected_set(&info, small, &radii)
    );
    // Forty steps of a tenth of a unit, one every 5 ms: each short, together four units.
    let mut c = small;
    for _ in 0..40 {
        c[2] += 0.1;
        streamer.set_camera(c);
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    settle(&streamer, &mut rx, 1).await;
    let last = expected_set(&info, c, &radii);
    assert_ne!(last, expected_set(&info, small, &radii));
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        last
    );
    streamer.shutdown().await;
}

// ---------------------------------------------------------------------------------------------
// 3. Content deduplication, and the byte bound of the cache
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_brick_shared_by_many_positions_is_fetched_once() {
    let w = world([128, 64, 96], 8, [0.5, 0.75, 1.0]);
    let server = TestServer::start(w.dir.path(), None);
    let (client, counter) = counted_client(&server.base);
    // Default radii: derived for 1 px at 1080 px and 60 degrees, far larger than this volume,
    // so the whole level 0 is selected. Every tile fetched: no descent.
    let config = StreamerConfig {
        descent: false,
        ..StreamerConfig::default()
    };
    let (streamer, mut rx) = Streamer::start(client, NAME, config).await.unwrap();
    let info = streamer.info().clone();
    assert_eq!(
        streamer.radii(),
        StreamerConfig::radii_for_screen_error(&info, 60f32.to_radians(), 1080.0, 1.0)
    );
    let camera = [30.0, 40.0, 50.0];
    streamer.set_camera(camera);
    let events = settle(&streamer, &mut rx, 1).await;
    let expected = expected_set(&info, camera, streamer.radii());
    assert!(expected.iter().all(|k| k.level == 0));
    assert_eq!(expected.len(), 16 * 8 * 12);
    assert_eq!(once(&ready_keys(&events), "was ready"), expected);

    let snap = Vod2::open(&w.path).unwrap().head();
    let distinct: HashSet<u64> = expected.iter().map(|&k| snap.hash(k).unwrap()).collect();
    assert!(
        distinct.len() * 2 < expected.len(),
        "the world shares content: {} distinct of {}",
        distinct.len(),
        expected.len()
    );
    let blobs = counter.snapshot().get("blob").copied().unwrap_or(0);
    assert_eq!(
        blobs,
        distinct.len() as u64,
        "one blob request per distinct hash"
    );
    let stats = streamer.stats();
    assert_eq!(stats.cache_misses, distinct.len() as u64);
    assert_eq!(stats.cache_hits, (expected.len() - distinct.len()) as u64);
    assert_bricks_match_file(&events, &snap);
    streamer.shutdown().await;

    // A cache of 5 bricks holds at most 5 bricks' bytes, and every tile is still delivered right.
    let (client, _) = counted_client(&server.base);
    let brick_bytes = 8 * 8 * 8;
    let (small, mut rx) = Streamer::start(
        client,
        NAME,
        StreamerConfig {
            cache_bytes: 5 * brick_bytes,
            radii: vec![10.0, 20.0],
            // The whole desired set, every tile fetched (the descent has its own tests).
            descent: false,
            ..StreamerConfig::default()
        },
    )
    .await
    .unwrap();
    small.set_camera(camera);
    let events = settle(&small, &mut rx, 1).await;
    let expected = expected_set(&info, camera, &[10.0, 20.0]);
    assert_eq!(once(&ready_keys(&events), "was ready"), expected);
    assert_bricks_match_file(&events, &snap);
    let stats = small.stats();
    assert!(stats.cache_bytes <= 5 * brick_bytes, "{stats:?}");
    assert!(stats.cache_bytes > 0);
    small.shutdown().await;
}

// ---------------------------------------------------------------------------------------------
// 4. Live updates
// ---------------------------------------------------------------------------------------------

fn carve(center: [i64; 3], r: u32) -> EditRequest {
    EditRequest {
        op: "difference".into(),
        term: Some(Term::Ellipsoid {
            center,
            radii: [r, r, r],
        }),
        s_l: None,
        k: None,
        region: None,
        message: None,
        channel: None,
        overwrite: None,
    }
}

/// A point on the terrain's surface (level-0 voxels).
fn ground(w: &World, x: u32, z: u32) -> [i64; 3] {
    [x as i64, w.source.height(x, z).round() as i64, z as i64]
}

/// Checks every `Ready` brick of `events` against the file's version `snap`: its voxels and its
/// content hash. Returns the hashes delivered.
fn assert_bricks_match_file(events: &[StreamEvent], snap: &Snapshot) -> HashSet<u64> {
    let mut hashes = HashSet::new();
    for e in events {
        if let StreamEvent::Ready {
            key, data, hash, ..
        } = e
        {
            let TileData::Brick(bytes) = data else {
                panic!("a brick streamer delivered a mesh");
            };
            assert_eq!(
                bytes.as_ref(),
                snap.read(*key).unwrap().as_slice(),
                "brick {key}"
            );
            assert_eq!(*hash, snap.hash(*key).unwrap(), "hash of {key}");
            hashes.insert(*hash);
        }
    }
    hashes
}

/// A served terrain of `dims` (brick 8), a counted client's streamer on it as `config` says,
/// its camera `above` voxels over the ground at (x, z), settled at version 1.
struct Scenario {
    w: World,
    server: TestServer,
    counter: Arc<Counter>,
    streamer: Streamer,
    rx: Receiver<StreamEvent>,
    camera: [f32; 3],
    /// The events up to the first settled state.
    before: Vec<StreamEvent>,
}

async fn scenario(
    dims: [u32; 3],
    config: StreamerConfig,
    (x, z): (u32, u32),
    above: f32,
) -> Scenario {
    let w = world(dims, 8, [1.0; 3]);
    let server = TestServer::start(w.dir.path(), None);
    let (client, counter) = counted_client(&server.base);
    let (streamer, mut rx) = Streamer::start(client, NAME, config).await.unwrap();
    let g = ground(&w, x, z);
    let camera = [x as f32, g[1] as f32 + above, z as f32];
    streamer.set_camera(camera);
    let before = settle(&streamer, &mut rx, 1).await;
    Scenario {
        w,
        server,
        counter,
        streamer,
        rx,
        camera,
        before,
    }
}

/// The bricks an edit changed, as keys.
fn changed_keys(changed: &[Vec<[u32; 3]>]) -> BTreeSet<BrickKey> {
    changed
        .iter()
        .enumerate()
        .flat_map(|(l, ps)| {
            ps.iter().map(move |p| BrickKey {
                level: l as u8,
                x: p[0],
                y: p[1],
                z: p[2],
            })
        })
        .collect()
}

/// Mesh tiles whose own inputs include a changed brick (brick 8), per `server/src/mesh/tile.rs`:
/// tile (x, y, z) reads the bricks at offsets -1..=1 around it at its level.
fn mesh_readers(changed: &BTreeSet<BrickKey>) -> BTreeSet<BrickKey> {
    let mut out = BTreeSet::new();
    for b in changed {
        for dz in -1i64..=1 {
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    let c = [b.x as i64 + dx, b.y as i64 + dy, b.z as i64 + dz];
                    if c.iter().all(|&v| v >= 0) {
                        out.insert(BrickKey {
                            level: b.level,
                            x: c[0] as u32,
                            y: c[1] as u32,
                            z: c[2] as u32,
                        });
                    }
                }
            }
        }
    }
    out
}

/// Whether the transition strip of face `face` of tile `t` (brick 8) reads brick `b`, per
/// `server/src/mesh/tile.rs`. Of the tile's level, the layer of cells along the face: on the
/// face's axis lattice points 8 t + 6 ..= 8 t + 9 on a high face, 8 t - 1 ..= 8 t + 2 on a low
/// one, across it the tile's field 8 t - 1 ..= 8 t + 9 (from -2 for a first tile). Of the next
/// coarser level, stored voxels: on the face's axis the plane 4 t + 4 (high) or 4 t (low) and
/// one lattice point on either side, 2 below and 1 above for the interpolation: 4 t + 1 ..=
/// 4 t + 6 or 4 t - 3 ..= 4 t + 2; across it 4 t - 3 ..= 4 t + 6 (from -4 for a first tile).
fn strip_reads_brick(t: BrickKey, face: usize, b: BrickKey) -> bool {
    let tp = [t.x, t.y, t.z].map(i64::from);
    let bp = [b.x, b.y, b.z].map(i64::from);
    let axis = face / 2;
    let high = face % 2 == 1;
    let within = |lo: i64, hi: i64, p: i64| lo.div_euclid(8) <= p && p <= hi.div_euclid(8);
    if b.level == t.level {
        (0..3).all(|a| {
            let t = tp[a];
            let (lo, hi) = match (a == axis, high) {
                (true, true) => (8 * t + 6, 8 * t + 9),
                (true, false) => (8 * t - 1, 8 * t + 2),
                _ => (if t == 0 { -2 } else { 8 * t - 1 }, 8 * t + 9),
            };
            within(lo, hi, bp[a])
        })
    } else if b.level == t.level + 1 {
        (0..3).all(|a| {
            let t = tp[a];
            let (lo, hi) = match (a == axis, high) {
                (true, true) => (4 * t + 1, 4 * t + 6),
                (true, false) => (4 * t - 3, 4 * t + 2),
                _ => (if t == 0 { -4 } else { 4 * t - 3 }, 4 * t + 6),
            };
            within(lo, hi, bp[a])
        })
    } else {
        false
    }
}

/// The strips (tile, face) of the resident tiles' masks that read a changed brick.
fn strip_readers(
    info: &VolumeInfo,
    resident: &BTreeSet<BrickKey>,
    changed: &BTreeSet<BrickKey>,
) -> BTreeSet<(BrickKey, usize)> {
    let mut out = BTreeSet::new();
    for &t in resident {
        let mask = expected_mask(info, resident, t);
        for face in (0..6).filter(|f| mask >> f & 1 == 1) {
            if changed.iter().any(|&b| strip_reads_brick(t, face, b)) {
                out.insert((t, face));
            }
        }
    }
    out
}

/// Asserts the events after an edit: exactly `expected` went stale and came back ready, each
/// Stale before its Ready, and the version was announced.
fn assert_stale_then_ready(events: &[StreamEvent], expected: &BTreeSet<BrickKey>, version: u64) {
    let stale: BTreeSet<BrickKey> = stale_keys(events).into_iter().collect();
    assert_eq!(&stale, expected, "the stale tiles");
    assert_eq!(
        &once(&ready_keys(events), "was ready"),
        expected,
        "the refetched tiles"
    );
    assert!(dropped_keys(events).is_empty());
    let position = |want: &dyn Fn(&StreamEvent) -> bool| events.iter().position(want);
    for key in expected {
        let s = position(&|e| matches!(e, StreamEvent::Stale { key: k, .. } if k == key));
        let r = position(&|e| matches!(e, StreamEvent::Ready { key: k, .. } if k == key));
        assert!(s.unwrap() < r.unwrap(), "{key}: Stale before Ready");
    }
    for e in events {
        match e {
            StreamEvent::Stale { version: v, .. } => assert!(*v <= version && *v > 1),
            StreamEvent::Ready { version: v, .. } => assert_eq!(*v, version),
            _ => {}
        }
    }
    assert!(events
        .iter()
        .any(|e| matches!(e, StreamEvent::Version { version: v } if *v == version)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edit_by_another_client_refetches_exactly_the_affected_bricks() {
    // Grids 12x8x12, 6x4x6, 3x2x3, 2x1x2, 1x1x1.
    let radii = vec![12.0, 30.0, 60.0, 120.0];
    let config = StreamerConfig {
        radii: radii.clone(),
        // The whole desired set, every tile fetched (the descent has its own tests).
        descent: false,
        ..StreamerConfig::default()
    };
    let Scenario {
        w,
        server,
        counter,
        streamer,
        mut rx,
        camera,
        before,
    } = scenario([96, 64, 96], config, (30, 40), 4.0).await;
    let resident: BTreeSet<BrickKey> = streamer.resident().into_iter().collect();
    assert_eq!(resident, expected_set(streamer.info(), camera, &radii));
    let cached: HashSet<u64> = before
        .iter()
        .filter_map(|e| match e {
            StreamEvent::Ready { hash, .. } => Some(*hash),
            _ => None,
        })
        .collect();

    isovox_server::client_tls::install_provider();
    let editor = Client::new(&server.base).unwrap().with_token(TOKEN);
    let counts = counter.snapshot();
    let resp = editor
        .edit(NAME, &carve(ground(&w, 46, 40), 8), None)
        .await
        .unwrap();
    assert_eq!(resp.version, 2);
    let changed = changed_keys(&resp.changed);
    let expected: BTreeSet<BrickKey> = resident.intersection(&changed).copied().collect();
    assert!(
        expected.iter().any(|k| k.level == 0) && expected.iter().any(|k| k.level > 0),
        "the edit reaches resident tiles of several levels: {expected:?}"
    );
    assert!(
        resident.len() > expected.len() + 10,
        "most tiles are untouched"
    );

    let events = settle(&streamer, &mut rx, resp.version).await;
    assert_stale_then_ready(&events, &expected, resp.version);
    let snap = Vod2::open(&w.path).unwrap().head();
    let new_hashes = assert_bricks_match_file(&events, &snap);
    assert!(
        new_hashes.iter().any(|h| !cached.contains(h)),
        "new content"
    );
    // No other tile refetched: one blob per new content not cached before, nothing by position,
    // and no grid region: the change event listed the changed bricks' new hashes.
    assert_eq!(
        counter.since(&counts, "blob"),
        new_hashes.difference(&cached).count() as u64
    );
    assert_eq!(counter.since(&counts, "brick"), 0);
    assert_eq!(counter.since(&counts, "mesh"), 0);
    assert_eq!(counter.since(&counts, "level"), 0);
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        resident
    );
    let stats = streamer.stats();
    assert_eq!(stats.version, resp.version);
    assert_eq!(stats.stale_refetches, expected.len() as u64);
    streamer.shutdown().await;
}

/// The server's offline mesher on the file, with its moves, through the compact encoding the
/// route sends.
fn offline_tile(path: &Path, key: BrickKey) -> TileMesh {
    use isovox_server::mesh::tile::{default_iso, mesh_tile_with_moves, TileScratch};
    let snap = Vod2::open(path).unwrap().head();
    let mut t = TileMesh::default();
    let iso = default_iso(snap.layout().voxel_type());
    mesh_tile_with_moves(&snap, key, iso, &mut t, &mut TileScratch::default()).unwrap();
    decode_tile(&encode_tile(&t)).unwrap()
}

/// The server's offline mesher's strip of face `face` of tile `key`, through the compact
/// encoding the route sends.
fn offline_strip(path: &Path, key: BrickKey, face: usize) -> Mesh {
    use isovox_server::mesh::tile::{default_iso, mesh_strip_world, TileScratch};
    let snap = Vod2::open(path).unwrap().head();
    let mut s = Mesh::default();
    let iso = default_iso(snap.layout().voxel_type());
    mesh_strip_world(&snap, key, face, iso, &mut s, &mut TileScratch::default()).unwrap();
    decode_strip(&encode_compact(&s)).unwrap()
}

/// Checks every `Ready` mesh tile of `events` against the offline mesher, its strips (those of
/// its mask's faces, and no other) too, and its drawn mesh against the tile stitched with its
/// mask and strips. Returns the regular triangles delivered.
fn assert_meshes_match_file(events: &[StreamEvent], path: &Path) -> usize {
    let mut triangles = 0;
    for e in events {
        if let StreamEvent::Ready { key, data, .. } = e {
            let TileData::Mesh(m) = data else {
                panic!("a mesh streamer delivered a brick");
            };
            assert_eq!(*m.tile, offline_tile(path, *key), "mesh tile {key}");
            for face in 0..6 {
                match &m.strips[face] {
                    Some(s) if m.mask >> face & 1 == 1 => {
                        assert_eq!(
                            **s,
                            offline_strip(path, *key, face),
                            "strip {face} of {key}"
                        );
                    }
                    None if m.mask >> face & 1 == 0 => {}
                    _ => panic!(
                        "tile {key}, mask {:#b}: strip {face} delivered or not",
                        m.mask
                    ),
                }
            }
            let mut drawn = Mesh::default();
            stitch(
                &m.tile,
                m.mask,
                std::array::from_fn(|f| m.strips[f].as_deref()),
                &mut drawn,
            );
            assert_eq!(*m.mesh, drawn, "mesh tile {key} stitched");
            triangles += m.tile.mesh.triangles();
        }
    }
    triangles
}

/// The selection a mesh streamer uses, computed from [`expected_set`] on a raster of level-0
/// bricks: a tile is split while a tile two or more levels finer touches it (by a face, an edge
/// or a corner).
fn expected_balanced(info: &VolumeInfo, camera: [f32; 3], radii: &[f32]) -> BTreeSet<BrickKey> {
    let mut set = expected_set(info, camera, radii);
    let g = info.levels[0].grid.map(i64::from);
    loop {
        let level_at = raster(info, &set);
        let split = set.iter().copied().find(|t| {
            let span = 1i64 << t.level;
            let lo = [t.x, t.y, t.z].map(|c| i64::from(c) * span);
            // The level-0 bricks around the tile's region, one layer thick.
            let mut finest = u8::MAX;
            for z in lo[2] - 1..=lo[2] + span {
                for y in lo[1] - 1..=lo[1] + span {
                    for x in lo[0] - 1..=lo[0] + span {
                        let p = [x, y, z];
                        let inside = (0..3).all(|a| p[a] >= lo[a] && p[a] < lo[a] + span);
                        if inside || (0..3).any(|a| p[a] < 0 || p[a] >= g[a]) {
                            continue;
                        }
                        finest = finest.min(level_at[&[x, y, z]]);
                    }
                }
            }
            finest != u8::MAX && t.level >= finest + 2
        });
        let Some(t) = split else {
            return set;
        };
        set.remove(&t);
        let lg = info.levels[t.level as usize - 1].grid;
        for o in 0..8u32 {
            let c = [
                2 * t.x + (o & 1),
                2 * t.y + (o >> 1 & 1),
                2 * t.z + (o >> 2),
            ];
            if (0..3).all(|a| c[a] < lg[a]) {
                set.insert(BrickKey {
                    level: t.level - 1,
                    x: c[0],
                    y: c[1],
                    z: c[2],
                });
            }
        }
    }
}

/// The level of the tile covering each level-0 brick.
fn raster(info: &VolumeInfo, set: &BTreeSet<BrickKey>) -> HashMap<[i64; 3], u8> {
    let g = info.levels[0].grid;
    let mut out = HashMap::new();
    for t in set {
        let span = 1u32 << t.level;
        for z in t.z * span..((t.z + 1) * span).min(g[2]) {
            for y in t.y * span..((t.y + 1) * span).min(g[1]) {
                for x in t.x * span..((t.x + 1) * span).min(g[0]) {
                    out.insert([x, y, z].map(i64::from), t.level);
                }
            }
        }
    }
    out
}

/// Each tile's face mask on the raster: bit f when the level-0 bricks just across face f belong
/// to a coarser tile (faces -x, +x, -y, +y, -z, +z).
fn expected_mask(info: &VolumeInfo, set: &BTreeSet<BrickKey>, t: BrickKey) -> u8 {
    let level_at = raster(info, set);
    let span = 1i64 << t.level;
    let lo = [t.x, t.y, t.z].map(|c| i64::from(c) * span);
    let mut mask = 0;
    for f in 0..6 {
        let a = f / 2;
        let across = if f % 2 == 1 { lo[a] + span } else { lo[a] - 1 };
        let mut p = lo;
        p[a] = across;
        if level_at.get(&p).is_some_and(|&l| l > t.level) {
            mask |= 1 << f;
        }
    }
    mask
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edit_by_another_client_refetches_exactly_the_affected_mesh_tiles() {
    // Grids 8x6x8, 4x3x4, 2x2x2, 1x1x1.
    let radii = vec![14.0, 30.0, 60.0];
    let config = StreamerConfig {
        kind: TileKind::Meshes { iso: None },
        radii: radii.clone(),
        // The whole desired set, every tile fetched (the descent and the skipping of empty
        // tiles have their own tests).
        descent: false,
        skip_empty: false,
        ..StreamerConfig::default()
    };
    let Scenario {
        w,
        server,
        counter,
        streamer,
        mut rx,
        camera,
        before,
    } = scenario([64, 48, 64], config, (20, 24), 3.0).await;
    let resident: BTreeSet<BrickKey> = streamer.resident().into_iter().collect();
    assert_eq!(resident, expected_balanced(streamer.info(), camera, &radii));
    assert_eq!(once(&ready_keys(&before), "was ready"), resident);
    let triangles = assert_meshes_match_file(&before, &w.path);
    assert!(triangles > 100, "the tiles hold the terrain's surface");
    let mut drawn = HashMap::new();
    collect_drawn(&before, &mut drawn);
    assert_stitched_closed(streamer.info(), &resident, &drawn, "before the edit");
    assert_eq!(
        counter.snapshot().get("mesh").copied(),
        Some(resident.len() as u64)
    );
    // One strip request per face of a mask: the masks of proto's face_masks, and the raster's.
    let info = streamer.info().clone();
    let list: Vec<BrickKey> = resident.iter().copied().collect();
    let masks = isovox_client::proto::lod::face_masks(&layout_of(&info), &list);
    for (t, m) in list.iter().zip(&masks) {
        assert_eq!(*m, expected_mask(&info, &resident, *t), "mask of {t}");
    }
    let faces: u64 = masks.iter().map(|m| u64::from(m.count_ones())).sum();
    assert!(faces > 0, "some tiles touch a coarser one");
    assert_eq!(counter.snapshot().get("strip").copied(), Some(faces));
    assert_eq!(counter.snapshot().get("blob"), None);

    isovox_server::client_tls::install_provider();
    let editor = Client::new(&server.base).unwrap().with_token(TOKEN);
    let counts = counter.snapshot();
    let resp = editor
        .edit(NAME, &carve(ground(&w, 22, 27), 4), None)
        .await
        .unwrap();
    let changed = changed_keys(&resp.changed);
    let tiles: BTreeSet<BrickKey> = resident
        .intersection(&mesh_readers(&changed))
        .copied()
        .collect();
    let strips = strip_readers(&info, &resident, &changed);
    let expected: BTreeSet<BrickKey> = tiles
        .iter()
        .copied()
        .chain(strips.iter().map(|&(t, _)| t))
        .collect();
    assert!(
        strips.iter().any(|(t, _)| !tiles.contains(t)),
        "a tile goes stale for its strip alone"
    );
    assert!(expected.iter().any(|k| k.level == 0));
    assert!(
        expected.len() > changed.intersection(&resident).count(),
        "neighbours of changed bricks go stale too"
    );
    assert!(resident.len() > expected.len(), "some tiles are untouched");

    let events = settle(&streamer, &mut rx, resp.version).await;
    assert_stale_then_ready(&events, &expected, resp.version);
    assert_meshes_match_file(&events, &w.path);
    collect_drawn(&events, &mut drawn);
    assert_stitched_closed(streamer.info(), &resident, &drawn, "after the edit");
    assert_eq!(counter.since(&counts, "mesh"), tiles.len() as u64);
    assert_eq!(counter.since(&counts, "strip"), strips.len() as u64);
    assert_eq!(counter.since(&counts, "blob"), 0);
    assert_eq!(counter.since(&counts, "brick"), 0);
    // The strips' reads of the next coarser level count: some stale strip reads a changed brick
    // of the level above its tile's.
    assert!(strips.iter().any(|&(t, f)| changed
        .iter()
        .any(|b| b.level == t.level + 1 && strip_reads_brick(t, f, *b))));
    // No grid region: the change event listed the changed bricks' new hashes, which give the
    // stale tiles' and strips' new content keys (the meshes asked for match the file).
    assert_eq!(counter.since(&counts, "level"), 0);
    assert_eq!(streamer.stats().stale_refetches, expected.len() as u64);
    streamer.shutdown().await;
}

/// The latest drawn mesh and mask of each tile, from `Ready` events (`Dropped` ones removed).
fn collect_drawn(events: &[StreamEvent], drawn: &mut HashMap<BrickKey, (u8, Arc<Mesh>)>) {
    for e in events {
        match e {
            StreamEvent::Ready {
                key,
                data: TileData::Mesh(m),
                ..
            } => {
                drawn.insert(*key, (m.mask, m.mesh.clone()));
            }
            StreamEvent::Dropped { key } => {
                drawn.remove(key);
            }
            _ => {}
        }
    }
}

/// The drawn tiles are exactly the `resident` set, each with the mask the raster gives it, and
/// together, welded, a closed 2-manifold without degenerate triangles. Returns (triangles,
/// pairs of crossing triangles).
fn assert_stitched_closed(
    info: &VolumeInfo,
    resident: &BTreeSet<BrickKey>,
    drawn: &HashMap<BrickKey, (u8, Arc<Mesh>)>,
    what: &str,
) -> (usize, usize) {
    use isovox_server::mesh::check::{crossing_triangles, degenerate_triangles, open_edges};
    use isovox_server::mesh::level::weld;
    assert_eq!(
        drawn.keys().copied().collect::<BTreeSet<_>>(),
        *resident,
        "{what}: the drawn tiles"
    );
    let mut all = Mesh::default();
    for (key, (mask, mesh)) in drawn {
        assert_eq!(
            *mask,
            expected_mask(info, resident, *key),
            "{what}: mask of {key}"
        );
        all.append(mesh);
    }
    let welded = weld(&all);
    assert_eq!(
        open_edges(&welded),
        0,
        "{what}: the streamed tiles are not closed"
    );
    assert_eq!(
        degenerate_triangles(&welded, 1e-12),
        0,
        "{what}: degenerate triangles"
    );
    let every = vec![true; welded.triangles()];
    (welded.triangles(), crossing_triangles(&welded, &every))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamed_mesh_tiles_stitch_closed_wherever_the_camera_goes() {
    // Grids 12x8x12, 6x4x6, 3x2x3, 2x1x2, 1x1x1: levels 0-4.
    let w = world([96, 64, 96], 8, [1.0; 3]);
    let server = TestServer::start(w.dir.path(), None);
    let (client, counter) = counted_client(&server.base);
    let radii = vec![10.0, 22.0, 45.0];
    let config = every_tile(TileKind::Meshes { iso: None }, &radii);
    let (streamer, mut rx) = Streamer::start(client, NAME, config).await.unwrap();
    let info = streamer.info().clone();
    let mut drawn = HashMap::new();
    let mut next = 0x9e37_79b9_7f4a_7c15u64;
    let mut random = move || {
        next ^= next << 13;
        next ^= next >> 7;
        next ^= next << 17;
        (next >> 11) as f32 / (1u64 << 53) as f32
    };
    let (mut restitched, mut crossing, mut triangles) = (0, 0, 0);
    let mut hashes: HashMap<BrickKey, u64> = HashMap::new();
    // Every strip (tile, face) a mask has needed so far: each is fetched once.
    let mut asked: BTreeSet<(BrickKey, usize)> = BTreeSet::new();
    let layout = layout_of(&info);
    for step in 0..8 {
        let camera = [random() * 96.0, 20.0 + random() * 50.0, random() * 96.0];
        let requests = counter.snapshot().get("mesh").copied().unwrap_or(0);
        let strip_requests = counter.snapshot().get("strip").copied().unwrap_or(0);
        streamer.set_camera(camera);
        let events = settle(&streamer, &mut rx, 1).await;
        // A tile delivered again with the content key it had was stitched anew (a neighbour's
        // level changed), without a request.
        let mut again = 0;
        for e in &events {
            match e {
                StreamEvent::Ready { key, hash, .. } => {
                    again += usize::from(hashes.insert(*key, *hash) == Some(*hash));
                }
                StreamEvent::Dropped { key } => {
                    hashes.remove(key);
                }
                _ => {}
            }
        }
        restitched += again;
        collect_drawn(&events, &mut drawn);
        let resident: BTreeSet<BrickKey> = streamer.resident().into_iter().collect();
        assert_eq!(resident, expected_balanced(&info, camera, &radii));
        assert_eq!(
            resident,
            select_stitched_tiles(&info, camera, &radii)
                .into_iter()
                .collect()
        );
        let what = format!("step {step}, camera {camera:?}");
        let (t, c) = assert_stitched_closed(&info, &resident, &drawn, &what);
        triangles += t;
        crossing += c;
        // The strips fetched are exactly those of the new selection's masks (proto's
        // face_masks) not fetched before: none for faces without a coarser neighbour.
        let list: Vec<BrickKey> = resident.iter().copied().collect();
        let masks = isovox_client::proto::lod::face_masks(&layout, &list);
        let wanted: BTreeSet<(BrickKey, usize)> = list
            .iter()
            .zip(&masks)
            .flat_map(|(&t, &m)| (0..6).filter(move |f| m >> f & 1 == 1).map(move |f| (t, f)))
            .collect();
        let new = wanted.difference(&asked).count() as u64;
        asked.extend(wanted);
        assert_eq!(
            counter.snapshot().get("strip").copied().unwrap_or(0) - strip_requests,
            new,
            "{what}: strip requests"
        );
        let fetched = counter.snapshot().get("mesh").copied().unwrap_or(0) - requests;
        let delivered = events
            .iter()
            .filter(|e| matches!(e, StreamEvent::Ready { .. }))
            .count();
        assert!(
            fetched as usize <= delivered - again,
            "a restitched tile was fetched"
        );
    }
    eprintln!(
        "{triangles} triangles over 8 views, {crossing} crossing pairs; {restitched} tiles \
         stitched again as their neighbours' levels changed"
    );
    assert!(restitched > 0, "the camera's moves change some masks");
    assert_eq!(crossing, 0, "triangles of the streamed meshes cross");
    streamer.shutdown().await;
}

// ---------------------------------------------------------------------------------------------
// 5. Catching up after a disconnect
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_disconnect_the_streamer_catches_up_from_its_last_version() {
    let config = StreamerConfig {
        radii: vec![12.0, 30.0, 60.0, 120.0],
        // The whole desired set, every tile fetched (the descent has its own tests).
        descent: false,
        ..StreamerConfig::default()
    };
    let Scenario {
        w,
        mut server,
        counter,
        streamer,
        mut rx,
        ..
    } = scenario([96, 64, 96], config, (60, 30), 4.0).await;
    let resident: BTreeSet<BrickKey> = streamer.resident().into_iter().collect();

    // The server goes away (every connection closed, the feed's too); two edits are committed
    // to the file while no server runs; a new server starts on the same port and data.
    let addr = server.addr;
    tokio::task::block_in_place(|| server.stop());
    let first = isovox_server::volume::edit_file(&w.path, &carve(ground(&w, 62, 33), 5)).unwrap();
    let second = isovox_server::volume::edit_file(&w.path, &carve(ground(&w, 57, 27), 4)).unwrap();
    assert_eq!((first.version, second.version), (2, 3));
    let counts = counter.snapshot();
    let _server = TestServer::start(w.dir.path(), Some(addr));

    let events = settle(&streamer, &mut rx, 3).await;
    let mut changed = changed_keys(&first.changed);
    changed.extend(changed_keys(&second.changed));
    let expected: BTreeSet<BrickKey> = resident.intersection(&changed).copied().collect();
    assert!(!expected.is_empty());
    assert!(
        events
            .iter()
            .any(|e| matches!(e, StreamEvent::Error { key: None, .. })),
        "the disconnect was reported"
    );
    // The server replays both versions after the reconnect, and the streamer applies them in
    // one step: exactly the changed tiles go stale, come back at version 3 only (no content of
    // the superseded version 2 is fetched), and each one's last event is Ready with the file's
    // current content.
    let stale: BTreeSet<BrickKey> = stale_keys(&events).into_iter().collect();
    assert_eq!(stale, expected, "the stale tiles");
    let ready: BTreeSet<BrickKey> = ready_keys(&events).into_iter().collect();
    assert_eq!(ready, expected, "the refetched tiles");
    assert!(
        events
            .iter()
            .all(|e| !matches!(e, StreamEvent::Ready { version, .. } if *version != 3)),
        "content of version 3 only"
    );
    assert!(dropped_keys(&events).is_empty());
    for key in &expected {
        let last = events
            .iter()
            .rev()
            .find(|e| {
                matches!(e, StreamEvent::Stale { key: k, .. } | StreamEvent::Ready { key: k, .. } if k == key)
            })
            .unwrap();
        assert!(
            matches!(last, StreamEvent::Ready { .. }),
            "{key} ends ready"
        );
    }
    assert!(events
        .iter()
        .any(|e| matches!(e, StreamEvent::Version { version: 3 })));
    // A tile changed by both versions went stale once per version.
    let per_version: BTreeMap<u64, BTreeSet<BrickKey>> =
        events.iter().fold(BTreeMap::new(), |mut m, e| {
            if let StreamEvent::Stale { key, version } = e {
                assert!(m.entry(*version).or_default().insert(*key));
            }
            m
        });
    let want_2: BTreeSet<BrickKey> = resident
        .intersection(&changed_keys(&first.changed))
        .copied()
        .collect();
    let want_3: BTreeSet<BrickKey> = resident
        .intersection(&changed_keys(&second.changed))
        .copied()
        .collect();
    assert_eq!(per_version.get(&2).cloned().unwrap_or_default(), want_2);
    assert_eq!(per_version.get(&3).cloned().unwrap_or_default(), want_3);
    let snap = Vod2::open(&w.path).unwrap().head();
    assert_bricks_match_file(&events, &snap);
    assert_eq!(streamer.stats().version, 3);
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        resident
    );
    // Only the changed tiles' content was fetched again (at most one blob per Ready).
    assert!(counter.since(&counts, "blob") <= ready_keys(&events).len() as u64);
    assert_eq!(counter.since(&counts, "brick"), 0);
    streamer.shutdown().await;
}

// ---------------------------------------------------------------------------------------------
// 6. Reloading when the versions it missed were compacted away
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn when_the_missed_versions_were_compacted_away_the_streamer_reloads() {
    let config = StreamerConfig {
        radii: vec![12.0, 30.0, 60.0, 120.0],
        // The whole desired set, every tile fetched (the descent has its own tests).
        descent: false,
        ..StreamerConfig::default()
    };
    let Scenario {
        w,
        mut server,
        counter,
        streamer,
        mut rx,
        before,
        ..
    } = scenario([96, 64, 96], config, (40, 50), 4.0).await;
    let resident: BTreeSet<BrickKey> = streamer.resident().into_iter().collect();
    let cached: HashSet<u64> = before
        .iter()
        .filter_map(|e| match e {
            StreamEvent::Ready { hash, .. } => Some(*hash),
            _ => None,
        })
        .collect();

    // While the streamer is cut off: two versions, then a compaction (through a server on
    // another port, which the streamer does not know) that keeps only the last one.
    let addr = server.addr;
    tokio::task::block_in_place(|| server.stop());
    isovox_server::volume::edit_file(&w.path, &carve(ground(&w, 42, 52), 6)).unwrap();
    isovox_server::volume::edit_file(&w.path, &carve(ground(&w, 38, 47), 5)).unwrap();
    let mut other = TestServer::start(w.dir.path(), None);
    isovox_server::client_tls::install_provider();
    let compacted = Client::new(&other.base)
        .unwrap()
        .with_token(TOKEN)
        .compact(NAME)
        .await
        .unwrap();
    assert_eq!(compacted.version, 3);
    tokio::task::block_in_place(|| other.stop());
    let counts = counter.snapshot();
    let _server = TestServer::start(w.dir.path(), Some(addr));

    // Its version 1 is gone (410): it reloads, and every resident tile goes stale and comes back
    // with the file's content; content it already held is not fetched again.
    let events = settle(&streamer, &mut rx, 3).await;
    assert_eq!(once(&stale_keys(&events), "went stale"), resident);
    assert_eq!(once(&ready_keys(&events), "was ready"), resident);
    assert!(dropped_keys(&events).is_empty());
    let snap = Vod2::open(&w.path).unwrap().head();
    let hashes = assert_bricks_match_file(&events, &snap);
    assert!(hashes.iter().any(|h| !cached.contains(h)), "the edits show");
    assert_eq!(
        counter.since(&counts, "blob"),
        hashes.difference(&cached).count() as u64
    );
    assert_eq!(streamer.stats().version, 3);
    streamer.shutdown().await;
}

// ---------------------------------------------------------------------------------------------
// 7. In screen order, with bounded concurrency
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn missing_tiles_come_in_screen_order_within_the_concurrency_bound() {
    let w = world([128, 64, 96], 8, [0.5, 0.75, 1.0]);
    let server = TestServer::start(w.dir.path(), None);
    let (client, _) = counted_client(&server.base);
    let radii = vec![6.5, 14.3, 29.9, 61.1];
    let (streamer, mut rx) = Streamer::start(
        client,
        NAME,
        StreamerConfig {
            radii: radii.clone(),
            max_in_flight: 1,
            // The whole desired set, every tile fetched (the descent has its own tests).
            descent: false,
            ..StreamerConfig::default()
        },
    )
    .await
    .unwrap();
    let info = streamer.info().clone();
    let camera = [40.3, 25.1, 60.7];
    streamer.set_camera(camera);
    let mut ready: Vec<(BrickKey, u64)> = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    while ready.len() < expected_set(&info, camera, &radii).len() {
        assert!(Instant::now() < deadline, "not all tiles arrived");
        let e = tokio::time::timeout(Duration::from_secs(60), rx.recv())
            .await
            .unwrap()
            .unwrap();
        assert!(streamer.stats().in_flight <= 1);
        if let StreamEvent::Ready { key, hash, .. } = e {
            ready.push((key, hash));
        }
    }
    streamer.wait_idle().await;
    let d = |k: BrickKey| box_distance(&info, k.level as usize, [k.x, k.y, k.z], camera);
    // The tile around the camera comes with the first content fetched.
    let home = expected_set(&info, camera, &radii)
        .into_iter()
        .find(|&k| d(k) == 0.0)
        .unwrap();
    let first_other = ready
        .iter()
        .position(|&(_, h)| h != ready[0].1)
        .unwrap_or(ready.len());
    assert!(
        ready[..first_other].iter().any(|&(k, _)| k == home),
        "the camera's own tile {home} is among the first delivered"
    );
    // On the whole, tiles come in screen order: distance over edge length, the levels
    // interleaved. Of the pairs delivered one before the other, more agree with that order
    // than with the distance alone, and the earlier half shows larger on screen.
    let screen = |k: BrickKey| d(k) / f64::from(1u32 << k.level);
    let agree = |f: &dyn Fn(BrickKey) -> f64| {
        let mut n = 0u64;
        for (i, &(a, _)) in ready.iter().enumerate() {
            n += ready[i + 1..]
                .iter()
                .filter(|&&(b, _)| f(a) <= f(b))
                .count() as u64;
        }
        n
    };
    let (by_screen, by_distance) = (agree(&screen), agree(&d));
    assert!(
        by_screen > by_distance,
        "pairs in screen order {by_screen}, in distance order {by_distance}"
    );
    let half = ready.len() / 2;
    let mean =
        |s: &[(BrickKey, u64)]| s.iter().map(|&(k, _)| screen(k)).sum::<f64>() / s.len() as f64;
    assert!(
        mean(&ready[..half]) < mean(&ready[half..]),
        "screen order: {} vs {}",
        mean(&ready[..half]),
        mean(&ready[half..])
    );
    streamer.shutdown().await;
}

/// A streamer plans only the nearest few hundred waiting tiles at a time (so that many
/// streamers in one process spend their time on answers, not on planning thousands of tiles).
/// With four times as many tiles waiting, of bricks or of meshes, every one still arrives (the
/// window moves on as tiles arrive, also bricks, whose blobs complete tiles without a replan),
/// each grid region and each mesh tile is asked for once (a plan kept while its tile was beyond
/// the window would ask again), and the nearer half of the tiles comes first.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thousands_of_waiting_tiles_each_arrive_once_nearest_first() {
    // Every tile within the first radius, all at level 0: bricks of a 32x8x32 grid (8,192
    // tiles, over a thousand of them with a brick of their own, in 4x1x4 regions of 8x8x8),
    // mesh tiles of a 16x8x16 grid (2,048 tiles, each asked for, in 2x1x2 regions).
    let radii = vec![1000.0];
    let camera = [20.5, 40.5, 30.5];
    let cases = [
        (TileKind::Bricks, [256, 64, 256], 8192, 16),
        (TileKind::Meshes { iso: None }, [128, 64, 128], 2048, 4),
    ];
    for (kind, dims, tiles, regions) in cases {
        let w = world(dims, 8, [1.0; 3]);
        let server = TestServer::start(w.dir.path(), None);
        let (client, counter) = counted_client(&server.base);
        let config = every_tile(kind, &radii);
        let (streamer, mut rx) = Streamer::start(client, NAME, config).await.unwrap();
        let info = streamer.info().clone();
        let all = select_tiles(&info, camera, &radii);
        assert_eq!(all.len(), tiles);
        assert!(all.iter().all(|k| k.level == 0));
        streamer.set_camera(camera);
        let events = settle(&streamer, &mut rx, 1).await;
        let ready = ready_keys(&events);
        let delivered = once(&ready, "ready");
        assert_eq!(delivered, all.iter().copied().collect::<BTreeSet<_>>());
        let snapshot = counter.snapshot();
        let count = |route| snapshot.get(route).copied().unwrap_or(0);
        assert_eq!(count("level"), regions, "{kind:?}: grid regions");
        let distinct: HashSet<u64> = events
            .iter()
            .filter_map(|e| match e {
                StreamEvent::Ready { hash, .. } => Some(*hash),
                _ => None,
            })
            .collect();
        match kind {
            TileKind::Bricks => {
                assert!(distinct.len() > 1000, "{} distinct bricks", distinct.len());
                assert_eq!(count("blob") as usize, distinct.len(), "each blob once");
            }
            TileKind::Meshes { .. } => {
                assert!(count("mesh") <= 2048, "{} mesh requests", count("mesh"));
                assert_eq!(count("strip"), 0, "one level: no strips");
            }
        }
        let d = |k: BrickKey| box_distance(&info, 0, [k.x, k.y, k.z], camera);
        let half = ready.len() / 2;
        let mean = |s: &[BrickKey]| s.iter().map(|&k| d(k)).sum::<f64>() / s.len() as f64;
        assert!(
            mean(&ready[..half]) < mean(&ready[half..]),
            "{kind:?}: nearer first: {} vs {}",
            mean(&ready[..half]),
            mean(&ready[half..])
        );
        streamer.shutdown().await;
    }
}

// ---------------------------------------------------------------------------------------------
// 8. Cancelling requests the camera no longer needs
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn requests_the_camera_no_longer_needs_are_cancelled() {
    let w = world([128, 64, 96], 8, [0.5, 0.75, 1.0]);
    let mut server = TestServer::start(w.dir.path(), None);
    let (client, _) = counted_client(&server.base);
    let radii = vec![6.5, 14.3, 29.9, 61.1];
    let (streamer, mut rx) = Streamer::start(
        client,
        NAME,
        StreamerConfig {
            radii: radii.clone(),
            // The whole desired set, every tile fetched (the descent has its own tests).
            descent: false,
            ..StreamerConfig::default()
        },
    )
    .await
    .unwrap();
    let info = streamer.info().clone();
    let a = [8.2, 20.3, 12.7];
    let b = [55.9, 30.1, 80.3];
    streamer.set_camera(a);
    settle(&streamer, &mut rx, 1).await;
    let set_a = expected_set(&info, a, &radii);
    let set_b = expected_set(&info, b, &radii);

    // With the server gone, requests for camera b stay in flight (the client retries a refused
    // connection for at least ~0.4 s) ...
    tokio::task::block_in_place(|| server.stop());
    streamer.set_camera(b);
    let deadline = Instant::now() + Duration::from_secs(5);
    while streamer.stats().in_flight == 0 {
        assert!(Instant::now() < deadline, "no request started for camera b");
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    // ... and moving back to a, whose content is all cached, cancels them: the streamer is idle
    // with nothing in flight, and the cancelled requests never report.
    streamer.set_camera(a);
    let mut events = settle(&streamer, &mut rx, 1).await;
    assert_eq!(streamer.stats().in_flight, 0);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    while let Ok(e) = rx.try_recv() {
        events.push(e);
    }
    for e in &events {
        if let StreamEvent::Error { error, .. } = e {
            assert!(
                error.starts_with("change feed"),
                "a cancelled request reported: {error}"
            );
        }
    }
    // Tiles of b whose hashes were known (grid regions come in 8x8x8 blocks) and whose content
    // was cached (air, rock) were delivered even without a server, and dropped again; the
    // others never were.
    let a_only: BTreeSet<BrickKey> = set_a.difference(&set_b).copied().collect();
    let b_only: BTreeSet<BrickKey> = set_b.difference(&set_a).copied().collect();
    assert!(!a_only.is_empty());
    let ready = once(&ready_keys(&events), "was ready");
    let b_delivered: BTreeSet<BrickKey> = ready.difference(&a_only).copied().collect();
    assert!(b_delivered.is_subset(&b_only));
    assert!(
        b_delivered.len() < b_only.len(),
        "some of b needed the server"
    );
    let both: BTreeSet<BrickKey> = a_only.union(&b_delivered).copied().collect();
    assert_eq!(ready, both);
    assert_eq!(once(&dropped_keys(&events), "was dropped"), both);
    assert_eq!(
        streamer.resident().into_iter().collect::<BTreeSet<_>>(),
        set_a
    );
    assert_eq!(streamer.stats().in_flight, 0);
    streamer.shutdown().await;
}

// ---------------------------------------------------------------------------------------------
// 9. Sharing an overloaded server: fewer requests in flight after 503s
// ---------------------------------------------------------------------------------------------

/// Counts a client's answers with status 503.
#[derive(Debug, Default)]
struct Refusals(std::sync::atomic::AtomicU64);

impl Observer for Refusals {
    fn exchange(&self, _: &'static str, outcome: Result<u16, &str>, _: Duration, _: u64, _: bool) {
        if outcome == Ok(503) {
            self.0.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamers_sharing_a_tiny_cpu_queue_lower_their_limit_and_get_every_tile() {
    // Grids 4x4x4, 2x2x2, 1x1x1; one radius beyond every tile's distance: the 64 level-0 tiles.
    let w = world([128, 128, 128], 32, [1.0; 3]);
    // Two places for CPU work (every mesh tile and grid region takes one), against four
    // streamers of up to 16 requests each.
    let server = TestServer::start_with(
        w.dir.path(),
        None,
        ServerConfig {
            cpu_queue: 2,
            ..ServerConfig::default()
        },
    );
    const MAX: usize = 16;
    let radii = vec![1.0e6];
    let camera = [64.0, 64.0, 64.0];
    let mut streamers = Vec::new();
    let mut receivers = Vec::new();
    let mut refusals = Vec::new();
    for _ in 0..4 {
        isovox_server::client_tls::install_provider();
        let counted = Arc::new(Refusals::default());
        let client = Client::new(&server.base)
            .unwrap()
            .with_observer(counted.clone());
        let (streamer, rx) = Streamer::start(
            client,
            NAME,
            StreamerConfig {
                kind: TileKind::Meshes { iso: None },
                radii: radii.clone(),
                max_in_flight: MAX,
                // The whole desired set, every tile fetched (the descent has its own tests).
                descent: false,
                ..StreamerConfig::default()
            },
        )
        .await
        .unwrap();
        assert_eq!(
            streamer.stats().in_flight_limit,
            MAX,
            "starts at the maximum"
        );
        streamers.push(streamer);
        receivers.push(rx);
        refusals.push(counted);
    }
    for s in &streamers {
        s.set_camera(camera);
    }

    // Every streamer settles; meanwhile each one's limit is sampled.
    let mut lowest = [MAX; 4];
    let events = {
        let settled = async {
            let mut all = Vec::new();
            for (s, rx) in streamers.iter().zip(receivers.iter_mut()) {
                all.push(settle(s, rx, 0).await);
            }
            all
        };
        tokio::pin!(settled);
        loop {
            tokio::select! {
                all = &mut settled => break all,
                () = tokio::time::sleep(Duration::from_millis(1)) => {
                    for (i, s) in streamers.iter().enumerate() {
                        let st = s.stats();
                        assert!((1..=MAX).contains(&st.in_flight_limit), "{st:?}");
                        assert!(st.in_flight <= MAX, "{st:?}");
                        lowest[i] = lowest[i].min(st.in_flight_limit);
                    }
                }
            }
        }
    };

    let expected: BTreeSet<BrickKey> = (0..64)
        .map(|i| BrickKey {
            level: 0,
            x: i % 4,
            y: i / 4 % 4,
            z: i / 16,
        })
        .collect();
    for (i, (s, events)) in streamers.iter().zip(&events).enumerate() {
        // Every tile came, once, and is the offline mesher's.
        assert_eq!(
            once(&ready_keys(events), "was ready"),
            expected,
            "streamer {i}"
        );
        assert_eq!(s.resident().into_iter().collect::<BTreeSet<_>>(), expected);
        assert!(assert_meshes_match_file(events, &w.path) > 100);
        // What failed was refused for load, and retried.
        for e in events {
            if let StreamEvent::Error { error, .. } = e {
                assert!(error.contains("503 Service Unavailable"), "{error}");
            }
        }
        // The server refused this streamer's requests, and it lowered its limit. Its requests'
        // answers reach the observer its client already had.
        let refused = refusals[i].0.load(std::sync::atomic::Ordering::SeqCst);
        let st = s.stats();
        eprintln!(
            "streamer {i}: {refused} answers 503, limit lowest {} (sampled), {} at the end, {} requests",
            lowest[i], st.in_flight_limit, st.requests
        );
        assert!(
            refused > 0,
            "streamer {i}: no 503 with two places for four streamers"
        );
        assert!(lowest[i] < MAX, "streamer {i}: the limit stayed {MAX}");
        // And it is still below the maximum: after a cut to 8 at most, growing back to 16 takes
        // 8 + 9 + ... + 15 = 92 successes, and a streamer has at most 66 (64 tiles, the grid
        // regions of levels 0 and 1).
        assert!(st.in_flight_limit < MAX, "{st:?}");
        assert_eq!(st.in_flight, 0);
    }
    for s in streamers {
        s.shutdown().await;
    }
}

/// The layout of a volume's metadata.
fn layout_of(info: &VolumeInfo) -> VolumeLayout {
    VolumeLayout::new(info.dims, info.brick, info.voxel_type).unwrap()
}

// ---------------------------------------------------------------------------------------------
// 10. The octree descent
// ---------------------------------------------------------------------------------------------

/// A settled run's events, stats and HTTP exchanges by route ([`settled_run`]).
type Run = (
    Vec<StreamEvent>,
    isovox_client::StreamerStats,
    HashMap<&'static str, u64>,
);

/// One settled streamer on `w` at `camera`: its events, stats and the HTTP exchanges by route.
async fn settled_run(base: &str, config: StreamerConfig, camera: [f32; 3]) -> Run {
    let (client, counter) = counted_client(base);
    let (streamer, mut rx) = Streamer::start(client, NAME, config).await.unwrap();
    streamer.set_camera(camera);
    let events = settle(&streamer, &mut rx, 1).await;
    let stats = streamer.stats();
    streamer.shutdown().await;
    (events, stats, counter.snapshot())
}

/// Whether the offline mesher draws a triangle in tile `key` of `snap` at the default iso, or
/// the brick's own voxels lie on both sides of it: a brick holding the surface.
fn holds_surface(snap: &Snapshot, key: BrickKey) -> bool {
    use isovox_server::mesh::tile::{default_iso, mesh_tile_with_moves, TileScratch};
    let iso = default_iso(snap.layout().voxel_type());
    let voxels = snap.read(key).unwrap();
    let below = voxels.iter().any(|&v| f32::from(v) < iso);
    let above = voxels.iter().any(|&v| f32::from(v) > iso);
    let mut t = TileMesh::default();
    mesh_tile_with_moves(snap, key, iso, &mut t, &mut TileScratch::default()).unwrap();
    (below && above) || t.mesh.triangles() > 0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_descent_fetches_every_brick_holding_the_surface() {
    // 256 x 128 x 256 voxels, brick 8: grids 32x16x32 down to 1x1x1 (6 levels); the terrain
    // crosses the middle levels, air above and rock below are most of the volume.
    let w = world([256, 128, 256], 8, [1.0; 3]);
    let server = TestServer::start(w.dir.path(), None);
    // Level 0 within 40 voxels of a camera 30 above the ground: mostly air and rock.
    let g = ground(&w, 128, 128);
    let camera = [128.0, g[1] as f32 + 30.0, 128.0];
    let radii = vec![40.0, 80.0, 160.0, 320.0];
    let config = |descent| StreamerConfig {
        radii: radii.clone(),
        descent,
        ..StreamerConfig::default()
    };
    let (all, all_stats, all_routes) = settled_run(&server.base, config(false), camera).await;
    let (some, some_stats, some_routes) = settled_run(&server.base, config(true), camera).await;
    let snap = Vod2::open(&w.path).unwrap().head();
    for events in [&all, &some] {
        assert_no_errors(events);
        assert_bricks_match_file(events, &snap);
    }
    let all_keys = once(&ready_keys(&all), "was ready");
    let some_keys = once(&ready_keys(&some), "was ready");
    let client = Client::new(&server.base).unwrap();
    let info = client.volume(NAME).await.unwrap();
    assert_eq!(
        all_keys,
        select_tiles(&info, camera, &radii).into_iter().collect()
    );
    // Every brick with surface in it is there; nothing outside the camera's set is.
    let surface: BTreeSet<BrickKey> = all_keys
        .iter()
        .copied()
        .filter(|&k| holds_surface(&snap, k))
        .collect();
    let missed: Vec<_> = surface.difference(&some_keys).collect();
    assert!(
        missed.is_empty(),
        "the descent skipped surface bricks {missed:?}"
    );
    assert!(some_keys.is_subset(&all_keys));
    // And it skipped something, asking for fewer grid regions and blobs.
    assert!(some_keys.len() < all_keys.len(), "nothing skipped");
    assert_eq!(
        some_stats.skipped as usize,
        all_keys.len() - some_keys.len()
    );
    assert_eq!(all_stats.skipped, 0);
    let count = |r: &HashMap<&'static str, u64>, route| r.get(route).copied().unwrap_or(0);
    // (Grid regions are not fewer on so small a volume: the descent asks for the coarse
    // levels' too, and the 8x8x8 regions of the finest levels cover most of it either way.
    // docs/benchmarks.md measures them on a large one.)
    // (Nor blobs much: air and rock bricks share one hash each.)
    assert!(count(&some_routes, "blob") <= count(&all_routes, "blob"));
    // Every region asked for reached the server, but those aborted on the way (a region no
    // tile needs any more once a coarser answer decided them is aborted, and may or may not
    // have been sent).
    let regions = count(&some_routes, "level");
    assert!(
        some_stats.grid_requests - some_stats.grid_aborted <= regions
            && regions <= some_stats.grid_requests,
        "{regions} grid regions answered; {some_stats:?}"
    );
    eprintln!(
        "descent: {} of {} tiles ({} holding the surface), {} grid regions instead of {}, {} blobs instead of {}",
        some_keys.len(),
        all_keys.len(),
        surface.len(),
        count(&some_routes, "level"),
        count(&all_routes, "level"),
        count(&some_routes, "blob"),
        count(&all_routes, "blob"),
    );
}

/// The radii of the mesh runs of [`two_mesh_runs`].
const MESH_RUN_RADII: [f32; 4] = [32.0, 64.0, 128.0, 256.0];

/// A mesh streamer within [`MESH_RUN_RADII`], with or without the descent and the skipping of
/// empty tiles.
fn mesh_run_config(descent: bool, skip_empty: bool) -> StreamerConfig {
    StreamerConfig {
        kind: TileKind::Meshes { iso: None },
        radii: MESH_RUN_RADII.to_vec(),
        descent,
        skip_empty,
        ..StreamerConfig::default()
    }
}

/// The world of the skipping tests and a camera 20 voxels over its ground at (100, 140).
const MESH_RUN_WORLD: ([u32; 3], (u32, u32), f32) = ([256, 128, 256], (100, 140), 20.0);

/// Two settled runs of mesh streamers on one world at one camera ([`MESH_RUN_WORLD`]): the
/// `reference`, then the `tested`, each without an error and equal to the offline mesher.
async fn two_mesh_runs(
    reference: StreamerConfig,
    tested: StreamerConfig,
) -> (World, TestServer, Run, Run) {
    let (dims, (x, z), above) = MESH_RUN_WORLD;
    let w = world(dims, 8, [1.0; 3]);
    let server = TestServer::start(w.dir.path(), None);
    let g = ground(&w, x, z);
    let camera = [x as f32, g[1] as f32 + above, z as f32];
    let a = settled_run(&server.base, reference, camera).await;
    let b = settled_run(&server.base, tested, camera).await;
    for events in [&a.0, &b.0] {
        assert_no_errors(events);
        assert_meshes_match_file(events, &w.path);
    }
    (w, server, a, b)
}

/// The mesh tiles of `events` whose drawing (regular mesh and strips) has a triangle, or
/// (`draws` false) has none.
fn tiles_drawing(events: &[StreamEvent], draws: bool) -> BTreeSet<BrickKey> {
    events
        .iter()
        .filter_map(|e| match e {
            StreamEvent::Ready {
                key,
                data: TileData::Mesh(m),
                ..
            } if (m.mesh.triangles() > 0) == draws => Some(*key),
            _ => None,
        })
        .collect()
}

/// A cache far smaller than the view's mesh tiles and strips: parts are evicted while other
/// parts of their tiles are still on their way, and every tile is still drawn, as the offline
/// mesher draws it, with the same tiles as with room for all.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mesh_cache_smaller_than_the_view_still_draws_every_tile() {
    const SMALL: usize = 256 << 10;
    let small = StreamerConfig {
        cache_bytes: SMALL,
        ..mesh_run_config(true, true)
    };
    let (_w, _server, (roomy, roomy_stats, _), (tight, tight_stats, _)) =
        two_mesh_runs(mesh_run_config(true, true), small).await;
    assert!(
        roomy_stats.cache_bytes > 4 * SMALL,
        "the view's parts fit in a small cache: {roomy_stats:?}"
    );
    assert!(tight_stats.cache_bytes <= SMALL, "{tight_stats:?}");
    assert_eq!(
        once(&ready_keys(&tight), "was ready"),
        once(&ready_keys(&roomy), "was ready")
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_descent_fetches_every_mesh_tile_that_draws_a_triangle() {
    // The reference run asks for every tile.
    let (_w, _server, (all, _, all_routes), (some, some_stats, some_routes)) =
        two_mesh_runs(mesh_run_config(false, false), mesh_run_config(true, true)).await;
    // The tiles whose drawing has a triangle, without the descent.
    let drawn = tiles_drawing(&all, true);
    let all_keys = once(&ready_keys(&all), "was ready");
    let some_keys = once(&ready_keys(&some), "was ready");
    assert!(!drawn.is_empty());
    let missed: Vec<_> = drawn.difference(&some_keys).collect();
    assert!(
        missed.is_empty(),
        "the descent skipped drawn tiles {missed:?}"
    );
    assert!(some_keys.is_subset(&all_keys));
    assert!(some_keys.len() < all_keys.len(), "nothing skipped");
    assert!(some_stats.skipped > 0);
    let count = |r: &HashMap<&'static str, u64>, route| r.get(route).copied().unwrap_or(0);
    assert!(count(&some_routes, "mesh") < count(&all_routes, "mesh"));
    eprintln!(
        "descent, meshes: {} of {} tiles ({} drawn), {} grid regions instead of {}, {} meshes instead of {}",
        some_keys.len(),
        all_keys.len(),
        drawn.len(),
        count(&some_routes, "level"),
        count(&all_routes, "level"),
        count(&some_routes, "mesh"),
        count(&all_routes, "mesh"),
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_the_descent_only_mesh_tiles_that_draw_nothing_are_skipped() {
    let (_w, _server, (all, all_stats, all_routes), (some, some_stats, some_routes)) =
        two_mesh_runs(mesh_run_config(false, false), mesh_run_config(false, true)).await;
    let all_keys = once(&ready_keys(&all), "was ready");
    let some_keys = once(&ready_keys(&some), "was ready");
    // The reference asked for every desired tile, each checked against the offline mesher:
    // the tiles whose drawing has no triangle.
    let empty = tiles_drawing(&all, false);
    assert!(some_keys.is_subset(&all_keys));
    let skipped: BTreeSet<BrickKey> = all_keys.difference(&some_keys).copied().collect();
    let drawn: Vec<_> = skipped.difference(&empty).collect();
    assert!(drawn.is_empty(), "skipped tiles that draw: {drawn:?}");
    assert!(!skipped.is_empty(), "nothing skipped");
    assert_eq!(some_stats.skipped as usize, skipped.len());
    assert_eq!(all_stats.skipped, 0);
    // A tile is asked for once, and a skipped one never.
    let count = |r: &HashMap<&'static str, u64>, route| r.get(route).copied().unwrap_or(0);
    assert_eq!(count(&all_routes, "mesh"), all_keys.len() as u64);
    assert_eq!(count(&some_routes, "mesh"), some_keys.len() as u64);
    // The same grid regions: the skipping reads the ranges the tiles' regions bring anyway.
    assert_eq!(count(&some_routes, "level"), count(&all_routes, "level"));
    eprintln!(
        "skipping empty mesh tiles: {} of {} tiles asked for ({} draw nothing)",
        some_keys.len(),
        all_keys.len(),
        empty.len()
    );

    // A cave carved into rock where every tile was skipped (all solid) is drawn after the
    // commit, from the event's ranges.
    let (dims, (x, z), above) = MESH_RUN_WORLD;
    let mut s = scenario(dims, mesh_run_config(false, true), (x, z), above).await;
    let resident_before: BTreeSet<BrickKey> = s.streamer.resident().into_iter().collect();
    let g = ground(&s.w, x, z);
    let cave = [g[0] + 12, g[1] - 30, g[2] - 12];
    let (client, _) = counted_client(&s.server.base);
    let version = client
        .with_token(TOKEN)
        .edit(NAME, &carve(cave, 5), None)
        .await
        .unwrap()
        .version;
    let events = settle(&s.streamer, &mut s.rx, version).await;
    assert_no_errors(&events);
    assert_meshes_match_file(&events, &s.w.path);
    let info = s.streamer.info().clone();
    let resident: BTreeSet<BrickKey> = s.streamer.resident().into_iter().collect();
    let desired = expected_balanced(&info, s.camera, &MESH_RUN_RADII);
    assert!(resident.is_subset(&desired));
    let missed: Vec<_> = desired
        .iter()
        .filter(|&&k| !resident.contains(&k) && offline_tile(&s.w.path, k).mesh.triangles() > 0)
        .collect();
    assert!(
        missed.is_empty(),
        "tiles that draw are not resident: {missed:?}"
    );
    let opened: Vec<_> = resident.difference(&resident_before).collect();
    assert!(
        !opened.is_empty(),
        "the cave was drawn in no tile skipped before it"
    );
    s.streamer.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_an_edit_the_descent_has_every_surface_brick_without_asking_for_grids() {
    let radii = vec![24.0, 48.0, 96.0];
    let config = StreamerConfig {
        radii: radii.clone(),
        descent: true,
        ..StreamerConfig::default()
    };
    let mut s = scenario([128, 64, 128], config, (64, 64), 8.0).await;
    let grids_before = s.streamer.stats().grid_requests;
    // A crater at the ground under the camera and a cave in the rock below it, where the
    // descent had skipped every brick (all solid).
    let (client, _) = counted_client(&s.server.base);
    let client = client.with_token(TOKEN);
    let g = ground(&s.w, 64, 64);
    let mut version = 1;
    for (center, r) in [(g, 6), ([g[0] + 10, g[1] - 20, g[2] - 10], 4)] {
        version = client
            .edit(NAME, &carve(center, r), None)
            .await
            .unwrap()
            .version;
    }
    let events = settle(&s.streamer, &mut s.rx, version).await;
    assert_no_errors(&events);
    let snap = Vod2::open(&s.w.path).unwrap().head();
    assert_bricks_match_file(&events, &snap);
    let info = s.streamer.info().clone();
    let resident: BTreeSet<BrickKey> = s.streamer.resident().into_iter().collect();
    let desired = select_tiles(&info, s.camera, &radii);
    let surface: BTreeSet<BrickKey> = desired
        .into_iter()
        .filter(|&k| holds_surface(&snap, k))
        .collect();
    let missed: Vec<_> = surface.difference(&resident).collect();
    assert!(
        missed.is_empty(),
        "after the edits, surface bricks {missed:?} are not resident"
    );
    let stats = s.streamer.stats();
    eprintln!(
        "after the edits: {} grid regions ({} for edits), {} resident, {} holding the surface, {} skipped",
        stats.grid_requests - grids_before,
        stats.edit_grid_requests,
        resident.len(),
        surface.len(),
        stats.skipped
    );
    // The descent skipped tiles, and after the edits it decided again from the events alone:
    // the camera did not move, so no grid region was asked for after the first settle.
    assert!(stats.skipped > 0, "the descent skipped nothing: {stats:?}");
    assert_eq!(stats.grid_requests, grids_before, "{stats:?}");
    assert_eq!(stats.edit_grid_requests, 0, "{stats:?}");
    s.streamer.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edit_where_the_descent_skipped_whole_regions_asks_for_no_grid() {
    for kind in [TileKind::Bricks, TileKind::Meshes { iso: None }] {
        edit_where_the_descent_skipped_whole_regions(kind).await;
    }
}

/// A streamer of `kind` with the descent, high in the air of a tall world, and an edit at the
/// camera: after it, no grid region is asked for.
async fn edit_where_the_descent_skipped_whole_regions(kind: TileKind) {
    // A world 32 bricks tall: level 0's grid regions (8 bricks a side) stack four high, so a
    // camera high in the air sees bricks whose regions are never asked for: the descent skips
    // them from the coarser levels' ranges (all air).
    let radii = vec![24.0, 48.0, 96.0];
    let config = StreamerConfig {
        kind,
        radii: radii.clone(),
        descent: true,
        ..StreamerConfig::default()
    };
    let w = world([128, 256, 128], 8, [1.0; 3]);
    let server = TestServer::start(w.dir.path(), None);
    let (client, counter) = counted_client(&server.base);
    let (streamer, mut rx) = Streamer::start(client, NAME, config).await.unwrap();
    let g = ground(&w, 64, 64);
    // 30 voxels below the top, in level 0's highest regions (y 192..256), with no surface
    // within reach of level 0.
    let y = 256 - 30;
    assert!(y - g[1] > 64, "ground at {g:?}: too high for the test");
    let camera = [64.0, y as f32, 64.0];
    streamer.set_camera(camera);
    settle(&streamer, &mut rx, 1).await;
    let before = streamer.stats();
    let routes_before = counter.snapshot();
    assert!(before.skipped > 0, "{kind:?}: nothing skipped: {before:?}");
    // A ball at the camera: its level-0 bricks and their coarser bricks now hold a surface.
    // The event lists what they hold; their unchanged neighbours, which now show the ball's
    // side, were never in a grid region the streamer asked for.
    let (client, _) = counted_client(&server.base);
    let client = client.with_token(TOKEN);
    let ball = EditRequest {
        op: "union".into(),
        ..carve([64, y, 64], 6)
    };
    let version = client.edit(NAME, &ball, None).await.unwrap().version;
    let events = settle(&streamer, &mut rx, version).await;
    assert_no_errors(&events);
    let snap = Vod2::open(&w.path).unwrap().head();
    let info = streamer.info().clone();
    let resident: BTreeSet<BrickKey> = streamer.resident().into_iter().collect();
    let routes = counter.snapshot();
    let count = |r: &HashMap<&'static str, u64>, route| r.get(route).copied().unwrap_or(0);
    let after = streamer.stats();
    match kind {
        TileKind::Bricks => {
            assert_bricks_match_file(&events, &snap);
            let surface: BTreeSet<BrickKey> = select_tiles(&info, camera, &radii)
                .into_iter()
                .filter(|&k| holds_surface(&snap, k))
                .collect();
            assert!(!surface.is_empty(), "the ball holds no surface");
            let missed: Vec<_> = surface.difference(&resident).collect();
            assert!(
                missed.is_empty(),
                "surface bricks {missed:?} are not resident"
            );
            // The streamer asked for the bricks themselves at the new version.
            let by_position = count(&routes, "brick") - count(&routes_before, "brick");
            assert!(by_position > 0, "no brick fetched by position");
        }
        TileKind::Meshes { .. } => {
            // The ball is drawn, by meshes the offline mesher makes of the file.
            let drawn = events.iter().any(|e| {
                matches!(e, StreamEvent::Ready { data: TileData::Mesh(m), .. } if m.mesh.triangles() > 0)
            });
            assert!(drawn, "no tile draws the ball");
            assert!(assert_meshes_match_file(&events, &w.path) > 0);
        }
    }
    eprintln!(
        "{kind:?}: {} grid regions before, {} after ({} for edits), {} bricks, {} mesh tiles after",
        before.grid_requests,
        after.grid_requests - before.grid_requests,
        after.edit_grid_requests,
        count(&routes, "brick") - count(&routes_before, "brick"),
        count(&routes, "mesh") - count(&routes_before, "mesh"),
    );
    assert_eq!(
        after.grid_requests, before.grid_requests,
        "{kind:?}: {after:?}"
    );
    assert_eq!(after.edit_grid_requests, 0, "{kind:?}: {after:?}");
    streamer.shutdown().await;
}
