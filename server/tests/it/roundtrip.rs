//! RAW -> VOD 2 -> RAW round trips.
//!
//! Proves that importing a RAW volume and exporting level 0 again gives back the same bytes for
//! u8 and u16, for odd and single-voxel shapes, every brick size and every compression; that
//! exporting a sub-region equals slicing the original array; and that every level of detail,
//! read brick by brick, equals a straightforward downsampling of whole arrays computed here
//! (level k+1 voxel = (sum of its 2x2x2 level-k voxels + 4) / 8, voxels outside level k's extent
//! counting as 0), with every voxel of a brick beyond its level's extent equal to 0.

// unwrap is how a test says "this must work"; clippy exempts only #[test] functions.

use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::geometry::Box3;
use isovox_server::progress::Silent;
use isovox_server::store::codec::Compression;
use isovox_server::store::inspect::inspect;
use isovox_server::store::raw::{export_raw, RawInput};
use isovox_server::store::{build_vod2, BuildOptions, DenseGrid, Snapshot, Vod2};
use std::path::Path;

use crate::common;
use common::{mixed_volume, pyramid, Grid, XorShift};

fn build_from_raw_file(
    dir: &Path,
    volume: &Grid,
    voxel_type: VoxelType,
    brick: u32,
    compression: Compression,
) -> Vod2 {
    let dims = volume.dims.map(|d| d as u32);
    let raw_path = dir.join("in.raw");
    std::fs::write(&raw_path, volume.to_bytes(voxel_type)).unwrap();
    let input = RawInput::open(&raw_path, false, Some(dims), Some(voxel_type)).unwrap();
    assert_eq!(input.dims, dims);
    let layout = VolumeLayout::new(dims, brick, voxel_type).unwrap();
    let grid = DenseGrid::new(dims, voxel_type, brick, input.voxels());
    let vod_path = dir.join("out.vod");
    let options = BuildOptions {
        compression,
        progress: std::sync::Arc::new(Silent),
    };
    build_vod2(&vod_path, &layout, [1.0; 3], &grid, &options).unwrap();
    Vod2::open(&vod_path).unwrap()
}

fn export(snap: &Snapshot, level: u8, min: [u32; 3], max: [u32; 3]) -> Vec<u8> {
    let mut out = Vec::new();
    let region = Box3::new(min.map(i64::from), max.map(i64::from));
    export_raw(snap, level, region, &mut out, &Silent).unwrap();
    out
}

/// Every brick of every level equals the independent pyramid, zero beyond each level's extent.
fn check_levels(snap: &Snapshot, levels: &[Grid], voxel_type: VoxelType, what: &str) {
    let layout = snap.layout();
    assert_eq!(
        layout.levels() as usize,
        levels.len(),
        "{what}: number of levels"
    );
    let b = layout.brick() as usize;
    for (k, level) in levels.iter().enumerate() {
        let k8 = k as u8;
        assert_eq!(
            layout.level_dims(k8).map(|d| d as usize),
            level.dims,
            "{what}: extent of level {k}"
        );
        let grid = layout.grid(k8);
        assert_eq!(
            grid.map(|g| g as usize),
            level.dims.map(|d| d.div_ceil(b)),
            "{what}: grid of level {k}"
        );
        for z in 0..grid[2] {
            for y in 0..grid[1] {
                for x in 0..grid[0] {
                    let key = layout.key(k8, x, y, z).unwrap();
                    let got = snap.read(key).unwrap();
                    let pos = [x, y, z].map(|c| c as usize);
                    let expected = level.brick(pos, b, voxel_type);
                    assert_eq!(
                        got.len(),
                        b * b * b * voxel_type.bytes(),
                        "{what}: brick {key} size"
                    );
                    // Voxels beyond the level's extent are L, whatever their neighbours.
                    let vb = voxel_type.bytes();
                    for (i, chunk) in got.chunks_exact(vb).enumerate() {
                        let v = [i % b, i / b % b, i / (b * b)];
                        let outside = (0..3).any(|a| pos[a] * b + v[a] >= level.dims[a]);
                        if outside {
                            assert!(
                                chunk.iter().all(|&c| c == 0),
                                "{what}: brick {key} voxel {v:?} beyond the extent is not 0"
                            );
                        }
                    }
                    assert!(
                        got == expected,
                        "{what}: brick {key} differs from the independent downsampling"
                    );
                }
            }
        }
    }
}

/// Imports `volume` from a RAW file, exports level 0 and compares; then checks every level.
fn check_round_trip(volume: &Grid, voxel_type: VoxelType, brick: u32, compression: Compression) {
    let what = format!(
        "{:?} {voxel_type} brick {brick} {compression:?}",
        volume.dims
    );
    let dir = tempfile::tempdir().unwrap();
    let vod = build_from_raw_file(dir.path(), volume, voxel_type, brick, compression);
    let snap = vod.head();
    assert_eq!(snap.version, 1, "{what}");
    let dims = volume.dims.map(|d| d as u32);
    let exported = export(&snap, 0, [0; 3], dims);
    assert!(
        exported == volume.to_bytes(voxel_type),
        "{what}: level 0 export differs from the RAW input"
    );
    check_levels(&snap, &pyramid(volume, brick), voxel_type, &what);
}

const COMPRESSIONS: [Compression; 4] = [
    Compression::None,
    Compression::Lz4,
    Compression::Zstd(1),
    Compression::Zstd(19),
];

#[test]
fn single_voxel_volume_round_trips_for_every_type_brick_and_compression() {
    for voxel_type in [VoxelType::U8, VoxelType::U16] {
        let volume = mixed_volume([1, 1, 1], voxel_type, 11);
        // The single voxel is from the step third: non-zero, so its brick is not constant L.
        assert_ne!(volume.values[0], 0);
        for brick in [4, 16, 32] {
            for compression in COMPRESSIONS {
                check_round_trip(&volume, voxel_type, brick, compression);
            }
        }
    }
}

#[test]
fn odd_u8_volume_round_trips_for_every_brick_and_compression() {
    let volume = mixed_volume([17, 33, 5], VoxelType::U8, 12);
    for brick in [4, 16, 32] {
        for compression in COMPRESSIONS {
            check_round_trip(&volume, VoxelType::U8, brick, compression);
        }
    }
}

#[test]
fn odd_u16_volume_round_trips_for_every_brick_and_compression() {
    let volume = mixed_volume([17, 33, 5], VoxelType::U16, 13);
    assert!(
        volume.values.iter().any(|&v| v > 255),
        "u16 content uses the high byte"
    );
    for brick in [4, 16, 32] {
        for compression in COMPRESSIONS {
            check_round_trip(&volume, VoxelType::U16, brick, compression);
        }
    }
}

#[test]
fn large_u8_volume_brick16_zstd_round_trips_with_every_level() {
    let volume = mixed_volume([200, 160, 160], VoxelType::U8, 14);
    check_round_trip(&volume, VoxelType::U8, 16, Compression::Zstd(3));
}

#[test]
fn large_u16_volume_brick32_lz4_round_trips_at_level0() {
    let volume = mixed_volume([200, 160, 160], VoxelType::U16, 15);
    let dir = tempfile::tempdir().unwrap();
    let vod = build_from_raw_file(dir.path(), &volume, VoxelType::U16, 32, Compression::Lz4);
    let exported = export(&vod.head(), 0, [0; 3], [200, 160, 160]);
    assert!(
        exported == volume.to_bytes(VoxelType::U16),
        "level 0 export differs from the RAW input"
    );
    // 200x160x160 with brick 32: grids 7x5x5, 4x3x3, 2x2x2, 1x1x1.
    assert_eq!(vod.layout().levels(), 4);
    assert_eq!(vod.layout().node_count(), 175 + 36 + 8 + 1);
}

/// The test volume really has constant, compressible and incompressible bricks, and each
/// compression setting stores them with the codecs it should.
#[test]
fn content_exercises_constant_compressed_and_raw_bricks() {
    for voxel_type in [VoxelType::U8, VoxelType::U16] {
        let volume = mixed_volume([96, 48, 64], voxel_type, 16);
        for compression in [Compression::None, Compression::Lz4, Compression::Zstd(5)] {
            let dir = tempfile::tempdir().unwrap();
            let vod = build_from_raw_file(dir.path(), &volume, voxel_type, 16, compression);
            let c = inspect(&vod).unwrap().codecs;
            let what = format!("{voxel_type} {compression:?}: {c:?}");
            assert!(c.constant_bricks > 0, "{what}: no constant brick");
            assert!(
                c.raw_records > 0,
                "{what}: noise bricks should be stored raw"
            );
            match compression {
                Compression::None => assert_eq!((c.lz4_records, c.zstd_records), (0, 0), "{what}"),
                Compression::Lz4 => assert!(c.lz4_records > 0 && c.zstd_records == 0, "{what}"),
                Compression::Zstd(_) => assert!(c.zstd_records > 0 && c.lz4_records == 0, "{what}"),
            }
            let exported = export(&vod.head(), 0, [0; 3], [96, 48, 64]);
            assert!(
                exported == volume.to_bytes(voxel_type),
                "{what}: level 0 export differs"
            );
        }
    }
}

/// Random boxes (and a few fixed edge cases) of every level, exported, equal the slice of the
/// independently downsampled array.
#[test]
fn sub_region_exports_equal_slices_of_the_original_and_of_each_level() {
    let mut rng = XorShift(0xDEAD_BEEF);
    for (dims, voxel_type, brick) in [
        ([17, 33, 5], VoxelType::U16, 4),
        ([61, 40, 23], VoxelType::U8, 8),
    ] {
        let volume = mixed_volume(dims, voxel_type, 17);
        let dir = tempfile::tempdir().unwrap();
        let vod = build_from_raw_file(dir.path(), &volume, voxel_type, brick, Compression::Zstd(3));
        let snap = vod.head();
        let levels = pyramid(&volume, brick);
        for (k, level) in levels.iter().enumerate() {
            let ext = level.dims.map(|d| d as u32);
            let mut boxes = vec![
                ([0, 0, 0], ext),
                (ext.map(|e| e - 1), ext),
                ([0, 0, 0], [1, 1, 1]),
                (
                    [0, ext[1] / 2, ext[2] / 2],
                    [ext[0], ext[1] / 2 + 1, ext[2] / 2 + 1],
                ),
            ];
            for _ in 0..25 {
                let mut min = [0u32; 3];
                let mut max = [0u32; 3];
                for a in 0..3 {
                    let p = rng.below(ext[a] as u64) as u32;
                    let q = rng.below(ext[a] as u64) as u32;
                    min[a] = p.min(q);
                    max[a] = p.max(q) + 1;
                }
                boxes.push((min, max));
            }
            for (min, max) in boxes {
                let got = export(&snap, k as u8, min, max);
                let expected =
                    level.slice(min.map(|v| v as usize), max.map(|v| v as usize), voxel_type);
                assert!(
                    got == expected,
                    "{dims:?} level {k}: region {min:?}..{max:?} differs from the slice"
                );
            }
        }
    }
}

#[test]
fn export_rejects_empty_and_out_of_range_regions() {
    let volume = mixed_volume([17, 33, 5], VoxelType::U8, 18);
    let dir = tempfile::tempdir().unwrap();
    let vod = build_from_raw_file(dir.path(), &volume, VoxelType::U8, 4, Compression::Lz4);
    let snap = vod.head();
    let bad = [
        (0u8, [0, 0, 0], [0, 33, 5]),                   // empty along x
        (0, [3, 0, 0], [2, 33, 5]),                     // min above max
        (0, [0, 0, 0], [18, 33, 5]),                    // beyond x
        (1, [0, 0, 0], [9, 17, 4]),                     // level 1 is 9x17x3
        (snap.layout().levels(), [0, 0, 0], [1, 1, 1]), // no such level
        (0, [-1, 0, 0], [2, 33, 5]),                    // before x
    ];
    for (level, min, max) in bad {
        let mut out = Vec::new();
        let r = export_raw(&snap, level, Box3::new(min, max), &mut out, &Silent);
        let e = r.expect_err("export of an invalid region must fail");
        assert!(!e.to_string().is_empty());
    }
    // The largest valid box of level 1 still works.
    assert_eq!(export(&snap, 1, [0, 0, 0], [9, 17, 3]).len(), 9 * 17 * 3);
}
