//! Test vectors of the tile selection (`proto::lod`) for the web viewer's TypeScript port
//! (`web/src/lod.ts`), which its unit tests check against `web/test-vectors/lod.json`.
//!
//! This test computes the vectors and fails when the committed file differs, so a change to the
//! selection cannot land without the vectors (and then the TypeScript port) following it.
//! `ISOVOX_WRITE_VECTORS=1 cargo test -p isovox-proto --test lod_vectors` rewrites the file.

use isovox_proto::lod::{adaptive_tiles, tile_distance};
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
                cases.push(format!(
                    "{{\"dims\":{:?},\"brick\":{},\"voxel_scale\":{},\"camera\":{},\"radii\":{},\"tiles\":[{}]}}",
                    v.dims,
                    v.brick,
                    json_f32s(&v.scale),
                    json_f32s(camera),
                    json_f32s(&radii),
                    keys.join(",")
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

#[test]
fn web_lod_vectors_are_current() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../web/test-vectors/lod.json");
    let fresh = vectors();
    // Parses as JSON, so the TypeScript side can read it.
    let parsed: serde_json::Value =
        serde_json::from_str(&fresh).unwrap_or_else(|e| panic!("vectors are not JSON: {e}"));
    assert!(parsed["cases"].as_array().is_some_and(|c| c.len() > 100));
    if std::env::var_os("ISOVOX_WRITE_VECTORS").is_some() {
        std::fs::write(&path, &fresh).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == fresh,
        "{} is stale: the tile selection changed. Rewrite it with \
         ISOVOX_WRITE_VECTORS=1 cargo test -p isovox-proto --test lod_vectors, \
         then make web/src/lod.ts pass `npm test` in web/ again",
        path.display()
    );
}
