//! The rest of the HTTP read side against a real server on an ephemeral port: bricks by content
//! hash, batches, level grids and voxels, Prometheus metrics, the OpenAPI document, and 503 under
//! overload. Every expected value comes from reading the same files directly (`Vod2::open`) or
//! from arithmetic by hand, never from the handlers' code paths.

use isovox_proto::api::LevelGrid;
use isovox_proto::batch::{decode_batch, BatchCodec, BatchEntry};
use isovox_proto::vod2::{content_hash, Codec};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::{EllipsoidSource, WorldSource};
use isovox_server::http::{spawn, AppState, Spawned};
use isovox_server::store::codec::Compression;
use isovox_server::store::{build_vod2, BrickSource, BuildOptions, Snapshot, StoredBrick, Vod2};
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::common;
use common::problem;

const BRICK_ROUTE: &str = "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}";
const MESH_ROUTE: &str = "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}";

/// The volumes a test server may serve.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Vol {
    /// 100x40x70 u8 world, brick 16, zstd (the default): zstd bricks, constants (air, solid).
    Terrain,
    /// 80x48x40 u16 world, brick 16, lz4: stored lz4 blocks, u16 constants.
    Dunes,
    /// 40x40x40 u8 ellipsoid, brick 8, uncompressed: raw records.
    Plain,
    /// 512x256x257 u16 of air, brick 32: level 0 is 67,371,008 bytes as voxels, over 64 MiB.
    Big,
}

impl Vol {
    fn name(self) -> &'static str {
        match self {
            Vol::Terrain => "terrain",
            Vol::Dunes => "dunes",
            Vol::Plain => "plain",
            Vol::Big => "big",
        }
    }
}

/// Level 0 all L, answered without touching voxels.
#[derive(Debug)]
struct Air;

impl BrickSource for Air {
    fn fill(&self, _: BrickKey, _: &mut [u8]) {}
    fn constant(&self, _: BrickKey) -> Option<u64> {
        Some(0)
    }
}

fn build(dir: &Path, vol: Vol) -> PathBuf {
    let path = dir.join(format!("{}.vod", vol.name()));
    let (dims, brick, t, compression) = match vol {
        Vol::Terrain => ([100, 40, 70], 16, VoxelType::U8, Compression::default()),
        Vol::Dunes => ([80, 48, 40], 16, VoxelType::U16, Compression::Lz4),
        Vol::Plain => ([40, 40, 40], 8, VoxelType::U8, Compression::None),
        Vol::Big => ([512, 256, 257], 32, VoxelType::U16, Compression::default()),
    };
    let layout = VolumeLayout::new(dims, brick, t).unwrap();
    let source: Box<dyn BrickSource> = match vol {
        Vol::Terrain => Box::new(WorldSource::new(layout.clone(), 3)),
        Vol::Dunes => Box::new(WorldSource::new(layout.clone(), 5)),
        Vol::Plain => Box::new(EllipsoidSource::new(layout.clone())),
        Vol::Big => Box::new(Air),
    };
    let options = BuildOptions {
        compression,
        ..BuildOptions::default()
    };
    build_vod2(&path, &layout, [1.0; 3], source.as_ref(), &options).unwrap();
    path
}

struct Server {
    base: String,
    paths: HashMap<Vol, PathBuf>,
    _server: Spawned,
    _dir: tempfile::TempDir,
}

impl Server {
    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// The newest version of a served volume, read straight from its file.
    fn snap(&self, vol: Vol) -> Arc<Snapshot> {
        Vod2::open(&self.paths[&vol]).unwrap().head()
    }
}

async fn start(vols: &[Vol], cpu_queue: usize) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let paths = vols.iter().map(|&v| (v, build(dir.path(), v))).collect();
    let catalog = Catalog::open_dir(dir.path()).unwrap();
    assert_eq!(catalog.len(), vols.len());
    let server = spawn("127.0.0.1:0", AppState::new(catalog, 64 << 20, cpu_queue))
        .await
        .unwrap();
    Server {
        base: server.base(),
        paths,
        _server: server,
        _dir: dir,
    }
}

fn header(resp: &reqwest::Response, name: &str) -> Option<String> {
    resp.headers()
        .get(name)
        .map(|v| v.to_str().unwrap().to_string())
}

/// Every key of every level, in node order.
fn all_keys(layout: &VolumeLayout) -> Vec<BrickKey> {
    let mut keys = Vec::new();
    for level in 0..layout.levels() {
        let g = layout.grid(level);
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    keys.push(BrickKey { level, x, y, z });
                }
            }
        }
    }
    keys
}

/// A brick filled with `v` by hand: u8 bricks take the low byte, u16 bricks little endian.
fn filled(layout: &VolumeLayout, v: u16) -> Vec<u8> {
    match layout.voxel_type() {
        VoxelType::U8 => vec![v as u8; layout.brick_voxels()],
        VoxelType::U16 => v.to_le_bytes().repeat(layout.brick_voxels()),
        other => panic!("these volumes' density is u8 or u16, not {other}"),
    }
}

/// Smallest and largest voxel of decoded bytes, by hand.
fn min_max(bytes: &[u8], t: VoxelType) -> (u16, u16) {
    let values: Vec<u16> = match t {
        VoxelType::U8 => bytes.iter().map(|&b| b as u16).collect(),
        VoxelType::U16 => bytes
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect(),
        other => panic!("these volumes' density is u8 or u16, not {other}"),
    };
    (*values.iter().min().unwrap(), *values.iter().max().unwrap())
}

// ---------------------------------------------------------------------------------------------
// 1. Blobs by content hash.

/// Bricks worth fetching by hash: per volume, the first constant and the first record of each
/// codec at level 0, the first record above level 0, and the root.
fn blob_samples(snap: &Snapshot) -> Vec<BrickKey> {
    let layout = snap.layout();
    let mut picked = Vec::new();
    let mut seen = HashSet::new();
    for key in all_keys(layout) {
        let class = match snap.stored(key).unwrap() {
            StoredBrick::Constant(v) => format!("L{} constant {v}", key.level.min(1)),
            StoredBrick::Record { header, .. } => {
                format!("L{} {:?}", key.level.min(1), header.codec)
            }
        };
        if seen.insert(class) {
            picked.push(key);
        }
    }
    let root = all_keys(layout).pop().unwrap();
    if !picked.contains(&root) {
        picked.push(root);
    }
    picked
}

#[tokio::test]
async fn blobs_by_content_hash() {
    let s = start(&[Vol::Terrain, Vol::Dunes, Vol::Plain], 16).await;
    let c = common::http();
    let mut seen_codecs = HashSet::new();
    let (mut constants, mut coarse, mut zstd_sent, mut lz4_as_stored) = (0, 0, 0, 0);
    for vol in [Vol::Terrain, Vol::Dunes, Vol::Plain] {
        let snap = s.snap(vol);
        for key in blob_samples(&snap) {
            let want = snap.read(key).unwrap();
            let hash = format!("{:016x}", snap.hash(key).unwrap());
            let stored = snap.stored(key).unwrap();
            let url = s.url(&format!("/v1/volumes/{}/blobs/{hash}", vol.name()));
            let ctx = format!("{} {key}", vol.name());
            match stored {
                StoredBrick::Constant(_) => constants += 1,
                StoredBrick::Record { header, .. } => {
                    seen_codecs.insert(header.codec as u8);
                }
            }
            coarse += usize::from(key.level > 0);

            let r = c.get(&url).send().await.unwrap();
            assert_eq!(r.status().as_u16(), 200, "{ctx}");
            assert_eq!(
                header(&r, "cache-control").as_deref(),
                Some("public, max-age=31536000, immutable"),
                "{ctx}"
            );
            assert_eq!(header(&r, "etag"), Some(format!("\"{hash}\"")), "{ctx}");
            assert_eq!(
                header(&r, "content-type").as_deref(),
                Some("application/octet-stream")
            );
            assert_eq!(header(&r, "content-encoding"), None, "{ctx}");
            assert_eq!(r.bytes().await.unwrap().to_vec(), want, "{ctx}");

            // Revalidation: the hash itself, a list holding it, and a different one.
            for inm in [
                format!("\"{hash}\""),
                format!("\"0\", \"{hash}\""),
                "*".to_string(),
            ] {
                let r = c
                    .get(&url)
                    .header("If-None-Match", inm)
                    .send()
                    .await
                    .unwrap();
                assert_eq!(r.status().as_u16(), 304, "{ctx}");
                assert_eq!(header(&r, "etag"), Some(format!("\"{hash}\"")));
                assert_eq!(
                    header(&r, "cache-control").as_deref(),
                    Some("public, max-age=31536000, immutable")
                );
                assert!(r.bytes().await.unwrap().is_empty());
            }
            let r = c
                .get(&url)
                .header("If-None-Match", "\"ffffffffffffffff\"")
                .send()
                .await
                .unwrap();
            assert_eq!(r.status().as_u16(), 200, "{ctx}");

            // lz4 block: the stored one when the brick is stored as lz4.
            let r = c
                .get(&url)
                .header("Accept", "application/x-lz4")
                .send()
                .await
                .unwrap();
            assert_eq!(r.status().as_u16(), 200, "{ctx}");
            assert_eq!(
                header(&r, "content-type").as_deref(),
                Some("application/x-lz4"),
                "{ctx}"
            );
            let block = r.bytes().await.unwrap();
            let mut out = vec![0u8; want.len()];
            assert_eq!(
                lz4_flex::block::decompress_into(&block, &mut out).unwrap(),
                want.len(),
                "{ctx}"
            );
            assert_eq!(out, want, "{ctx}");
            if let StoredBrick::Record {
                header: h, payload, ..
            } = stored
            {
                if h.codec == Codec::Lz4 {
                    assert_eq!(&block[..], payload, "{ctx}: the stored lz4 block as it is");
                    lz4_as_stored += 1;
                }
            }

            // zstd content encoding: only for bricks stored as zstd.
            let r = c
                .get(&url)
                .header("Accept-Encoding", "gzip, zstd")
                .send()
                .await
                .unwrap();
            assert_eq!(r.status().as_u16(), 200, "{ctx}");
            let encoding = header(&r, "content-encoding");
            let body = r.bytes().await.unwrap();
            match stored {
                StoredBrick::Record {
                    header: h, payload, ..
                } if h.codec == Codec::Zstd => {
                    assert_eq!(encoding.as_deref(), Some("zstd"), "{ctx}");
                    assert_eq!(&body[..], payload, "{ctx}: the stored zstd frame as it is");
                    assert_eq!(
                        zstd::bulk::decompress(&body, want.len()).unwrap(),
                        want,
                        "{ctx}"
                    );
                    zstd_sent += 1;
                }
                _ => {
                    assert_eq!(encoding, None, "{ctx}");
                    assert_eq!(body.to_vec(), want, "{ctx}");
                }
            }
        }
    }
    assert!(constants >= 3, "constant bricks checked: {constants}");
    assert!(coarse >= 3, "coarse bricks checked: {coarse}");
    assert!(zstd_sent >= 1 && lz4_as_stored >= 1);
    assert_eq!(
        seen_codecs.len(),
        3,
        "raw, lz4 and zstd records all checked"
    );

    // Errors.
    let get = |p: String| c.get(s.url(&p)).send();
    let terrain = s.snap(Vol::Terrain);
    let hashes: HashSet<u64> = all_keys(terrain.layout())
        .into_iter()
        .map(|k| terrain.hash(k).unwrap())
        .collect();
    let absent = (0x0123_4567_89ab_cdefu64..)
        .find(|h| !hashes.contains(h))
        .unwrap();
    let p = problem(
        get(format!("/v1/volumes/terrain/blobs/{absent:016x}"))
            .await
            .unwrap(),
        404,
    )
    .await;
    assert!(p.detail.contains(&format!("{absent:016x}")), "{}", p.detail);
    // A hash of another volume is unknown here.
    let dunes = s.snap(Vol::Dunes);
    let foreign = all_keys(dunes.layout())
        .into_iter()
        .map(|k| dunes.hash(k).unwrap())
        .find(|h| !hashes.contains(h))
        .unwrap();
    problem(
        get(format!("/v1/volumes/terrain/blobs/{foreign:016x}"))
            .await
            .unwrap(),
        404,
    )
    .await;
    let known = format!("{:016x}", hashes.iter().next().unwrap());
    problem(
        get(format!("/v1/volumes/nope/blobs/{known}"))
            .await
            .unwrap(),
        404,
    )
    .await;
    for bad in [
        "xyz",
        "0123",
        "0123456789abcde",
        "0123456789abcdef0",
        "0123456789abcdeg",
        "%200123456789abcde",
    ] {
        problem(
            get(format!("/v1/volumes/terrain/blobs/{bad}"))
                .await
                .unwrap(),
            400,
        )
        .await;
    }
}

/// Not 16 hex digits, yet `u64::from_str_radix` takes a leading `+`: the hash must be refused
/// as malformed (400), as the handler's own message and the OpenAPI pattern say.
#[tokio::test]
async fn blob_hash_with_a_sign_is_malformed() {
    let s = start(&[Vol::Plain], 16).await;
    let c = common::http();
    let r = c
        .get(s.url("/v1/volumes/plain/blobs/+123456789abcdef"))
        .send()
        .await
        .unwrap();
    problem(r, 400).await;
}

/// RFC 9110 section 13.1.2: If-None-Match compares entity tags weakly, so `W/"<hash>"` (what a
/// cache or proxy that re-encodes bodies sends back) names the same representation: 304.
#[tokio::test]
async fn weak_if_none_match_revalidates() {
    let s = start(&[Vol::Plain], 16).await;
    let c = common::http();
    let snap = s.snap(Vol::Plain);
    let root = all_keys(snap.layout()).pop().unwrap();
    let hash = format!("{:016x}", snap.hash(root).unwrap());
    for url in [
        s.url(&format!("/v1/volumes/plain/blobs/{hash}")),
        s.url(&format!(
            "/v1/volumes/plain/bricks/{}/{}/{}/{}",
            root.level, root.x, root.y, root.z
        )),
    ] {
        let r = c
            .get(&url)
            .header("If-None-Match", format!("W/\"{hash}\""))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 304, "{url}");
    }
}

// ---------------------------------------------------------------------------------------------
// 2. Batches.

async fn post_batch(
    c: &reqwest::Client,
    s: &Server,
    name: &str,
    body: String,
) -> reqwest::Response {
    c.post(s.url(&format!("/v1/volumes/{name}/batch")))
        .header("content-type", "application/json")
        .body(body)
        .send()
        .await
        .unwrap()
}

fn keys_json(keys: &[BrickKey]) -> String {
    let items: Vec<String> = keys
        .iter()
        .map(|k| format!("[{},{},{},{}]", k.level, k.x, k.y, k.z))
        .collect();
    format!("[{}]", items.join(","))
}

/// A mix in no particular order: coarse levels first, then every fourth level-0 brick backwards,
/// then duplicates of the first and of the root.
fn batch_keys(layout: &VolumeLayout) -> Vec<BrickKey> {
    let all = all_keys(layout);
    let (l0, coarse): (Vec<BrickKey>, Vec<BrickKey>) = all.iter().partition(|k| k.level == 0);
    let mut keys = coarse.clone();
    keys.extend(l0.iter().rev().step_by(4));
    keys.push(keys[0]);
    keys.push(*all.last().unwrap());
    keys.push(l0[0]);
    keys
}

async fn batch_ok(c: &reqwest::Client, s: &Server, name: &str, body: String) -> Vec<BatchEntry> {
    let r = post_batch(c, s, name, body).await;
    assert_eq!(r.status().as_u16(), 200, "{name}");
    assert_eq!(
        header(&r, "content-type").as_deref(),
        Some("application/x-isovox-bricks")
    );
    decode_batch(&r.bytes().await.unwrap()).unwrap()
}

#[tokio::test]
async fn batches_match_the_file() {
    let s = start(&[Vol::Terrain, Vol::Dunes, Vol::Plain], 16).await;
    let c = common::http();
    let mut by_codec: HashMap<u8, usize> = HashMap::new();
    for vol in [Vol::Terrain, Vol::Dunes, Vol::Plain] {
        let snap = s.snap(vol);
        let layout = snap.layout();
        let keys = batch_keys(layout);
        assert!(keys.len() > 20);

        // Raw (the default, and by name).
        for body in [
            format!("{{\"keys\": {}}}", keys_json(&keys)),
            format!("{{\"keys\": {}, \"encoding\": \"raw\"}}", keys_json(&keys)),
            format!(
                "{{\"encoding\": \"raw\", \"version\": 1, \"keys\": {}}}",
                keys_json(&keys)
            ),
        ] {
            let entries = batch_ok(&c, &s, vol.name(), body).await;
            assert_eq!(entries.len(), keys.len());
            for (e, &key) in entries.iter().zip(&keys) {
                assert_eq!(e.key, key, "{}: order preserved", vol.name());
                assert_eq!(e.codec, BatchCodec::Raw);
                assert_eq!(e.payload, snap.read(key).unwrap(), "{} {key}", vol.name());
                assert_eq!(e.hash, content_hash(&e.payload));
                assert_eq!(e.hash, snap.hash(key).unwrap());
            }
        }

        // Stored: each entry decoded by its codec.
        let body = format!(
            "{{\"keys\": {}, \"encoding\": \"stored\"}}",
            keys_json(&keys)
        );
        let entries = batch_ok(&c, &s, vol.name(), body).await;
        assert_eq!(entries.len(), keys.len());
        for (e, &key) in entries.iter().zip(&keys) {
            let ctx = format!("{} {key}", vol.name());
            assert_eq!(e.key, key, "{ctx}: order preserved");
            let want = snap.read(key).unwrap();
            let got = match e.codec {
                BatchCodec::Raw => e.payload.clone(),
                BatchCodec::Lz4 => {
                    let mut out = vec![0u8; want.len()];
                    assert_eq!(
                        lz4_flex::block::decompress_into(&e.payload, &mut out).unwrap(),
                        want.len()
                    );
                    out
                }
                BatchCodec::Zstd => zstd::bulk::decompress(&e.payload, want.len()).unwrap(),
                BatchCodec::Constant => {
                    assert_eq!(e.payload.len(), 2, "{ctx}");
                    filled(layout, u16::from_le_bytes([e.payload[0], e.payload[1]]))
                }
            };
            assert_eq!(got, want, "{ctx}");
            assert_eq!(e.hash, snap.hash(key).unwrap(), "{ctx}");
            assert_eq!(e.hash, content_hash(&want), "{ctx}");
            match snap.stored(key).unwrap() {
                StoredBrick::Constant(v) => {
                    assert_eq!(e.codec, BatchCodec::Constant, "{ctx}");
                    // Density bricks: the value as a u16, whatever the voxel type.
                    assert_eq!(e.payload, u16::try_from(v).unwrap().to_le_bytes());
                }
                StoredBrick::Record {
                    header: h, payload, ..
                } => {
                    let codec = match h.codec {
                        Codec::Raw => BatchCodec::Raw,
                        Codec::Lz4 => BatchCodec::Lz4,
                        Codec::Zstd => BatchCodec::Zstd,
                        Codec::Palette => panic!("{ctx}: a density brick in the palette codec"),
                    };
                    assert_eq!(e.codec, codec, "{ctx}");
                    assert_eq!(e.payload, payload, "{ctx}: as stored");
                }
            }
            *by_codec.entry(e.codec as u8).or_default() += 1;
        }
    }
    assert_eq!(by_codec.len(), 4, "every batch codec seen: {by_codec:?}");

    // An empty batch is a batch.
    let entries = batch_ok(&c, &s, "plain", "{\"keys\": []}".into()).await;
    assert!(entries.is_empty());
    // The largest batch allowed: 4096 duplicates of the root.
    let root = all_keys(s.snap(Vol::Plain).layout()).pop().unwrap();
    let body = format!("{{\"keys\": {}}}", keys_json(&vec![root; 4096]));
    let entries = batch_ok(&c, &s, "plain", body).await;
    assert_eq!(entries.len(), 4096);
    assert!(entries.iter().all(|e| e.key == root));
}

#[tokio::test]
async fn batch_errors_are_problem_details() {
    let s = start(&[Vol::Terrain, Vol::Big], 16).await;
    let c = common::http();
    // Malformed JSON, of every kind.
    for body in [
        "",
        "{\"keys\": [",
        "[[0,0,0,0]]",
        "{\"keys\": [[0,0,0]]}",
        "{\"keys\": [[0,0,0,0,0]]}",
        "{\"keys\": [[0,-1,0,0]]}",
        "{\"keys\": [[256,0,0,0]]}",
        "{\"keys\": [[0,0,0,0]], \"encoding\": \"lz4\"}",
        "{\"keys\": [[0,0,0,0]], \"extra\": 1}",
        "{\"version\": 1}",
    ] {
        problem(post_batch(&c, &s, "terrain", body.into()).await, 400).await;
    }
    // Keys outside the volume (grid 7x3x5 at level 0; 4 levels), a version it lacks, a volume
    // that is not served.
    for body in [
        "{\"keys\": [[0,0,0,0],[0,7,0,0]]}",
        "{\"keys\": [[0,0,3,0]]}",
        "{\"keys\": [[3,1,0,0]]}",
        "{\"keys\": [[4,0,0,0]]}",
        "{\"keys\": [[0,0,0,0]], \"version\": 2}",
    ] {
        problem(post_batch(&c, &s, "terrain", body.into()).await, 404).await;
    }
    problem(
        post_batch(&c, &s, "nope", "{\"keys\": [[0,0,0,0]]}".into()).await,
        404,
    )
    .await;
    // Too many keys.
    let body = format!(
        "{{\"keys\": {}}}",
        keys_json(&vec![
            BrickKey {
                level: 0,
                x: 0,
                y: 0,
                z: 0
            };
            4097
        ])
    );
    let p = problem(post_batch(&c, &s, "terrain", body).await, 413).await;
    assert!(p.detail.contains("4097"), "{}", p.detail);
    // Raw bricks of "big" are 32^3 x 2 = 65,536 bytes: 1025 of them exceed 64 MiB, while the
    // same keys stored (constants, two bytes each) are fine, up to 4096.
    let big = BrickKey {
        level: 0,
        x: 15,
        y: 7,
        z: 8,
    };
    let body = format!("{{\"keys\": {}}}", keys_json(&vec![big; 1025]));
    let p = problem(post_batch(&c, &s, "big", body).await, 413).await;
    assert!(p.detail.contains("65536"), "{}", p.detail);
    let body = format!(
        "{{\"keys\": {}, \"encoding\": \"stored\"}}",
        keys_json(&vec![big; 4096])
    );
    let entries = batch_ok(&c, &s, "big", body).await;
    assert_eq!(entries.len(), 4096);
    assert!(entries
        .iter()
        .all(|e| e.key == big && e.codec == BatchCodec::Constant && e.payload == [0, 0]));
    // A body over 1 MiB, however few keys it holds.
    let body = format!("{{\"keys\": [[0,0,0,0]]{}}}", " ".repeat(1 << 20));
    problem(post_batch(&c, &s, "terrain", body).await, 413).await;
    // Only POST.
    let r = c
        .get(s.url("/v1/volumes/terrain/batch"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 405);
    assert_eq!(header(&r, "allow").as_deref(), Some("POST,OPTIONS"));
}

/// Browsers: every response lets any origin read it (and the headers it needs, such as ETag),
/// and a preflight on any route allows the methods and request headers the API uses.
#[tokio::test]
async fn cors_for_browsers() {
    let s = start(&[Vol::Plain], 16).await;
    let c = common::http();
    for url in [
        "/v1/volumes",
        "/v1/volumes/plain/bricks/0/0/0/0",
        "/v1/volumes/nope",
        "/healthz",
    ] {
        let r = c
            .get(s.url(url))
            .header("origin", "https://viewer.example")
            .send()
            .await
            .unwrap();
        assert_eq!(
            header(&r, "access-control-allow-origin").as_deref(),
            Some("*"),
            "{url}"
        );
        assert_eq!(
            header(&r, "access-control-expose-headers").as_deref(),
            Some("*"),
            "{url}"
        );
    }
    for (url, method) in [
        ("/v1/volumes/plain/bricks/0/0/0/0", "GET"),
        ("/v1/volumes/plain/edits", "POST"),
        ("/v1/volumes/plain/batch", "POST"),
        ("/v1/volumes/plain/events", "GET"),
    ] {
        let r = c
            .request(reqwest::Method::OPTIONS, s.url(url))
            .header("origin", "https://viewer.example")
            .header("access-control-request-method", method)
            .header(
                "access-control-request-headers",
                "authorization, content-type, if-match",
            )
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 204, "{url}");
        assert_eq!(
            header(&r, "access-control-allow-origin").as_deref(),
            Some("*")
        );
        let methods = header(&r, "access-control-allow-methods").unwrap();
        assert!(methods.contains(method), "{url}: {methods}");
        let allowed = header(&r, "access-control-allow-headers").unwrap();
        for h in ["authorization", "content-type", "if-match", "if-none-match"] {
            assert!(allowed.contains(h), "{url}: {allowed}");
        }
    }
}

/// A batch whose body is JSON but whose media type is not: axum's `Json` rejects it with 415
/// Unsupported Media Type, and the OpenAPI document lists 415 for this operation.
#[tokio::test]
async fn batch_of_the_wrong_media_type_is_415() {
    let s = start(&[Vol::Plain], 16).await;
    let c = common::http();
    // Not JSON by content type: the body is fine, the media type is not.
    for ctype in [
        Some("text/plain"),
        Some("application/x-www-form-urlencoded"),
        None,
    ] {
        let mut req = c
            .post(s.url("/v1/volumes/plain/batch"))
            .body("{\"keys\": [[0,0,0,0]]}");
        if let Some(t) = ctype {
            req = req.header("content-type", t);
        }
        let r = req.send().await.unwrap();
        problem(r, 415).await;
    }
}

// ---------------------------------------------------------------------------------------------
// 3. Levels.

async fn level_grid(c: &reqwest::Client, s: &Server, query: &str) -> LevelGrid {
    let r = c.get(s.url(query)).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200, "{query}");
    assert_eq!(
        header(&r, "content-type").as_deref(),
        Some("application/json"),
        "{query}"
    );
    serde_json::from_slice(&r.bytes().await.unwrap()).unwrap()
}

/// Checks a grid answer against the file: the box `min..max` of `level`, x fastest.
fn check_grid(snap: &Snapshot, g: &LevelGrid, level: u8, min: [u32; 3], max: [u32; 3]) {
    let layout = snap.layout();
    assert_eq!(g.level, level);
    assert_eq!(g.grid, layout.grid(level));
    assert_eq!((g.min, g.max), (min, max));
    assert_eq!(g.version, snap.version);
    let mut want = Vec::new();
    for z in min[2]..max[2] {
        for y in min[1]..max[1] {
            for x in min[0]..max[0] {
                want.push(layout.key(level, x, y, z).unwrap());
            }
        }
    }
    assert_eq!(g.bricks.len(), want.len());
    for (b, key) in g.bricks.iter().zip(want) {
        assert_eq!(b.hash, format!("{:016x}", snap.hash(key).unwrap()), "{key}");
        let (lo, hi) = min_max(&snap.read(key).unwrap(), layout.voxel_type());
        assert_eq!((b.min, b.max), (lo.into(), hi.into()), "{key}");
        assert_eq!((b.min, b.max), snap.stored(key).unwrap().min_max(), "{key}");
    }
}

/// The voxels of the box `min..max` (voxels) of `level`, x fastest, read brick by brick.
fn voxels_by_hand(snap: &Snapshot, level: u8, min: [u32; 3], max: [u32; 3]) -> Vec<u8> {
    let layout = snap.layout();
    let b = layout.brick();
    let vb = layout.voxel_type().bytes();
    let mut bricks: HashMap<[u32; 3], Vec<u8>> = HashMap::new();
    let mut out = Vec::new();
    for z in min[2]..max[2] {
        for y in min[1]..max[1] {
            for x in min[0]..max[0] {
                let at = [x / b, y / b, z / b];
                let brick = bricks.entry(at).or_insert_with(|| {
                    snap.read(layout.key(level, at[0], at[1], at[2]).unwrap())
                        .unwrap()
                });
                let i = ((((z % b) * b + y % b) * b + x % b) as usize) * vb;
                out.extend_from_slice(&brick[i..i + vb]);
            }
        }
    }
    out
}

async fn level_voxels(c: &reqwest::Client, s: &Server, query: &str) -> Vec<u8> {
    let r = c.get(s.url(query)).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200, "{query}");
    assert_eq!(
        header(&r, "content-type").as_deref(),
        Some("application/octet-stream"),
        "{query}"
    );
    r.bytes().await.unwrap().to_vec()
}

#[tokio::test]
async fn levels_match_the_file() {
    let s = start(&[Vol::Terrain, Vol::Dunes, Vol::Big], 16).await;
    let c = common::http();
    let snap = s.snap(Vol::Terrain);
    let layout = snap.layout();
    // Grids by hand: 100x40x70 with brick 16.
    let grids: Vec<[u32; 3]> = (0..layout.levels()).map(|l| layout.grid(l)).collect();
    assert_eq!(grids, vec![[7, 3, 5], [4, 2, 3], [2, 1, 2], [1, 1, 1]]);
    for level in 0..layout.levels() {
        let g = level_grid(&c, &s, &format!("/v1/volumes/terrain/levels/{level}")).await;
        check_grid(&snap, &g, level, [0; 3], grids[level as usize]);
        let g = level_grid(
            &c,
            &s,
            &format!("/v1/volumes/terrain/levels/{level}?format=grid&version=1"),
        )
        .await;
        check_grid(&snap, &g, level, [0; 3], grids[level as usize]);
    }
    let g = level_grid(&c, &s, "/v1/volumes/terrain/levels/0?region=2,1,1,5,3,4").await;
    check_grid(&snap, &g, 0, [2, 1, 1], [5, 3, 4]);
    assert_eq!(g.bricks.len(), 3 * 2 * 3);
    let g = level_grid(&c, &s, "/v1/volumes/terrain/levels/1?region=3,1,2,4,2,3").await;
    check_grid(&snap, &g, 1, [3, 1, 2], [4, 2, 3]);
    assert_eq!(g.bricks.len(), 1);

    // Voxels: whole coarse levels (50x20x35, 25x10x18, 13x5x9 by hand), regions of level 0
    // (one inside, one at the far corner where the edge bricks hold L beyond the volume).
    for (level, dims) in [(1u8, [50u32, 20, 35]), (2, [25, 10, 18]), (3, [13, 5, 9])] {
        assert_eq!(layout.level_dims(level), dims);
        let got = level_voxels(
            &c,
            &s,
            &format!("/v1/volumes/terrain/levels/{level}?format=voxels"),
        )
        .await;
        assert_eq!(got.len(), (dims[0] * dims[1] * dims[2]) as usize);
        assert_eq!(
            got,
            voxels_by_hand(&snap, level, [0; 3], dims),
            "level {level}"
        );
    }
    for (region, min, max) in [
        ("5,3,7,42,33,40", [5, 3, 7], [42, 33, 40]),
        ("90,30,60,100,40,70", [90, 30, 60], [100, 40, 70]),
        ("0,0,0,100,40,70", [0, 0, 0], [100, 40, 70]),
        ("17,17,17,18,18,18", [17, 17, 17], [18, 18, 18]),
    ] {
        let got = level_voxels(
            &c,
            &s,
            &format!("/v1/volumes/terrain/levels/0?format=voxels&region={region}"),
        )
        .await;
        assert_eq!(got, voxels_by_hand(&snap, 0, min, max), "region {region}");
    }
    // u16: two bytes a voxel, little endian.
    let dunes = s.snap(Vol::Dunes);
    let got = level_voxels(
        &c,
        &s,
        "/v1/volumes/dunes/levels/0?format=voxels&region=10,5,3,70,47,33",
    )
    .await;
    assert_eq!(got.len(), 60 * 42 * 30 * 2);
    assert_eq!(got, voxels_by_hand(&dunes, 0, [10, 5, 3], [70, 47, 33]));
    let got = level_voxels(&c, &s, "/v1/volumes/dunes/levels/1?format=voxels").await;
    assert_eq!(got, voxels_by_hand(&dunes, 1, [0; 3], [40, 24, 20]));

    // Errors: a malformed query is 400; a region reaching beyond the level is 404, as a brick
    // beyond the grid is.
    let get = |p: &str| c.get(s.url(p)).send();
    for q in [
        "region=1,2,3",
        "region=1,2,3,4,5,6,7",
        "region=a,b,c,d,e,f",
        "region=-1,0,0,1,1,1",
        "region=+1,0,0,2,2,2",
        "region=%201,0,0,2,2,2",
        "region=12345678901,0,0,1,1,1",
        "region=",
        "format=png",
        "format=",
        "version=x!",
    ] {
        problem(
            get(&format!("/v1/volumes/terrain/levels/0?{q}"))
                .await
                .unwrap(),
            400,
        )
        .await;
    }
    for q in [
        "region=0,0,0,8,1,1",
        "region=0,0,0,7,3,6",
        "region=9999999999,0,0,1,1,1",
        "region=0,0,0,101,40,70&format=voxels",
        "region=0,0,70,1,1,71&format=voxels",
    ] {
        let p = problem(
            get(&format!("/v1/volumes/terrain/levels/0?{q}"))
                .await
                .unwrap(),
            404,
        )
        .await;
        assert!(p.detail.contains("beyond level 0"), "{q}: {}", p.detail);
    }
    // An axis with MAX <= MIN selects nothing, as the slice a[3:2] does: an empty answer.
    for q in [
        "region=0,0,0,0,1,1",
        "region=3,0,0,2,1,1",
        "region=7,3,5,7,3,5",
    ] {
        let g = level_grid(&c, &s, &format!("/v1/volumes/terrain/levels/0?{q}")).await;
        assert!(g.bricks.is_empty(), "{q}: {g:?}");
        assert_eq!(g.grid, [7, 3, 5], "{q}");
    }
    let got = level_voxels(
        &c,
        &s,
        "/v1/volumes/terrain/levels/0?format=voxels&region=5,5,5,5,40,70",
    )
    .await;
    assert!(got.is_empty());
    problem(get("/v1/volumes/terrain/levels/x").await.unwrap(), 400).await;
    problem(get("/v1/volumes/terrain/levels/256").await.unwrap(), 400).await;
    for p in [
        "/v1/volumes/terrain/levels/4",
        "/v1/volumes/terrain/levels/255",
        "/v1/volumes/terrain/levels/0?version=2",
        "/v1/volumes/nope/levels/0",
    ] {
        problem(get(p).await.unwrap(), 404).await;
    }
    // Too large: level 0 of "big" is 512*256*257*2 = 67,371,008 bytes > 64 MiB.
    let big = s.snap(Vol::Big);
    assert_eq!(big.layout().level_dims(0), [512, 256, 257]);
    for q in ["format=voxels", "format=voxels&region=0,0,0,512,256,257"] {
        let p = problem(
            get(&format!("/v1/volumes/big/levels/0?{q}")).await.unwrap(),
            413,
        )
        .await;
        assert!(p.detail.contains("33685504"), "{}", p.detail);
    }
    // The grid of that level is small, and so are its coarser levels' voxels.
    let g = level_grid(&c, &s, "/v1/volumes/big/levels/0").await;
    assert_eq!(g.grid, [16, 8, 9]);
    assert_eq!(g.bricks.len(), 16 * 8 * 9);
    let got = level_voxels(&c, &s, "/v1/volumes/big/levels/2?format=voxels").await;
    assert_eq!(got.len(), 128 * 64 * 65 * 2);
    assert!(got.iter().all(|&b| b == 0));
}

// ---------------------------------------------------------------------------------------------
// 4. Metrics.

/// The value of the sample `series` (name and labels, exactly) in a Prometheus text body.
fn sample(body: &str, series: &str) -> Option<f64> {
    body.lines().find_map(|l| {
        l.strip_prefix(series)
            .and_then(|rest| rest.strip_prefix(' '))
            .map(|v| v.trim().parse().unwrap())
    })
}

async fn metrics(c: &reqwest::Client, s: &Server) -> String {
    let r = c.get(s.url("/metrics")).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let ctype = header(&r, "content-type").unwrap();
    assert!(ctype.starts_with("text/plain"), "{ctype}");
    r.text().await.unwrap()
}

#[tokio::test]
async fn metrics_count_requests_and_mesh_cache() {
    let s = start(&[Vol::Terrain], 16).await;
    let c = common::http();
    let n = 7;
    for i in 0..n {
        let r = c
            .get(s.url(&format!("/v1/volumes/terrain/bricks/0/{i}/1/2")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200);
        r.bytes().await.unwrap();
    }
    for _ in 0..2 {
        let r = c
            .get(s.url("/v1/volumes/terrain/bricks/0/9/0/0"))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 404);
    }
    let body = metrics(&c, &s).await;
    let ok = format!("isovox_requests_total{{route=\"{BRICK_ROUTE}\",status=\"200\"}}");
    let count = sample(&body, &ok).unwrap_or_else(|| panic!("no {ok} in\n{body}"));
    assert!(count >= n as f64, "{ok} = {count}");
    let missing = format!("isovox_requests_total{{route=\"{BRICK_ROUTE}\",status=\"404\"}}");
    assert!(sample(&body, &missing).unwrap() >= 2.0);
    // The histogram of that route: cumulative buckets, +Inf = count, a positive sum.
    let mut last = 0.0;
    let mut buckets = 0;
    for l in body.lines() {
        if let Some(rest) = l.strip_prefix(&format!(
            "isovox_request_seconds_bucket{{route=\"{BRICK_ROUTE}\",le=\""
        )) {
            let v: f64 = rest.rsplit(' ').next().unwrap().parse().unwrap();
            assert!(v >= last, "buckets are cumulative: {l}");
            last = v;
            buckets += 1;
        }
    }
    assert!(buckets >= 2, "bucket lines for the brick route:\n{body}");
    let inf = sample(
        &body,
        &format!("isovox_request_seconds_bucket{{route=\"{BRICK_ROUTE}\",le=\"+Inf\"}}"),
    )
    .unwrap();
    let hcount = sample(
        &body,
        &format!("isovox_request_seconds_count{{route=\"{BRICK_ROUTE}\"}}"),
    )
    .unwrap();
    let hsum = sample(
        &body,
        &format!("isovox_request_seconds_sum{{route=\"{BRICK_ROUTE}\"}}"),
    )
    .unwrap();
    assert!(hcount >= (n + 2) as f64, "{hcount}");
    assert_eq!(inf, hcount);
    assert_eq!(last, hcount);
    assert!(hsum > 0.0);
    assert!(body.contains("# TYPE isovox_request_seconds histogram"));
    assert!(body.contains("# TYPE isovox_requests_total counter"));
    assert_eq!(sample(&body, "isovox_volumes"), Some(1.0));

    // Mesh cache: a miss, then a hit for the same tile in another encoding (an answer of its
    // own, from the cached mesh), then the first answer again, sent as kept (no mesh cache
    // lookup at all).
    let tile = s.url("/v1/volumes/terrain/meshes/0/2/1/2");
    let r = c.get(&tile).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let first = r.bytes().await.unwrap();
    let body = metrics(&c, &s).await;
    let misses = sample(&body, "isovox_mesh_cache_misses_total").unwrap();
    let hits = sample(&body, "isovox_mesh_cache_hits_total").unwrap();
    let kept = sample(&body, "isovox_mesh_answers_kept_hits_total").unwrap();
    assert!(misses >= 1.0, "misses {misses}");
    let r = c.get(format!("{tile}?format=glb")).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    r.bytes().await.unwrap();
    let body = metrics(&c, &s).await;
    let hits_after = sample(&body, "isovox_mesh_cache_hits_total").unwrap();
    assert!(hits_after >= hits + 1.0);
    assert_eq!(
        sample(&body, "isovox_mesh_cache_misses_total").unwrap(),
        misses,
        "the repeat was not meshed again"
    );
    assert!(sample(&body, "isovox_mesh_cache_bytes").unwrap() > 0.0);
    let r = c.get(&tile).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    assert_eq!(r.bytes().await.unwrap(), first);
    let body = metrics(&c, &s).await;
    assert_eq!(
        sample(&body, "isovox_mesh_answers_kept_hits_total").unwrap(),
        kept + 1.0
    );
    assert_eq!(
        sample(&body, "isovox_mesh_cache_hits_total").unwrap(),
        hits_after
    );
    assert!(sample(&body, "isovox_mesh_answers_kept_bytes").unwrap() > 0.0);
    let meshes = format!("isovox_requests_total{{route=\"{MESH_ROUTE}\",status=\"200\"}}");
    assert_eq!(sample(&body, &meshes), Some(3.0));
}

/// `isovox_response_bytes_total` ("response body bytes sent (known lengths)") grows by the bodies
/// sent: seven 4096-byte bricks and a JSON document all have lengths known up front.
#[tokio::test]
async fn metrics_count_response_bytes() {
    let s = start(&[Vol::Terrain], 16).await;
    let c = common::http();
    let mut sent = 0;
    for i in 0..7 {
        let r = c
            .get(s.url(&format!("/v1/volumes/terrain/bricks/0/{i}/1/2")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.content_length(), Some(4096));
        sent += r.bytes().await.unwrap().len();
    }
    let r = c.get(s.url("/v1/volumes/terrain")).send().await.unwrap();
    sent += r.bytes().await.unwrap().len();
    let body = metrics(&c, &s).await;
    let counted = sample(&body, "isovox_response_bytes_total").unwrap();
    assert!(
        counted >= sent as f64,
        "counted {counted} of {sent} bytes sent"
    );
}

// ---------------------------------------------------------------------------------------------
// 5. OpenAPI.

/// Every route the router serves, with its method (from `server/src/http/mod.rs`).
const ROUTES: [(&str, &str); 29] = [
    ("/healthz", "get"),
    ("/metrics", "get"),
    ("/openapi.json", "get"),
    ("/v1/volumes", "get"),
    ("/v1/volumes/{name}", "get"),
    ("/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}", "get"),
    ("/v1/volumes/{name}/blobs/{hash}", "get"),
    ("/v1/volumes/{name}/batch", "post"),
    ("/v1/volumes/{name}/levels/{level}", "get"),
    ("/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}", "get"),
    (
        "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}/strips/{face}",
        "get",
    ),
    ("/v1/volumes/{name}/edits", "post"),
    ("/v1/volumes/{name}/compact", "post"),
    ("/v1/volumes/{name}/changes", "get"),
    ("/v1/volumes/{name}/events", "get"),
    ("/v1/volumes/{name}/history", "get"),
    ("/v1/volumes/{name}/tags", "get"),
    ("/v1/volumes/{name}/tags/{tag}", "put"),
    ("/v1/volumes/{name}/undo", "post"),
    ("/v1/volumes/{name}/revert", "post"),
    ("/v1/volumes/{name}/presence", "get"),
    ("/v1/volumes/{name}/channels/{channel}/segments", "get"),
    (
        "/v1/volumes/{name}/channels/{channel}/segments/{id}/mesh",
        "get",
    ),
    ("/v1/auth", "get"),
    ("/v1/meshes", "post"),
    ("/v1/volumes/{name}/zarr/{path}", "get"),
    ("/v1/volumes/{name}/precomputed/{path}", "get"),
    ("/v1/volumes/{name}/versions/{version}/zarr/{path}", "get"),
    (
        "/v1/volumes/{name}/versions/{version}/precomputed/{path}",
        "get",
    ),
];

#[tokio::test]
async fn openapi_lists_every_route() {
    let s = start(&[Vol::Plain], 16).await;
    let c = common::http();
    let r = c.get(s.url("/openapi.json")).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    assert_eq!(
        header(&r, "content-type").as_deref(),
        Some("application/json")
    );
    let doc: serde_json::Value = serde_json::from_slice(&r.bytes().await.unwrap()).unwrap();
    assert!(doc["openapi"].as_str().unwrap().starts_with("3."));
    assert!(doc["info"]["title"].is_string());
    let paths = doc["paths"].as_object().unwrap();
    for (route, method) in ROUTES {
        let op = &paths
            .get(route)
            .unwrap_or_else(|| panic!("{route} not documented"))[method];
        assert!(op.is_object(), "{method} {route} not documented");
        assert!(op["responses"]["200"].is_object(), "{method} {route}");
        // Every path parameter of the template is declared.
        let declared: HashSet<String> = op["parameters"]
            .as_array()
            .map(|ps| {
                ps.iter()
                    .filter(|p| p["in"] == "path")
                    .map(|p| p["name"].as_str().unwrap().to_string())
                    .collect()
            })
            .unwrap_or_default();
        let in_template: HashSet<String> = route
            .split('/')
            .filter_map(|seg| seg.strip_prefix('{').and_then(|s| s.strip_suffix('}')))
            .map(str::to_string)
            .collect();
        assert_eq!(declared, in_template, "{method} {route}");
    }
    assert_eq!(
        paths.len(),
        ROUTES.len(),
        "documented paths: {:?}",
        paths.keys()
    );

    // And every documented operation is served (not the fallback, not 405).
    let snap = s.snap(Vol::Plain);
    let root = all_keys(snap.layout()).pop().unwrap();
    let hash = format!("{:016x}", snap.hash(root).unwrap());
    for (route, ops) in paths {
        for method in ops.as_object().unwrap().keys() {
            let url = s.url(
                &route
                    .replace("{name}", "plain")
                    .replace("{level}", "0")
                    .replace(['{', '}'], "")
                    .replace("/x/y/z", "/0/0/0")
                    .replace("/strips/face", "/strips/+x")
                    .replace("/segments/id/", "/segments/1/")
                    .replace("/versions/version/", "/versions/1/")
                    .replace("/zarr/path", "/zarr/zarr.json")
                    .replace("/precomputed/path", "/precomputed/info")
                    .replace("/hash", &format!("/{hash}")),
            );
            let r = match method.as_str() {
                "get" => c.get(&url).send().await.unwrap(),
                "post" => c
                    .post(&url)
                    .header("content-type", "application/json")
                    .body("{\"keys\": [[0,0,0,0]]}")
                    .send()
                    .await
                    .unwrap(),
                "put" => c
                    .put(&url)
                    .header("content-type", "application/json")
                    .body("{\"version\": 1}")
                    .send()
                    .await
                    .unwrap(),
                other => panic!("unexpected method {other} for {route}"),
            };
            // The volume has no attribute channel: a channel's routes answer from their handler
            // that it has none (not the router's fallback). The channel tests use them fully.
            if route.contains("{channel}") {
                assert_eq!(r.status().as_u16(), 404, "{method} {url}");
                let body = r.text().await.unwrap();
                assert!(body.contains("no channel"), "{method} {url}: {body}");
                continue;
            }
            // Write routes exist but need a token (the write tests use them fully).
            let expected = if ops[method]["security"].is_array() {
                401
            } else {
                200
            };
            assert_eq!(r.status().as_u16(), expected, "{method} {url}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 6. Overload.

#[tokio::test]
async fn no_cpu_permits_means_503_with_retry_after() {
    let s = start(&[Vol::Terrain], 0).await;
    let c = common::http();
    let requests = [
        c.get(s.url("/v1/volumes/terrain/meshes/0/2/1/2")),
        c.get(s.url("/v1/volumes/terrain/meshes/1/1/0/1?format=glb")),
        c.post(s.url("/v1/volumes/terrain/batch"))
            .header("content-type", "application/json")
            .body("{\"keys\": [[0,0,0,0]]}"),
        c.post(s.url("/v1/volumes/terrain/batch"))
            .header("content-type", "application/json")
            .body("{\"keys\": [[0,1,1,1]], \"encoding\": \"stored\"}"),
        c.get(s.url("/v1/volumes/terrain/levels/1")),
    ];
    for req in requests {
        let r = req.send().await.unwrap();
        let retry = header(&r, "retry-after");
        problem(r, 503).await;
        let secs: u32 = retry.expect("retry-after").parse().unwrap();
        assert!(secs >= 1);
    }
    // Work that needs no CPU permit is still served.
    let r = c
        .get(s.url("/v1/volumes/terrain/bricks/0/1/1/1"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    // Client errors are still told apart from overload.
    problem(
        c.get(s.url("/v1/volumes/terrain/meshes/0/9/0/0"))
            .send()
            .await
            .unwrap(),
        404,
    )
    .await;
    let body = metrics(&c, &s).await;
    assert_eq!(sample(&body, "isovox_cpu_queue_depth"), Some(0.0));
    let busy = format!("isovox_requests_total{{route=\"{MESH_ROUTE}\",status=\"503\"}}");
    assert_eq!(sample(&body, &busy), Some(2.0));
}
