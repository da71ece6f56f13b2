//! Mesh tiles over real files: the GLB passes a structural check with the `gltf` crate
//! (accessor counts and bounds agree with the mesh), the compact encoding round-trips, and the
//! vertices on a face shared by two tiles are bit-identical from both sides.

use isovox_proto::mesh::{decode_compact, encode_compact, encode_glb, Mesh};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::mesh::level::{level_tiles, mesh_tiles, weld};
use isovox_server::mesh::tile::{default_iso, mesh_tile, TileScratch};
use isovox_server::store::{build_vod2, BuildOptions, Vod2};
use std::collections::HashSet;

fn world() -> (tempfile::TempDir, Vod2) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.vod");
    let layout = VolumeLayout::new([64, 48, 64], 16, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [0.5, 1.0, 2.0],
        &WorldSource::new(layout.clone(), 5),
        &BuildOptions::default(),
    )
    .unwrap();
    let vod = Vod2::open(&path).unwrap();
    (dir, vod)
}

fn tile(vod: &Vod2, key: BrickKey) -> Mesh {
    let mut m = Mesh::default();
    mesh_tile(
        &vod.head(),
        key,
        default_iso(VoxelType::U8),
        &mut m,
        &mut TileScratch::default(),
    )
    .unwrap();
    m
}

#[test]
fn glb_loads_in_gltf_with_matching_accessors() {
    let (_dir, vod) = world();
    let snap = vod.head();
    let mesh = weld(
        &mesh_tiles(
            &snap,
            &level_tiles(&snap, 0),
            default_iso(VoxelType::U8),
            &isovox_server::progress::Silent,
        )
        .unwrap(),
    );
    assert!(mesh.triangles() > 1000);
    let glb = encode_glb(&mesh);
    let gltf = gltf::Gltf::from_slice(&glb).unwrap();
    let doc = &gltf.document;
    assert_eq!(doc.meshes().count(), 1);
    let prim = doc.meshes().next().unwrap().primitives().next().unwrap();
    assert_eq!(prim.mode(), gltf::mesh::Mode::Triangles);
    let pos = prim.get(&gltf::Semantic::Positions).unwrap();
    assert_eq!(pos.count(), mesh.positions.len());
    assert_eq!(
        prim.get(&gltf::Semantic::Normals).unwrap().count(),
        mesh.normals.len()
    );
    assert_eq!(prim.indices().unwrap().count(), mesh.indices.len());
    // Bounds: computed here independently of Mesh::bounds.
    let lo: Vec<f32> = (0..3)
        .map(|a| {
            mesh.positions
                .iter()
                .map(|p| p[a])
                .fold(f32::INFINITY, f32::min)
        })
        .collect();
    let hi: Vec<f32> = (0..3)
        .map(|a| {
            mesh.positions
                .iter()
                .map(|p| p[a])
                .fold(f32::NEG_INFINITY, f32::max)
        })
        .collect();
    let min: Vec<f32> = serde_json::from_value(pos.min().unwrap()).unwrap();
    let max: Vec<f32> = serde_json::from_value(pos.max().unwrap()).unwrap();
    assert_eq!((min, max), (lo, hi.clone()));
    // The positions read back through gltf's reader equal ours.
    let blob = gltf.blob.as_deref().unwrap();
    let reader = prim.reader(|_| Some(blob));
    let read: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
    assert_eq!(read, mesh.positions);
    let idx: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
    assert_eq!(idx, mesh.indices);
    // World coordinates follow the voxel scale (0.5, 1, 2): x within [0, 64*0.5], z within 128.
    assert!(hi[0] <= 32.0 && hi[2] <= 128.0 && hi[2] > 64.0, "{hi:?}");
}

#[test]
fn compact_encoding_round_trips_a_tile() {
    let (_dir, vod) = world();
    let m = tile(
        &vod,
        BrickKey {
            level: 0,
            x: 1,
            y: 1,
            z: 1,
        },
    );
    assert!(m.triangles() > 0);
    let d = decode_compact(&encode_compact(&m)).unwrap();
    assert_eq!(d.positions, m.positions);
    assert_eq!(d.indices, m.indices);
    for (a, b) in d.normals.iter().zip(&m.normals) {
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() <= 1.0 / 32767.0 + 1e-6);
        }
    }
}

#[test]
fn shared_tile_faces_have_bit_identical_vertices() {
    let (_dir, vod) = world();
    let b = 16.0f32;
    let mut checked = 0;
    for (a, key, next) in [
        (
            0usize,
            BrickKey {
                level: 0,
                x: 1,
                y: 1,
                z: 1,
            },
            BrickKey {
                level: 0,
                x: 2,
                y: 1,
                z: 1,
            },
        ),
        (
            2,
            BrickKey {
                level: 0,
                x: 2,
                y: 1,
                z: 0,
            },
            BrickKey {
                level: 0,
                x: 2,
                y: 1,
                z: 1,
            },
        ),
        (
            1,
            BrickKey {
                level: 0,
                x: 3,
                y: 0,
                z: 2,
            },
            BrickKey {
                level: 0,
                x: 3,
                y: 1,
                z: 2,
            },
        ),
    ] {
        let scale = [0.5f32, 1.0, 2.0];
        // The shared plane: grid coordinate (key + 1) * b on axis a, in world units.
        let plane = ([key.x, key.y, key.z][a] as f32 + 1.0) * b * scale[a];
        let on = |m: &Mesh| -> HashSet<[u32; 3]> {
            m.positions
                .iter()
                .filter(|p| p[a] == plane)
                .map(|p| p.map(f32::to_bits))
                .collect()
        };
        let (left, right) = (on(&tile(&vod, key)), on(&tile(&vod, next)));
        assert_eq!(left, right, "axis {a}: the shared face's vertices differ");
        checked += left.len();
    }
    assert!(
        checked > 20,
        "the chosen faces cross the terrain ({checked} vertices)"
    );
}
