//! Segments of a categorical channel over HTTP: the list (ids, voxel counts, boxes) checked
//! against boxes painted by hand and against an independent recount of the level-0 voxels the
//! server serves, after paints, undo, redo and revert; its pages; a segment's mesh closed, of
//! the volume marching cubes gives a box of ones (derived by hand below), as compact and GLB;
//! hostile parameters answered with a 4xx.

use isovox_server::mesh::check::{enclosed_volume, open_edges};
use serde_json::{json, Value};
use std::collections::BTreeMap;

use crate::server_process::ServerProcess;

const G: usize = 64;

fn ground(dir: &std::path::Path) {
    crate::channel_volumes::ground_64(dir);
}

fn serve(dir: &std::path::Path) -> ServerProcess {
    // The index's builds are logged at info.
    crate::channel_volumes::serve(
        dir,
        &[("ISOVOX_LOG", "warn,isovox_server::volume::segments=info")],
    )
}

fn get(server: &ServerProcess, path: &str) -> (u16, Vec<u8>) {
    let r = reqwest::blocking::get(server.url(path)).unwrap();
    let status = r.status().as_u16();
    (status, r.bytes().unwrap().to_vec())
}

fn get_json(server: &ServerProcess, path: &str) -> Value {
    let (status, body) = get(server, path);
    let text = String::from_utf8_lossy(&body);
    assert_eq!(status, 200, "{path}: {text}");
    serde_json::from_slice(&body).unwrap()
}

use crate::channel_volumes::post_ok;

/// Paints `id` into the cuboid leaf at `origin` of `size`: inside (S or H) on
/// `[origin + 1, origin + size - 1)` on each axis (its outer layer is L).
fn paint(server: &ServerProcess, origin: [u32; 3], size: [u32; 3], id: u16) -> u64 {
    let answer = post_ok(
        server,
        "/v1/volumes/world/edits",
        json!({"op": "paint", "channel": "label",
               "term": {"cuboid": {"origin": origin, "size": size, "label": id}}}),
    );
    answer["version"].as_u64().unwrap()
}

/// Segments as `id -> (voxels, box)`.
type Segments = BTreeMap<u64, (u64, [[u64; 3]; 2])>;

/// The segments of a channel counted here, voxel by voxel, from its level-0 voxels as the
/// server serves them (`levels/0?format=voxels`), at `version`.
fn recount(server: &ServerProcess, channel: &str, version: u64) -> Segments {
    let (status, bytes) = get(
        server,
        &format!("/v1/volumes/world/levels/0?channel={channel}&format=voxels&version={version}"),
    );
    assert_eq!(status, 200);
    let two = channel == "label";
    assert_eq!(bytes.len(), G * G * G * if two { 2 } else { 1 });
    let mut out = Segments::new();
    for i in 0..G * G * G {
        let v = if two {
            u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]])
        } else {
            u16::from(bytes[i])
        };
        if v == 0 {
            continue;
        }
        let p = [i % G, i / G % G, i / (G * G)].map(|c| c as u64);
        let e = out
            .entry(u64::from(v))
            .or_insert((0, [[u64::MAX; 3], [0; 3]]));
        e.0 += 1;
        for (a, &c) in p.iter().enumerate() {
            e.1[0][a] = e.1[0][a].min(c);
            e.1[1][a] = e.1[1][a].max(c + 1);
        }
    }
    out
}

/// The list's segments as [`Segments`], with the version it names.
fn listed(list: &Value) -> (u64, Segments) {
    let segments = list["segments"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            let b = |i: usize| -> [u64; 3] {
                let c = s["box"][i].as_array().unwrap();
                [0, 1, 2].map(|a| c[a].as_u64().unwrap())
            };
            (
                s["id"].as_u64().unwrap(),
                (s["voxels"].as_u64().unwrap(), [b(0), b(1)]),
            )
        })
        .collect();
    (list["version"].as_u64().unwrap(), segments)
}

/// The label list at the head, checked against a recount at the version it names.
fn labels_checked(server: &ServerProcess, what: &str) -> Segments {
    let list = get_json(server, "/v1/volumes/world/channels/label/segments");
    assert_eq!(list["channel"], "label");
    let (version, segments) = listed(&list);
    assert_eq!(
        segments,
        recount(server, "label", version),
        "{what}: the list differs from a recount at version {version}"
    );
    assert_eq!(list["total"].as_u64(), Some(segments.len() as u64));
    segments
}

#[test]
fn segments_follow_paints_undo_redo_and_revert_and_equal_a_recount() {
    isovox_server::client_tls::install_provider();
    let dir = tempfile::tempdir().unwrap();
    ground(dir.path());
    let server = serve(dir.path());

    // Materials in use: rock everywhere, by construction.
    let (_, materials) = listed(&get_json(
        &server,
        "/v1/volumes/world/channels/material/segments",
    ));
    assert_eq!(
        materials,
        Segments::from([(1, (64 * 64 * 64, [[0; 3], [64; 3]]))])
    );

    assert!(labels_checked(&server, "fresh").is_empty());
    let first = paint(&server, [10, 12, 14], [12, 8, 6], 5);
    // Inside on [11, 21) x [13, 19) x [15, 19): 10 x 6 x 4 voxels, across two bricks in x.
    let after_first = labels_checked(&server, "id 5 painted");
    assert_eq!(
        after_first,
        Segments::from([(5, (240, [[11, 13, 15], [21, 19, 19]]))])
    );

    // Id 9 on [19, 27) x [15, 23) x [11, 19), 8^3, over id 5's corner [19, 21) x [15, 19) x
    // [15, 19) (2 x 4 x 4 = 32 voxels): id 5 keeps 208 and its box (its voxels at x < 19
    // reach every y and z of it).
    let second = paint(&server, [18, 14, 10], [10, 10, 10], 9);
    assert_eq!(second, first + 1);
    assert_eq!(
        labels_checked(&server, "id 9 painted over 5"),
        Segments::from([
            (5, (208, [[11, 13, 15], [21, 19, 19]])),
            (9, (512, [[19, 15, 11], [27, 23, 19]])),
        ])
    );

    // Undo the 9s: the list is the first one again.
    let undo = post_ok(
        &server,
        "/v1/volumes/world/undo",
        json!({"version": second}),
    );
    assert_eq!(labels_checked(&server, "id 9 undone"), after_first);
    // Redo (undo of the undo): the 9s are back.
    post_ok(
        &server,
        "/v1/volumes/world/undo",
        json!({"version": undo["version"]}),
    );
    assert_eq!(
        labels_checked(&server, "id 9 redone")
            .keys()
            .copied()
            .collect::<Vec<_>>(),
        [5, 9]
    );
    // Revert to the fresh volume: nothing labelled.
    post_ok(
        &server,
        "/v1/volumes/world/revert",
        json!({"to": first - 1}),
    );
    assert!(labels_checked(&server, "reverted to the start").is_empty());

    // Several ids, some in one brick, some across bricks; then the pages of one id each.
    for (i, id) in [300u16, 2, 65535, 41, 7].into_iter().enumerate() {
        let i = i as u32;
        paint(&server, [2 + 11 * i, 3 + 5 * i, 4 + 7 * i], [5, 4, 6], id);
    }
    let all = labels_checked(&server, "five ids");
    assert_eq!(
        all.keys().copied().collect::<Vec<_>>(),
        [2, 7, 41, 300, 65535]
    );
    // Each is 3 x 2 x 4 voxels (the boxes lie apart in x).
    assert_eq!(all[&300], (24, [[3, 4, 5], [6, 6, 9]]));
    let mut walked = Segments::new();
    let mut after = None;
    let mut pages = 0;
    loop {
        let path = match after {
            None => "/v1/volumes/world/channels/label/segments?limit=1".to_string(),
            Some(a) => format!("/v1/volumes/world/channels/label/segments?limit=1&after={a}"),
        };
        let page = get_json(&server, &path);
        let (_, got) = listed(&page);
        assert!(got.len() <= 1, "{page}");
        walked.extend(got);
        pages += 1;
        match page["next"].as_u64() {
            Some(next) => after = Some(next),
            None => break,
        }
        assert!(pages <= 10, "the pages do not end: {page}");
    }
    assert_eq!(walked, all);
    assert_eq!(pages, 5);
    // after= past every id: an empty page without next.
    let past = get_json(
        &server,
        "/v1/volumes/world/channels/label/segments?after=65535",
    );
    assert_eq!(past["segments"], json!([]));
    assert!(past.get("next").is_none());

    // An older version, pinned: the list of that version (a scan; the volume is small).
    let pinned = get_json(
        &server,
        &format!("/v1/volumes/world/channels/label/segments?version={first}"),
    );
    assert_eq!(listed(&pinned), (first, after_first.clone()));

    // One build per channel, then updates from the commits: the log says so.
    let builds = || {
        server
            .log()
            .lines()
            .filter(|l| l.contains("segment index built") && l.contains("label"))
            .count()
    };
    assert_eq!(builds(), 1, "the label index was built more than once");

    // A paint the index has not seen, then compaction (the file starts again from the head,
    // its first commit relative to nothing), then another paint: the commits no longer lead
    // from the indexed version, and the index is built again, right.
    paint(&server, [40, 40, 40], [6, 6, 6], 12);
    post_ok(&server, "/v1/volumes/world/compact", json!({}));
    paint(&server, [50, 2, 2], [4, 4, 4], 13);
    let compacted = labels_checked(&server, "after compaction");
    assert_eq!(compacted[&12], (64, [[41, 41, 41], [45, 45, 45]]));
    assert_eq!(compacted[&13], (8, [[51, 3, 3], [53, 5, 5]]));
    assert_eq!(builds(), 2, "the index was not rebuilt after compaction");
    // From there on, updates again.
    paint(&server, [50, 2, 2], [4, 4, 4], 14);
    let later = labels_checked(&server, "id 14 over 13");
    assert!(!later.contains_key(&13) && later[&14].0 == 8);
    assert_eq!(builds(), 2);
}

/// The precomputed view's segmentation sources name their segment properties, and those list
/// each segment as Neuroglancer reads them (inline ids as decimal strings, one value per id in
/// every property), with the hand-counted sizes and boxes of the paints; pinned to a version,
/// that version's segments, immutable.
#[test]
fn precomputed_segmentations_list_their_segments_as_neuroglancer_segment_properties() {
    isovox_server::client_tls::install_provider();
    let dir = tempfile::tempdir().unwrap();
    ground(dir.path());
    let server = serve(dir.path());
    let base = "/v1/volumes/world/precomputed";
    let info = get_json(&server, &format!("{base}/label/info"));
    assert_eq!(info["segment_properties"], "segment_properties");
    assert!(get_json(&server, &format!("{base}/info"))
        .get("segment_properties")
        .is_none());

    let properties = |path: &str| get_json(&server, &format!("{path}/segment_properties/info"));
    // Nothing labelled: no ids, and every property empty.
    let empty = properties(&format!("{base}/label"));
    assert_eq!(empty["@type"], "neuroglancer_segment_properties");
    assert_eq!(empty["inline"]["ids"], json!([]));

    // The paints of the test above: id 5 inside [11, 21) x [13, 19) x [15, 19), then id 9 on
    // [19, 27) x [15, 23) x [11, 19) over 32 of its voxels.
    let first = paint(&server, [10, 12, 14], [12, 8, 6], 5);
    paint(&server, [18, 14, 10], [10, 10, 10], 9);
    let expected = |ids: &[&str], texts: &[&str], voxels: &[u64]| {
        json!({
            "@type": "neuroglancer_segment_properties",
            "inline": {
                "ids": ids,
                "properties": [
                    {"id": "description", "type": "description", "values": texts},
                    {"id": "voxels", "type": "number", "data_type": "uint32",
                     "description": "level-0 voxels holding the id", "values": voxels}
                ]
            }
        })
    };
    assert_eq!(
        properties(&format!("{base}/label")),
        expected(
            &["5", "9"],
            &[
                "208 voxels in [11, 13, 15] .. [21, 19, 19]",
                "512 voxels in [19, 15, 11] .. [27, 23, 19]"
            ],
            &[208, 512]
        )
    );
    // The material channel: rock everywhere.
    assert_eq!(
        properties(&format!("{base}/material")),
        expected(
            &["1"],
            &["262144 voxels in [0, 0, 0] .. [64, 64, 64]"],
            &[262_144]
        )
    );

    // Pinned to the first paint's version: id 5 alone, whole, and cached for good.
    let pinned =
        format!("/v1/volumes/world/versions/{first}/precomputed/label/segment_properties/info");
    let r = reqwest::blocking::get(server.url(&pinned)).unwrap();
    assert_eq!(r.status(), 200);
    assert!(r.headers()["cache-control"]
        .to_str()
        .unwrap()
        .contains("immutable"));
    let doc: Value = r.json().unwrap();
    assert_eq!(
        doc,
        expected(
            &["5"],
            &["240 voxels in [11, 13, 15] .. [21, 19, 19]"],
            &[240]
        )
    );
    // The live document names its version's pinned URL.
    let r = reqwest::blocking::get(server.url(&format!("{base}/label/segment_properties/info")))
        .unwrap();
    assert_eq!(
        r.headers()["content-location"].to_str().unwrap(),
        format!(
            "/v1/volumes/world/versions/{}/precomputed/label/segment_properties/info",
            first + 1
        )
    );

    // A channel the volume lacks: 404 naming the ones it has.
    let (status, body) = get(&server, &format!("{base}/nothing/segment_properties/info"));
    assert_eq!(status, 404, "{}", String::from_utf8_lossy(&body));
    assert!(String::from_utf8_lossy(&body).contains("label"));
}

/// The volume marching cubes (iso 0.5) encloses around an `n x m x k` box of ones in a field
/// of zeros, voxel units, derived cell by cell: every cell of the grid whose corners are all
/// inside is whole (as in the box of side n, m, k around the voxel centres, grown by 0.5);
/// a cell with a face of four corners inside holds half a cell, as that box does; a cell with
/// an edge of two corners inside holds the prism under the cut from midpoint to midpoint,
/// 1/8, where the box holds 1/4; a cell with one corner inside, the tetrahedron of legs 1/2,
/// 1/48, where the box holds 1/8. There are 4(n-1) + 4(m-1) + 4(k-1) edge cells and 8 corner
/// cells, so the mesh holds nmk - (n+m+k-3)/2 - 8 (5/48). One voxel: 1 - 5/6 = 1/6, the
/// octahedron of radius 1/2.
fn box_volume(n: f64, m: f64, k: f64) -> f64 {
    n * m * k - (n + m + k - 3.0) / 2.0 - 5.0 / 6.0
}

#[test]
fn a_segment_s_mesh_is_closed_and_encloses_what_marching_cubes_gives_a_box() {
    isovox_server::client_tls::install_provider();
    let dir = tempfile::tempdir().unwrap();
    ground(dir.path());
    let server = serve(dir.path());
    // Id 5 on [11, 21) x [13, 19) x [15, 19): 10 x 6 x 4.
    let version = paint(&server, [10, 12, 14], [12, 8, 6], 5);
    assert_eq!(
        labels_checked(&server, "id 5"),
        Segments::from([(5, (240, [[11, 13, 15], [21, 19, 19]]))])
    );

    let mesh_at = |query: &str| {
        let r = reqwest::blocking::get(server.url(&format!(
            "/v1/volumes/world/channels/label/segments/5/mesh{query}"
        )))
        .unwrap();
        assert_eq!(r.status().as_u16(), 200, "{query}");
        let meshed = r.headers()["isovox-version"].to_str().unwrap().to_string();
        assert_eq!(meshed, version.to_string());
        r.bytes().unwrap().to_vec()
    };
    let compact = mesh_at("");
    let mesh = isovox_proto::mesh::decode_compact(&compact).unwrap();
    assert!(mesh.triangles() > 0);
    assert_eq!(open_edges(&mesh), 0, "the mesh is not closed");
    // One vertex per crossed grid edge, welded: one per face of the box's voxels,
    // 2 (10 x 6 + 10 x 4 + 6 x 4) = 248.
    assert_eq!(mesh.positions.len(), 248);
    let v = enclosed_volume(&mesh);
    let want = box_volume(10.0, 6.0, 4.0);
    // Every vertex lies at a midpoint, exact in f32: only the sum's rounding differs.
    assert!((v - want).abs() < 1e-3, "volume {v}, by hand {want}");
    assert!(v > 9.0 * 5.0 * 3.0 && v < 240.0);
    // The surface lies half a voxel outside the voxel centres of the box.
    let (lo, hi) = mesh.bounds();
    assert_eq!((lo, hi), ([10.5, 12.5, 14.5], [20.5, 18.5, 18.5]));

    // GLB: the same mesh, which a glTF reader opens.
    let glb = mesh_at("?format=glb");
    let gltf = gltf::Gltf::from_slice(&glb).unwrap();
    let prim = gltf.meshes().next().unwrap().primitives().next().unwrap();
    assert_eq!(
        prim.get(&gltf::Semantic::Positions).unwrap().count(),
        mesh.positions.len()
    );
    assert_eq!(prim.indices().unwrap().count(), mesh.indices.len());

    // Level 1 (sparse mode: every 2x2x2 holding a 5 is 5): [5, 11) x [6, 10) x [7, 10), 6 x 4
    // x 3 voxels of side 2 in world units.
    let coarse = isovox_proto::mesh::decode_compact(&mesh_at("?level=1&format=compact")).unwrap();
    assert_eq!(open_edges(&coarse), 0);
    let v1 = enclosed_volume(&coarse);
    let want1 = 8.0 * box_volume(6.0, 4.0, 3.0);
    assert!(
        (v1 - want1).abs() < 1e-2,
        "level 1 volume {v1}, by hand {want1}"
    );
    assert_eq!(coarse.bounds(), ([9.0, 11.0, 13.0], [21.0, 19.0, 19.0]));

    // Hostile and wrong requests: a 4xx with words, never a panic.
    let seg = "/v1/volumes/world/channels/label/segments";
    for (path, want) in [
        (format!("{seg}/70000/mesh"), 404),
        (format!("{seg}/0/mesh"), 404),
        (format!("{seg}/6/mesh"), 404),
        (format!("{seg}/abc/mesh"), 400),
        (format!("{seg}/99999999999999999999999/mesh"), 400),
        (format!("{seg}/5/mesh?level=7"), 404),
        (format!("{seg}/5/mesh?level=256"), 400),
        (format!("{seg}/5/mesh?level=x"), 400),
        (format!("{seg}/5/mesh?format=obj"), 400),
        (format!("{seg}?limit=0"), 400),
        (format!("{seg}?limit=1000000000"), 400),
        (format!("{seg}?limit=1e9"), 400),
        (format!("{seg}?after=x"), 400),
        (format!("{seg}?version=999"), 404),
        ("/v1/volumes/world/channels/density/segments".into(), 422),
        (
            "/v1/volumes/world/channels/density/segments/5/mesh".into(),
            422,
        ),
        ("/v1/volumes/world/channels/colour/segments".into(), 404),
        ("/v1/volumes/nowhere/channels/label/segments".into(), 404),
        ("/v1/volumes/world/channels/a%20b/segments".into(), 400),
    ] {
        let (status, body) = get(&server, &path);
        let body = String::from_utf8_lossy(&body);
        assert_eq!(status, want, "{path}: {body}");
        assert!(body.contains("detail"), "{path}: no words: {body}");
    }
    // A negative id is not a number of the API's spelling: some 4xx.
    let (status, _) = get(&server, &format!("{seg}/-5/mesh"));
    assert!((400..500).contains(&status), "-5: {status}");
    let (_, body) = get(&server, "/v1/volumes/world/channels/colour/segments");
    assert!(
        String::from_utf8_lossy(&body).contains("label"),
        "the 404 names the channels there are"
    );
    // Still serving.
    assert_eq!(get(&server, seg).0, 200);
}
