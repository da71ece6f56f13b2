//! Damage is a server error, not the client's: a corrupt record in a served file answers 500
//! with problem details (a generic body; the cause goes to the log) on every route that reads
//! it (the formats' views included), never 404; and the server goes on serving the rest of the
//! file.
//!
//! The damage is written by the test itself, with its own bytes: garbage over one brick's
//! payload before the server starts (opening reads no brick data), and garbage over one commit
//! record while it runs (opening checks every commit record). One flipped payload byte is a 500
//! on every route and in every encoding, the stored payload sent as it is included, in zstd,
//! lz4 and uncompressed files, and in files written before payload checksums.

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::vod2::{NodeEntry, BRICK_HEADER_LEN};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::ServerConfig;
use isovox_server::store::codec::Compression;
use isovox_server::store::{build_vod2, BrickSource, BuildOptions, StoredBrick, Vod2};
use isovox_server::volume::edit_file;
use std::os::unix::fs::FileExt;

use crate::common;
use common::{problem, serve};

/// The generic detail of every 500 (`http/error.rs`): nothing about the cause leaks.
const GENERIC: &str = "the server failed to answer; the cause is in its log";

async fn server_error(resp: reqwest::Response, what: &str) {
    let p = problem(resp, 500).await;
    assert_eq!(p.detail, GENERIC, "{what}");
}

/// `x/y/z` of a brick, as its routes spell it.
fn at(k: BrickKey) -> String {
    format!("{}/{}/{}", k.x, k.y, k.z)
}

/// The level-0 voxels route for exactly the voxels of brick `k` (bricks of edge `b`).
fn voxels_of(k: BrickKey, b: u32) -> String {
    format!(
        "/levels/0?format=voxels&region={},{},{},{},{},{}",
        k.x * b,
        k.y * b,
        k.z * b,
        k.x * b + b,
        k.y * b + b,
        k.z * b + b
    )
}

/// The routes of the formats' views for exactly level-0 brick `k` (bricks of edge `b`) as a
/// chunk: the Zarr and the precomputed view, live and pinned to version `pinned`.
fn views_of(k: BrickKey, b: u32, pinned: u64) -> [String; 4] {
    let range = |c: u32| format!("{}-{}", c * b, c * b + b);
    let zarr = format!("zarr/0/c/{}/{}/{}", k.z, k.y, k.x);
    let precomputed = format!("precomputed/0/{}_{}_{}", range(k.x), range(k.y), range(k.z));
    [
        format!("/{zarr}"),
        format!("/{precomputed}"),
        format!("/versions/{pinned}/{zarr}"),
        format!("/versions/{pinned}/{precomputed}"),
    ]
}

async fn ok(resp: reqwest::Response, what: &str) -> Vec<u8> {
    let status = resp.status().as_u16();
    let body = resp.bytes().await.unwrap();
    assert_eq!(
        status,
        200,
        "{what}: status (body {:?})",
        String::from_utf8_lossy(&body)
    );
    body.to_vec()
}

fn carve(center: [i64; 3]) -> EditRequest {
    EditRequest {
        op: "difference".into(),
        term: Some(Term::Ellipsoid {
            center,
            radii: [6, 6, 6],
        }),
        s_l: None,
        k: None,
        region: None,
        message: None,
        channel: None,
        overwrite: None,
    }
}

#[tokio::test]
async fn corrupt_records_answer_500_and_the_rest_is_served() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    // A 128 x 64 x 128 terrain, brick 16, zstd; then three edits: versions 2, 3 and 4.
    let layout = VolumeLayout::new([128, 64, 128], 16, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &WorldSource::new(layout.clone(), 11),
        &BuildOptions::default(),
    )
    .unwrap();
    for c in [[20, 30, 20], [100, 30, 100], [64, 30, 64]] {
        edit_file(&path, &carve(c)).unwrap();
    }
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    assert_eq!(snap.version, 4);

    // Two level-0 bricks stored as records of their own, both crossing the surface (so their
    // tiles are meshed, not skipped), far apart: one is damaged, the other must stay readable.
    let iso = VoxelType::U8.surface() as f32 - 0.5;
    let g = layout.grid(0);
    let mut crossing = Vec::new();
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                let key = BrickKey { level: 0, x, y, z };
                if let (NodeEntry::Stored(offset), StoredBrick::Record { header, .. }) =
                    (snap.entry(key).unwrap(), snap.stored(key).unwrap())
                {
                    if (header.min as f32) < iso && (header.max as f32) >= iso {
                        crossing.push((key, offset, header));
                    }
                }
            }
        }
    }
    let (bad, bad_offset, bad_header) = crossing[0];
    let (good, good_offset, _) = *crossing
        .iter()
        .find(|(k, offset, _)| {
            *offset != bad_offset
                && ((k.x as i64 - bad.x as i64).abs() > 2 || (k.z as i64 - bad.z as i64).abs() > 2)
        })
        .unwrap();
    assert_ne!(good_offset, bad_offset);
    // Version 2's commit record (neither the head's nor the first).
    let (commit_at, commit) = vod
        .commits()
        .unwrap()
        .into_iter()
        .find(|(_, h)| h.version == 2)
        .unwrap();
    assert_eq!(commit.version, 2);
    drop((snap, vod));

    // Garbage over the damaged brick's payload (its header, hash included, stays intact).
    let file = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
    let payload_at = bad_offset + BRICK_HEADER_LEN as u64;
    let garbage = vec![0xA5u8; bad_header.stored_len as usize];
    file.write_all_at(&garbage, payload_at).unwrap();
    file.sync_all().unwrap();

    assert_eq!(
        Catalog::open_dir(dir.path()).unwrap().len(),
        1,
        "opening reads no brick data"
    );
    let server = serve(dir.path(), ServerConfig::default()).await;
    let base = format!("{}/v1/volumes/w", server.base());
    let c = common::http();
    let get = |p: String| c.get(format!("{base}{p}")).send();
    let voxels_of = |k: BrickKey| voxels_of(k, layout.brick());
    let views_of = |k: BrickKey| views_of(k, layout.brick(), 4);

    for round in 0..2 {
        // The damaged brick, on every route that decodes it.
        server_error(
            get(format!("/bricks/0/{}", at(bad))).await.unwrap(),
            "brick",
        )
        .await;
        server_error(
            get(format!("/blobs/{:016x}", bad_header.hash))
                .await
                .unwrap(),
            "blob",
        )
        .await;
        server_error(get(voxels_of(bad)).await.unwrap(), "level voxels").await;
        server_error(
            get(format!("/meshes/0/{}", at(bad))).await.unwrap(),
            "mesh tile",
        )
        .await;
        for view in views_of(bad) {
            server_error(get(view.clone()).await.unwrap(), &view).await;
        }
        // The rest of the file, on the same routes (twice: after the failures too).
        let brick = ok(
            get(format!("/bricks/0/{}", at(good))).await.unwrap(),
            "brick",
        )
        .await;
        assert_eq!(brick.len(), layout.brick_bytes(), "round {round}");
        ok(get(voxels_of(good)).await.unwrap(), "level voxels").await;
        ok(
            get(format!("/meshes/0/{}", at(good))).await.unwrap(),
            "mesh",
        )
        .await;
        ok(get("/levels/1".into()).await.unwrap(), "level grid").await;
        for view in views_of(good) {
            ok(get(view.clone()).await.unwrap(), &view).await;
        }
        ok(get("/changes?since=0".into()).await.unwrap(), "changes").await;
    }

    // Garbage over version 2's commit record while the server runs: the feed's catch-up list
    // reads it back.
    file.write_all_at(&[0x5Au8; 16], commit_at + 8).unwrap();
    file.sync_all().unwrap();
    server_error(
        get("/changes?since=1".into()).await.unwrap(),
        "changes over the damaged commit",
    )
    .await;
    server_error(
        get("/changes?since=0".into()).await.unwrap(),
        "changes from the start",
    )
    .await;
    // Versions after it are still listed, and everything else still served.
    let list: serde_json::Value =
        serde_json::from_slice(&ok(get("/changes?since=2".into()).await.unwrap(), "changes").await)
            .unwrap();
    assert_eq!(list["changes"].as_array().unwrap().len(), 2);
    ok(get(String::new()).await.unwrap(), "volume info").await;
    ok(
        get(format!("/bricks/0/{}", at(good))).await.unwrap(),
        "brick",
    )
    .await;
    ok(
        get(format!("/meshes/0/{}", at(good))).await.unwrap(),
        "mesh",
    )
    .await;
}

/// How a test asks for a brick: the three encodings a client can ask for.
const ENCODINGS: [(&str, Option<(&str, &str)>); 3] = [
    ("raw", None),
    ("zstd", Some(("accept-encoding", "zstd"))),
    ("lz4", Some(("accept", "application/x-lz4"))),
];

/// The voxels a brick response carries, decoded as its headers say.
fn decoded(encoding: &str, content_encoding: Option<&str>, body: &[u8], len: usize) -> Vec<u8> {
    match (encoding, content_encoding) {
        (_, Some("zstd")) => zstd::bulk::decompress(body, len).unwrap(),
        ("lz4", _) => {
            let mut out = vec![0u8; len];
            assert_eq!(
                lz4_flex::block::decompress_into(body, &mut out).unwrap(),
                len
            );
            out
        }
        _ => body.to_vec(),
    }
}

/// A level-0 brick of `snap` stored as a record of `codec` that no other node shares and
/// whose tile holds a surface (so meshing it reads it), more than `apart` bricks away from
/// `away_from` along x or z (3: neither tile's halo reaches the other).
fn lone_record(
    snap: &isovox_server::store::Snapshot,
    codec: isovox_proto::vod2::Codec,
    away_from: Option<BrickKey>,
    apart: i64,
) -> (BrickKey, u64, isovox_proto::vod2::BrickHeader) {
    let layout = snap.layout();
    let mut references = std::collections::HashMap::new();
    for node in 0..layout.node_count() {
        if let NodeEntry::Stored(offset) = snap.entry_at(node).unwrap() {
            *references.entry(offset).or_insert(0) += 1;
        }
    }
    let iso = VoxelType::U8.surface() as f32 - 0.5;
    let g = layout.grid(0);
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                let key = BrickKey { level: 0, x, y, z };
                let far = away_from.is_none_or(|a| {
                    (a.x as i64 - x as i64).abs() >= apart || (a.z as i64 - z as i64).abs() >= apart
                });
                if let (NodeEntry::Stored(offset), StoredBrick::Record { header, .. }) =
                    (snap.entry(key).unwrap(), snap.stored(key).unwrap())
                {
                    if far
                        && header.codec == codec
                        && references[&offset] == 1
                        && (header.min as f32) < iso
                        && (header.max as f32) >= iso
                    {
                        return (key, offset, header);
                    }
                }
            }
        }
    }
    panic!("no lone {codec:?} record crossing the surface");
}

/// Flips one bit of the byte at `offset`.
fn flip(path: &std::path::Path, offset: u64) {
    let file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .unwrap();
    let mut b = [0u8; 1];
    file.read_exact_at(&mut b, offset).unwrap();
    file.write_all_at(&[b[0] ^ 0x10], offset).unwrap();
    file.sync_all().unwrap();
}

/// Flips one bit in the middle of the payload of the brick record at `offset`.
fn flip_payload(path: &std::path::Path, offset: u64, header: &isovox_proto::vod2::BrickHeader) {
    flip(
        path,
        offset + BRICK_HEADER_LEN as u64 + header.stored_len as u64 / 2,
    );
}

/// Every read route and encoding on a file whose one brick has one flipped payload byte:
/// 500 for that brick wherever it is read (its stored payload sent as it is, decoded, or
/// meshed), 200 and the generator's voxels for every other brick.
async fn one_flipped_payload_byte(compression: Compression, codec: isovox_proto::vod2::Codec) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    let layout = VolumeLayout::new([128, 64, 128], 16, VoxelType::U8).unwrap();
    let source = WorldSource::new(layout.clone(), 11);
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &source,
        &BuildOptions {
            compression,
            ..BuildOptions::default()
        },
    )
    .unwrap();
    // The voxels every brick must have: the generator's, not the file's.
    let expect = |k: BrickKey| {
        let mut out = vec![0u8; layout.brick_bytes()];
        source.fill(k, &mut out);
        out
    };
    let snap = Vod2::open(&path).unwrap().head();
    let (bad, bad_offset, bad_header) = lone_record(&snap, codec, None, 0);
    let (good, _, _) = lone_record(&snap, codec, Some(bad), 3);
    drop(snap);
    flip_payload(&path, bad_offset, &bad_header);

    let server = serve(dir.path(), ServerConfig::default()).await;
    let base = format!("{}/v1/volumes/w", server.base());
    let c = common::http();
    let what = format!("{codec:?} file");
    let voxels_of = |k: BrickKey| voxels_of(k, layout.brick());
    let batch = |keys: &[BrickKey], encoding: &str| {
        let keys: Vec<String> = keys
            .iter()
            .map(|k| format!("[0,{},{},{}]", k.x, k.y, k.z))
            .collect();
        c.post(format!("{base}/batch"))
            .header("content-type", "application/json")
            .body(format!(
                "{{\"keys\": [{}], \"encoding\": \"{encoding}\"}}",
                keys.join(",")
            ))
            .send()
    };
    let get = |path: String, header: Option<(&str, &str)>| {
        let mut r = c.get(format!("{base}{path}"));
        if let Some((name, value)) = header {
            r = r.header(name, value);
        }
        r.send()
    };

    // The damaged brick: by position and by hash, in every encoding; in batches, alone and
    // with a good brick; in a level's voxels; meshed.
    for (encoding, header) in ENCODINGS {
        let w = format!("{what}: brick, {encoding}");
        server_error(
            get(format!("/bricks/0/{}", at(bad)), header).await.unwrap(),
            &w,
        )
        .await;
        let w = format!("{what}: blob, {encoding}");
        let blob = format!("/blobs/{:016x}", bad_header.hash);
        server_error(get(blob, header).await.unwrap(), &w).await;
    }
    for encoding in ["raw", "stored"] {
        for keys in [vec![bad], vec![good, bad]] {
            let w = format!("{what}: batch {encoding} of {} bricks", keys.len());
            server_error(batch(&keys, encoding).await.unwrap(), &w).await;
        }
    }
    let w = format!("{what}: level voxels");
    server_error(get(voxels_of(bad), None).await.unwrap(), &w).await;
    let w = format!("{what}: mesh tile");
    server_error(
        get(format!("/meshes/0/{}", at(bad)), None).await.unwrap(),
        &w,
    )
    .await;
    // As a chunk of the formats' views: in a zstd file the Zarr chunk is the stored frame as it
    // is, in the others it is made from the decoded voxels, as the precomputed chunk is.
    for view in views_of(bad, layout.brick(), 1) {
        server_error(
            get(view.clone(), None).await.unwrap(),
            &format!("{what}: {view}"),
        )
        .await;
    }

    // A good brick on the same routes: 200 and the generator's voxels.
    let len = layout.brick_bytes();
    for (encoding, header) in ENCODINGS {
        for path in [
            format!("/bricks/0/{}", at(good)),
            format!(
                "/blobs/{:016x}",
                isovox_proto::vod2::content_hash(&expect(good))
            ),
        ] {
            let r = get(path.clone(), header).await.unwrap();
            let ce = r
                .headers()
                .get("content-encoding")
                .map(|v| v.to_str().unwrap().to_string());
            let body = ok(r, &format!("{what}: {path} {encoding}")).await;
            if encoding == "zstd" && codec == isovox_proto::vod2::Codec::Zstd {
                assert_eq!(ce.as_deref(), Some("zstd"), "the stored frame as it is");
            }
            let got = decoded(encoding, ce.as_deref(), &body, len);
            assert_eq!(got, expect(good), "{what}: {path} {encoding}");
        }
    }
    for encoding in ["raw", "stored"] {
        let body = ok(batch(&[good], encoding).await.unwrap(), &what).await;
        let entries = isovox_proto::batch::decode_batch(&body).unwrap();
        let e = &entries[0];
        let got = match e.codec {
            isovox_proto::batch::BatchCodec::Raw => e.payload.clone(),
            isovox_proto::batch::BatchCodec::Lz4 => decoded("lz4", None, &e.payload, len),
            isovox_proto::batch::BatchCodec::Zstd => decoded("", Some("zstd"), &e.payload, len),
            other => panic!("{what}: a record came back as {other:?}"),
        };
        assert_eq!(got, expect(good), "{what}: batch {encoding}");
    }
    let body = ok(get(voxels_of(good), None).await.unwrap(), &what).await;
    assert_eq!(body, expect(good), "{what}: level voxels");
    for view in views_of(good, layout.brick(), 1) {
        let body = ok(get(view.clone(), None).await.unwrap(), &view).await;
        let got = if view.contains("/zarr/") {
            zstd::bulk::decompress(&body, len).unwrap()
        } else {
            body
        };
        assert_eq!(got, expect(good), "{what}: {view}");
    }
    ok(
        get(format!("/meshes/0/{}", at(good)), None).await.unwrap(),
        &what,
    )
    .await;

    // Every other level-0 brick, in every encoding.
    let g = layout.grid(0);
    for z in 0..g[2] {
        for y in 0..g[1] {
            for x in 0..g[0] {
                let key = BrickKey { level: 0, x, y, z };
                if key == bad {
                    continue;
                }
                for (encoding, header) in ENCODINGS {
                    let r = get(format!("/bricks/0/{}", at(key)), header).await.unwrap();
                    let ce = r
                        .headers()
                        .get("content-encoding")
                        .map(|v| v.to_str().unwrap().to_string());
                    let w = format!("{what}: {key} {encoding}");
                    let body = ok(r, &w).await;
                    assert_eq!(
                        decoded(encoding, ce.as_deref(), &body, len),
                        expect(key),
                        "{w}"
                    );
                }
            }
        }
    }
}

#[tokio::test]
async fn a_flipped_payload_byte_answers_500_on_every_route_and_encoding() {
    use isovox_proto::vod2::Codec;
    one_flipped_payload_byte(Compression::Zstd(5), Codec::Zstd).await;
    one_flipped_payload_byte(Compression::Lz4, Codec::Lz4).await;
    one_flipped_payload_byte(Compression::None, Codec::Raw).await;
}

/// Files written before payload checksums (`tests/data/legacy-*.vod`, made by `isovox generate
/// world --dims 64,48,64 --brick 16 --seed 7 [--codec lz4]` before the format revision): they
/// open, read as the generator says, still have their stored payloads sent as they are, and a
/// flipped payload byte is a 500 there too (verified by decoding); compaction gives every
/// record a checksum.
#[tokio::test]
async fn files_written_before_payload_checksums_are_verified_by_decoding() {
    use isovox_proto::vod2::Codec;
    for (fixture, codec, encoding) in [
        ("legacy-zstd.vod", Codec::Zstd, ENCODINGS[1]),
        ("legacy-lz4.vod", Codec::Lz4, ENCODINGS[2]),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.vod");
        let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data");
        std::fs::copy(data.join(fixture), &path).unwrap();
        let vod = Vod2::open(&path).unwrap();
        let layout = vod.layout().clone();
        assert_eq!(layout.dims(), [64, 48, 64]);
        let source = WorldSource::new(layout.clone(), 7);
        let expect = |k: BrickKey| {
            let mut out = vec![0u8; layout.brick_bytes()];
            source.fill(k, &mut out);
            out
        };
        let snap = vod.head();
        let head = snap.version;
        let g = layout.grid(0);
        let mut records = 0;
        for node in 0..(g[0] * g[1] * g[2]) as u64 {
            let key = layout.key_of(node).unwrap();
            assert_eq!(snap.read(key).unwrap(), expect(key), "{fixture} {key}");
            if let StoredBrick::Record { checksum, .. } = snap.stored(key).unwrap() {
                assert_eq!(
                    checksum, None,
                    "{fixture}: written before payload checksums"
                );
                records += 1;
            }
        }
        assert!(records > 10);
        let (bad, bad_offset, bad_header) = lone_record(&snap, codec, None, 0);
        let (good, _, good_header) = lone_record(&snap, codec, Some(bad), 1);
        let good_payload = match snap.stored(good).unwrap() {
            StoredBrick::Record { payload, .. } => payload.to_vec(),
            StoredBrick::Constant(_) => unreachable!(),
        };
        drop((snap, vod));

        // Compaction of a copy: every record gets a checksum, every voxel stays.
        let elsewhere = tempfile::tempdir().unwrap();
        let copy = elsewhere.path().join("copy.vod");
        std::fs::copy(&path, &copy).unwrap();
        let old = Vod2::open(&copy).unwrap();
        isovox_server::store::compact::compact(&old, &old.head(), &isovox_server::progress::Silent)
            .unwrap();
        let compacted = Vod2::open(&copy).unwrap().head();
        for node in 0..layout.node_count() {
            let key = layout.key_of(node).unwrap();
            if key.level == 0 {
                assert_eq!(
                    compacted.read(key).unwrap(),
                    expect(key),
                    "{fixture} compacted"
                );
            }
            if let StoredBrick::Record { checksum, .. } = compacted.stored(key).unwrap() {
                assert!(checksum.is_some(), "{fixture}: compaction adds checksums");
            }
        }

        flip_payload(&path, bad_offset, &bad_header);
        let server = serve(dir.path(), ServerConfig::default()).await;
        let base = format!("{}/v1/volumes/w", server.base());
        let c = common::http();
        let (name, value) = encoding.1.unwrap();
        for _ in 0..2 {
            // The good brick's stored payload goes out as it is (twice: the second time from
            // what the first verification remembered).
            let r = c
                .get(format!("{base}/bricks/0/{}", at(good)))
                .header(name, value)
                .send()
                .await
                .unwrap();
            let body = ok(r, fixture).await;
            assert_eq!(body, good_payload, "{fixture}: the stored payload as it is");
            assert_eq!(good_header.stored_len as usize, body.len());
            // The damaged one is a 500, every time.
            let r = c
                .get(format!("{base}/bricks/0/{}", at(bad)))
                .header(name, value)
                .send()
                .await
                .unwrap();
            server_error(r, fixture).await;
            // The same as chunks of the formats' views: the Zarr chunk of the zstd file is the
            // stored frame as it is, verified by decoding like the brick route's.
            for view in views_of(good, layout.brick(), head) {
                let body = ok(c.get(format!("{base}{view}")).send().await.unwrap(), &view).await;
                let got = if view.contains("/zarr/") {
                    if codec == Codec::Zstd {
                        assert_eq!(body, good_payload, "{fixture}: {view} is the stored frame");
                    }
                    zstd::bulk::decompress(&body, layout.brick_bytes()).unwrap()
                } else {
                    body
                };
                assert_eq!(got, expect(good), "{fixture}: {view}");
            }
            for view in views_of(bad, layout.brick(), head) {
                let r = c.get(format!("{base}{view}")).send().await.unwrap();
                server_error(r, &format!("{fixture}: {view}")).await;
            }
            let r = c
                .post(format!("{base}/batch"))
                .header("content-type", "application/json")
                .body(format!(
                    "{{\"keys\": [[0,{},{},{}]], \"encoding\": \"stored\"}}",
                    bad.x, bad.y, bad.z
                ))
                .send()
                .await
                .unwrap();
            server_error(r, fixture).await;
        }
    }
}
