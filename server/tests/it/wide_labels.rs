//! Label channels of u32 and u64 ids over HTTP (`docs/channels.md`): a u64 channel painted with
//! ids past 2^53 and past 2^63 gives, at every level, exactly what a u16 channel painted with
//! the same terms gives with its ids renamed (the u16 path is the independent method: its
//! rules are checked by hand elsewhere); level 0 by hand; its grid, segments (ids as strings),
//! a segment's mesh and its precomputed source; the reserved id 2^64 - 1 refused; and the
//! painted ids still there after a kill -9.

use crate::channel_volumes::post_ok;
use crate::server_process::ServerProcess;
use isovox_proto::channel::ChannelInfo;
use isovox_proto::vod2::FileHeader;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::store::{build_streams, BrickSource, BuildOptions, DenseGrid, Vod2};
use serde_json::{json, Value};

const G: usize = 64;
/// Past 2^53: a float64 (and a JavaScript number) would round it.
const B: u64 = (1 << 53) + 3;
/// Past 2^63: no constant index entry holds it, so a whole brick of it is a record.
const C: u64 = (1 << 63) + 9;

/// `path`: a 64^3 u8 ground (255 below z = 20) and a sparse `label` channel of `label_type`,
/// 0 everywhere, brick 16.
fn volume(path: &std::path::Path, label_type: VoxelType) {
    let dims = [G as u32; 3];
    let n = G * G * G;
    let density: Vec<u8> = (0..n)
        .map(|i| if i / (G * G) < 20 { 255 } else { 0 })
        .collect();
    let zeros = vec![0u8; label_type.bytes() * n];
    let grids = [
        DenseGrid::new(dims, VoxelType::U8, 16, &density),
        DenseGrid::new(dims, label_type, 16, &zeros),
    ];
    let sources: Vec<&dyn BrickSource> = grids.iter().map(|g| g as _).collect();
    let channels = vec![ChannelInfo {
        sparse: true,
        ..ChannelInfo::new("label", label_type)
    }];
    let layout = VolumeLayout::new(dims, 16, VoxelType::U8).unwrap();
    let header = FileHeader::with_channels(layout, [1.0; 3], channels).unwrap();
    build_streams(path, header, &sources, &BuildOptions::default()).unwrap();
}

fn get(server: &ServerProcess, path: &str) -> (u16, Vec<u8>) {
    let r = reqwest::blocking::get(server.url(path)).unwrap();
    (r.status().as_u16(), r.bytes().unwrap().to_vec())
}

/// Paints `id` (as JSON writes it: exactly, whatever its size) into `volume`'s label over the cuboid
/// at `origin` of `size`: inside on `[origin + 1, origin + size - 1)` per axis.
fn paint(server: &ServerProcess, volume: &str, origin: [u32; 3], size: [u32; 3], id: u64) {
    post_ok(
        server,
        &format!("/v1/volumes/{volume}/edits"),
        json!({"op": "paint", "channel": "label",
               "term": {"cuboid": {"origin": origin, "size": size, "label": id}}}),
    );
}

/// Level `level` of `volume`'s label channel as values, from `format=voxels`.
fn level(server: &ServerProcess, volume: &str, level: u8, bytes_per_voxel: usize) -> Vec<u64> {
    let (status, body) = get(
        server,
        &format!("/v1/volumes/{volume}/levels/{level}?format=voxels&channel=label"),
    );
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    body.chunks_exact(bytes_per_voxel)
        .map(|c| {
            let mut b = [0u8; 8];
            b[..c.len()].copy_from_slice(c);
            u64::from_le_bytes(b)
        })
        .collect()
}

#[test]
fn a_u64_label_channel_holds_ids_past_2_to_the_53_and_63_at_every_level() {
    isovox_server::client_tls::install_provider();
    let dir = tempfile::tempdir().unwrap();
    volume(&dir.path().join("w16.vod"), VoxelType::U16);
    volume(&dir.path().join("world.vod"), VoxelType::U64);
    let mut server = crate::channel_volumes::serve(dir.path(), &[]);
    let info: Value = serde_json::from_slice(&get(&server, "/v1/volumes/world").1).unwrap();
    assert_eq!(info["channels"][0]["type"], "u64", "{info}");

    // The same terms into both volumes: 5 and B over one box, 9 and C over brick (2, 2, 2)
    // whole ([32, 48) on each axis), which then holds one value past MAX_CONSTANT.
    let boxes = [([10, 12, 14], [12, 8, 6]), ([31, 31, 31], [18, 18, 18])];
    for ((origin, size), (small, big)) in boxes.into_iter().zip([(5, B), (9, C)]) {
        paint(&server, "w16", origin, size, small);
        paint(&server, "world", origin, size, big);
    }

    // Level 0 by hand: B on [11, 21) x [13, 19) x [15, 19), C on [32, 48)^3, 0 elsewhere.
    let l0 = level(&server, "world", 0, 8);
    assert_eq!(l0.len(), G * G * G);
    let inside = |p: [usize; 3], lo: [usize; 3], hi: [usize; 3]| {
        (0..3).all(|a| (lo[a]..hi[a]).contains(&p[a]))
    };
    for (i, &v) in l0.iter().enumerate() {
        let p = [i % G, i / G % G, i / (G * G)];
        let want = if inside(p, [11, 13, 15], [21, 19, 19]) {
            B
        } else if inside(p, [32; 3], [48; 3]) {
            C
        } else {
            0
        };
        assert_eq!(v, want, "level 0 voxel {p:?}");
    }
    // Every level: the u16 channel's, renamed (5 -> B, 9 -> C). The mode keeps the order of
    // the values it chooses between, and B < C as 5 < 9, so ties go the same way.
    let levels = info["levels"].as_array().unwrap().len() as u8;
    for k in 0..levels {
        let small = level(&server, "w16", k, 2);
        let big = level(&server, "world", k, 8);
        let renamed: Vec<u64> = small
            .iter()
            .map(|&v| match v {
                5 => B,
                9 => C,
                other => other,
            })
            .collect();
        assert_eq!(big, renamed, "level {k}");
        assert!(k > 0 || small.contains(&5) && small.contains(&9));
    }

    // The grid: brick (2, 2, 2) of level 0 holds C alone, exactly (JSON numbers are exact in
    // serde_json); a brick's bytes are 8 a voxel.
    let grid: Value = serde_json::from_slice(
        &get(
            &server,
            "/v1/volumes/world/levels/0?channel=label&region=2,2,2,3,3,3",
        )
        .1,
    )
    .unwrap();
    let brick = &grid["bricks"][0];
    assert_eq!(
        (brick["min"].as_u64(), brick["max"].as_u64()),
        (Some(C), Some(C)),
        "{grid}"
    );
    let (status, bytes) = get(&server, "/v1/volumes/world/bricks/0/2/2/2?channel=label");
    assert_eq!((status, bytes.len()), (200, 8 * 16 * 16 * 16));
    assert!(bytes.chunks_exact(8).all(|c| c == C.to_le_bytes()));

    // A batch of stored bricks: a constant's payload is its value as a u64 in a u64 channel;
    // every record's payload (sent as stored in a codec the batch names, or decoded: a palette
    // record) decodes to the brick's voxels.
    use isovox_proto::batch::BatchCodec;
    let keys = [[0, 3, 3, 3], [0, 2, 2, 2], [0, 0, 0, 0], [0, 1, 0, 0]];
    let r = reqwest::blocking::Client::new()
        .post(server.url("/v1/volumes/world/batch?channel=label"))
        .json(&json!({"keys": keys, "encoding": "stored"}))
        .send()
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let entries = isovox_proto::batch::decode_batch(&r.bytes().unwrap()).unwrap();
    assert_eq!(entries[0].codec, BatchCodec::Constant);
    assert_eq!(entries[0].payload, 0u64.to_le_bytes());
    for (e, [l, x, y, z]) in entries.iter().zip(keys).skip(1) {
        let voxels = match e.codec {
            BatchCodec::Raw => e.payload.clone(),
            BatchCodec::Zstd => zstd::bulk::decompress(&e.payload, 1 << 16).unwrap(),
            other => panic!("brick {x} {y} {z}: {other:?}"),
        };
        let (_, want) = get(
            &server,
            &format!("/v1/volumes/world/bricks/{l}/{x}/{y}/{z}?channel=label"),
        );
        assert_eq!(voxels, want, "brick {x} {y} {z}");
    }

    // Segments: ids as decimal strings in a u64 channel, numbers in a u16 one.
    let (status, list) = get(&server, "/v1/volumes/world/channels/label/segments");
    let text = String::from_utf8_lossy(&list);
    assert_eq!(status, 200, "{text}");
    let list: Value = serde_json::from_str(&text).unwrap();
    let ids: Vec<(&str, u64)> = list["segments"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| (s["id"].as_str().unwrap(), s["voxels"].as_u64().unwrap()))
        .collect();
    let (b, c) = (B.to_string(), C.to_string());
    assert_eq!(ids, [(b.as_str(), 10 * 6 * 4), (c.as_str(), 16 * 16 * 16)]);
    let small: Value =
        serde_json::from_slice(&get(&server, "/v1/volumes/w16/channels/label/segments").1).unwrap();
    assert_eq!(small["segments"][0]["id"], json!(5));
    // A page after B lists C; a segment's mesh by its full id.
    let page: Value = serde_json::from_slice(
        &get(
            &server,
            &format!("/v1/volumes/world/channels/label/segments?after={B}"),
        )
        .1,
    )
    .unwrap();
    assert_eq!(page["segments"][0]["id"], json!(c));
    let (status, mesh) = get(
        &server,
        &format!("/v1/volumes/world/channels/label/segments/{C}/mesh?level=0"),
    );
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&mesh));
    assert!(mesh.len() > 100);

    // The precomputed source of a u64 channel is uint64; of a u16 one, uint32.
    for (volume, want) in [("world", "uint64"), ("w16", "uint32")] {
        let info: Value = serde_json::from_slice(
            &get(
                &server,
                &format!("/v1/volumes/{volume}/precomputed/label/info"),
            )
            .1,
        )
        .unwrap();
        assert_eq!(info["data_type"], want, "{volume}");
    }

    // 2^64 - 1 is the evaluator's "no attribute": an edit may not write it.
    let r = reqwest::blocking::Client::new()
        .post(server.url("/v1/volumes/world/edits"))
        .bearer_auth(crate::channel_volumes::TOKEN)
        .json(&json!({"op": "paint", "channel": "label",
                      "term": {"cuboid": {"origin": [0, 0, 0], "size": [4, 4, 4], "label": u64::MAX}}}))
        .send()
        .unwrap();
    let status = r.status().as_u16();
    let text = r.text().unwrap();
    assert_eq!(status, 422, "{text}");
    assert!(text.contains(&(u64::MAX - 1).to_string()), "{text}");

    // Killed (SIGKILL) after the acknowledged paints: the file holds them.
    let _ = server.stop();
    let vod = Vod2::open(&dir.path().join("world.vod")).unwrap();
    let label = vod.head().channel("label").unwrap();
    let brick = label
        .read(BrickKey {
            level: 0,
            x: 2,
            y: 2,
            z: 2,
        })
        .unwrap();
    assert!(brick.chunks_exact(8).all(|c| c == C.to_le_bytes()));
    // The whole file checks out (every record, summary and checksum); a salvage (which
    // rebuilds the index from the records) and a compaction give the same channel.
    let path = dir.path().join("world.vod");
    let level1 = |path: &std::path::Path| {
        let vod = Vod2::open(path).unwrap();
        let view = vod.head().channel("label").unwrap();
        let (start, count) = view.layout().level_range(1);
        (start..start + count)
            .map(|n| view.read(view.layout().key_of(n).unwrap()).unwrap())
            .collect::<Vec<_>>()
    };
    let before = level1(&path);
    let salvaged = dir.path().join("salvaged.vod");
    let (p, s) = (path.to_str().unwrap(), salvaged.to_str().unwrap());
    crate::server_process::run_isovox(&["check", p]);
    // The painted brick of B and 0 was stored with the palette codec (one byte a voxel before
    // zstd, not eight).
    let stored = label.stored(BrickKey {
        level: 0,
        x: 0,
        y: 0,
        z: 0,
    });
    let codec = match stored.unwrap() {
        isovox_server::store::StoredBrick::Record { header, .. } => header.codec,
        other => panic!("brick (0, 0, 0) is {other:?}"),
    };
    assert_eq!(codec, isovox_proto::vod2::Codec::Palette);
    crate::server_process::run_isovox(&["salvage", p, "-o", s]);
    crate::server_process::run_isovox(&["compact", p]);
    crate::server_process::run_isovox(&["check", p]);
    assert_eq!(level1(&salvaged), before);
    assert_eq!(level1(&path), before);
    // Inspect lists the channel with its palette records, and counts its records as the head's:
    // a file just compacted references every byte it holds.
    let i = isovox_server::store::inspect::inspect(&Vod2::open(&path).unwrap()).unwrap();
    assert_eq!(i.channels.len(), 1);
    let c = &i.channels[0];
    assert_eq!((c.name.as_str(), c.voxel_type), ("label", VoxelType::U64));
    assert!(c.codecs.palette_records >= 1, "{:?}", c.codecs);
    assert_eq!(c.raw_bytes, 8 * (G * G * G) as u64);
    assert_eq!(i.garbage_bytes, 0);
}
