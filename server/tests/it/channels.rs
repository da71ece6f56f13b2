//! Attribute channels (materials, labels) as brick streams of their own in a VOD 2 file: built
//! beside density, read back level by level against a mode pyramid computed here by counting,
//! changed by a transaction that touches only their nodes, carried through reopening, appending,
//! compaction and a full check.

use isovox_proto::channel::ChannelInfo;
use isovox_proto::vod2::FileHeader;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::progress::Silent;
use isovox_server::store::check::{check, Depth};
use isovox_server::store::compact::compact;
use isovox_server::store::{
    build_streams, BrickVoxels, BuildOptions, CheckpointPolicy, DenseGrid, Snapshot, Transaction,
    Vod2, Vod2Writer,
};
use std::collections::BTreeMap;

use crate::common::{mixed_volume, pyramid, Grid, XorShift};

const DIMS: [u32; 3] = [40, 24, 20];
const BRICK: u32 = 8;

/// The next coarser level by counting each 2x2x2 (voxels beyond the grid count as 0): the most
/// frequent value, ties to the smallest; with `sparse`, 0 only when nothing else is there.
fn mode_down(g: &Grid, sparse: bool) -> Grid {
    let dims = g.dims.map(|d| d.div_ceil(2));
    let mut values = Vec::new();
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let mut counts: BTreeMap<u16, usize> = BTreeMap::new();
                for d in 0..8 {
                    let v = g.at_or_zero(2 * x + (d & 1), 2 * y + (d >> 1 & 1), 2 * z + (d >> 2));
                    if !(sparse && v == 0) {
                        *counts.entry(v).or_default() += 1;
                    }
                }
                // BTreeMap iterates ascending: the first value with the top count is the smallest.
                let top = counts.values().copied().max().unwrap_or(0);
                values.push(
                    counts
                        .iter()
                        .find(|(_, &c)| c == top)
                        .map_or(0, |(&v, _)| v),
                );
            }
        }
    }
    Grid { dims, values }
}

fn mode_pyramid(level0: &Grid, levels: usize, sparse: bool) -> Vec<Grid> {
    let mut out = vec![level0.clone()];
    while out.len() < levels {
        let next = mode_down(out.last().unwrap(), sparse);
        out.push(next);
    }
    out
}

/// Materials in slabs of 1..=4 with a sprinkling of 9s (so that 2x2x2 groups disagree).
fn materials(seed: u64) -> Grid {
    let mut rng = XorShift(seed);
    let dims = DIMS.map(|d| d as usize);
    let mut values = Vec::new();
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let base = 1 + ((x / 5 + y / 7 + z / 3) % 4) as u16;
                values.push(if rng.below(7) == 0 { 9 } else { base });
            }
        }
    }
    Grid { dims, values }
}

/// Labels: mostly 0, a few thin boxes of ids above 255 (a u16 channel).
fn labels(seed: u64) -> Grid {
    let mut rng = XorShift(seed);
    let dims = DIMS.map(|d| d as usize);
    let mut values = vec![0u16; dims.iter().product()];
    for id in 0..6u16 {
        let lo = [0, 1, 2].map(|a| rng.below(dims[a] as u64 - 3) as usize);
        let len = [0, 1, 2].map(|a| (1 + rng.below(12) as usize).min(dims[a] - lo[a]));
        for z in lo[2]..lo[2] + len[2] {
            for y in lo[1]..lo[1] + len[1] {
                for x in lo[0]..lo[0] + len[0].min(2) {
                    values[(z * dims[1] + y) * dims[0] + x] = 1000 + 7 * id;
                }
            }
        }
    }
    Grid { dims, values }
}

fn header() -> FileHeader {
    let layout = VolumeLayout::new(DIMS, BRICK, VoxelType::U8).unwrap();
    let material = ChannelInfo {
        palette: vec!["#808080".into(), "#8b5a2b".into()],
        ..ChannelInfo::new("material", VoxelType::U8)
    };
    let label = ChannelInfo {
        sparse: true,
        ..ChannelInfo::new("label", VoxelType::U16)
    };
    FileHeader::with_channels(layout, [1.0; 3], vec![material, label]).unwrap()
}

/// Every brick of every level of `view` equals the brick cut from `expected`.
fn assert_pyramid(view: &Snapshot, expected: &[Grid], what: &str) {
    let layout = view.layout();
    assert_eq!(expected.len(), layout.levels() as usize);
    for (level, grid) in expected.iter().enumerate() {
        let g = layout.grid(level as u8);
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    let key = BrickKey {
                        level: level as u8,
                        x,
                        y,
                        z,
                    };
                    let want = grid.brick(
                        [x as usize, y as usize, z as usize],
                        BRICK as usize,
                        layout.voxel_type(),
                    );
                    assert!(
                        view.read(key).unwrap() == want,
                        "{what}: brick {key} differs from the hand-made pyramid"
                    );
                }
            }
        }
    }
}

fn build(path: &std::path::Path, density: &Grid, material: &Grid, label: &Grid) {
    let density_bytes = density.to_bytes(VoxelType::U8);
    let material_bytes = material.to_bytes(VoxelType::U8);
    let label_bytes = label.to_bytes(VoxelType::U16);
    let sources = [
        DenseGrid::new(DIMS, VoxelType::U8, BRICK, &density_bytes),
        DenseGrid::new(DIMS, VoxelType::U8, BRICK, &material_bytes),
        DenseGrid::new(DIMS, VoxelType::U16, BRICK, &label_bytes),
    ];
    let sources: Vec<&dyn isovox_server::store::BrickSource> =
        sources.iter().map(|s| s as _).collect();
    build_streams(path, header(), &sources, &BuildOptions::default()).unwrap();
}

#[test]
fn channels_are_pyramids_of_their_own_built_edited_compacted_and_checked() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("world.vod");
    let density = mixed_volume(DIMS, VoxelType::U8, 5);
    let mut material = materials(11);
    let label = labels(12);
    build(&path, &density, &material, &label);

    let vod = Vod2::open(&path).unwrap();
    let head = vod.head();
    assert_eq!(head.header().channels, header().channels);
    let levels = head.layout().levels() as usize;
    assert_pyramid(&head, &pyramid(&density, BRICK), "density");
    let material_view = head.channel("material").unwrap();
    assert_eq!(material_view.layout().voxel_type(), VoxelType::U8);
    assert_pyramid(
        &material_view,
        &mode_pyramid(&material, levels, false),
        "material",
    );
    let label_view = head.channel("label").unwrap();
    assert_eq!(label_view.layout().voxel_type(), VoxelType::U16);
    assert_pyramid(&label_view, &mode_pyramid(&label, levels, true), "label");
    assert!(head.channel("density").is_none() && head.channel("colour").is_none());
    let density_entries: Vec<_> = (0..head.layout().node_count())
        .map(|n| head.entry_at(n).unwrap())
        .collect();
    drop((head, material_view, label_view, vod));

    // A version that paints material 7 into one box: only material bricks change.
    let (lo, hi) = ([3usize, 2, 1], [19usize, 11, 9]);
    for z in lo[2]..hi[2] {
        for y in lo[1]..hi[1] {
            for x in lo[0]..hi[0] {
                material.values[(z * DIMS[1] as usize + y) * DIMS[0] as usize + x] = 7;
            }
        }
    }
    {
        let vod = Vod2::open(&path).unwrap();
        let head = vod.head();
        let view = head.channel("material").unwrap();
        let mut writer = Vod2Writer::open_append(&path, Default::default()).unwrap();
        let mut level0 = Vec::new();
        for z in 0..2 {
            for y in 0..2 {
                for x in 0..3 {
                    let key = BrickKey { level: 0, x, y, z };
                    let bytes =
                        material.brick([x as usize, y as usize, z as usize], 8, VoxelType::U8);
                    level0.push((key, BrickVoxels::from_bytes(bytes, VoxelType::U8)));
                }
            }
        }
        let mut t = Transaction::on(&mut writer, &head);
        t.update_channel_level0(&view, level0).unwrap();
        let committed = t.commit(CheckpointPolicy::default()).unwrap();
        assert!(
            committed.changed.iter().all(|l| l.is_empty()),
            "density changed"
        );
        let material_changed = &committed.channels_changed[&1];
        assert!(!material_changed[0].is_empty() && !material_changed[1].is_empty());
        assert!(
            !committed.channels_changed.contains_key(&2),
            "labels changed"
        );
    }
    let check_all = |what: &str| {
        let vod = Vod2::open(&path).unwrap();
        let head = vod.head();
        assert_eq!(head.version, 2, "{what}");
        if what == "after the edit" {
            let entries: Vec<_> = (0..head.layout().node_count())
                .map(|n| head.entry_at(n).unwrap())
                .collect();
            assert_eq!(entries, density_entries, "{what}: density entries moved");
        }
        // Compaction moves every record: there, density is checked by content.
        assert_pyramid(
            &head,
            &pyramid(&density, BRICK),
            &format!("{what}: density"),
        );
        assert_pyramid(
            &head.channel("material").unwrap(),
            &mode_pyramid(&material, levels, false),
            &format!("{what}: material"),
        );
        assert_pyramid(
            &head.channel("label").unwrap(),
            &mode_pyramid(&label, levels, true),
            &format!("{what}: label"),
        );
        let report = check(&path, Depth::Everything, &Silent).unwrap();
        assert!(!report.is_damaged(), "{what}: {}", report.summary());
    };
    check_all("after the edit");
    {
        let vod = Vod2::open(&path).unwrap();
        compact(&vod, &vod.head(), &Silent).unwrap();
    }
    check_all("after compaction");
}

#[test]
fn channel_headers_refuse_what_does_not_fit() {
    let layout = VolumeLayout::new(DIMS, BRICK, VoxelType::U8).unwrap();
    // 256 palette entries for each of 7 channels: the table outgrows the header page.
    let big: Vec<ChannelInfo> = (0..7)
        .map(|i| ChannelInfo {
            palette: vec!["#123456".into(); 256],
            ..ChannelInfo::new(&format!("c{i}"), VoxelType::U8)
        })
        .collect();
    assert!(FileHeader::with_channels(layout.clone(), [1.0; 3], big).is_err());
    // One channel with a full palette fits, and reads back.
    let one = vec![ChannelInfo {
        palette: vec!["#123456".into(); 256],
        ..ChannelInfo::new("material", VoxelType::U8)
    }];
    let h = FileHeader::with_channels(layout, [1.0; 3], one).unwrap();
    let page = h.encode_page();
    assert_eq!(FileHeader::decode(&page).unwrap(), h);
    // Any flipped byte of the table is refused.
    for at in [128usize, 140, 300, 128 + 2000] {
        let mut bad = page.clone();
        bad[at] ^= 0x20;
        assert!(FileHeader::decode(&bad).is_err(), "flip at {at} accepted");
    }
}
