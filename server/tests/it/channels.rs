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
        t.update_channel_level0(
            &view,
            level0,
            &isovox_proto::geometry::Box3::of_volume(head.layout()),
        )
        .unwrap();
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

// ---- Edits of channels: CVG's rule, paint, and which streams an edit touches ----

use isovox_proto::icvg::EditRequest;
use isovox_server::cancel::CancelToken;
use isovox_server::icvg::edit::{apply_edit, Edit, EditOutcome};
use isovox_server::icvg::term::{NoVolumes, TermLimits};

const G: [u32; 3] = [24, 24, 24];

/// Ground: density 255 below z = 10, 0 above; material 1 (rock) everywhere; labels 0 but for
/// a box of 77 at x, y, z in [2, 6).
fn ground(path: &std::path::Path) {
    let n = G.iter().product::<u32>() as usize;
    let idx = |x: usize, y: usize, z: usize| (z * 24 + y) * 24 + x;
    let mut density = vec![0u8; n];
    let material = vec![1u8; n];
    let mut label = vec![0u16; n];
    for z in 0..24 {
        for y in 0..24 {
            for x in 0..24 {
                if z < 10 {
                    density[idx(x, y, z)] = 255;
                }
                if (2..6).contains(&x) && (2..6).contains(&y) && (2..6).contains(&z) {
                    label[idx(x, y, z)] = 77;
                }
            }
        }
    }
    let label_bytes: Vec<u8> = label.iter().flat_map(|v| v.to_le_bytes()).collect();
    let sources = [
        DenseGrid::new(G, VoxelType::U8, BRICK, &density),
        DenseGrid::new(G, VoxelType::U8, BRICK, &material),
        DenseGrid::new(G, VoxelType::U16, BRICK, &label_bytes),
    ];
    let sources: Vec<&dyn isovox_server::store::BrickSource> =
        sources.iter().map(|s| s as _).collect();
    let layout = VolumeLayout::new(G, BRICK, VoxelType::U8).unwrap();
    let channels = vec![
        ChannelInfo::new("material", VoxelType::U8),
        ChannelInfo {
            sparse: true,
            ..ChannelInfo::new("label", VoxelType::U16)
        },
    ];
    let header = FileHeader::with_channels(layout, [1.0; 3], channels).unwrap();
    build_streams(path, header, &sources, &BuildOptions::default()).unwrap();
}

fn edit(path: &std::path::Path, json: &str) -> EditOutcome {
    let req: EditRequest = serde_json::from_str(json).unwrap();
    let vod = Vod2::open(path).unwrap();
    let snap = vod.head();
    let mut edit = Edit::for_volume(
        &req,
        snap.header(),
        &TermLimits::default(),
        &NoVolumes,
        None,
        &CancelToken::never(),
    )
    .unwrap();
    let mut w = Vod2Writer::open_append(path, Default::default()).unwrap();
    let policy = CheckpointPolicy::default();
    apply_edit(&mut w, &snap, &mut edit, policy, &CancelToken::never()).unwrap()
}

/// The level-0 voxels of a stream of the head (density for `None`), one u16 per voxel.
fn level0(path: &std::path::Path, channel: Option<&str>) -> Vec<u16> {
    let vod = Vod2::open(path).unwrap();
    let head = vod.head();
    let channel_view = channel.map(|c| head.channel(c).unwrap());
    let view: &Snapshot = channel_view.as_deref().unwrap_or(&head);
    let t = view.layout().voxel_type();
    let b = BRICK as usize;
    let mut out = vec![0u16; G.iter().product::<u32>() as usize];
    for bz in 0..3u32 {
        for by in 0..3u32 {
            for bx in 0..3u32 {
                let key = BrickKey {
                    level: 0,
                    x: bx,
                    y: by,
                    z: bz,
                };
                let bytes = view.read(key).unwrap();
                for i in 0..b * b * b {
                    let (x, y, z) = (i % b, i / b % b, i / (b * b));
                    let v = match t {
                        VoxelType::U8 => bytes[i] as u16,
                        _ => u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]]),
                    };
                    let at = ((bz as usize * b + z) * 24 + by as usize * b + y) * 24
                        + bx as usize * b
                        + x;
                    out[at] = v;
                }
            }
        }
    }
    out
}

fn at(x: usize, y: usize, z: usize) -> usize {
    (z * 24 + y) * 24 + x
}

fn inside(p: [usize; 3], lo: [usize; 3], hi: [usize; 3]) -> bool {
    (0..3).all(|a| lo[a] <= p[a] && p[a] < hi[a])
}

fn each_voxel() -> impl Iterator<Item = [usize; 3]> {
    (0..24).flat_map(|z| (0..24).flat_map(move |y| (0..24).map(move |x| [x, y, z])))
}

#[test]
fn union_takes_the_denser_operand_s_material_and_difference_keeps_the_volume_s() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ground.vod");
    ground(&path);
    let density_before = level0(&path, None);

    // A cuboid of material 5 from z = 6 to 16: its padding (the outer layer) is L, its next
    // layer S, the rest H. Above the ground (z >= 10) the term is denser than air wherever it
    // is S or H; inside the ground (255) it never is. So material 5 at x, y in [5, 11) (origin
    // 4 + 1 up to the padding at 4 + 8 - 1), z in [10, 15), rock elsewhere.
    let out = edit(
        &path,
        r#"{"op": "union", "term": {"cuboid": {"origin": [4, 4, 6], "size": [8, 8, 10], "material": 5}}}"#,
    );
    assert!(
        out.channels.contains_key("material"),
        "{:?}",
        out.channels.keys()
    );
    assert!(!out.channels.contains_key("label"), "labels were not named");
    let material = level0(&path, Some("material"));
    for p in each_voxel() {
        let want = if inside(p, [5, 5, 10], [11, 11, 15]) {
            5
        } else {
            1
        };
        assert_eq!(material[at(p[0], p[1], p[2])], want, "material at {p:?}");
    }

    // A difference takes attributes from the left operand, the volume: density changes,
    // material and labels do not.
    let out = edit(
        &path,
        r#"{"op": "difference", "term": {"ellipsoid": {"center": [12, 12, 8], "radii": [4, 4, 4], "material": 9}}}"#,
    );
    assert!(!out.changed[0].is_empty(), "the carve changed no density");
    assert!(
        out.channels.is_empty(),
        "a difference changed {:?}",
        out.channels.keys()
    );
    assert_eq!(level0(&path, Some("material")), material);
    assert_ne!(level0(&path, None), density_before);
}

#[test]
fn paint_writes_a_channel_where_its_term_is_inside_and_leaves_density_alone() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ground.vod");
    ground(&path);
    let density = level0(&path, None);
    let entries = |path: &std::path::Path| -> Vec<_> {
        let vod = Vod2::open(path).unwrap();
        let head = vod.head();
        (0..head.layout().node_count())
            .map(|n| head.entry_at(n).unwrap())
            .collect()
    };
    let density_entries = entries(&path);

    // Paint material 3 with a cuboid [0, 12)^3: inside (S or H) is [1, 11)^3.
    let out = edit(
        &path,
        r#"{"op": "paint", "term": {"cuboid": {"origin": [0, 0, 0], "size": [12, 12, 12], "material": 3}}}"#,
    );
    assert!(
        out.changed.iter().all(|l| l.is_empty()),
        "paint changed density bricks"
    );
    assert_eq!(entries(&path), density_entries);
    assert_eq!(level0(&path, None), density);
    let material = level0(&path, Some("material"));
    for p in each_voxel() {
        let want = if inside(p, [1, 1, 1], [11, 11, 11]) {
            3
        } else {
            1
        };
        assert_eq!(material[at(p[0], p[1], p[2])], want, "material at {p:?}");
    }

    // Labels, "empty" mode: 9 only where the label was 0; the 77 box stays.
    edit(
        &path,
        r#"{"op": "paint", "channel": "label", "overwrite": "empty", "term": {"cuboid": {"origin": [0, 0, 0], "size": [10, 10, 10], "label": 9}}}"#,
    );
    let label = level0(&path, Some("label"));
    for p in each_voxel() {
        let want = if inside(p, [2, 2, 2], [6, 6, 6]) {
            77
        } else if inside(p, [1, 1, 1], [9, 9, 9]) {
            9
        } else {
            0
        };
        assert_eq!(label[at(p[0], p[1], p[2])], want, "label at {p:?}");
    }
    // "all" paints over the 77s too.
    edit(
        &path,
        r#"{"op": "paint", "channel": "label", "term": {"cuboid": {"origin": [0, 0, 0], "size": [5, 5, 5], "label": 4}}}"#,
    );
    let label = level0(&path, Some("label"));
    assert_eq!(label[at(3, 3, 3)], 4);
    assert_eq!(label[at(5, 5, 5)], 77);
    assert_eq!(
        level0(&path, Some("material")),
        material,
        "paint of labels moved materials"
    );
}

#[test]
fn edits_of_channels_refuse_what_the_volume_cannot_take() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ground.vod");
    ground(&path);
    let vod = Vod2::open(&path).unwrap();
    let head = vod.head();
    let try_edit = |json: &str| {
        let req: EditRequest = serde_json::from_str(json).unwrap();
        Edit::for_volume(
            &req,
            head.header(),
            &TermLimits::default(),
            &NoVolumes,
            None,
            &CancelToken::never(),
        )
        .map(|_| ())
        .map_err(|e| e.to_string())
    };
    let cube =
        |attrs: &str| format!(r#"{{"cuboid": {{"origin": [0, 0, 0], "size": [4, 4, 4]{attrs}}}}}"#);
    for (json, says) in [
        (
            format!(
                r#"{{"op": "paint", "channel": "colour", "term": {}}}"#,
                cube(r#", "material": 2"#)
            ),
            "not \"colour\"",
        ),
        (
            format!(r#"{{"op": "paint", "term": {}}}"#, cube("")),
            "carry",
        ),
        (
            format!(
                r#"{{"op": "union", "term": {}}}"#,
                cube(r#", "material": 256"#)
            ),
            "beyond",
        ),
        (
            format!(
                r#"{{"op": "union", "overwrite": "empty", "term": {}}}"#,
                cube("")
            ),
            "belong to paint",
        ),
    ] {
        let err = try_edit(&json).expect_err(&json);
        assert!(err.contains(says), "{json}: {err}");
    }
    assert!(try_edit(&format!(
        r#"{{"op": "union", "term": {}}}"#,
        cube(r#", "material": 255, "label": 65535"#)
    ))
    .is_ok());
}

#[test]
fn terms_give_attributes_by_cvg_s_rule_by_hand() {
    use isovox_server::geometry::Box3;
    use isovox_server::icvg::term::{CompiledTerm, KEEP};
    // A: cuboid [0, 6)^3, material 1; B: cuboid x in [3, 9), y, z in [0, 6), material 2. Along
    // the row y = z = 2 a cuboid is L on its outer layer, S on the next, H inside:
    //   x:  0  1  2  3  4  5  6  7  8
    //   A:  L  S  H  H  S  L  .  .  .
    //   B:  .  .  .  L  S  H  H  S  L
    // Where a term's result is L it gives no attribute (KEEP), whatever its operands gave.
    let a = r#"{"cuboid": {"origin": [0, 0, 0], "size": [6, 6, 6], "material": 1}}"#;
    let b = r#"{"cuboid": {"origin": [3, 0, 0], "size": [6, 6, 6], "material": 2}}"#;
    let k = KEEP;
    let cases: [(&str, String, [u64; 9]); 5] = [
        // Union and intersection: the denser operand's, the left one on a tie (x = 4: S, S).
        (
            "union",
            format!(r#"{{"union": [{a}, {b}]}}"#),
            [k, 1, 1, 1, 1, 2, 2, 2, k],
        ),
        (
            "union, swapped",
            format!(r#"{{"union": [{b}, {a}]}}"#),
            [k, 1, 1, 1, 2, 2, 2, 2, k],
        ),
        // Intersection is S only at x = 4, where the two tie.
        (
            "intersection",
            format!(r#"{{"intersection": [{a}, {b}]}}"#),
            [k, k, k, k, 1, k, k, k, k],
        ),
        // Difference: always the left operand's; at x = 4 it carves A down to L.
        (
            "difference",
            format!(r#"{{"difference": [{a}, {b}]}}"#),
            [k, 1, 1, 1, k, k, k, k, k],
        ),
        // A leaf without a material gives none: where it is denser, the other's is not taken.
        (
            "union with a plain leaf",
            format!(
                r#"{{"union": [{a}, {{"cuboid": {{"origin": [3, 0, 0], "size": [6, 6, 6]}}}}]}}"#
            ),
            [k, 1, 1, 1, 1, k, k, k, k],
        ),
    ];
    for (what, json, want) in cases {
        let term: isovox_proto::icvg::Term = serde_json::from_str(&json).unwrap();
        let compiled =
            CompiledTerm::compile(&term, VoxelType::U8, &TermLimits::default(), &NoVolumes)
                .unwrap();
        // Evaluated over the row, and over boxes that cut it: the same values.
        for cut in [9, 4, 1] {
            let mut got = Vec::new();
            let mut x = 0;
            while x < 9 {
                let end = (x + cut).min(9);
                let bx = Box3::new([x, 2, 2], [end, 3, 3]);
                let n = (end - x) as usize;
                let (mut d, mut v) = (vec![0u16; n], vec![0u64; n]);
                compiled
                    .eval_channel(&bx, "material", &mut d, &mut v)
                    .unwrap();
                got.extend(v);
                x = end;
            }
            assert_eq!(got, want, "{what}, boxes of {cut}");
        }
    }
}

// ---- Over HTTP: metadata, ?channel=, and kill -9 during channel edits ----

use crate::channel_volumes::{ground_64, serve as serve_with};

fn serve(dir: &std::path::Path) -> crate::server_process::ServerProcess {
    serve_with(dir, &[])
}

fn get_bytes(url: &str) -> (u16, Vec<u8>) {
    let r = reqwest::blocking::get(url).unwrap();
    let status = r.status().as_u16();
    (status, r.bytes().unwrap().to_vec())
}

#[test]
fn channels_over_http_and_a_kill_during_channel_edits_loses_nothing_acknowledged() {
    isovox_server::client_tls::install_provider();
    let dir = tempfile::tempdir().unwrap();
    ground_64(dir.path());
    let server = serve(dir.path());
    let info: serde_json::Value = reqwest::blocking::get(server.url("/v1/volumes/world"))
        .unwrap()
        .json()
        .unwrap();
    let names: Vec<&str> = info["channels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["material", "label"]);
    // Level 1 of material is all 1; of density, 255 below z = 10 and 0 above.
    let (status, material) =
        get_bytes(&server.url("/v1/volumes/world/levels/1?channel=material&format=voxels"));
    assert_eq!((status, material.len()), (200, 32 * 32 * 32));
    assert!(material.iter().all(|&m| m == 1));
    let (_, density) = get_bytes(&server.url("/v1/volumes/world/levels/1?format=voxels"));
    assert_eq!(density[9 * 32 * 32], 255);
    assert_eq!(density[10 * 32 * 32], 0);
    // A brick of the label channel is u16: 2 bytes a voxel.
    let (status, brick) = get_bytes(&server.url("/v1/volumes/world/bricks/0/0/0/0?channel=label"));
    assert_eq!((status, brick.len()), (200, 2 * 16 * 16 * 16));
    for bad in ["colour", "dens%20ity"] {
        let (status, body) =
            get_bytes(&server.url(&format!("/v1/volumes/world/levels/0?channel={bad}")));
        let body = String::from_utf8_lossy(&body);
        assert!(status == 404 || status == 400, "{bad}: {status} {body}");
    }
    let (status, body) = get_bytes(&server.url("/v1/volumes/world/levels/0?channel=colour"));
    assert_eq!(status, 404);
    assert!(
        String::from_utf8_lossy(&body).contains("material"),
        "the 404 names the channels"
    );
    drop(server);

    // Two editors paint disjoint 4^3 cubes of distinct materials while the server is killed.
    let mut server = serve(dir.path());
    let acknowledged = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let editors: Vec<_> = (0..2u64)
        .map(|e| {
            let (url, acknowledged, stop) = (
                server.url("/v1/volumes/world/edits"),
                acknowledged.clone(),
                stop.clone(),
            );
            std::thread::spawn(move || {
                let client = reqwest::blocking::Client::new();
                for i in 0..200u64 {
                    if stop.load(std::sync::atomic::Ordering::Relaxed) {
                        break;
                    }
                    let cube = 2 * i + e; // 0..400: a cell of an 8 x 8 x 7 grid of 8^3 cells
                    let origin = [cube % 8 * 8, cube / 8 % 8 * 8, cube / 64 * 8];
                    let material = 2 + cube % 250;
                    // A cuboid of size 6 is S or H on [origin + 1, origin + 5).
                    let body = serde_json::json!({"op": "paint", "term": {"cuboid": {
                        "origin": origin, "size": [6, 6, 6], "material": material}}});
                    let sent = client
                        .post(&url)
                        .bearer_auth("secret-alice-0123456")
                        .json(&body)
                        .timeout(std::time::Duration::from_secs(10))
                        .send();
                    match sent {
                        Ok(r) if r.status().is_success() => {
                            acknowledged.lock().unwrap().push((origin, material))
                        }
                        _ => break, // the server is gone
                    }
                    if cube >= 7 * 64 - 2 {
                        break;
                    }
                }
            })
        })
        .collect();
    // Kill once some edits were acknowledged, with more in flight.
    let start = std::time::Instant::now();
    while acknowledged.lock().unwrap().len() < 20 && start.elapsed().as_secs() < 60 {
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let _ = server.stop();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    for e in editors {
        e.join().unwrap();
    }
    let acknowledged = acknowledged.lock().unwrap().clone();
    assert!(
        acknowledged.len() >= 20,
        "only {} edits before the kill",
        acknowledged.len()
    );

    // Every acknowledged paint is there after a restart; the file checks clean.
    let server = serve(dir.path());
    let (_, material) =
        get_bytes(&server.url("/v1/volumes/world/levels/0?channel=material&format=voxels"));
    for (origin, m) in &acknowledged {
        for d in [[1, 1, 1], [4, 4, 4], [1, 4, 2]] {
            let p = [0, 1, 2].map(|a| (origin[a] + d[a]) as usize);
            assert_eq!(
                material[(p[2] * 64 + p[1]) * 64 + p[0]] as u64,
                *m,
                "the acknowledged paint at {origin:?} is missing at {p:?}"
            );
        }
    }
    drop(server);
    let report = check(&dir.path().join("world.vod"), Depth::Everything, &Silent).unwrap();
    assert!(!report.is_damaged(), "{}", report.summary());
}

use crate::channel_volumes::post_ok;

#[test]
fn undo_takes_back_an_edit_s_materials_and_keeps_a_later_edit_s() {
    isovox_server::client_tls::install_provider();
    let dir = tempfile::tempdir().unwrap();
    ground_64(dir.path());
    let server = serve(dir.path());
    let material =
        || get_bytes(&server.url("/v1/volumes/world/levels/0?channel=material&format=voxels")).1;
    let at = |m: &[u8], p: [usize; 3]| m[(p[2] * 64 + p[1]) * 64 + p[0]];
    // Alice raises a marble block (6) on the ground, z in [20, 30); a second edit raises a
    // block of material 9 overlapping it on x in [20, 40). Then the first is undone.
    let first = post_ok(
        &server,
        "/v1/volumes/world/edits",
        serde_json::json!({"op": "union", "term": {"cuboid": {"origin": [4, 4, 18], "size": [24, 24, 12], "material": 6}}}),
    );
    post_ok(
        &server,
        "/v1/volumes/world/edits",
        serde_json::json!({"op": "union", "term": {"cuboid": {"origin": [20, 4, 18], "size": [24, 24, 12], "material": 9}}}),
    );
    assert!(
        first["channels"]["material"][0]
            .as_array()
            .is_some_and(|l| !l.is_empty()),
        "the answer lists the changed material bricks: {first}"
    );
    let both = material();
    // Inside the first block only: marble; inside the second (denser than the air it took
    // over, never denser than the first block's H where they overlap): 9 where the first was
    // not, marble where the first already stood (H against H: the volume keeps its own).
    assert_eq!(at(&both, [10, 10, 24]), 6);
    assert_eq!(
        at(&both, [24, 10, 24]),
        6,
        "the overlap stays the first block's"
    );
    assert_eq!(at(&both, [35, 10, 24]), 9);
    let undo = post_ok(
        &server,
        "/v1/volumes/world/undo",
        serde_json::json!({"version": first["version"]}),
    );
    assert_eq!(undo["replayed"], 1, "{undo}");
    let after = material();
    // Without the first block: rock (1) where it stood alone, the second block's 9 where they
    // overlapped (it now rises from air there), and 9 where it was alone.
    assert_eq!(at(&after, [10, 10, 24]), 1);
    assert_eq!(
        at(&after, [24, 10, 24]),
        9,
        "the second edit, applied again, owns the overlap"
    );
    assert_eq!(at(&after, [35, 10, 24]), 9);
    // Below the ground nothing ever changed.
    assert_eq!(at(&after, [10, 10, 5]), 1);
}

#[test]
fn a_dry_run_counts_the_voxels_the_edit_then_changes() {
    isovox_server::client_tls::install_provider();
    let dir = tempfile::tempdir().unwrap();
    ground_64(dir.path());
    let server = serve(dir.path());
    let density = || get_bytes(&server.url("/v1/volumes/world/levels/0?format=voxels")).1;
    let before = density();
    let carve = serde_json::json!({"op": "difference", "term": {"ellipsoid": {"center": [30, 30, 19], "radii": [9, 7, 5]}}});
    let dry = post_ok(
        &server,
        "/v1/volumes/world/edits?dry_run=true",
        carve.clone(),
    );
    assert_eq!(dry["dry_run"], true);
    assert_eq!(density(), before, "a dry run changed the volume");
    let real = post_ok(&server, "/v1/volumes/world/edits", carve);
    let after = density();
    // Counted here, voxel by voxel, from what the server serves before and after.
    let differing = before.iter().zip(&after).filter(|(a, b)| a != b).count() as u64;
    assert!(differing > 100, "the carve changed only {differing} voxels");
    assert_eq!(dry["voxels_changed"].as_u64(), Some(differing), "{dry}");
    assert_eq!(real["voxels_changed"].as_u64(), Some(differing), "{real}");
}
