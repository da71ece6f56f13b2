//! VOD 1 (the thesis's Figure 24 layout) written from VOD 2 and read back.
//!
//! Proves that VOD 2 -> VOD 1 -> VOD 2 -> VOD 1 keeps every level-0 voxel (and every level of
//! detail), that the two VOD 1 files are byte-identical (the writer is deterministic), compressed
//! and uncompressed, u8 and u16; and that the VOD 1 bytes follow the layout by hand: '.VOD',
//! version 1, dims, brick size, voxel scale, treeHeight = number of levels, (8^h - 1) / 7 u32
//! node entries after the 64-byte header in preorder (children x fastest, then y, then z), then
//! the brick table and the sized payloads, ending exactly at the end of the file.

// unwrap is how a test says "this must work"; clippy exempts only #[test] functions.

use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::geometry::Box3;
use isovox_server::progress::Silent;
use isovox_server::store::codec::Compression;
use isovox_server::store::raw::export_raw;
use isovox_server::store::vod1::{write_vod1, Vod1, Vod1Source};
use isovox_server::store::{build_vod2, BuildOptions, DenseGrid, Vod2};
use std::collections::HashMap;
use std::path::Path;

use crate::common;
use common::{level_count, mixed_volume, pyramid, Grid};

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

fn build(path: &Path, volume: &Grid, voxel_type: VoxelType, brick: u32, scale: [f32; 3]) -> Vod2 {
    let dims = volume.dims_u32();
    let bytes = volume.to_bytes(voxel_type);
    let layout = VolumeLayout::new(dims, brick, voxel_type).unwrap();
    let grid = DenseGrid::new(dims, voxel_type, brick, &bytes);
    let options = BuildOptions {
        compression: Compression::Zstd(3),
        progress: std::sync::Arc::new(Silent),
    };
    build_vod2(path, &layout, scale, &grid, &options).unwrap();
    Vod2::open(path).unwrap()
}

fn vod1_bytes(vod: &Vod2, compress: bool) -> Vec<u8> {
    let mut out = Vec::new();
    let n = write_vod1(&vod.head(), compress, &mut out).unwrap();
    assert_eq!(n, out.len() as u64, "write_vod1 reports the bytes it wrote");
    out
}

/// Every key of the complete octree of `height` levels, in preorder: root first, then each
/// child's subtree in turn, children x fastest, then y, then z. Written from the spec's wording.
fn preorder(height: u32) -> Vec<BrickKey> {
    fn visit(level: u8, x: u32, y: u32, z: u32, out: &mut Vec<BrickKey>) {
        out.push(BrickKey { level, x, y, z });
        if level == 0 {
            return;
        }
        for cz in 0..2 {
            for cy in 0..2 {
                for cx in 0..2 {
                    visit(level - 1, 2 * x + cx, 2 * y + cy, 2 * z + cz, out);
                }
            }
        }
    }
    let mut out = Vec::new();
    visit(height as u8 - 1, 0, 0, 0, &mut out);
    out
}

/// The expected decoded content of every node of the complete octree: the level's brick from
/// the independent pyramid when the key is inside the volume, all L otherwise.
fn expected_nodes(levels: &[Grid], brick: u32, voxel_type: VoxelType) -> Vec<(BrickKey, Vec<u8>)> {
    let b = brick as usize;
    preorder(levels.len() as u32)
        .into_iter()
        .map(|key| {
            let level = &levels[key.level as usize];
            let pos = [key.x, key.y, key.z].map(|c| c as usize);
            let inside = (0..3).all(|a| pos[a] < level.dims[a].div_ceil(b));
            let content = if inside {
                level.brick(pos, b, voxel_type)
            } else {
                vec![0u8; b * b * b * voxel_type.bytes()]
            };
            (key, content)
        })
        .collect()
}

/// Reads every level-0 brick of a VOD 1 file and assembles the volume's voxels.
fn level0_of_vod1(vod1: &Vod1<'_>) -> Vec<u8> {
    let layout = &vod1.layout;
    let b = layout.brick() as usize;
    let vb = layout.voxel_type().bytes();
    let [dx, dy, dz] = layout.dims().map(|d| d as usize);
    let mut volume = vec![0u8; dx * dy * dz * vb];
    let g = layout.grid(0);
    let mut brick = vec![0u8; layout.brick_bytes()];
    for bz in 0..g[2] {
        for by in 0..g[1] {
            for bx in 0..g[0] {
                vod1.read_into(layout.key(0, bx, by, bz).unwrap(), &mut brick)
                    .unwrap();
                for z in 0..b {
                    for y in 0..b {
                        for x in 0..b {
                            let (vx, vy, vz) = (
                                bx as usize * b + x,
                                by as usize * b + y,
                                bz as usize * b + z,
                            );
                            if vx < dx && vy < dy && vz < dz {
                                let src = ((z * b + y) * b + x) * vb;
                                let dst = ((vz * dy + vy) * dx + vx) * vb;
                                volume[dst..dst + vb].copy_from_slice(&brick[src..src + vb]);
                            }
                        }
                    }
                }
            }
        }
    }
    volume
}

fn chain(voxel_type: VoxelType, compress: bool) {
    let dims = [37, 21, 14];
    let brick = 8;
    let scale = [1.0, 0.5, 2.0];
    let volume = mixed_volume(dims, voxel_type, 21);
    let levels = pyramid(&volume, brick);
    let what = format!("{voxel_type} compress={compress}");
    let dir = tempfile::tempdir().unwrap();

    let first = build(&dir.path().join("a.vod"), &volume, voxel_type, brick, scale);
    let bytes1 = vod1_bytes(&first, compress);
    let vod1 = Vod1::parse(&bytes1).unwrap();
    assert_eq!(vod1.layout, *first.layout(), "{what}");
    assert_eq!(vod1.voxel_scale, scale, "{what}");
    assert!(
        level0_of_vod1(&vod1) == volume.to_bytes(voxel_type),
        "{what}: a level-0 voxel of the VOD 1 file differs"
    );
    // Every level of detail is carried over too.
    let mut buf = vec![0u8; vod1.layout.brick_bytes()];
    for (key, content) in expected_nodes(&levels, brick, voxel_type) {
        if vod1.layout.contains(key) {
            vod1.read_into(key, &mut buf).unwrap();
            assert!(
                buf == content,
                "{what}: VOD 1 brick {key} differs from the independent pyramid"
            );
        }
    }

    // VOD 1 -> VOD 2 (level 0 from the VOD 1 file, levels rebuilt).
    let second_path = dir.path().join("b.vod");
    let source = Vod1Source::new(&vod1);
    let options = BuildOptions {
        compression: Compression::Lz4,
        progress: std::sync::Arc::new(Silent),
    };
    build_vod2(
        &second_path,
        &vod1.layout,
        vod1.voxel_scale,
        &source,
        &options,
    )
    .unwrap();
    source.finish().unwrap();
    let second = Vod2::open(&second_path).unwrap();
    let mut exported = Vec::new();
    let region = Box3::new([0; 3], dims.map(i64::from));
    export_raw(&second.head(), 0, region, &mut exported, &Silent).unwrap();
    assert!(
        exported == volume.to_bytes(voxel_type),
        "{what}: level 0 of the re-imported VOD 2 differs"
    );
    for (key, content) in expected_nodes(&levels, brick, voxel_type) {
        if second.layout().contains(key) {
            assert!(
                second.head().read(key).unwrap() == content,
                "{what}: re-imported brick {key} differs"
            );
        }
    }

    // VOD 2 -> VOD 1 again: the same bytes.
    let bytes2 = vod1_bytes(&second, compress);
    assert_eq!(
        bytes1.len(),
        bytes2.len(),
        "{what}: the two VOD 1 files differ in length"
    );
    assert!(bytes1 == bytes2, "{what}: the two VOD 1 files differ");
}

#[test]
fn u8_chain_compressed_preserves_voxels_and_bytes() {
    chain(VoxelType::U8, true);
}

#[test]
fn u8_chain_uncompressed_preserves_voxels_and_bytes() {
    chain(VoxelType::U8, false);
}

#[test]
fn u16_chain_compressed_preserves_voxels_and_bytes() {
    chain(VoxelType::U16, true);
}

#[test]
fn u16_chain_uncompressed_preserves_voxels_and_bytes() {
    chain(VoxelType::U16, false);
}

/// Walks a VOD 1 file by hand and checks each field against the thesis layout, returning the
/// node array and, per brick ID, the payload's (offset, size).
fn walk_layout(
    b: &[u8],
    dims: [u32; 3],
    brick: u32,
    scale: [f32; 3],
    height: u32,
    bits: u32,
    compress: bool,
) -> (Vec<u32>, HashMap<u32, (usize, usize)>) {
    assert_eq!(
        &b[0..4],
        &[0x2E, 0x56, 0x4F, 0x44],
        "signature '.VOD' in file order"
    );
    assert_eq!(u32_at(b, 4), 1, "fileVersion");
    assert_eq!(
        [u32_at(b, 8), u32_at(b, 12), u32_at(b, 16)],
        dims,
        "volumeSize"
    );
    assert_eq!(
        [u32_at(b, 20), u32_at(b, 24), u32_at(b, 28)],
        [brick; 3],
        "brickSize"
    );
    assert_eq!(
        [f32_at(b, 32), f32_at(b, 36), f32_at(b, 40)],
        scale,
        "voxelScale"
    );
    assert_eq!(u32_at(b, 44), height, "treeHeight");
    assert_eq!(u32_at(b, 48), bits, "voxelSize");
    assert_eq!(&b[52..56], b"XH64", "hashAlgorithm");
    assert_eq!(
        &b[56..60],
        if compress { b"LZ4B" } else { b"NONE" },
        "compAlgorithm"
    );
    let flags = u32_at(b, 60);
    assert_eq!(
        flags & 1,
        compress as u32,
        "flag bit 0: inlined compression"
    );
    assert_eq!(flags & 2, 2, "flag bit 1: right-hand padding");
    assert_eq!(flags & 4, 0, "flag bit 2: float data");
    let n_nodes = ((8u64.pow(height) - 1) / 7) as usize;
    let nodes: Vec<u32> = (0..n_nodes).map(|i| u32_at(b, 64 + 4 * i)).collect();
    let count_at = 64 + 4 * n_nodes;
    let n_bricks = u32_at(b, count_at) as usize;
    let table_at = count_at + 4;
    let mut data_at = table_at + 16 * n_bricks;
    let mut payloads = HashMap::new();
    for i in 0..n_bricks {
        let e = table_at + 16 * i;
        let id = u32_at(b, e);
        assert_eq!(id as usize, i + 1, "brick IDs are 1, 2, ... in table order");
        assert_eq!(
            u32_at(b, e + 4) as usize,
            data_at,
            "brickFileOffset of brick {id} points at its dataSize"
        );
        let size = u32_at(b, data_at) as usize;
        payloads.insert(id, (data_at + 4, size));
        data_at += 4 + size;
    }
    assert_eq!(data_at, b.len(), "the last payload ends the file");
    for (i, &id) in nodes.iter().enumerate() {
        assert!(
            id >= 1 && id as usize <= n_bricks,
            "node {i} names brick {id} of {n_bricks}"
        );
    }
    (nodes, payloads)
}

#[test]
fn vod1_bytes_follow_the_thesis_layout() {
    // 37x21x14 with brick 8: grids 5x3x2, 3x2x1, 2x1x1, 1x1x1, so treeHeight 4 and
    // (8^4 - 1) / 7 = 585 nodes.
    let dims = [37, 21, 14];
    let scale = [1.0, 0.5, 2.0];
    for (voxel_type, bits) in [(VoxelType::U8, 8), (VoxelType::U16, 16)] {
        let volume = mixed_volume(dims, voxel_type, 22);
        let levels = pyramid(&volume, 8);
        assert_eq!(levels.len(), 4);
        let dir = tempfile::tempdir().unwrap();
        let vod = build(&dir.path().join("a.vod"), &volume, voxel_type, 8, scale);
        for compress in [false, true] {
            let b = vod1_bytes(&vod, compress);
            let (nodes, payloads) = walk_layout(&b, dims, 8, scale, 4, bits, compress);
            assert_eq!(nodes.len(), 585);
            let expected = expected_nodes(&levels, 8, voxel_type);
            assert_eq!(expected.len(), 585);
            // Distinct contents are stored once each, and nodes with equal content share an ID.
            let mut by_content: HashMap<&[u8], u32> = HashMap::new();
            for ((key, content), &id) in expected.iter().zip(&nodes) {
                let prev = *by_content.entry(content.as_slice()).or_insert(id);
                assert_eq!(
                    prev, id,
                    "node {key}: equal contents must share one brick ID"
                );
                if !compress {
                    // Uncompressed payloads are the decoded brick itself.
                    let (at, size) = payloads[&id];
                    assert_eq!(
                        size,
                        512 * voxel_type.bytes(),
                        "dataSize of an uncompressed brick"
                    );
                    assert!(
                        b[at..at + size] == content[..],
                        "node {key} (ID {id}) payload differs"
                    );
                }
            }
            assert_eq!(
                payloads.len(),
                by_content.len(),
                "one brick per distinct content"
            );
        }
    }
}

#[test]
fn single_voxel_volume_is_a_one_node_octree() {
    let volume = Grid {
        dims: [1, 1, 1],
        values: vec![0xA5],
    };
    assert_eq!(level_count([1, 1, 1], 16), 1);
    let dir = tempfile::tempdir().unwrap();
    let vod = build(
        &dir.path().join("a.vod"),
        &volume,
        VoxelType::U8,
        16,
        [1.0; 3],
    );
    let b = vod1_bytes(&vod, false);
    let (nodes, payloads) = walk_layout(&b, [1, 1, 1], 16, [1.0; 3], 1, 8, false);
    assert_eq!(nodes, vec![1]);
    let (at, size) = payloads[&1];
    assert_eq!(size, 4096);
    assert_eq!(b[at], 0xA5);
    assert!(b[at + 1..at + size].iter().all(|&v| v == 0), "padding is L");
    // 64-byte header, 1 node, the brick count, one table entry, one sized payload.
    assert_eq!(b.len(), 64 + 4 + 4 + 16 + 4 + 4096);
}

/// The reader's other documented paths: 32-bit hashes ('XH32', 12-byte table entries holding the
/// low 32 bits of xxh3-64) and the thesis's brick ID 0, an empty node that reads as all L. Both
/// files are made here by rewriting the writer's bytes by hand.
#[test]
fn xh32_hashes_and_empty_nodes_are_read() {
    let dims = [37, 21, 14];
    let volume = mixed_volume(dims, VoxelType::U8, 23);
    let levels = pyramid(&volume, 8);
    let dir = tempfile::tempdir().unwrap();
    let vod = build(
        &dir.path().join("a.vod"),
        &volume,
        VoxelType::U8,
        8,
        [1.0; 3],
    );
    let b = vod1_bytes(&vod, false);
    let (nodes, _) = walk_layout(&b, dims, 8, [1.0; 3], 4, 8, false);
    let count_at = 64 + 4 * nodes.len();
    let n_bricks = u32_at(&b, count_at) as usize;
    let table_at = count_at + 4;
    let data_at = table_at + 16 * n_bricks;

    let mut xh32 = b[..table_at].to_vec();
    xh32[52..56].copy_from_slice(b"XH32");
    for i in 0..n_bricks {
        let e = table_at + 16 * i;
        xh32.extend_from_slice(&b[e..e + 4]);
        let offset = u32_at(&b, e + 4) - 4 * n_bricks as u32;
        xh32.extend_from_slice(&offset.to_le_bytes());
        xh32.extend_from_slice(&b[e + 8..e + 12]); // the low half of the little-endian u64
    }
    xh32.extend_from_slice(&b[data_at..]);
    assert_eq!(xh32.len(), b.len() - 4 * n_bricks);

    let expected = expected_nodes(&levels, 8, VoxelType::U8);
    let parsed = Vod1::parse(&xh32).unwrap();
    let mut buf = vec![0u8; 512];
    for (key, content) in &expected {
        if parsed.layout.contains(*key) {
            parsed.read_into(*key, &mut buf).unwrap();
            assert!(buf == *content, "XH32 brick {key} differs");
        }
    }
    // A wrong 32-bit hash is still caught: exactly the nodes of brick 1 fail.
    let mut bad = xh32.clone();
    bad[table_at + 8] ^= 1;
    let parsed = Vod1::parse(&bad).unwrap();
    for ((key, _), &id) in expected.iter().zip(&nodes) {
        if parsed.layout.contains(*key) {
            let r = parsed.read_into(*key, &mut buf);
            assert_eq!(
                r.is_err(),
                id == 1,
                "brick {key} (ID {id}) with brick 1's hash damaged"
            );
        }
    }

    // Brick ID 0 for every node whose content is all L: the file still reads the same.
    let mut empty = b.clone();
    let mut zeroed = 0;
    for (i, (_, content)) in expected.iter().enumerate() {
        if content.iter().all(|&v| v == 0) {
            empty[64 + 4 * i..68 + 4 * i].copy_from_slice(&0u32.to_le_bytes());
            zeroed += 1;
        }
    }
    assert!(zeroed > 0, "the volume has all-L nodes");
    let parsed = Vod1::parse(&empty).unwrap();
    for (key, content) in &expected {
        if parsed.layout.contains(*key) {
            parsed.read_into(*key, &mut buf).unwrap();
            assert!(buf == *content, "brick {key} with ID 0 differs");
        }
    }
}
