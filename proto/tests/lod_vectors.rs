//! Test vectors of the tile selection (`proto::lod`), of stitching mesh tiles (`proto::mesh`)
//! and of what a mesh tile and its strips read (`proto::tile`) for the web viewer's TypeScript
//! ports (`web/src/lod.ts`, `web/src/mesh.ts`, `web/src/tile.ts`), which its unit tests check
//! against `web/test-vectors/lod.json`, `mesh.json` and `tile.json`. (The bound on lattice
//! values `tile.ts` also ports lives in the server crate: its vectors, `value_range.json`, are
//! written by a unit test in `server/src/mesh/lattice.rs`.)
//!
//! These tests compute the vectors and fail when the committed files differ, so a change to the
//! selection or the encoding cannot land without the vectors (and then the TypeScript ports)
//! following it. `ISOVOX_WRITE_VECTORS=1 cargo test -p isovox-proto --test lod_vectors`
//! rewrites the files.

use isovox_proto::lod::{adaptive_tiles, balanced_tiles, face_masks, tile_distance};
use isovox_proto::mesh::{
    apply_moves, decode_strip, decode_tile, encode_compact, encode_tile, stitch, Mesh, TileMesh,
    VertexMove,
};
use isovox_proto::tile::{
    bricks_of, cells, coarse_box, field_box, has_strip, mesh_tile_reads, stored_box,
    strip_coarse_box, strip_field_box, strip_reads, GridBox,
};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use std::fmt::Write as _;

/// A small deterministic generator (xorshift64*), so the vectors do not change between runs.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    /// Uniform in [lo, hi), as an f32.
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        let u = (self.next() >> 40) as f32 / (1u64 << 24) as f32;
        lo + u * (hi - lo)
    }
}

struct Volume {
    dims: [u32; 3],
    brick: u32,
    scale: [f32; 3],
}

/// Largest selection kept as a case.
const MAX_CASE_TILES: usize = 600;

fn volumes() -> Vec<Volume> {
    vec![
        // The shapes of proto's own lod tests and the demo world.
        Volume {
            dims: [40, 24, 16],
            brick: 8,
            scale: [1.0; 3],
        },
        Volume {
            dims: [512, 256, 512],
            brick: 32,
            scale: [1.0; 3],
        },
        // Uneven grids and anisotropic voxels (an MRI's shape).
        Volume {
            dims: [197, 233, 189],
            brick: 16,
            scale: [1.0, 1.2, 0.8],
        },
        Volume {
            dims: [64, 64, 64],
            brick: 8,
            scale: [1.0, 2.0, 1.0],
        },
        Volume {
            dims: [1000, 300, 700],
            brick: 64,
            scale: [0.5, 0.5, 0.5],
        },
    ]
}

fn json_f32(v: f32) -> String {
    // serde_json writes an f32 with the shortest digits that read back as the same f32.
    serde_json::to_string(&v).unwrap_or_else(|e| panic!("{v}: {e}"))
}

fn json_f32s(v: &[f32]) -> String {
    let parts: Vec<String> = v.iter().map(|&x| json_f32(x)).collect();
    format!("[{}]", parts.join(","))
}

fn json_key(k: BrickKey) -> String {
    format!("[{},{},{},{}]", k.level, k.x, k.y, k.z)
}

/// Radii sets for a volume: none, nothing within reach, and three geometric series, one of them
/// scaled by the volume's extent.
fn radii_sets(v: &Volume, levels: u8) -> Vec<Vec<f32>> {
    let n = levels.saturating_sub(1) as usize;
    let extent = v.dims.iter().map(|&d| d as f32).fold(0.0, f32::max);
    let series = |r0: f32| -> Vec<f32> { (0..n).map(|k| r0 * (1u32 << k) as f32).collect() };
    vec![
        Vec::new(),
        vec![-1.0; n],
        series(v.brick as f32 / 2.0),
        series(extent / 8.0),
        series(extent / 3.0),
        vec![4.0],
    ]
}

fn vectors() -> String {
    let mut rng = Rng(0x1505_0a0b_0c0d_0e0f);
    let mut cases = Vec::new();
    let mut distances = Vec::new();
    for v in volumes() {
        let layout =
            VolumeLayout::new(v.dims, v.brick, VoxelType::U8).unwrap_or_else(|e| panic!("{e}"));
        let world = [0, 1, 2].map(|a| v.dims[a] as f32 * v.scale[a]);
        let mut cameras: Vec<[f32; 3]> = vec![
            [0.0; 3],
            world,
            world.map(|w| w / 2.0),
            [-world[0], world[1] * 2.0, -world[2]],
        ];
        for _ in 0..4 {
            cameras.push([0, 1, 2].map(|a| rng.range(-0.5 * world[a], 1.5 * world[a])));
        }
        for radii in radii_sets(&v, layout.levels()) {
            // On the boundary: a camera exactly r0 away from the first tile's -x face.
            if let Some(&r0) = radii.first() {
                if r0 > 0.0 {
                    cameras.push([-r0, 0.0, 0.0]);
                }
            }
            // Without radii, or with none reachable, the camera does not matter: one will do.
            let reach = if radii.iter().any(|&r| r > 0.0) {
                cameras.len()
            } else {
                1
            };
            for camera in &cameras[..reach] {
                let tiles = adaptive_tiles(&layout, v.scale, *camera, &radii);
                // Selections of many hundreds of tiles add bytes to the file, not coverage.
                if tiles.len() > MAX_CASE_TILES {
                    continue;
                }
                let keys: Vec<String> = tiles.iter().map(|&k| json_key(k)).collect();
                // The balanced selection and its face masks, in the same order.
                let balanced = balanced_tiles(&layout, v.scale, *camera, &radii);
                let masks = face_masks(&layout, &balanced);
                let stitched: Vec<String> = balanced
                    .iter()
                    .zip(&masks)
                    .map(|(&k, m)| format!("[{},{},{},{},{m}]", k.level, k.x, k.y, k.z))
                    .collect();
                cases.push(format!(
                    "{{\"dims\":{:?},\"brick\":{},\"voxel_scale\":{},\"camera\":{},\"radii\":{},\"tiles\":[{}],\"balanced\":[{}]}}",
                    v.dims,
                    v.brick,
                    json_f32s(&v.scale),
                    json_f32s(camera),
                    json_f32s(&radii),
                    keys.join(","),
                    stitched.join(",")
                ));
            }
        }
        for _ in 0..40 {
            let level = (rng.next() % layout.levels() as u64) as u8;
            let g = layout.grid(level);
            let key = BrickKey {
                level,
                x: (rng.next() % g[0] as u64) as u32,
                y: (rng.next() % g[1] as u64) as u32,
                z: (rng.next() % g[2] as u64) as u32,
            };
            let camera = [0, 1, 2].map(|a| rng.range(-0.5 * world[a], 1.5 * world[a]));
            distances.push(format!(
                "{{\"dims\":{:?},\"brick\":{},\"voxel_scale\":{},\"key\":{},\"camera\":{},\"distance\":{}}}",
                v.dims,
                v.brick,
                json_f32s(&v.scale),
                json_key(key),
                json_f32s(&camera),
                json_f32(tile_distance(&layout, v.scale, key, camera))
            ));
        }
    }
    let mut out = String::new();
    out.push_str("{\"generated_by\":\"proto/tests/lod_vectors.rs\",\n\"cases\":[\n");
    out.push_str(&cases.join(",\n"));
    out.push_str("\n],\n\"distances\":[\n");
    out.push_str(&distances.join(",\n"));
    let _ = writeln!(out, "\n]}}");
    out
}

/// Checks the committed vectors file `name` equals `fresh` (or rewrites it).
fn check_vectors(name: &str, fresh: &str) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../web/test-vectors")
        .join(name);
    if std::env::var_os("ISOVOX_WRITE_VECTORS").is_some() {
        std::fs::write(&path, fresh).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == fresh,
        "{} is stale: the code it was written from changed. Rewrite it with \
         ISOVOX_WRITE_VECTORS=1 cargo test -p isovox-proto --test lod_vectors, \
         then make web/src pass `npm test` in web/ again",
        path.display()
    );
}

/// Deterministic tiles of the shapes stitching meets: regular vertices with moves on every
/// face (some vertices on two faces), and a strip per face (a mesh of its own).
fn tiles() -> Vec<(TileMesh, [Mesh; 6])> {
    let mut rng = Rng(0x7e57_0001_5717_c400);
    let mut out = Vec::new();
    for (n, t) in [(12usize, 5usize), (40, 17), (200, 30)] {
        let point = |rng: &mut Rng| [0; 3].map(|_| rng.range(-40.0, 40.0));
        let unit = |rng: &mut Rng| {
            let v = [0; 3].map(|_| rng.range(-1.0, 1.0));
            let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
            v.map(|c| c / len)
        };
        let mesh = Mesh {
            positions: (0..n).map(|_| point(&mut rng)).collect(),
            normals: (0..n).map(|_| unit(&mut rng)).collect(),
            indices: (0..3 * n.min(50))
                .map(|_| (rng.next() % n as u64) as u32)
                .collect(),
            materials: vec![],
        };
        // Grouped by face, as the encoding gives them back; a vertex may move on two faces.
        let mut moves: Vec<VertexMove> = (0..2 * t)
            .map(|_| VertexMove {
                vertex: (rng.next() % n as u64) as u32,
                face: (rng.next() % 6) as u8,
                distance: rng.range(-0.6, 0.6),
            })
            .collect();
        moves.sort_by_key(|m| m.face);
        let strips = std::array::from_fn(|f| {
            let k = t / 3 + f;
            Mesh {
                positions: (0..k).map(|_| point(&mut rng)).collect(),
                normals: (0..k).map(|_| unit(&mut rng)).collect(),
                indices: (0..3 * (f + 1))
                    .map(|_| (rng.next() % k as u64) as u32)
                    .collect(),
                materials: vec![],
            }
        });
        out.push((TileMesh { mesh, moves }, strips));
    }
    out
}

fn json_f32_list(v: &[[f32; 3]]) -> String {
    let parts: Vec<String> = v
        .iter()
        .flat_map(|p| p.iter().map(|&c| json_f32(c)))
        .collect();
    format!("[{}]", parts.join(","))
}

/// The mesh vectors: each tile's compact encoding (hex), its six strips' (hex), and the tile
/// stitched with several masks and its strips, from the decoded tile and strips (normals as
/// their i16 values).
fn mesh_vectors() -> String {
    let hex = |bytes: &[u8]| -> String { bytes.iter().map(|b| format!("{b:02x}")).collect() };
    let mut cases = Vec::new();
    for (tile, strips) in tiles() {
        let bytes = encode_tile(&tile);
        let decoded = decode_tile(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(decoded.moves, tile.moves);
        let strip_bytes: Vec<Vec<u8>> = strips.iter().map(encode_compact).collect();
        let decoded_strips: Vec<Mesh> = strip_bytes
            .iter()
            .map(|b| decode_strip(b).unwrap_or_else(|e| panic!("{e}")))
            .collect();
        let mut stitched = Vec::new();
        for mask in [0u8, 1, 2, 0b1010, 0b10_0101, 63] {
            let mut m = Mesh::default();
            stitch(
                &decoded,
                mask,
                std::array::from_fn(|f| Some(&decoded_strips[f])),
                &mut m,
            );
            let normals: Vec<String> = m
                .normals
                .iter()
                .flat_map(|n| {
                    n.iter()
                        .map(|&c| ((c * 32767.0).round() as i16).to_string())
                })
                .collect();
            let indices: Vec<String> = m.indices.iter().map(u32::to_string).collect();
            stitched.push(format!(
                "{{\"mask\":{mask},\"positions\":{},\"normals\":[{}],\"indices\":[{}]}}",
                json_f32_list(&m.positions),
                normals.join(","),
                indices.join(",")
            ));
        }
        let strips: Vec<String> = strip_bytes
            .iter()
            .map(|b| format!("\"{}\"", hex(b)))
            .collect();
        cases.push(format!(
            "{{\"bytes\":\"{}\",\"strips\":[{}],\"stitched\":[{}]}}",
            hex(&bytes),
            strips.join(","),
            stitched.join(",\n")
        ));
    }
    format!(
        "{{\"generated_by\":\"proto/tests/lod_vectors.rs\",\n\"tiles\":[\n{}\n]}}\n",
        cases.join(",\n")
    )
}

#[test]
fn web_mesh_vectors_are_current() {
    let fresh = mesh_vectors();
    let parsed: serde_json::Value =
        serde_json::from_str(&fresh).unwrap_or_else(|e| panic!("vectors are not JSON: {e}"));
    assert_eq!(parsed["tiles"].as_array().map(Vec::len), Some(3));
    check_vectors("mesh.json", &fresh);
}

#[test]
fn web_lod_vectors_are_current() {
    let fresh = vectors();
    // Parses as JSON, so the TypeScript side can read it.
    let parsed: serde_json::Value =
        serde_json::from_str(&fresh).unwrap_or_else(|e| panic!("vectors are not JSON: {e}"));
    assert!(parsed["cases"].as_array().is_some_and(|c| c.len() > 100));
    check_vectors("lod.json", &fresh);
}

fn json_box((lo, hi): GridBox) -> String {
    format!(
        "[[{},{},{}],[{},{},{}]]",
        lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
    )
}

/// Reads as `tile.ts` gives them: `[level, bricks, crossing]`.
fn json_reads(reads: &[(u8, GridBox, GridBox)]) -> String {
    let parts: Vec<String> = reads
        .iter()
        .map(|&(level, bricks, crossing)| {
            format!("[{level},{},{}]", json_box(bricks), json_box(crossing))
        })
        .collect();
    format!("[{}]", parts.join(","))
}

/// The tiles of one level sampled for the vectors: on each axis the first, middle and last
/// position (so the grid's corners, the middles of its edges and faces, and its centre: the
/// first tile owns one more cell, the last has no neighbour across its high faces), and a few
/// random ones, sorted and without repeats.
fn sample_tiles(layout: &VolumeLayout, level: u8, rng: &mut Rng) -> Vec<BrickKey> {
    let g = layout.grid(level);
    let axis = |n: u32| {
        let mut v = vec![0, n / 2, n - 1];
        v.dedup();
        v
    };
    let (xs, ys, zs) = (axis(g[0]), axis(g[1]), axis(g[2]));
    let mut keys = Vec::new();
    for &z in &zs {
        for &y in &ys {
            for &x in &xs {
                keys.push(BrickKey { level, x, y, z });
            }
        }
    }
    for _ in 0..3 {
        let [x, y, z] = g.map(|n| (rng.next() % u64::from(n)) as u32);
        keys.push(BrickKey { level, x, y, z });
    }
    keys.sort();
    keys.dedup();
    keys
}

/// The tile vectors: for every layout of [`volumes`] and sampled tiles of every level, the
/// tile's cells, field box and coarse box, what its mesh reads, `has_strip` of faces 0..=6
/// (6 is out of range: never a strip) and per face 0..6 the strip's field and coarse boxes and
/// what it reads; then `stored_box` and `bricks_of` of random boxes (negative corners
/// included: tiles at the volume's low faces read outside it); then `apply_moves` of two tiles
/// under every face mask.
fn tile_vectors() -> String {
    let mut rng = Rng(0x7113_0b0c_5e7f_a11d);
    let mut layouts = Vec::new();
    for v in volumes() {
        let layout =
            VolumeLayout::new(v.dims, v.brick, VoxelType::U8).unwrap_or_else(|e| panic!("{e}"));
        let mut tiles = Vec::new();
        for level in 0..layout.levels() {
            for key in sample_tiles(&layout, level, &mut rng) {
                let (lo, hi, _) = cells(&layout, key);
                // proto's `mesh_tile_reads` names the bricks read; which of them decide whether a
                // surface crosses is the server's `tile_inputs` rule (the bricks of the stored
                // voxels under the cells' corners, `stored_box` of the cells), which `tile.ts`
                // ports as `crossing`.
                let reads: Vec<(u8, GridBox, GridBox)> = mesh_tile_reads(&layout, key)
                    .into_iter()
                    .map(|(level, bricks)| {
                        let crossing = bricks_of(layout.brick(), stored_box(level, (lo, hi)));
                        (level, bricks, crossing)
                    })
                    .collect();
                let strip_flags: Vec<String> = (0..=6)
                    .map(|f| has_strip(&layout, key, f).to_string())
                    .collect();
                let strips: Vec<String> = (0..6)
                    .map(|f| {
                        // A strip's every brick decides whether a surface crosses it (the
                        // server's `strip_inputs`).
                        let reads: Vec<(u8, GridBox, GridBox)> = strip_reads(&layout, key, f)
                            .into_iter()
                            .map(|(level, bricks)| (level, bricks, bricks))
                            .collect();
                        format!(
                            "{{\"field\":{},\"coarse\":{},\"reads\":{}}}",
                            json_box(strip_field_box(&layout, key, f)),
                            json_box(strip_coarse_box(&layout, key, f)),
                            json_reads(&reads)
                        )
                    })
                    .collect();
                tiles.push(format!(
                    "{{\"key\":{},\"cells\":{},\"field\":{},\"coarse\":{},\"reads\":{},\"has_strip\":[{}],\"strips\":[{}]}}",
                    json_key(key),
                    json_box((lo, hi)),
                    json_box(field_box(&layout, key)),
                    json_box(coarse_box(&layout, key)),
                    json_reads(&reads),
                    strip_flags.join(","),
                    strips.join(",")
                ));
            }
        }
        layouts.push(format!(
            "{{\"dims\":{:?},\"brick\":{},\"levels\":{},\"tiles\":[\n{}\n]}}",
            v.dims,
            v.brick,
            layout.levels(),
            tiles.join(",\n")
        ));
    }
    let mut boxes = Vec::new();
    for i in 0..48 {
        let level = (i % 4) as u8;
        let brick = [2u32, 8, 16, 64][i / 4 % 4];
        let lo: [i64; 3] = [0; 3].map(|_| (rng.next() % 200) as i64 - 70);
        let hi = lo.map(|c| c + (rng.next() % 150) as i64);
        let stored = stored_box(level, (lo, hi));
        boxes.push(format!(
            "{{\"level\":{level},\"brick\":{brick},\"box\":{},\"stored\":{},\"bricks\":{}}}",
            json_box((lo, hi)),
            json_box(stored),
            json_box(bricks_of(brick, (lo, hi)))
        ));
    }
    format!(
        "{{\"generated_by\":\"proto/tests/lod_vectors.rs\",\n\"layouts\":[\n{}\n],\n\"boxes\":[\n{}\n],\n\"moves\":[\n{}\n]}}\n",
        layouts.join(",\n"),
        boxes.join(",\n"),
        move_vectors(&mut rng).join(",\n")
    )
}

/// `apply_moves` of two tiles under all 64 face masks. The first is built by hand so that every
/// face has moves and one vertex moves on all six faces and one on both faces of an axis (two
/// f32 additions to one coordinate, in the moves' order); the second is random. Positions are
/// in [-40, 40) and distances below one, so the f32 sums round.
fn move_vectors(rng: &mut Rng) -> Vec<String> {
    let mut out = Vec::new();
    for n in [8u32, 24] {
        let positions: Vec<[f32; 3]> = (0..n)
            .map(|_| [0; 3].map(|_| rng.range(-40.0, 40.0)))
            .collect();
        let mut moves: Vec<VertexMove> = Vec::new();
        if n == 8 {
            for face in 0..6u8 {
                let inwards = if face % 2 == 0 { 1.0 } else { -1.0 };
                moves.push(VertexMove {
                    vertex: 0,
                    face,
                    distance: inwards * rng.range(0.05, 0.6),
                });
                moves.push(VertexMove {
                    vertex: 1 + u32::from(face),
                    face,
                    distance: inwards * rng.range(0.05, 0.6),
                });
            }
            moves.push(VertexMove {
                vertex: 7,
                face: 2,
                distance: rng.range(0.05, 0.6),
            });
            moves.push(VertexMove {
                vertex: 7,
                face: 3,
                distance: -rng.range(0.05, 0.6),
            });
        } else {
            moves = (0..3 * n)
                .map(|_| VertexMove {
                    vertex: (rng.next() % u64::from(n)) as u32,
                    face: (rng.next() % 6) as u8,
                    distance: rng.range(-0.6, 0.6),
                })
                .collect();
        }
        // Grouped by face, as a tile carries them (`TileMesh::moves`).
        moves.sort_by_key(|m| m.face);
        let moved: Vec<String> = (0..64u8)
            .map(|mask| {
                let mut p = positions.clone();
                apply_moves(&mut p, &moves, mask);
                json_f32_list(&p)
            })
            .collect();
        let listed: Vec<String> = moves
            .iter()
            .map(|m| format!("[{},{},{}]", m.vertex, m.face, json_f32(m.distance)))
            .collect();
        out.push(format!(
            "{{\"positions\":{},\"moves\":[{}],\"moved\":[\n{}\n]}}",
            json_f32_list(&positions),
            listed.join(","),
            moved.join(",\n")
        ));
    }
    out
}

#[test]
fn web_tile_vectors_are_current() {
    let fresh = tile_vectors();
    let parsed: serde_json::Value =
        serde_json::from_str(&fresh).unwrap_or_else(|e| panic!("vectors are not JSON: {e}"));
    assert_eq!(
        parsed["layouts"].as_array().map(Vec::len),
        Some(volumes().len())
    );
    assert_eq!(parsed["moves"].as_array().map(Vec::len), Some(2));
    check_vectors("tile.json", &fresh);
}
