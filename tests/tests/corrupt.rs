//! Damage is a server error, not the client's: a corrupt record in a served file answers 500
//! with problem details (a generic body; the cause goes to the log) on every route that reads
//! it, never 404; and the server goes on serving the rest of the file.
//!
//! The damage is written by the test itself, with its own bytes: garbage over one brick's
//! payload before the server starts (opening reads no brick data), and garbage over one commit
//! record while it runs (opening checks every commit record).

#![allow(clippy::unwrap_used)] // tests fail loudly on purpose

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::vod2::{NodeEntry, BRICK_HEADER_LEN};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::ServerConfig;
use isovox_server::store::{build_vod2, BuildOptions, StoredBrick, Vod2};
use isovox_server::volume::edit_file;
use std::os::unix::fs::FileExt;

mod common;
use common::{problem, serve};

/// The generic detail of every 500 (`http/error.rs`): nothing about the cause leaks.
const GENERIC: &str = "the server failed to answer; the cause is in its log";

async fn server_error(resp: reqwest::Response, what: &str) {
    let p = problem(resp, 500).await;
    assert_eq!(p.detail, GENERIC, "{what}");
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
    let c = reqwest::Client::new();
    let get = |p: String| c.get(format!("{base}{p}")).send();
    let b = layout.brick();
    let voxels_of = |k: BrickKey| {
        format!(
            "/levels/0?format=voxels&region={},{},{},{},{},{}",
            k.x * b,
            k.y * b,
            k.z * b,
            k.x * b + b,
            k.y * b + b,
            k.z * b + b
        )
    };
    let at = |k: BrickKey| format!("{}/{}/{}", k.x, k.y, k.z);

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
