//! Micro-benchmarks of the kernels a regression would hide in (criterion; `cargo bench -p
//! isovox-tools`): marching cubes on one tile (with and without its transition data), term
//! evaluation on one brick, brick decoding (zstd, lz4), the check of a stored payload before it
//! is sent as it is, index lookups, and a streamer's selection of stitched tiles for a camera.
//! The data is a generated terrain, built once per run.

#![allow(clippy::unwrap_used)] // a benchmark that cannot set up should stop loudly

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use isovox_proto::icvg::Term;
use isovox_proto::mesh::TileMesh;
use isovox_proto::vod2::payload_check;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::geometry::Box3;
use isovox_server::icvg::term::{CompiledTerm, NoVolumes, TermLimits};
use isovox_server::mesh::mc::Mesh;
use isovox_server::mesh::tile::{
    default_iso, mesh_strip_world, mesh_tile, mesh_tile_with_moves, TileScratch,
};
use isovox_server::store::codec::{decode, encode, Compression};
use isovox_server::store::decoded::DecodedBricks;
use isovox_server::store::{build_vod2, BuildOptions, StoredBrick, Vod2};
use std::hint::black_box;
use std::sync::Arc;

const BRICK: u32 = 32;

/// A 256 x 128 x 256 terrain, brick 32, and a level-0 brick the surface crosses.
fn world(dir: &std::path::Path) -> (Vod2, BrickKey) {
    let path = dir.join("world.vod");
    let layout = VolumeLayout::new([256, 128, 256], BRICK, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &WorldSource::new(layout.clone(), 7),
        &BuildOptions::default(),
    )
    .unwrap();
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    let iso = default_iso(VoxelType::U8);
    let g = layout.grid(0);
    let crossing = (0..g[1])
        .map(|y| BrickKey {
            level: 0,
            x: g[0] / 2,
            y,
            z: g[2] / 2,
        })
        .find(|&k| match snap.stored(k).unwrap() {
            StoredBrick::Record { header, .. } => {
                (header.min as f32) < iso && (header.max as f32) >= iso
            }
            StoredBrick::Constant(_) => false,
        })
        .unwrap();
    (vod, crossing)
}

fn kernels(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let (vod, key) = world(dir.path());
    let snap = vod.head();
    let layout = snap.layout().clone();
    let voxels = (BRICK as u64).pow(3);

    let mut group = c.benchmark_group("marching cubes");
    group.throughput(Throughput::Elements(voxels));
    // Decoded bricks are cached, as in a server: the figure is gathering and marching.
    let mut scratch = TileScratch::with_bricks(Arc::new(DecodedBricks::new(64 << 20)));
    let mut mesh = Mesh::default();
    let iso = default_iso(VoxelType::U8);
    group.bench_function("tile 32^3 (terrain)", |b| {
        b.iter(|| {
            mesh_tile(&snap, key, iso, &mut mesh, &mut scratch).unwrap();
            black_box(mesh.triangles())
        })
    });
    // The same tile as served: with the secondary positions of its boundary vertices.
    let mut tile = TileMesh::default();
    group.bench_function("tile 32^3 (terrain) with moves", |b| {
        b.iter(|| {
            mesh_tile_with_moves(&snap, key, iso, &mut tile, &mut scratch).unwrap();
            black_box(tile.moves.len())
        })
    });
    // One of its transition strips, as served.
    let mut strip = Mesh::default();
    group.bench_function("strip +x of tile 32^3 (terrain)", |b| {
        b.iter(|| {
            mesh_strip_world(&snap, key, 1, iso, &mut strip, &mut scratch).unwrap();
            black_box(strip.triangles())
        })
    });
    group.finish();

    let mut group = c.benchmark_group("term evaluation");
    group.throughput(Throughput::Elements(voxels));
    let term: Term = serde_json::from_str(
        r#"{"difference": [
            {"union": [{"ellipsoid": {"center": [16, 16, 16], "radii": [14, 10, 12]}},
                       {"torus": {"center": [16, 16, 16], "major": 10, "minor": 4}}]},
            {"cylinder": {"base": [16, 0, 16], "radii": [4, 4], "height": 32}}]}"#,
    )
    .unwrap();
    let compiled =
        CompiledTerm::compile(&term, VoxelType::U8, &TermLimits::default(), &NoVolumes).unwrap();
    let brick = Box3::new([0; 3], [BRICK as i64; 3]);
    let mut out = vec![0u16; voxels as usize];
    group.bench_function("brick 32^3 (ellipsoid, torus, cylinder)", |b| {
        b.iter(|| {
            compiled.eval(&brick, &mut out).unwrap();
            black_box(out[out.len() / 2])
        })
    });
    group.finish();

    let mut group = c.benchmark_group("brick decode");
    let raw = snap.read(key).unwrap();
    group.throughput(Throughput::Bytes(raw.len() as u64));
    let mut decoded = vec![0u8; raw.len()];
    for (name, compression) in [("zstd 5", Compression::Zstd(5)), ("lz4", Compression::Lz4)] {
        let (codec, payload) = encode(&raw, compression);
        group.bench_function(name, |b| {
            b.iter(|| {
                decode(codec, &payload, &mut decoded, 0).unwrap();
                black_box(decoded[0])
            })
        });
    }
    group.finish();

    // What checking a stored payload before sending it as it is costs (`Accept-Encoding:
    // zstd`, `Accept: application/x-lz4`, stored batches): one xxh3 pass over its bytes.
    let mut group = c.benchmark_group("payload verification");
    let bricks = DecodedBricks::new(64 << 20);
    let stored = snap.stored(key).unwrap();
    let StoredBrick::Record { payload, .. } = stored else {
        panic!("the crossing brick is a record");
    };
    group.throughput(Throughput::Bytes(payload.len() as u64));
    group.bench_function(format!("stored zstd payload, {} B", payload.len()), |b| {
        b.iter(|| bricks.verify_payload(black_box(&stored), &layout).unwrap())
    });
    for (name, compression) in [("lz4", Compression::Lz4), ("raw", Compression::None)] {
        let (_, payload) = encode(&raw, compression);
        group.throughput(Throughput::Bytes(payload.len() as u64));
        group.bench_function(
            format!("{name} payload checksum, {} B", payload.len()),
            |b| b.iter(|| black_box(payload_check(black_box(&payload)))),
        );
    }
    group.finish();

    let mut group = c.benchmark_group("index lookup");
    let keys: Vec<BrickKey> = (0..layout.levels())
        .flat_map(|level| {
            let g = layout.grid(level);
            (0..g[0] * g[1] * g[2]).map(move |i| BrickKey {
                level,
                x: i % g[0],
                y: i / g[0] % g[1],
                z: i / (g[0] * g[1]),
            })
        })
        .collect();
    group.throughput(Throughput::Elements(keys.len() as u64));
    group.bench_function("every brick's stored form", |b| {
        b.iter(|| {
            for &k in &keys {
                black_box(snap.stored(k).unwrap());
            }
        })
    });
    group.finish();

    // A streamer of mesh tiles selects its tiles (balanced, with face masks) for each camera
    // move: isovox-load's viewers over a 2048^3 world in bricks of 16, at a point of their
    // orbit (0.35 of the width from the centre, 0.95 of the height), with its radii. These radii
    // keep the balance by themselves (`lod::radii_keep_balance`), so the streamer's selection
    // (`lod::stitched_tiles`) skips balancing and reads the masks off the radii; the general
    // path balances and finds the masks by membership tests, as it does for radii closer
    // together.
    let layout = VolumeLayout::new([2048; 3], 16, VoxelType::U8).unwrap();
    let radii: Vec<f32> = (0..7).map(|k| 116.9 * (1u32 << k) as f32).collect();
    let camera = [1024.0 + 0.35 * 2048.0, 0.95 * 2048.0, 1024.0];
    assert!(isovox_proto::lod::radii_keep_balance(
        &layout, [1.0; 3], camera, &radii
    ));
    let (tiles, _) = isovox_proto::lod::stitched_tiles(&layout, [1.0; 3], camera, &radii);
    let mut group = c.benchmark_group("selection");
    group.throughput(Throughput::Elements(tiles.len() as u64));
    group.bench_function(
        format!("stitched tiles and masks, 2048^3 ({} tiles)", tiles.len()),
        |b| {
            b.iter(|| {
                black_box(isovox_proto::lod::stitched_tiles(
                    &layout,
                    [1.0; 3],
                    black_box(camera),
                    &radii,
                ))
            })
        },
    );
    group.bench_function(
        format!(
            "balanced and masked by membership, 2048^3 ({} tiles)",
            tiles.len()
        ),
        |b| {
            b.iter(|| {
                let adaptive =
                    isovox_proto::lod::adaptive_tiles(&layout, [1.0; 3], black_box(camera), &radii);
                let tiles = isovox_proto::lod::balance(&layout, adaptive);
                black_box(isovox_proto::lod::face_masks(&layout, &tiles))
            })
        },
    );
    group.finish();
}

criterion_group!(benches, kernels);
criterion_main!(benches);
