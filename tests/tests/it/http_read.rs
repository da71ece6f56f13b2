//! The read side of the HTTP API against a real server on an ephemeral port: listing, metadata,
//! bricks byte-exact against the file (raw, lz4, zstd content encoding), ETag revalidation, and
//! every error status with its problem-details body.

use isovox_proto::api::{VolumeInfo, VolumeList};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::http::auth::{Scope, Tokens};
use isovox_server::http::{ServerConfig, Spawned};
use isovox_server::store::{build_vod2, BuildOptions, Vod2};
use std::path::{Path, PathBuf};

use crate::common;
use common::{problem, serve};

struct Server {
    base: String,
    path: PathBuf,
    _server: Spawned,
    _dir: tempfile::TempDir,
}

/// A 100x40x70 u8 world, brick 16, served as "terrain".
async fn start() -> Server {
    start_with(ServerConfig::default()).await
}

/// The same, served as `config` says.
async fn start_with(config: ServerConfig) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("terrain.vod");
    let layout = VolumeLayout::new([100, 40, 70], 16, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [0.5, 0.5, 0.5],
        &WorldSource::new(layout.clone(), 3),
        &BuildOptions::default(),
    )
    .unwrap();
    let server = serve(dir.path(), config).await;
    Server {
        base: server.base(),
        path,
        _server: server,
        _dir: dir,
    }
}

fn expected_brick(path: &Path, level: u8, x: u32, y: u32, z: u32) -> Vec<u8> {
    let vod = Vod2::open(path).unwrap();
    let snap = vod.head();
    snap.read(snap.layout().key(level, x, y, z).unwrap())
        .unwrap()
}

#[tokio::test]
async fn health_list_and_metadata() {
    let s = start().await;
    let c = common::http();
    let r = c.get(format!("{}/healthz", s.base)).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    assert_eq!(r.text().await.unwrap(), "ok");

    let list: VolumeList = serde_json::from_slice(
        &c.get(format!("{}/v1/volumes", s.base))
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap(),
    )
    .unwrap();
    assert_eq!(list.volumes.len(), 1);
    assert_eq!(list.volumes[0].name, "terrain");

    let info: VolumeInfo = serde_json::from_slice(
        &c.get(format!("{}/v1/volumes/terrain", s.base))
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap(),
    )
    .unwrap();
    assert_eq!(info.dims, [100, 40, 70]);
    assert_eq!((info.low, info.high, info.surface), (0, 255, 127));
    assert_eq!(info.brick, 16);
    assert_eq!(info.version, 1);
    assert_eq!(info.voxel_scale, [0.5; 3]);
    // Grids by hand: ceil(100/16)=7, ceil(40/16)=3, ceil(70/16)=5; then 4x2x3, 2x1x2, 1x1x1.
    let grids: Vec<[u32; 3]> = info.levels.iter().map(|l| l.grid).collect();
    assert_eq!(grids, vec![[7, 3, 5], [4, 2, 3], [2, 1, 2], [1, 1, 1]]);
    assert_eq!(info.levels[1].dims, [50, 20, 35]);
}

#[tokio::test]
async fn bricks_are_byte_exact_in_every_encoding() {
    let s = start().await;
    let c = common::http();
    let mut checked = 0;
    for (level, x, y, z) in [
        (0u8, 0u32, 0u32, 0u32),
        (0, 3, 1, 2),
        (0, 6, 2, 4),
        (1, 1, 0, 2),
        (3, 0, 0, 0),
    ] {
        let want = expected_brick(&s.path, level, x, y, z);
        let url = format!("{}/v1/volumes/terrain/bricks/{level}/{x}/{y}/{z}", s.base);

        let r = c.get(&url).send().await.unwrap();
        assert_eq!(r.status().as_u16(), 200);
        assert_eq!(r.headers()["content-type"], "application/octet-stream");
        let etag = r.headers()["etag"].to_str().unwrap().to_string();
        assert_eq!(
            etag,
            format!("\"{:016x}\"", isovox_proto::vod2::content_hash(&want))
        );
        assert_eq!(r.bytes().await.unwrap().to_vec(), want);

        let r = c
            .get(&url)
            .header("If-None-Match", &etag)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 304);
        assert!(r.bytes().await.unwrap().is_empty());
        let r = c
            .get(&url)
            .header("If-None-Match", "\"0000000000000000\"")
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200);

        let r = c
            .get(&url)
            .header("Accept", "application/x-lz4")
            .send()
            .await
            .unwrap();
        assert_eq!(r.headers()["content-type"], "application/x-lz4");
        let block = r.bytes().await.unwrap();
        let mut out = vec![0u8; want.len()];
        assert_eq!(
            lz4_flex::block::decompress_into(&block, &mut out).unwrap(),
            want.len()
        );
        assert_eq!(out, want);

        let r = c
            .get(&url)
            .header("Accept-Encoding", "zstd")
            .send()
            .await
            .unwrap();
        let encoded = r
            .headers()
            .get("content-encoding")
            .map(|v| v.to_str().unwrap().to_string());
        let body = r.bytes().await.unwrap();
        let got = if encoded.as_deref() == Some("zstd") {
            checked += 1;
            zstd::bulk::decompress(&body, want.len()).unwrap()
        } else {
            body.to_vec()
        };
        assert_eq!(got, want);
    }
    assert!(
        checked > 0,
        "at least one surface brick is stored as zstd and sent as it is"
    );
}

/// Plain brick requests are answered before the router (`http/fast_path.rs`); a query string
/// sends the same request through it. Both must give the same status, headers and body, for
/// stored and constant bricks, in every encoding, and for revalidations.
#[tokio::test]
async fn plain_brick_requests_are_answered_as_the_router_answers_them() {
    let s = start().await;
    let c = common::http();
    let vod = Vod2::open(&s.path).unwrap();
    let head = vod.head();
    let layout = head.layout().clone();
    let (mut stored, mut constant) = (0, 0);
    for level in 0..layout.levels() {
        let g = layout.grid(level);
        for (x, y, z) in [
            (0, 0, 0),
            (g[0] - 1, g[1] - 1, g[2] - 1),
            (g[0] / 2, 0, g[2] / 2),
        ] {
            let key = layout.key(level, x, y, z).unwrap();
            match head.stored(key).unwrap() {
                isovox_server::store::StoredBrick::Constant(_) => constant += 1,
                isovox_server::store::StoredBrick::Record { .. } => stored += 1,
            }
            let plain = format!("{}/v1/volumes/terrain/bricks/{level}/{x}/{y}/{z}", s.base);
            let routed = format!("{plain}?version={}", head.version);
            let etag = format!(
                "\"{:016x}\"",
                isovox_proto::vod2::content_hash(&expected_brick(&s.path, level, x, y, z))
            );
            for headers in [
                vec![],
                vec![("accept", "application/x-lz4")],
                vec![("accept-encoding", "zstd")],
                vec![("if-none-match", etag.as_str())],
                vec![("if-none-match", "\"0000000000000000\"")],
            ] {
                let mut answers = Vec::new();
                for url in [&plain, &routed] {
                    let mut req = c.get(url);
                    for (k, v) in &headers {
                        req = req.header(*k, *v);
                    }
                    let r = req.send().await.unwrap();
                    let status = r.status().as_u16();
                    let mut h: Vec<(String, String)> = r
                        .headers()
                        .iter()
                        .filter(|(k, _)| k.as_str() != "date")
                        .map(|(k, v)| (k.to_string(), v.to_str().unwrap().to_string()))
                        .collect();
                    h.sort();
                    answers.push((status, h, r.bytes().await.unwrap()));
                }
                assert_eq!(
                    answers[0], answers[1],
                    "brick {level}/{x}/{y}/{z} with {headers:?}: plain and routed answers differ"
                );
                assert!(matches!(answers[0].0, 200 | 304));
            }
        }
    }
    assert!(
        stored > 0 && constant > 0,
        "{stored} stored, {constant} constant"
    );
    // Answered before the router, still counted under the brick route.
    let text = c
        .get(format!("{}/metrics", s.base))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let count: u64 = text
        .lines()
        .find_map(|l| {
            l.strip_prefix(
                "isovox_request_seconds_count{route=\"/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}\"} ",
            )
        })
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(count, u64::from(layout.levels()) * 3 * 5 * 2);
}

/// With private reads, bricks need a token on both the plain and the routed way.
#[tokio::test]
async fn private_reads_guard_bricks() {
    let mut tokens = Tokens::default();
    tokens
        .add("viewer", "a-read-secret-of-enough-length", Scope::Read)
        .unwrap();
    let s = start_with(ServerConfig {
        tokens,
        private_reads: true,
        ..ServerConfig::default()
    })
    .await;
    let c = common::http();
    for url in [
        "/v1/volumes/terrain/bricks/0/1/1/1",
        "/v1/volumes/terrain/bricks/0/1/1/1?version=1",
        "/v1/volumes/terrain/blobs/0123456789abcdef",
        "/v1/volumes/terrain",
    ] {
        let url = format!("{}{url}", s.base);
        let get = |token: Option<&str>| {
            let req = c.get(&url);
            match token {
                Some(t) => req.bearer_auth(t).send(),
                None => req.send(),
            }
        };
        problem(get(None).await.unwrap(), 401).await;
        problem(get(Some("not-the-secret-at-all")).await.unwrap(), 401).await;
        let r = get(Some("a-read-secret-of-enough-length")).await.unwrap();
        assert_ne!(r.status().as_u16(), 401, "{url}");
        assert_ne!(r.status().as_u16(), 403, "{url}");
    }
}

/// A token limited to other volumes is refused (403, naming the volume) for reads with private
/// reads and for edits; a token limited to this volume, or to none, is let through.
#[tokio::test]
async fn tokens_limited_to_volumes_are_refused_elsewhere() {
    let tokens = Tokens::parse(
        "elsewhere a-secret-for-other-volumes-only write other,more\n\
         here a-secret-for-the-terrain-only-1 write terrain\n\
         everywhere a-secret-for-every-volume-22 read *\n",
    )
    .unwrap();
    let s = start_with(ServerConfig {
        tokens,
        private_reads: true,
        ..ServerConfig::default()
    })
    .await;
    let c = common::http();
    let carve = r#"{"op":"difference","term":{"ellipsoid":{"center":[20,20,20],"radii":[4,4,4]}}}"#;
    let brick = format!("{}/v1/volumes/terrain/bricks/0/1/1/1", s.base);
    let edits = format!("{}/v1/volumes/terrain/edits", s.base);

    let refused = c.get(&brick).bearer_auth("a-secret-for-other-volumes-only");
    let p = problem(refused.send().await.unwrap(), 403).await;
    assert!(p.detail.contains("\"terrain\""), "{}", p.detail);
    let refused = c
        .post(&edits)
        .bearer_auth("a-secret-for-other-volumes-only")
        .header("content-type", "application/json")
        .body(carve);
    let p = problem(refused.send().await.unwrap(), 403).await;
    assert!(p.detail.contains("elsewhere"), "{}", p.detail);

    let read = c.get(&brick).bearer_auth("a-secret-for-every-volume-22");
    assert_eq!(read.send().await.unwrap().status().as_u16(), 200);
    let read = c.get(&brick).bearer_auth("a-secret-for-the-terrain-only-1");
    assert_eq!(read.send().await.unwrap().status().as_u16(), 200);
    let edit = c
        .post(&edits)
        .bearer_auth("a-secret-for-the-terrain-only-1")
        .header("content-type", "application/json")
        .body(carve);
    assert_eq!(edit.send().await.unwrap().status().as_u16(), 200);
    // The list names no volume: any token of the scope may read it.
    let list = c
        .get(format!("{}/v1/volumes", s.base))
        .bearer_auth("a-secret-for-other-volumes-only");
    assert_eq!(list.send().await.unwrap().status().as_u16(), 200);
}

#[tokio::test]
async fn errors_are_problem_details() {
    let s = start().await;
    let c = common::http();
    let get = |p: &str| c.get(format!("{}{p}", s.base)).send();
    let p = problem(get("/v1/volumes/nope").await.unwrap(), 404).await;
    assert!(p.detail.contains("nope"));
    problem(get("/v1/volumes/nope/bricks/0/0/0/0").await.unwrap(), 404).await;
    let p = problem(
        get("/v1/volumes/terrain/bricks/0/7/0/0").await.unwrap(),
        404,
    )
    .await;
    assert!(p.detail.contains("out of range"), "{}", p.detail);
    problem(
        get("/v1/volumes/terrain/bricks/9/0/0/0").await.unwrap(),
        404,
    )
    .await;
    problem(
        get("/v1/volumes/terrain/bricks/0/x/0/0").await.unwrap(),
        400,
    )
    .await;
    problem(
        get("/v1/volumes/terrain/bricks/0/-1/0/0").await.unwrap(),
        400,
    )
    .await;
    problem(
        get("/v1/volumes/terrain/bricks/0/0/0/0?version=7")
            .await
            .unwrap(),
        404,
    )
    .await;
    // A name is a tag's (none here); text that is neither a number nor a tag's name is a
    // malformed request.
    problem(
        get("/v1/volumes/terrain/bricks/0/0/0/0?version=seven")
            .await
            .unwrap(),
        404,
    )
    .await;
    problem(
        get("/v1/volumes/terrain/bricks/0/0/0/0?version=seven!")
            .await
            .unwrap(),
        400,
    )
    .await;
    problem(get("/v1/nothing/here").await.unwrap(), 404).await;
}

#[tokio::test]
async fn mesh_tiles_match_the_offline_mesher() {
    use isovox_proto::mesh::{decode_compact, Mesh};
    use isovox_server::mesh::tile::{default_iso, mesh_tile, TileScratch};
    let s = start().await;
    let c = common::http();
    let vod = Vod2::open(&s.path).unwrap();
    let snap = vod.head();
    let mut nonempty = 0;
    for (level, x, y, z) in [
        (0u8, 2u32, 1u32, 2u32),
        (0, 0, 0, 0),
        (0, 6, 2, 4),
        (1, 1, 0, 1),
        (3, 0, 0, 0),
    ] {
        let key = snap.layout().key(level, x, y, z).unwrap();
        let mut want = Mesh::default();
        mesh_tile(
            &snap,
            key,
            default_iso(VoxelType::U8),
            &mut want,
            &mut TileScratch::default(),
        )
        .unwrap();
        let url = format!("{}/v1/volumes/terrain/meshes/{level}/{x}/{y}/{z}", s.base);
        let r = c.get(&url).send().await.unwrap();
        assert_eq!(r.status().as_u16(), 200);
        assert_eq!(r.headers()["content-type"], "application/x-isovox-mesh");
        let etag = r.headers()["etag"].to_str().unwrap().to_string();
        let got = decode_compact(&r.bytes().await.unwrap()).unwrap();
        assert_eq!(got.positions, want.positions, "tile {key}");
        assert_eq!(got.indices, want.indices, "tile {key}");
        nonempty += usize::from(!want.is_empty());
        // Twice more: from the cache, same bytes; and revalidation.
        let again =
            decode_compact(&c.get(&url).send().await.unwrap().bytes().await.unwrap()).unwrap();
        assert_eq!(again.positions, want.positions);
        let r = c
            .get(&url)
            .header("If-None-Match", &etag)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 304);
        let r = c.get(format!("{url}?format=glb")).send().await.unwrap();
        assert_eq!(r.headers()["content-type"], "model/gltf-binary");
        assert_eq!(&r.bytes().await.unwrap()[..4], b"glTF");
    }
    assert!(nonempty >= 2, "some chosen tiles cross the terrain");
    let get = |p: String| c.get(p).send();
    problem(
        get(format!(
            "{}/v1/volumes/terrain/meshes/0/0/0/0?format=stl",
            s.base
        ))
        .await
        .unwrap(),
        400,
    )
    .await;
    problem(
        get(format!("{}/v1/volumes/terrain/meshes/0/0/9/0", s.base))
            .await
            .unwrap(),
        404,
    )
    .await;
    problem(
        get(format!(
            "{}/v1/volumes/terrain/meshes/0/0/0/0?iso=abc",
            s.base
        ))
        .await
        .unwrap(),
        400,
    )
    .await;
    let p = problem(
        get(format!(
            "{}/v1/volumes/terrain/meshes/0/0/0/0?format=obj",
            s.base
        ))
        .await
        .unwrap(),
        400,
    )
    .await;
    assert!(
        p.detail.contains("compact") && p.detail.contains("glb"),
        "{}",
        p.detail
    );
    // An iso outside the u8 volume's [0, 255] would put every voxel on one side of the
    // surface: 400 naming the range, not an empty tile. Its ends are values like any other.
    for iso in ["256", "-0.5", "65535", "1e39", "NaN", "inf"] {
        let p = problem(
            get(format!(
                "{}/v1/volumes/terrain/meshes/0/2/1/2?iso={iso}",
                s.base
            ))
            .await
            .unwrap(),
            400,
        )
        .await;
        assert!(p.detail.contains("[0, 255]"), "iso={iso}: {}", p.detail);
    }
    // Tile 0/0/0/0 too: its strips reach into the padding below the volume.
    for (tile, iso) in [
        ("2/1/2", "0"),
        ("2/1/2", "255"),
        ("2/1/2", "127.5"),
        ("0/0/0", "0"),
        ("0/0/0", "0.5"),
    ] {
        let r = get(format!(
            "{}/v1/volumes/terrain/meshes/0/{tile}?iso={iso}",
            s.base
        ))
        .await
        .unwrap();
        assert_eq!(r.status().as_u16(), 200, "iso={iso}");
    }
}
