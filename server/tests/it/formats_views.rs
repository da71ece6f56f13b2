//! The Zarr and precomputed views over HTTP, byte for byte against the file: a Zarr chunk is the
//! stored zstd frame itself when the brick is stored as one (with its content size), a valid
//! frame of the brick otherwise, 404 for a brick of zeros; a precomputed chunk is the brick
//! cropped at the volume's far faces (cropped here by index arithmetic, not by the server's
//! code); caching headers, 304s, pinned versions (404 ahead, 410 compacted away); errors; and an
//! export holds exactly the bytes the server sends.

use isovox_proto::vod2::Codec;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::formats::export::{chunk_path, export_view};
use isovox_server::formats::ViewKind;
use isovox_server::http::auth::{Scope, Tokens};
use isovox_server::http::{spawn, AppState, ServerConfig, Spawned};
use isovox_server::progress::Silent;
use isovox_server::store::{build_vod2, BuildOptions, DenseGrid, StoredBrick, Vod2};
use std::path::PathBuf;

const TOKEN: &str = "a-write-token-long-enough";
/// 37 x 21 x 19 u16 voxels, brick 8: every axis ends in a partial brick.
const DIMS: [u32; 3] = [37, 21, 19];

struct Server {
    base: String,
    path: PathBuf,
    _server: Spawned,
    dir: tempfile::TempDir,
}

/// Voxels that make every kind of stored brick: zeros (x < 8: constant 0), a constant 7
/// (8 <= x < 16), a smooth ramp (zstd), and noise past x = 24 (stored raw: it does not
/// compress).
fn voxels() -> Vec<u8> {
    let mut out = Vec::new();
    let mut s = 0x2545_F491_4F6C_DD1Du64;
    for z in 0..DIMS[2] {
        for y in 0..DIMS[1] {
            for x in 0..DIMS[0] {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                let v: u16 = match x {
                    0..8 => 0,
                    8..16 => 7,
                    16..24 => (x * 100 + y * 10 + z) as u16,
                    _ => s as u16,
                };
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    out
}

async fn start() -> Server {
    start_with_queue(isovox_server::http::cpu::default_queue()).await
}

/// As [`start`], with `cpu_queue` places in the server's CPU queue.
async fn start_with_queue(cpu_queue: usize) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mixed.vod");
    let layout = VolumeLayout::new(DIMS, 8, VoxelType::U16).unwrap();
    let bytes = voxels();
    build_vod2(
        &path,
        &layout,
        [0.5, 1.0, 2.0],
        &DenseGrid::new(DIMS, VoxelType::U16, 8, &bytes),
        &BuildOptions::default(),
    )
    .unwrap();
    let catalog = Catalog::open_dir(dir.path()).unwrap();
    let mut tokens = Tokens::default();
    tokens.add("tester", TOKEN, Scope::Write).unwrap();
    let config = ServerConfig {
        tokens,
        cpu_queue,
        ..ServerConfig::default()
    };
    let server = spawn("127.0.0.1:0", AppState::with_config(catalog, config))
        .await
        .unwrap();
    Server {
        base: format!("{}/v1/volumes/mixed", server.base()),
        path,
        _server: server,
        dir,
    }
}

async fn get(url: &str) -> reqwest::Response {
    isovox_server::client_tls::install_provider();
    reqwest::get(url).await.unwrap()
}

#[tokio::test]
async fn zarr_chunks_are_stored_frames_or_frames_of_the_brick() {
    let s = start().await;
    let vod = Vod2::open(&s.path).unwrap();
    let snap = vod.head();
    let layout = snap.layout().clone();
    let mut seen = [0usize; 4]; // zero constants, other constants, zstd records, raw records
    for level in 0..layout.levels() {
        let [gx, gy, gz] = layout.grid(level);
        for (x, y, z) in
            (0..gz).flat_map(|z| (0..gy).flat_map(move |y| (0..gx).map(move |x| (x, y, z))))
        {
            let key = BrickKey { level, x, y, z };
            let resp = get(&format!("{}/zarr/{level}/c/{z}/{y}/{x}", s.base)).await;
            let status = resp.status().as_u16();
            let body = resp.bytes().await.unwrap();
            match snap.stored(key).unwrap() {
                StoredBrick::Constant(0) => {
                    assert_eq!(status, 404, "{key}: a brick of zeros is the fill value");
                    seen[0] += 1;
                    continue;
                }
                StoredBrick::Constant(_) => seen[1] += 1,
                StoredBrick::Record {
                    header, payload, ..
                } => {
                    if header.codec == Codec::Zstd {
                        assert_eq!(
                            &body[..],
                            payload,
                            "{key}: the stored frame goes out as it is"
                        );
                        seen[2] += 1;
                    } else {
                        seen[3] += 1;
                    }
                }
            }
            assert_eq!(status, 200, "{key}");
            // Every chunk is one zstd frame that records its content size (one brick).
            assert_eq!(
                zstd::zstd_safe::get_frame_content_size(&body).unwrap(),
                Some(layout.brick_bytes() as u64),
                "{key}"
            );
            let decoded = zstd::bulk::decompress(&body, layout.brick_bytes()).unwrap();
            assert_eq!(
                decoded,
                snap.read(key).unwrap(),
                "{key}: the chunk is the brick"
            );
        }
    }
    assert!(
        seen.iter().all(|&n| n > 0),
        "every kind of brick was met: {seen:?}"
    );
}

/// Brick `key` cropped to the level's extent, by index arithmetic.
fn cropped(snap: &isovox_server::store::Snapshot, key: BrickKey) -> Vec<u8> {
    let layout = snap.layout();
    let b = layout.brick() as usize;
    let brick = snap.read(key).unwrap();
    let extent = layout.level_dims(key.level);
    let origin = [key.x, key.y, key.z].map(|c| c as usize * b);
    let mut out = Vec::new();
    for z in 0..b {
        for y in 0..b {
            for x in 0..b {
                let inside = [x, y, z]
                    .iter()
                    .enumerate()
                    .all(|(a, &v)| origin[a] + v < extent[a] as usize);
                if inside {
                    let i = ((z * b + y) * b + x) * 2;
                    out.extend_from_slice(&brick[i..i + 2]);
                }
            }
        }
    }
    out
}

/// A client reading a level asks for many chunks at once (tensorstore: 32). Chunks that must be
/// made (compressed, or decoded and cropped) take places in the CPU queue; a burst larger than
/// the queue waits for places instead of being refused with 503s.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_of_chunks_to_make_waits_for_the_cpu_queue() {
    let s = start_with_queue(1).await;
    let vod = Vod2::open(&s.path).unwrap();
    let snap = vod.head();
    let layout = snap.layout().clone();
    // Every chunk the server must make: bricks not stored as a zstd frame, of every level, in
    // both views (a precomputed chunk of a stored frame is decoded and cropped too).
    let mut urls = Vec::new();
    for level in 0..layout.levels() {
        let [gx, gy, gz] = layout.grid(level);
        for (x, y, z) in
            (0..gz).flat_map(|z| (0..gy).flat_map(move |y| (0..gx).map(move |x| (x, y, z))))
        {
            let key = BrickKey { level, x, y, z };
            if matches!(snap.stored(key).unwrap(), StoredBrick::Constant(0)) {
                continue;
            }
            let [x0, y0, z0] = [x, y, z].map(|c| c * layout.brick());
            let dims = layout.level_dims(level);
            let [x1, y1, z1] =
                [0, 1, 2].map(|a| (([x, y, z][a] + 1) * layout.brick()).min(dims[a]));
            urls.push(format!(
                "{}/precomputed/{level}/{x0}-{x1}_{y0}-{y1}_{z0}-{z1}",
                s.base
            ));
            if !matches!(
                snap.stored(key).unwrap(),
                StoredBrick::Record { header, .. } if header.codec == Codec::Zstd
            ) {
                urls.push(format!("{}/zarr/{level}/c/{z}/{y}/{x}", s.base));
            }
        }
    }
    assert!(urls.len() > 40, "{} chunks to make", urls.len());
    isovox_server::client_tls::install_provider();
    let client = reqwest::Client::new();
    let answers = futures_util::future::join_all(urls.iter().map(|url| {
        let client = client.clone();
        async move { client.get(url).send().await.unwrap().status().as_u16() }
    }))
    .await;
    let refused = answers.iter().filter(|&&status| status != 200).count();
    assert_eq!(refused, 0, "{answers:?}");
}

/// A streamer asks for a level's grid in regions (512 bricks each), and many viewers starting
/// at once ask for hundreds: small regions are answered where they are read, so a burst of
/// them far larger than the CPU queue is never refused with 503s.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_of_grid_regions_is_answered_without_the_cpu_queue() {
    let s = start_with_queue(1).await;
    let layout = Vod2::open(&s.path).unwrap().head().layout().clone();
    // Every brick of every level as a region of its own, each asked twice.
    let mut urls = Vec::new();
    for level in 0..layout.levels() {
        let [gx, gy, gz] = layout.grid(level);
        for (x, y, z) in
            (0..gz).flat_map(|z| (0..gy).flat_map(move |y| (0..gx).map(move |x| (x, y, z))))
        {
            let url = format!(
                "{}/levels/{level}?format=grid&region={x},{y},{z},{},{},{}",
                s.base,
                x + 1,
                y + 1,
                z + 1
            );
            urls.push(url.clone());
            urls.push(url);
        }
    }
    assert!(urls.len() > 40, "{} regions", urls.len());
    isovox_server::client_tls::install_provider();
    let client = reqwest::Client::new();
    let answers = futures_util::future::join_all(urls.iter().map(|url| {
        let client = client.clone();
        async move {
            let response = client.get(url).send().await.unwrap();
            let status = response.status().as_u16();
            let grid: serde_json::Value = if status == 200 {
                response.json().await.unwrap()
            } else {
                serde_json::Value::Null
            };
            (status, grid["bricks"].as_array().map_or(0, Vec::len))
        }
    }))
    .await;
    let refused = answers.iter().filter(|(status, _)| *status != 200).count();
    assert_eq!(refused, 0, "{answers:?}");
    // Each answer lists its one brick.
    assert!(
        answers.iter().all(|&(_, bricks)| bricks == 1),
        "{answers:?}"
    );
}

#[tokio::test]
async fn precomputed_chunks_are_bricks_cropped_at_the_far_faces() {
    let s = start().await;
    let vod = Vod2::open(&s.path).unwrap();
    let snap = vod.head();
    let layout = snap.layout().clone();
    let info: serde_json::Value = get(&format!("{}/precomputed/info", s.base))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(info["scales"][0]["size"], serde_json::json!([37, 21, 19]));
    assert_eq!(
        info["scales"][1]["resolution"],
        serde_json::json!([1.0, 2.0, 4.0])
    );
    for level in 0..layout.levels() {
        let [gx, gy, gz] = layout.grid(level);
        let extent = layout.level_dims(level);
        for (x, y, z) in
            (0..gz).flat_map(|z| (0..gy).flat_map(move |y| (0..gx).map(move |x| (x, y, z))))
        {
            let key = BrickKey { level, x, y, z };
            let range = |c: u32, a: usize| format!("{}-{}", c * 8, (c * 8 + 8).min(extent[a]));
            let url = format!(
                "{}/precomputed/{level}/{}_{}_{}",
                s.base,
                range(x, 0),
                range(y, 1),
                range(z, 2)
            );
            let resp = get(&url).await;
            assert_eq!(resp.status(), 200, "{url}");
            assert_eq!(
                resp.bytes().await.unwrap().to_vec(),
                cropped(&snap, key),
                "{url}"
            );
        }
    }
}

#[tokio::test]
async fn bad_paths_are_400_or_404_problems() {
    let s = start().await;
    for (path, status) in [
        ("precomputed/0/1-9_0-8_0-8", 400),   // misaligned
        ("precomputed/0/32-40_0-8_0-8", 400), // the last x chunk ends at 37
        ("precomputed/0/0-8_0-8", 400),       // two ranges
        ("precomputed/0/x-8_0-8_0-8", 400),
        ("precomputed/0/40-48_0-8_0-8", 404), // past the extent
        ("precomputed/9/0-8_0-8_0-8", 404),   // no such level
        ("precomputed/01/0-8_0-8_0-8", 404),
        ("precomputed/provenance", 404),
        ("zarr/0/c/0/0/5", 404), // x grid is 5 bricks: 0..4
        ("zarr/0/c/0/0", 404),
        ("zarr/7/zarr.json", 404),
        ("zarr/.zattrs", 404),
        ("versions/2/zarr/zarr.json", 404), // not yet
        ("versions/0/zarr/zarr.json", 404),
        ("versions/x/zarr/zarr.json", 400),
    ] {
        let resp = get(&format!("{}/{path}", s.base)).await;
        assert_eq!(resp.status().as_u16(), status, "{path}");
        assert_eq!(
            resp.headers()["content-type"],
            "application/problem+json",
            "{path}"
        );
    }
    let unknown = get(&s.base.replace("/mixed", "/nothing/zarr/zarr.json")).await;
    assert_eq!(unknown.status(), 404);
}

#[tokio::test]
async fn live_views_revalidate_and_pinned_views_never_change() {
    let s = start().await;
    isovox_server::client_tls::install_provider();
    let client = reqwest::Client::new();
    let live = get(&format!("{}/zarr/0/c/1/1/2", s.base)).await;
    assert_eq!(live.status(), 200);
    assert_eq!(live.headers()["cache-control"], "public, max-age=1");
    let etag = live.headers()["etag"].to_str().unwrap().to_string();
    assert!(
        etag.starts_with('"') && !etag.starts_with("W/"),
        "a strong ETag: {etag}"
    );
    let location = live.headers()["content-location"]
        .to_str()
        .unwrap()
        .to_string();
    assert_eq!(location, "/v1/volumes/mixed/versions/1/zarr/0/c/1/1/2");
    let body = live.bytes().await.unwrap();
    let revalidated = client
        .get(format!("{}/zarr/0/c/1/1/2", s.base))
        .header("If-None-Match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(revalidated.status(), 304);
    let origin = s.base.split("/v1/").next().unwrap();
    let pinned = get(&format!("{origin}{location}")).await;
    assert_eq!(
        pinned.headers()["cache-control"],
        "public, max-age=31536000, immutable"
    );
    assert_eq!(pinned.bytes().await.unwrap(), body);

    // An edit fills the volume with H: the live chunk changes, the pinned one does not.
    let edit = client
        .post(format!("{}/edits", s.base))
        .bearer_auth(TOKEN)
        .json(&serde_json::json!({"op": "union", "term": {"cuboid": {"origin": [0, 0, 0], "size": [37, 21, 19]}}}))
        .send()
        .await
        .unwrap();
    assert_eq!(edit.status(), 200, "{}", edit.text().await.unwrap());
    let after = get(&format!("{}/zarr/0/c/1/1/2", s.base)).await;
    assert_ne!(after.headers()["etag"].to_str().unwrap(), etag);
    assert_eq!(
        after.headers()["content-location"],
        "/v1/volumes/mixed/versions/2/zarr/0/c/1/1/2"
    );
    let full = zstd::bulk::decompress(&after.bytes().await.unwrap(), 1024).unwrap();
    assert!(
        full.chunks(2).all(|v| v == [0xff, 0xff]),
        "the edited chunk is all H"
    );
    assert_eq!(
        get(&format!("{origin}{location}"))
            .await
            .bytes()
            .await
            .unwrap(),
        body
    );
    let stale = client
        .get(format!("{}/zarr/0/c/1/1/2", s.base))
        .header("If-None-Match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(stale.status(), 200, "the old ETag no longer matches");

    // Compaction keeps only version 2: version 1 is gone for good.
    let compact = client
        .post(format!("{}/compact", s.base))
        .bearer_auth(TOKEN)
        .send()
        .await
        .unwrap();
    assert_eq!(compact.status(), 200);
    assert_eq!(get(&format!("{origin}{location}")).await.status(), 410);
    assert_eq!(
        get(&format!("{}/versions/2/precomputed/info", s.base))
            .await
            .status(),
        200
    );
}

#[tokio::test]
async fn an_export_holds_the_bytes_the_server_sends() {
    let s = start().await;
    let vod = Vod2::open(&s.path).unwrap();
    let snap = vod.head();
    let layout = snap.layout().clone();
    for kind in [ViewKind::Zarr, ViewKind::Precomputed] {
        let dest = s.dir.path().join(kind.segment());
        let report = export_view(&snap, kind, "mixed", &dest, &Silent).unwrap();
        assert!(report.chunks > 0);
        let mut files = 0;
        for level in 0..layout.levels() {
            let [gx, gy, gz] = layout.grid(level);
            for (x, y, z) in
                (0..gz).flat_map(|z| (0..gy).flat_map(move |y| (0..gx).map(move |x| (x, y, z))))
            {
                let rel = chunk_path(kind, &layout, BrickKey { level, x, y, z });
                let resp = get(&format!("{}/{}/{rel}", s.base, kind.segment())).await;
                let on_disk = std::fs::read(dest.join(&rel));
                if resp.status() == 404 {
                    assert!(on_disk.is_err(), "{rel}: absent chunks are left out");
                    continue;
                }
                assert_eq!(
                    on_disk.unwrap(),
                    resp.bytes().await.unwrap().to_vec(),
                    "{rel}"
                );
                files += 1;
            }
        }
        assert_eq!(files as u64, report.chunks);
        let meta = if kind == ViewKind::Zarr {
            "zarr.json"
        } else {
            "info"
        };
        assert_eq!(
            std::fs::read(dest.join(meta)).unwrap(),
            get(&format!("{}/{}/{meta}", s.base, kind.segment()))
                .await
                .bytes()
                .await
                .unwrap()
                .to_vec()
        );
        // A second export to the same place is refused and leaves the first intact.
        assert!(export_view(&snap, kind, "mixed", &dest, &Silent).is_err());
        assert!(dest.join(meta).exists());
    }
}

/// Every file of an export of a volume with a material channel, labels and segmentation sources
/// included, holds the bytes the server sends for that path; and there are such files for the
/// channel (metadata and chunks).
#[tokio::test]
async fn an_export_of_a_volume_with_channels_holds_the_bytes_the_server_sends() {
    use isovox_server::generate::{world_header, WorldMaterials, WorldSource};
    use isovox_server::store::build::build_streams_file;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("world.vod");
    let layout = VolumeLayout::new([45, 30, 37], 8, VoxelType::U8).unwrap();
    let world = WorldSource::new(layout.clone(), 3);
    let materials = WorldMaterials::new(world.clone());
    build_streams_file(
        &path,
        world_header(&layout).unwrap(),
        &[&world, &materials],
        &BuildOptions::default(),
    )
    .unwrap();
    let catalog = Catalog::open_dir(dir.path()).unwrap();
    let server = spawn(
        "127.0.0.1:0",
        AppState::with_config(catalog, ServerConfig::default()),
    )
    .await
    .unwrap();
    let base = format!("{}/v1/volumes/world", server.base());
    let snap = Vod2::open(&path).unwrap().head();
    for (kind, channel_dir) in [
        (ViewKind::Zarr, "labels/material"),
        (ViewKind::Precomputed, "material"),
    ] {
        let dest = dir.path().join(format!("export-{}", kind.segment()));
        export_view(&snap, kind, "world", &dest, &Silent).unwrap();
        let mut files = Vec::new();
        let mut stack = vec![dest.clone()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    files.push(p);
                }
            }
        }
        let rels: Vec<String> = files
            .iter()
            .map(|f| {
                f.strip_prefix(&dest)
                    .unwrap()
                    .to_string_lossy()
                    .into_owned()
            })
            .collect();
        let of_channel = rels.iter().filter(|r| r.starts_with(channel_dir)).count();
        assert!(
            of_channel > layout.levels() as usize,
            "{kind:?}: {of_channel} files of the channel: {rels:?}"
        );
        for (file, rel) in files.iter().zip(&rels) {
            let resp = get(&format!("{base}/{}/{rel}", kind.segment())).await;
            assert_eq!(resp.status(), 200, "{kind:?} {rel}");
            assert_eq!(
                std::fs::read(file).unwrap(),
                resp.bytes().await.unwrap().to_vec(),
                "{kind:?} {rel}"
            );
        }
    }
}

/// Each document has one URL: a number in a path or `?version=` is read only in plain decimal
/// (no sign, no leading zero, no percent-escape); any other spelling is a 404 problem, and only
/// the canonical spelling answers 200. (Every spelling used to answer 200, so caches kept one
/// chunk under many keys; `00` was a 404 where `%30` was a 200.)
#[tokio::test]
async fn numbers_in_urls_have_one_spelling() {
    let s = start().await;
    // Chunk (z, y, x) = (1, 0, 1) of level 0 is in the constant-7 slab: not the fill value.
    let cases: [(&str, &[&str]); 9] = [
        (
            "zarr/0/c/1/0/1",
            &[
                "zarr/0/c/+1/0/1",
                "zarr/0/c/01/0/1",
                "zarr/0/c/%31/0/1",
                "zarr/0/c/1/0/%31",
                "zarr/0/c/1/00/1",
                "zarr/%30/c/1/0/1",
                "zarr/00/c/1/0/1",
                "zarr/+0/c/1/0/1",
            ],
        ),
        (
            "zarr/0/zarr.json",
            &[
                "zarr/%30/zarr.json",
                "zarr/+0/zarr.json",
                "zarr/0/zarr%2Ejson",
            ],
        ),
        (
            "precomputed/0/0-8_0-8_0-8",
            &[
                "precomputed/0/+0-+8_0-8_0-8",
                "precomputed/0/00-08_0-8_0-8",
                "precomputed/0/0-8_0-8_0-%38",
                "precomputed/%30/0-8_0-8_0-8",
                "precomputed/+0/0-8_0-8_0-8",
            ],
        ),
        (
            "versions/1/zarr/0/c/1/0/1",
            &[
                "versions/+1/zarr/0/c/1/0/1",
                "versions/01/zarr/0/c/1/0/1",
                "versions/%31/zarr/0/c/1/0/1",
                "versions/1/zarr/0/c/01/0/1",
            ],
        ),
        (
            "versions/1/precomputed/info",
            &[
                "versions/+1/precomputed/info",
                "versions/01/precomputed/info",
            ],
        ),
        (
            "bricks/0/1/0/0",
            &[
                "bricks/+0/1/0/0",
                "bricks/00/1/0/0",
                "bricks/0/01/0/0",
                "bricks/0/+1/0/0",
                "bricks/0/%31/0/0",
                "bricks/0/1/0/%30",
            ],
        ),
        (
            "bricks/0/1/0/0?version=1",
            &[
                "bricks/0/1/0/0?version=01",
                "bricks/0/1/0/0?version=+1",
                "bricks/0/1/0/0?version=%2B1",
                "bricks/0/1/0/0?version=%31",
            ],
        ),
        (
            "meshes/0/1/0/0/strips/+x",
            &[
                "meshes/0/01/0/0/strips/+x",
                "meshes/%30/1/0/0/strips/+x",
                "meshes/0/1/0/0/strips/+x?version=01",
            ],
        ),
        (
            "levels/0",
            &[
                "levels/00",
                "levels/+0",
                "levels/%30",
                "levels/0?version=+1",
            ],
        ),
    ];
    for (canonical, others) in cases {
        let resp = get(&format!("{}/{canonical}", s.base)).await;
        assert_eq!(resp.status(), 200, "{canonical}");
        for other in others {
            let resp = get(&format!("{}/{other}", s.base)).await;
            assert_eq!(
                resp.status(),
                404,
                "{other} (the canonical {canonical} is a 200)"
            );
            assert_eq!(
                resp.headers()["content-type"],
                "application/problem+json",
                "{other}"
            );
        }
    }
    // The problem says why: the spelling, not a chunk outside the grid.
    for other in [
        "zarr/0/c/+1/0/1",
        "precomputed/0/00-08_0-8_0-8",
        "versions/01/zarr/zarr.json",
        "bricks/0/1/0/0?version=%31",
    ] {
        let problem: serde_json::Value = get(&format!("{}/{other}", s.base))
            .await
            .json()
            .await
            .unwrap();
        let detail = problem["detail"].as_str().unwrap();
        assert!(detail.contains("plain decimal"), "{other}: {detail}");
    }
    // Text that is no number stays a malformed request, as before; but `?version=` also takes
    // a tag's name, and a name no tag has is not found.
    for (path, status) in [
        ("bricks/0/x/0/0", 400),
        ("bricks/0/-1/0/0", 400),
        ("bricks/0/1/0/0?version=x", 404),
        ("bricks/0/1/0/0?version=x!", 400),
        ("bricks/0/4294967296/0/0", 400),
        ("levels/x", 400),
        ("versions/x/precomputed/info", 400),
        ("precomputed/0/x-8_0-8_0-8", 400),
        ("zarr/0/c/x/0/1", 404),
    ] {
        let resp = get(&format!("{}/{path}", s.base)).await;
        assert_eq!(resp.status().as_u16(), status, "{path}");
    }
}
