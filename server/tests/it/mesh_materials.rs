//! Per-vertex materials of mesh tiles and strips (`?channel=NAME`, `docs/channels.md`), over
//! HTTP against a served `isovox serve`:
//!
//! - a volume built here whose surface, materials and crossings are known by hand: every
//!   vertex's (a, b, w) is recomputed from its position (which lattice edge it lies on, and
//!   where) and the materials defined below, never from the code's output;
//! - the geometry with and without `?channel` is the same, bit for bit, and the plain bytes are
//!   those of `?channel=density`;
//! - a u16 channel is a 422, an unknown one a 404 naming the channels;
//! - a `paint` (a channel edit, density untouched) changes the tile's materials and ETag and
//!   nothing else;
//! - strips carry the tile's materials on the vertices they copy from it;
//! - the GLB with its `_MATERIAL` and `_MATERIAL_WEIGHT` attributes passes the Khronos glTF
//!   validator (the `gltf-validator` npm package) with no error.

use crate::server_process::ServerProcess;
use isovox_proto::mesh::{decode_strip, decode_tile, stitch, Mesh, TileMesh};
use isovox_server::store::BuildOptions;
use std::path::{Path, PathBuf};

/// The hand-built volume: 32 x 16 x 16 voxels, bricks of 16 (two level-0 tiles along x, one
/// level-1 tile), voxel scale 1.
const DIMS: [usize; 3] = [32, 16, 16];

/// Density: 250 for y <= 6, `150 + 10 * (x % 8)` at y = 7 (still inside: >= S = 127), empty
/// above. The default iso value is S - 0.5 = 126.5, so the surface crosses each edge from
/// (x, 7, z) to (x, 8, z) at t = (126.5 - d) / (0 - d) = 1 - 126.5 / d, and closes along the
/// volume's faces (outside it everything is 0), at t = 126.5 / 250 from outside on the faces
/// of the full part. No t * 255 is near a half (250, not 255: 126.5 / 255 * 255 would be one),
/// so w = round(t * 255) does not depend on the last bit of a position.
fn density(x: usize, y: usize, _z: usize) -> u8 {
    match y {
        0..=6 => 250,
        7 => 150 + 10 * (x % 8) as u8,
        _ => 0,
    }
}

/// Materials: rock (1) for x < 8 and, for x >= 8, ore (5) where z < 8 and sand (4) where
/// z >= 8, up to y = 7; above, soil (2) for x < 8 and air (0) for x >= 8. So the surface's edges
/// (x, 7) -> (x, 8) blend rock into soil for x < 8, and are ore or sand alone for x >= 8 (air
/// takes the other end's value). Every 2x2x2 group is uniform (the boundaries x = 8, y = 8 and
/// z = 8 are even), so level 1 of the channel is `material(2J)`; and level-0 voxel J is not
/// always `material(2J)` (z = 5 is ore, z = 10 sand), so reading the wrong level shows.
fn material(x: usize, y: usize, z: usize) -> u8 {
    match (x < 8, y <= 7) {
        (true, true) => 1,
        (false, true) if z < 8 => 5,
        (false, true) => 4,
        (true, false) => 2,
        (false, false) => 0,
    }
}

/// The material at level-0 voxel `p`, 0 outside the volume.
fn material_at(p: [i64; 3]) -> u8 {
    if (0..3).all(|a| p[a] >= 0 && (p[a] as usize) < DIMS[a]) {
        material(p[0] as usize, p[1] as usize, p[2] as usize)
    } else {
        0
    }
}

/// Writes the hand-built volume to `dir/hand.vod`: density, `material` (u8) and `label` (u16,
/// all 0: a channel that cannot give materials).
fn hand_volume(dir: &Path) {
    let n = DIMS.iter().product::<usize>();
    let (mut d, mut m) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for z in 0..DIMS[2] {
        for y in 0..DIMS[1] {
            for x in 0..DIMS[0] {
                d.push(density(x, y, z));
                m.push(material(x, y, z));
            }
        }
    }
    let dims = DIMS.map(|c| c as u32);
    crate::channel_volumes::write_volume(&dir.join("hand.vod"), dims, &d, &m, false);
}

/// The demo world `isovox serve` generates on first start (512 x 256 x 512, brick 32, with a
/// material channel), as `dir/demo.vod`.
fn demo_world(dir: &Path) {
    isovox_server::generate::build_demo(dir, &BuildOptions::default()).unwrap();
}

/// Tiles of the demo world across its terrain's surface: level-0 columns at a few places, and
/// coarser tiles.
fn demo_tiles() -> Vec<String> {
    let mut keys = Vec::new();
    for (x, z) in [(3, 4), (8, 8), (12, 5)] {
        for y in 0..8 {
            keys.push(format!("0/{x}/{y}/{z}"));
        }
    }
    keys.extend(
        [
            "1/2/1/2", "1/4/2/4", "1/6/1/3", "2/1/0/1", "2/2/1/2", "3/0/0/0",
        ]
        .map(String::from),
    );
    keys
}

use crate::channel_volumes::TOKEN;

fn serve(dir: &Path) -> ServerProcess {
    crate::channel_volumes::serve(dir, &[])
}

/// Status, ETag and body of a GET.
fn get(url: &str) -> (u16, String, Vec<u8>) {
    let r = reqwest::blocking::get(url).unwrap_or_else(|e| panic!("{url}: {e}"));
    let status = r.status().as_u16();
    let etag = r
        .headers()
        .get("etag")
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    (status, etag, r.bytes().unwrap().to_vec())
}

fn tile(server: &ServerProcess, volume: &str, key: &str, query: &str) -> (String, TileMesh) {
    let url = server.url(&format!("/v1/volumes/{volume}/meshes/{key}{query}"));
    let (status, etag, body) = get(&url);
    assert_eq!(status, 200, "{url}: {}", String::from_utf8_lossy(&body));
    (etag, decode_tile(&body).unwrap())
}

/// The lattice edge a vertex at lattice coordinates `p` lies on (found from its position
/// alone: the one coordinate that is not an integer), and where on it: `(p0, p1, t)`.
fn edge_of(p: [f32; 3]) -> ([i64; 3], [i64; 3], f32) {
    let off: Vec<usize> = (0..3).filter(|&a| p[a].fract() != 0.0).collect();
    assert_eq!(off.len(), 1, "{p:?} lies on no lattice edge");
    let a = off[0];
    let p0 = p.map(|c| c.floor() as i64);
    let mut p1 = p0;
    p1[a] += 1;
    (p0, p1, p[a] - p0[a] as f32)
}

/// The rule, written out: the two ends' materials, an end of 0 taking the other's, and
/// round(t * 255).
fn rule(a: u8, b: u8, t: f32) -> [u8; 4] {
    let (a, b) = match (a, b) {
        (0, b) => (b, b),
        (a, 0) => (a, a),
        ab => ab,
    };
    [a, b, (t * 255.0).round() as u8, 0]
}

/// Checks every vertex of a tile of `level` (positions in world coordinates, voxel scale 1)
/// against the rule with the level-0 materials `at` (lattice point J of level k is level-0
/// voxel 2^k J); `w_slack` is how far w may be from round(t * 255) with t read off the world
/// position. Returns how many vertices blend two different non-zero materials.
fn assert_rule(tile: &Mesh, level: u8, at: &dyn Fn([i64; 3]) -> u8, w_slack: u8) -> usize {
    assert_eq!(tile.materials.len(), tile.positions.len());
    let step = (1u32 << level) as f32;
    let mut blends = 0;
    for (p, m) in tile.positions.iter().zip(&tile.materials) {
        let (p0, p1, t) = edge_of(p.map(|c| c / step));
        let scale = |q: [i64; 3]| q.map(|c| c << level);
        let want = rule(at(scale(p0)), at(scale(p1)), t);
        assert_eq!(&m[..2], &want[..2], "materials of the vertex at {p:?}");
        assert!(
            m[2].abs_diff(want[2]) <= w_slack && m[3] == 0,
            "weight of the vertex at {p:?}: {m:?}, by hand {want:?} (t = {t})"
        );
        blends += usize::from(m[0] != m[1] && m[0] != 0 && m[1] != 0);
    }
    blends
}

#[test]
fn tile_materials_follow_the_rule_by_hand() {
    let dir = tempfile::tempdir().unwrap();
    hand_volume(dir.path());
    let server = serve(dir.path());
    let mut blends = 0;
    for key in ["0/0/0/0", "0/1/0/0"] {
        let (_, t) = tile(&server, "hand", key, "?channel=material");
        assert!(t.mesh.triangles() > 100, "{key}: {}", t.mesh.triangles());
        blends += assert_rule(&t.mesh, 0, &material_at, 0);
        // The surface's crossings, by hand: on (x, 7, z) -> (x, 8, z), t = 1 - 126.5 / d.
        let mut on_top = 0;
        for (p, m) in t.mesh.positions.iter().zip(&t.mesh.materials) {
            if p[1] > 7.0 && p[1] < 8.0 && (0.0..31.0).contains(&p[0]) && p[0].fract() == 0.0 {
                let d = f32::from(density(p[0] as usize, 7, 0));
                assert!((p[1] - 7.0 - (1.0 - 126.5 / d)).abs() < 1e-5, "{p:?}");
                let want = match (p[0] < 8.0, p[2] < 8.0) {
                    (true, _) => [1, 2],
                    (false, true) => [5, 5],
                    (false, false) => [4, 4],
                };
                assert_eq!(&m[..2], &want, "{p:?}");
                on_top += 1;
            }
        }
        assert!(
            on_top >= 16 * 8,
            "{key}: {on_top} vertices on the top surface"
        );
    }
    // x in 0..8 on y = 7 blends rock into soil: 8 x 16 vertices on the top, and their
    // neighbours on the volume's faces.
    assert!(blends >= 8 * 16, "{blends} vertices blend two materials");
    // Level 1: the channel's level 1 at lattice point J is material(2J) (uniform 2x2x2 groups).
    // t is read off a world position that went through (local + 16) * 2 in f32: w may be off
    // by one where t * 255 lies within a few ulps of a half.
    let (_, t) = tile(&server, "hand", "1/0/0/0", "?channel=material");
    assert!(t.mesh.triangles() > 10);
    assert_rule(&t.mesh, 1, &material_at, 1);
}

#[test]
fn materials_leave_the_geometry_alone_and_bad_channels_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    hand_volume(dir.path());
    demo_world(dir.path());
    let server = serve(dir.path());
    let mut compared = 0;
    let mut strips = Vec::new();
    for key in demo_tiles() {
        let key = key.as_str();
        let (plain_tag, plain) = tile(&server, "demo", key, "");
        let (tag, with) = tile(&server, "demo", key, "?channel=material");
        assert_ne!(plain_tag, tag, "{key}: the ETag names the channel");
        assert!(plain.mesh.materials.is_empty());
        assert_eq!(with.mesh.positions, plain.mesh.positions, "{key}");
        assert_eq!(with.mesh.normals, plain.mesh.normals, "{key}");
        assert_eq!(with.mesh.indices, plain.mesh.indices, "{key}");
        assert_eq!(with.moves, plain.moves, "{key}");
        assert_eq!(with.mesh.materials.len(), with.mesh.positions.len());
        // The demo world's materials: air, rock, soil, grass, sand, ore, marble.
        assert!(with.mesh.materials.iter().all(|m| m[0] <= 6 && m[1] <= 6));
        if !with.mesh.positions.is_empty() {
            assert!(with.mesh.materials.iter().any(|m| m[0] != 0), "{key}");
            compared += 1;
            strips.push(key.to_string());
        }
        // `?channel=density` is the plain tile, byte for byte.
        let url = |q: &str| server.url(&format!("/v1/volumes/demo/meshes/{key}{q}"));
        assert_eq!(get(&url("")).2, get(&url("?channel=density")).2);
        // GLB too: the same geometry, and the attributes only when asked for.
        let (_, _, glb) = get(&url("?format=glb"));
        let (_, _, glb_m) = get(&url("?format=glb&channel=material"));
        assert!(!String::from_utf8_lossy(&glb).contains("_MATERIAL"));
        assert_eq!(
            String::from_utf8_lossy(&glb_m).contains("_MATERIAL_WEIGHT"),
            !with.mesh.positions.is_empty()
        );
    }
    assert!(compared >= 6, "{compared} tiles with a surface");
    // Strips of the tiles with a surface: the same geometry with and without materials.
    let mut strip_vertices = 0;
    for key in &strips {
        for face in ["-x", "+x", "-y", "+y", "-z", "+z"] {
            let url =
                |q: &str| server.url(&format!("/v1/volumes/demo/meshes/{key}/strips/{face}{q}"));
            let plain = decode_strip(&get(&url("")).2).unwrap();
            let with = decode_strip(&get(&url("?channel=material")).2).unwrap();
            assert_eq!(
                (&with.positions, &with.normals, &with.indices),
                (&plain.positions, &plain.normals, &plain.indices),
                "{key} {face}"
            );
            assert!(plain.materials.is_empty());
            assert_eq!(with.materials.len(), with.positions.len());
            assert!(with
                .materials
                .iter()
                .all(|m| m[0] <= 6 && m[1] <= 6 && m[3] == 0));
            strip_vertices += with.positions.len();
        }
    }
    assert!(strip_vertices > 0, "no strip had a vertex");
    // A u16 channel: 422, saying why. An unknown one: 404 naming the channels.
    for path in [
        "/v1/volumes/hand/meshes/0/0/0/0?channel=label",
        "/v1/volumes/hand/meshes/0/0/0/0/strips/+x?channel=label",
    ] {
        let (status, _, body) = get(&server.url(path));
        let body = String::from_utf8_lossy(&body);
        assert_eq!(status, 422, "{path}: {body}");
        assert!(
            body.contains("per-vertex materials need a u8 channel"),
            "{body}"
        );
    }
    for path in [
        "/v1/volumes/hand/meshes/0/0/0/0?channel=colour",
        "/v1/volumes/hand/meshes/0/0/0/0/strips/+x?channel=colour",
    ] {
        let (status, _, body) = get(&server.url(path));
        let body = String::from_utf8_lossy(&body);
        assert_eq!(status, 404, "{path}: {body}");
        assert!(
            body.contains("material") && body.contains("label"),
            "{body}"
        );
    }
}

#[test]
fn a_paint_changes_the_materials_and_the_etag_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    hand_volume(dir.path());
    let server = serve(dir.path());
    let (plain_tag, plain) = tile(&server, "hand", "0/0/0/0", "");
    let (tag, before) = tile(&server, "hand", "0/0/0/0", "?channel=material");
    let (again, _) = tile(&server, "hand", "0/0/0/0", "?channel=material");
    assert_eq!(tag, again, "the same content, the same ETag");
    assert!(before.mesh.materials.iter().all(|m| m[0] != 6));
    // Marble in a ball of radius 4 around (4, 8, 8), across the surface at y = 7..8.
    let r = reqwest::blocking::Client::new()
        .post(server.url("/v1/volumes/hand/edits"))
        .bearer_auth(TOKEN)
        .json(
            &serde_json::json!({"op": "paint", "channel": "material", "term": {
            "ellipsoid": {"center": [4, 8, 8], "radii": [4, 4, 4], "material": 6}}}),
        )
        .send()
        .unwrap();
    assert!(r.status().is_success(), "{}", r.text().unwrap());
    let (plain_after_tag, plain_after) = tile(&server, "hand", "0/0/0/0", "");
    assert_eq!(plain_after_tag, plain_tag, "density is untouched");
    assert_eq!(plain_after, plain);
    let (after_tag, after) = tile(&server, "hand", "0/0/0/0", "?channel=material");
    assert_ne!(after_tag, tag, "the paint changed the tile's ETag");
    assert_eq!(after.mesh.positions, before.mesh.positions);
    assert_eq!(after.mesh.normals, before.mesh.normals);
    assert_eq!(after.mesh.indices, before.mesh.indices);
    assert_eq!(after.moves, before.moves);
    // The channel as served now, and the rule by hand over it.
    let (status, _, voxels) =
        get(&server.url("/v1/volumes/hand/levels/0?channel=material&format=voxels"));
    assert_eq!((status, voxels.len()), (200, DIMS.iter().product()));
    let painted = |p: [i64; 3]| {
        if (0..3).all(|a| p[a] >= 0 && (p[a] as usize) < DIMS[a]) {
            let [x, y, z] = p.map(|c| c as usize);
            voxels[(z * DIMS[1] + y) * DIMS[0] + x]
        } else {
            0
        }
    };
    // Well inside the ball every voxel is marble; well outside, as built.
    for p in [[4, 8, 8], [4, 7, 9], [6, 8, 7]] {
        assert_eq!(painted(p), 6, "{p:?}");
    }
    assert_eq!(painted([4, 8, 14]), material_at([4, 8, 14]));
    assert_rule(&after.mesh, 0, &painted, 0);
    let marble = after
        .mesh
        .positions
        .iter()
        .zip(&after.mesh.materials)
        .filter(|(p, m)| {
            let d = [p[0] - 4.0, p[1] - 8.0, p[2] - 8.0];
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() < 2.0 && m[..2] == [6, 6]
        })
        .count();
    assert!(
        marble >= 4,
        "{marble} marble vertices near the ball's centre"
    );
    // Far from the ball, nothing changed.
    for ((p, a), b) in after
        .mesh
        .positions
        .iter()
        .zip(&after.mesh.materials)
        .zip(&before.mesh.materials)
    {
        let d = [p[0] - 4.0, p[1] - 8.0, p[2] - 8.0];
        if (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() > 6.0 {
            assert_eq!(a, b, "{p:?}");
        }
    }
}

#[test]
fn strips_carry_the_materials_of_the_vertices_they_copy() {
    let dir = tempfile::tempdir().unwrap();
    hand_volume(dir.path());
    let server = serve(dir.path());
    // Tile (0, 0, 0) of level 0 meets level 1 across +x: its strip there.
    let (_, t) = tile(&server, "hand", "0/0/0/0", "?channel=material");
    let url = server.url("/v1/volumes/hand/meshes/0/0/0/0/strips/+x?channel=material");
    let (status, _, body) = get(&url);
    assert_eq!(status, 200);
    let strip = decode_strip(&body).unwrap();
    assert!(strip.triangles() > 0);
    assert_eq!(strip.materials.len(), strip.positions.len());
    // Drawn with the +x face: the tile's moved vertices, which the strip copies bit for bit.
    let mut drawn = Mesh::default();
    stitch(&t, 0b10, [None; 6], &mut drawn);
    let mut copies = 0;
    for (p, m) in strip.positions.iter().zip(&strip.materials) {
        if let Some(i) = drawn.positions.iter().position(|q| q == p) {
            assert_eq!(
                m, &drawn.materials[i],
                "the copy of tile vertex {i} at {p:?}"
            );
            copies += 1;
        }
        // Every vertex here lies on an edge with an end below the surface (rock, ore or
        // sand), the other soil, ore, sand or air: never none.
        assert!(
            m[..2].iter().all(|v| [1, 2, 4, 5].contains(v)),
            "{p:?}: {m:?}"
        );
    }
    assert!(copies >= 4, "{copies} copies of tile vertices");
    // The strip's coarse vertices lie on the face's plane x = 16, never moved, on edges of the
    // level-1 lattice (level-0 positions 2J): one coordinate between two even ones. Their ends
    // are the channel's level-1 voxels J, which is material(2J) here; t is read off the
    // position, (y - 2 J0) / 2.
    let mut coarse = 0;
    for (p, m) in strip.positions.iter().zip(&strip.materials) {
        let copy = drawn.positions.contains(p);
        let off: Vec<usize> = (1..3).filter(|&a| p[a].fract() != 0.0).collect();
        if copy || p[0] != 16.0 || off.len() != 1 {
            continue;
        }
        let a = off[0];
        let b = 3 - a; // the other lateral axis: on the coarse lattice
        assert_eq!(p[b] % 2.0, 0.0, "{p:?} is on no coarse edge");
        let mut j0 = [8i64, 0, 0];
        j0[a] = (p[a] / 2.0).floor() as i64;
        j0[b] = (p[b] / 2.0) as i64;
        let mut j1 = j0;
        j1[a] += 1;
        let t = (p[a] - (2 * j0[a]) as f32) / 2.0;
        let want = rule(
            material_at(j0.map(|c| 2 * c)),
            material_at(j1.map(|c| 2 * c)),
            t,
        );
        assert_eq!(m, &want, "the coarse vertex at {p:?}");
        coarse += 1;
    }
    assert!(coarse >= 4, "{coarse} coarse vertices");
}

fn web() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../web")
}

/// `web/node_modules`, installed from the lock file when missing (as `web.rs` does).
fn node_modules() {
    static DONE: std::sync::Mutex<bool> = std::sync::Mutex::new(false);
    let mut done = DONE.lock().unwrap_or_else(|e| e.into_inner());
    if !*done && !web().join("node_modules/gltf-validator").exists() {
        let status = std::process::Command::new("npm")
            .args(["ci", "--no-audit", "--no-fund"])
            .current_dir(web())
            .status()
            .unwrap();
        assert!(status.success(), "npm ci failed");
    }
    *done = true;
}

/// The Khronos validator's report on each of `files`, as JSON.
fn validate(files: &[PathBuf]) -> Vec<serde_json::Value> {
    node_modules();
    let script = r#"
        const validator = require('gltf-validator');
        const fs = require('fs');
        (async () => {
            for (const f of process.argv.slice(1)) {
                const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)));
                console.log(JSON.stringify(report));
            }
        })().catch((e) => { console.error(e); process.exit(1); });
    "#;
    let out = std::process::Command::new("node")
        .arg("-e")
        .arg(script)
        .args(files)
        .current_dir(web())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "node: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn glb_tiles_with_materials_pass_the_khronos_validator() {
    let dir = tempfile::tempdir().unwrap();
    demo_world(dir.path());
    let server = serve(dir.path());
    // A tile with triangles (an empty one's accessors would have count 0, which glTF refuses).
    let key = demo_tiles()
        .into_iter()
        .find(|key| tile(&server, "demo", key, "").1.mesh.triangles() > 100)
        .unwrap();
    let mut files = Vec::new();
    for (name, query) in [
        ("plain.glb", "?format=glb"),
        ("materials.glb", "?format=glb&channel=material"),
    ] {
        let (status, _, body) = get(&server.url(&format!("/v1/volumes/demo/meshes/{key}{query}")));
        assert_eq!(status, 200);
        let path = dir.path().join(name);
        std::fs::write(&path, body).unwrap();
        files.push(path);
    }
    let reports = validate(&files);
    assert_eq!(reports.len(), 2);
    for (report, file) in reports.iter().zip(&files) {
        assert_eq!(
            report["issues"]["numErrors"],
            0,
            "{}: {report:#}",
            file.display()
        );
        assert!(report["info"]["totalTriangleCount"].as_u64().unwrap() > 0);
    }
    // The report counts the primitive's attributes (it does not name them): POSITION and
    // NORMAL, and with materials _MATERIAL and _MATERIAL_WEIGHT; the names are the GLB's own.
    assert_eq!(reports[0]["info"]["maxAttributes"], 2, "{:#}", reports[0]);
    assert_eq!(reports[1]["info"]["maxAttributes"], 4, "{:#}", reports[1]);
    let glb = std::fs::read(&files[1]).unwrap();
    let json_len = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    let json: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let attributes = json["meshes"][0]["primitives"][0]["attributes"]
        .as_object()
        .unwrap();
    let mut names: Vec<&str> = attributes.keys().map(String::as_str).collect();
    names.sort_unstable();
    assert_eq!(
        names,
        ["NORMAL", "POSITION", "_MATERIAL", "_MATERIAL_WEIGHT"]
    );
    let material = &json["accessors"][attributes["_MATERIAL"].as_u64().unwrap() as usize];
    assert_eq!(
        (&material["type"], &material["componentType"]),
        (&serde_json::json!("VEC2"), &serde_json::json!(5121))
    );
    assert_eq!(
        json["bufferViews"][material["bufferView"].as_u64().unwrap() as usize]["byteStride"],
        4
    );
}
