//! The transition strip route, `GET /v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}/strips/{face}`,
//! over a real socket: the strip is the offline mesher's, bit for bit, in both encodings; it is
//! named by a strong ETag (304 on If-None-Match, no-cache for the newest version, immutable when
//! pinned); faces that can never touch a coarser tile have an empty strip; bad faces are 400
//! problems, unknown volumes and tiles 404, as on the tile route. The tile route sends version 3
//! (its moves, no strip) equal to the offline mesher's.

use isovox_proto::mesh::{decode_strip, decode_tile, encode_tile, Mesh, TileMesh, FACE_NAMES};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::{spawn, AppState, ServerConfig, Spawned};
use isovox_server::mesh::tile::{
    default_iso, mesh_strip_world, mesh_tile_with_moves, strip_inputs, tile_inputs, Stitching,
    TileScratch,
};
use isovox_server::store::{build_vod2, BuildOptions, Snapshot, Vod2};

struct Server {
    base: String,
    snap: std::sync::Arc<Snapshot>,
    _vod: Vod2,
    _server: Spawned,
    _dir: tempfile::TempDir,
}

/// A 64 x 48 x 64 world (brick 8: grids 8x6x8, 4x3x4, 2x2x2, 1x1x1), anisotropic voxels.
async fn start() -> Server {
    start_with(ServerConfig::default()).await
}

/// As [`start`], served with `config`.
async fn start_with(config: ServerConfig) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    let layout = VolumeLayout::new([64, 48, 64], 8, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [0.5, 1.0, 2.0],
        &WorldSource::new(layout.clone(), 3),
        &BuildOptions::default(),
    )
    .unwrap();
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    let catalog = Catalog::open_dir(dir.path()).unwrap();
    let server = spawn("127.0.0.1:0", AppState::with_config(catalog, config))
        .await
        .unwrap();
    Server {
        base: format!("{}/v1/volumes/w", server.base()),
        snap,
        _vod: vod,
        _server: server,
        _dir: dir,
    }
}

async fn get(url: &str, etag: Option<&str>) -> reqwest::Response {
    isovox_server::client_tls::install_provider();
    let mut r = reqwest::Client::new().get(url);
    if let Some(e) = etag {
        r = r.header("If-None-Match", e);
    }
    r.send().await.unwrap()
}

fn offline_strip(snap: &Snapshot, key: BrickKey, face: usize) -> Mesh {
    let mut s = Mesh::default();
    let iso = default_iso(VoxelType::U8);
    mesh_strip_world(snap, key, face, iso, &mut s, &mut TileScratch::default()).unwrap();
    s
}

fn path(key: BrickKey) -> String {
    format!("meshes/{}/{}/{}/{}", key.level, key.x, key.y, key.z)
}

#[tokio::test]
async fn strips_are_the_offline_meshers_and_cached_by_etag() {
    let s = start().await;
    // A level-0 tile with a non-empty strip on some face.
    let grid = s.snap.layout().grid(0);
    let (key, face, want) = (0..grid[2])
        .flat_map(|z| (0..grid[1]).flat_map(move |y| (0..grid[0]).map(move |x| (x, y, z))))
        .flat_map(|(x, y, z)| (0..6).map(move |f| (BrickKey { level: 0, x, y, z }, f)))
        .find_map(|(k, f)| {
            let strip = offline_strip(&s.snap, k, f);
            (!strip.is_empty()).then_some((k, f, strip))
        })
        .unwrap();
    let url = format!("{}/{}/strips/{}", s.base, path(key), FACE_NAMES[face]);
    let resp = get(&url, None).await;
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["content-type"], "application/x-isovox-mesh");
    assert_eq!(resp.headers()["cache-control"], "no-cache");
    let etag = resp.headers()["etag"].to_str().unwrap().to_string();
    assert!(etag.len() > 2 && etag.starts_with('"') && etag.ends_with('"'));
    let body = resp.bytes().await.unwrap();
    // Version 1, a plain mesh: the offline strip, positions bit for bit.
    assert_eq!(&body[4..6], &[1, 0]);
    let got = decode_strip(&body).unwrap();
    assert_eq!(got.positions, want.positions);
    assert_eq!(got.indices, want.indices);

    // Revalidation: 304, the same caching headers.
    let again = get(&url, Some(&etag)).await;
    assert_eq!(again.status(), 304);
    assert_eq!(again.headers()["cache-control"], "no-cache");
    // Pinned: the same ETag, cached for good; a version ahead is 404 as for the tile.
    let pinned = get(&format!("{url}?version=1"), None).await;
    assert_eq!(pinned.status(), 200);
    assert_eq!(pinned.headers()["etag"].to_str().unwrap(), etag);
    assert_eq!(
        pinned.headers()["cache-control"],
        "public, max-age=31536000, immutable"
    );
    assert_eq!(pinned.bytes().await.unwrap(), body);
    let ahead = get(&format!("{url}?version=99"), None).await.status();
    let tile_ahead = get(&format!("{}/{}?version=99", s.base, path(key)), None)
        .await
        .status();
    assert_eq!(ahead, tile_ahead);
    assert_eq!(ahead, 404);

    // Another face of the same tile, and the GLB form, have ETags of their own.
    let other = format!("{}/{}/strips/{}", s.base, path(key), FACE_NAMES[face ^ 1]);
    let other_etag = get(&other, None).await.headers()["etag"].clone();
    assert_ne!(other_etag.to_str().unwrap(), etag);
    let glb = get(&format!("{url}?format=glb"), None).await;
    assert_eq!(glb.headers()["content-type"], "model/gltf-binary");
    assert_ne!(glb.headers()["etag"].to_str().unwrap(), etag);
    let glb = glb.bytes().await.unwrap();
    let gltf = gltf::Gltf::from_slice(&glb).unwrap();
    let prim = gltf
        .document
        .meshes()
        .next()
        .unwrap()
        .primitives()
        .next()
        .unwrap();
    let blob = gltf.blob.as_deref().unwrap();
    let reader = prim.reader(|_| Some(blob));
    let positions: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
    assert_eq!(positions, want.positions);

    // The tile: version 3, its moves, the offline mesher's.
    let tile = get(&format!("{}/{}", s.base, path(key)), None).await;
    assert_eq!(tile.status(), 200);
    let tile = tile.bytes().await.unwrap();
    assert_eq!(&tile[4..6], &[3, 0]);
    let mut offline = TileMesh::default();
    let iso = default_iso(VoxelType::U8);
    mesh_tile_with_moves(&s.snap, key, iso, &mut offline, &mut TileScratch::default()).unwrap();
    assert_eq!(tile, encode_tile(&offline));
    assert!(!decode_tile(&tile).unwrap().moves.is_empty());
}

#[tokio::test]
async fn faces_without_a_coarser_neighbour_have_empty_strips() {
    let s = start().await;
    let empty = |body: &[u8]| decode_strip(body).unwrap() == Mesh::default();
    // -x of a first tile: the volume's boundary. The coarsest level: nothing coarser.
    for (p, face) in [
        ("meshes/0/0/2/3", "-x"),
        ("meshes/0/7/2/3", "+x"),
        ("meshes/3/0/0/0", "+y"),
    ] {
        let resp = get(&format!("{}/{p}/strips/{face}", s.base), None).await;
        assert_eq!(resp.status(), 200, "{p} {face}");
        assert!(empty(&resp.bytes().await.unwrap()), "{p} {face}");
    }
}

#[tokio::test]
async fn bad_faces_unknown_volumes_and_tiles_are_problems() {
    let s = start().await;
    for face in ["x", "7", "0", "+X", "%2Bxx", "-"] {
        let resp = get(&format!("{}/meshes/0/1/1/1/strips/{face}", s.base), None).await;
        assert_eq!(resp.status(), 400, "face {face}");
        assert_eq!(resp.headers()["content-type"], "application/problem+json");
        let text = resp.text().await.unwrap();
        assert!(text.contains("-x, +x, -y, +y, -z, +z"), "{text}");
    }
    // Percent-encoded names are the names.
    let resp = get(&format!("{}/meshes/0/1/1/1/strips/%2Bx", s.base), None).await;
    assert_eq!(resp.status(), 200);
    let unknown = s.base.replace("/volumes/w", "/volumes/nope");
    for (route, want) in [
        (format!("{unknown}/meshes/0/1/1/1/strips/+x"), 404),
        (format!("{}/meshes/0/8/1/1/strips/+x", s.base), 404),
        (format!("{}/meshes/9/0/0/0/strips/+x", s.base), 404),
    ] {
        let strip = get(&route, None).await.status();
        let tile = get(route.trim_end_matches("/strips/+x"), None)
            .await
            .status();
        assert_eq!(strip, want, "{route}");
        assert_eq!(strip, tile, "{route}: as the tile route");
    }
}

/// A counter from the server's `/metrics`.
async fn metric(base: &str, name: &str) -> u64 {
    let root = &base[..base.find("/v1/").unwrap()];
    let text = get(&format!("{root}/metrics"), None)
        .await
        .text()
        .await
        .unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {name} in the metrics"))
}

#[tokio::test]
async fn a_mesh_answer_asked_again_is_sent_as_kept_without_a_cpu_job() {
    let s = start().await;
    let jobs = |base: String| async move {
        metric(&base, "isovox_mesh_cache_hits_total").await
            + metric(&base, "isovox_mesh_cache_misses_total").await
    };
    let kept =
        |base: String| async move { metric(&base, "isovox_mesh_answers_kept_hits_total").await };
    // The level-0 tile with the most triangles (offline), so that its answer compresses, and
    // its face with the longest strip.
    let grid = s.snap.layout().grid(0);
    let iso = default_iso(VoxelType::U8);
    let triangles = |key: BrickKey| {
        let mut offline = TileMesh::default();
        mesh_tile_with_moves(&s.snap, key, iso, &mut offline, &mut TileScratch::default()).unwrap();
        offline.mesh.indices.len()
    };
    let key = (0..grid[2])
        .flat_map(|z| (0..grid[1]).flat_map(move |y| (0..grid[0]).map(move |x| (x, y, z))))
        .map(|(x, y, z)| BrickKey { level: 0, x, y, z })
        .max_by_key(|&k| triangles(k))
        .unwrap();
    let face = (0..6)
        .max_by_key(|&f| offline_strip(&s.snap, key, f).indices.len())
        .unwrap();
    let tile = format!("{}/{}", s.base, path(key));
    let strip = format!("{tile}/strips/{}", FACE_NAMES[face]);
    for url in [&tile, &strip] {
        let (jobs0, kept0) = (jobs(s.base.clone()).await, kept(s.base.clone()).await);
        let first = get(url, None).await;
        assert_eq!(first.status(), 200);
        let etag = first.headers()["etag"].clone();
        let first = first.bytes().await.unwrap();
        let again = get(url, None).await;
        assert_eq!(again.status(), 200);
        assert_eq!(again.headers()["etag"], etag);
        assert_eq!(again.bytes().await.unwrap(), first, "{url}");
        // One tile meshed or taken from the mesh cache, in a CPU job; the second answer kept.
        assert_eq!(jobs(s.base.clone()).await - jobs0, 1, "{url}");
        assert_eq!(kept(s.base.clone()).await - kept0, 1, "{url}");
        // Compressed for a client that takes zstd: an answer of its own, the same content.
        let zstd = reqwest::Client::new()
            .get(url.as_str())
            .header("Accept-Encoding", "zstd")
            .send()
            .await
            .unwrap();
        assert_eq!(zstd.headers()["content-encoding"], "zstd", "{url}");
        let packed = zstd.bytes().await.unwrap();
        assert_eq!(zstd::bulk::decompress(&packed, 1 << 24).unwrap(), first);
        assert_eq!(jobs(s.base.clone()).await - jobs0, 2, "{url}");
    }
}

/// Viewers starting together ask for the same coarse tiles at the same moment: the requests for
/// an answer being made wait for it instead of each taking a place in the CPU queue (16) for
/// the same work and the rest being refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn many_requests_for_one_cold_answer_share_one_cpu_job() {
    let s = start().await;
    let jobs = |base: String| async move {
        metric(&base, "isovox_mesh_cache_hits_total").await
            + metric(&base, "isovox_mesh_cache_misses_total").await
    };
    let shared = |base: String| async move {
        metric(&base, "isovox_mesh_answers_kept_hits_total").await
            + metric(&base, "isovox_mesh_answers_joined_total").await
    };
    let tile = format!("{}/meshes/1/1/1/1", s.base);
    let strip = format!("{tile}/strips/+y");
    const ASKED: usize = 48;
    for url in [&tile, &strip] {
        let (jobs0, shared0) = (jobs(s.base.clone()).await, shared(s.base.clone()).await);
        // Each on a connection of its own, all at once.
        let answers = futures_util::future::join_all((0..ASKED).map(|_| async {
            let r = get(url, None).await;
            (r.status().as_u16(), r.bytes().await.unwrap())
        }))
        .await;
        let statuses: Vec<u16> = answers.iter().map(|(status, _)| *status).collect();
        assert!(statuses.iter().all(|&s| s == 200), "{url}: {statuses:?}");
        assert!(!answers[0].1.is_empty(), "{url}");
        assert!(answers.iter().all(|(_, b)| *b == answers[0].1), "{url}");
        // Made once; every other request got that answer.
        assert_eq!(jobs(s.base.clone()).await - jobs0, 1, "{url}");
        assert_eq!(
            shared(s.base.clone()).await - shared0,
            ASKED as u64 - 1,
            "{url}"
        );
    }
}

/// Most tiles of a large world hold no surface (air, rock), and the bricks' value ranges in the
/// index say so: such a tile or strip is answered where it is read, not as a job of the CPU
/// queue. With one place in the queue, a burst of them is never refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiles_no_surface_crosses_are_answered_without_the_cpu_queue() {
    let s = start_with(ServerConfig {
        cpu_queue: 1,
        ..ServerConfig::default()
    })
    .await;
    let iso = default_iso(VoxelType::U8);
    let layout = s.snap.layout().clone();
    let mut urls = Vec::new();
    for level in 0..2 {
        let [gx, gy, gz] = layout.grid(level);
        for (x, y, z) in
            (0..gz).flat_map(|z| (0..gy).flat_map(move |y| (0..gx).map(move |x| (x, y, z))))
        {
            let key = BrickKey { level, x, y, z };
            let inputs = tile_inputs(&s.snap, key, iso, Stitching::Moves).unwrap();
            if inputs.may_cross {
                continue;
            }
            // Empty as the offline mesher makes it.
            let mut offline = TileMesh::default();
            mesh_tile_with_moves(&s.snap, key, iso, &mut offline, &mut TileScratch::default())
                .unwrap();
            assert!(offline.mesh.indices.is_empty(), "{key}");
            let tile = format!("{}/{}", s.base, path(key));
            // Its +x strip too when that cannot hold a surface either (it also reads the
            // coarser level beside the face).
            let strip = strip_inputs(&s.snap, key, 1, iso).unwrap();
            if !strip.may_cross || strip.faces >> 1 & 1 == 0 {
                assert!(offline_strip(&s.snap, key, 1).indices.is_empty(), "{key}");
                urls.push(format!("{tile}/strips/+x"));
            }
            urls.push(tile);
        }
    }
    assert!(urls.len() > 100, "{} empty tiles and strips", urls.len());
    let answers = futures_util::future::join_all(urls.iter().map(|url| async move {
        let r = get(url, None).await;
        (r.status().as_u16(), r.bytes().await.unwrap())
    }))
    .await;
    for ((status, body), url) in answers.iter().zip(&urls) {
        assert_eq!(*status, 200, "{url}");
        if url.contains("/strips/") {
            assert!(decode_strip(body).unwrap().indices.is_empty(), "{url}");
        } else {
            assert!(decode_tile(body).unwrap().mesh.indices.is_empty(), "{url}");
        }
    }
}
