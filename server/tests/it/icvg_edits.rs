//! Edits on real VOD 2 files: brick-wise evaluation (with its shortcuts, deduplication and
//! level-of-detail upkeep) equals the naive whole-array computation done here, at every level and
//! in every version; plus deduplication, skipped bricks, constant bricks and checkpoints.
//!
//! The reference is independent of the engine's brick machinery: a plain array of level-0
//! values, edited voxel by voxel (`op(D1[v], term.sample(v))` inside the volume and the region,
//! unchanged elsewhere), and downsampled level by level (`(sum of 2x2x2 + 4) / 8`, voxels beyond
//! a level's extent 0).

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::cancel::CancelToken;
use isovox_server::geometry::Box3;
use isovox_server::icvg::edit::{apply_edit, Edit, EditKind, EditOutcome};
use isovox_server::icvg::ops::Outside;
use isovox_server::icvg::term::{CompiledTerm, NoVolumes, TermError, TermLimits, VolumeResolver};
use isovox_server::store::codec::Compression;
use isovox_server::store::CheckpointPolicy;
use isovox_server::store::{
    build_vod2, BuildOptions, DenseGrid, Snapshot, StoredBrick, Vod2, Vod2Writer,
};
use proptest::prelude::*;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::common::XorShift;
use crate::random_terms;

const BRICK: u32 = 8;
const DIMS: [u32; 3] = [37, 29, 23];

/// A whole level as a plain array, x fastest, then y, then z.
#[derive(Debug, Clone, PartialEq)]
struct Grid {
    dims: [usize; 3],
    values: Vec<u16>,
}

impl Grid {
    fn at(&self, x: usize, y: usize, z: usize) -> u16 {
        self.values[(z * self.dims[1] + y) * self.dims[0] + x]
    }

    fn at_or_zero(&self, x: usize, y: usize, z: usize) -> u16 {
        if x < self.dims[0] && y < self.dims[1] && z < self.dims[2] {
            self.at(x, y, z)
        } else {
            0
        }
    }

    /// The next coarser level: ceil(dims / 2), each voxel (sum of its 2x2x2 + 4) / 8.
    fn downsample(&self) -> Grid {
        let dims = self.dims.map(|d| d.div_ceil(2));
        let mut values = Vec::with_capacity(dims.iter().product());
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let mut sum = 0u32;
                    for (dx, dy, dz) in [
                        (0, 0, 0),
                        (1, 0, 0),
                        (0, 1, 0),
                        (1, 1, 0),
                        (0, 0, 1),
                        (1, 0, 1),
                        (0, 1, 1),
                        (1, 1, 1),
                    ] {
                        sum += self.at_or_zero(2 * x + dx, 2 * y + dy, 2 * z + dz) as u32;
                    }
                    values.push(((sum + 4) / 8) as u16);
                }
            }
        }
        Grid { dims, values }
    }

    fn bytes(&self, t: VoxelType) -> Vec<u8> {
        match t {
            VoxelType::U8 => self.values.iter().map(|&v| v as u8).collect(),
            _ => self.values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }
}

/// Initial content: a solid ground slab (y < 8, whole constant-H bricks), a ball of radius 9
/// with a ramp to radius 11, a box of noise, air elsewhere.
fn initial(dims: [u32; 3], t: VoxelType, seed: u64) -> Grid {
    let h = t.high() as f64;
    let mut rng = XorShift(seed | 1);
    let d = dims.map(|d| d as usize);
    let mut values = Vec::with_capacity(d.iter().product());
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let r = (((x as f64 - 24.0).powi(2)
                    + (y as f64 - 16.0).powi(2)
                    + (z as f64 - 12.0).powi(2))
                .sqrt()
                    - 9.0)
                    / 2.0;
                let v = if y < 8 {
                    t.high()
                } else if (2..18).contains(&x) && (9..20).contains(&y) && (3..14).contains(&z) {
                    (rng.next() % (t.high() as u64 + 1)) as u16
                } else if r <= 0.0 {
                    t.high()
                } else if r < 1.0 {
                    (h * (1.0 - r)) as u16
                } else {
                    0
                };
                values.push(v);
            }
        }
    }
    Grid { dims: d, values }
}

fn build(path: &Path, grid: &Grid, t: VoxelType) -> VolumeLayout {
    let dims = grid.dims.map(|d| d as u32);
    let layout = VolumeLayout::new(dims, BRICK, t).unwrap();
    let bytes = grid.bytes(t);
    let source = DenseGrid::new(dims, t, BRICK, &bytes);
    build_vod2(path, &layout, [1.0; 3], &source, &BuildOptions::default()).unwrap();
    layout
}

/// Decoded brick bytes as values.
fn values(bytes: &[u8], t: VoxelType) -> Vec<u16> {
    match t {
        VoxelType::U8 => bytes.iter().map(|&b| b as u16).collect(),
        _ => bytes
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect(),
    }
}

/// Every level of the reference pyramid, level 0 first.
fn pyramid(level0: &Grid, levels: u8) -> Vec<Grid> {
    let mut out = vec![level0.clone()];
    for _ in 1..levels {
        let next = out[out.len() - 1].downsample();
        out.push(next);
    }
    out
}

/// Level-k bricks whose content differs between two reference pyramids' levels.
fn differing_bricks(a: &Grid, b: &Grid, brick: usize) -> BTreeSet<[u32; 3]> {
    let mut out = BTreeSet::new();
    for z in 0..a.dims[2] {
        for y in 0..a.dims[1] {
            for x in 0..a.dims[0] {
                if a.at(x, y, z) != b.at(x, y, z) {
                    out.insert([x / brick, y / brick, z / brick].map(|c| c as u32));
                }
            }
        }
    }
    out
}

/// Every brick of every level of `snap` equals the reference pyramid of `level0`; voxels beyond
/// a level's extent read back 0.
fn check_snapshot(snap: &Snapshot, level0: &Grid, what: &str) {
    let layout = snap.layout();
    let t = layout.voxel_type();
    let b = layout.brick() as usize;
    let levels = pyramid(level0, layout.levels());
    for (level, grid) in levels.iter().enumerate() {
        let level = level as u8;
        assert_eq!(
            grid.dims,
            layout.level_dims(level).map(|d| d as usize),
            "{what}: reference level {level} extent"
        );
        let g = layout.grid(level);
        for bz in 0..g[2] {
            for by in 0..g[1] {
                for bx in 0..g[0] {
                    let key = layout.key(level, bx, by, bz).unwrap();
                    let got = values(&snap.read(key).unwrap(), t);
                    for z in 0..b {
                        for y in 0..b {
                            for x in 0..b {
                                let v = [
                                    bx as usize * b + x,
                                    by as usize * b + y,
                                    bz as usize * b + z,
                                ];
                                let want = grid.at_or_zero(v[0], v[1], v[2]);
                                let have = got[(z * b + y) * b + x];
                                if have != want {
                                    panic!(
                                        "{what}: level {level} voxel {v:?} (brick {bx},{by},{bz}) \
                                         reads {have}, expected {want}"
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The naive whole-array computation of an edit.
fn naive(level0: &Grid, edit: &Edit, t: VoxelType) -> Grid {
    let mut out = level0.clone();
    let d = level0.dims;
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let v = [x as i64, y as i64, z as i64];
                if let Some(r) = edit.region {
                    if !r.contains(v) {
                        continue;
                    }
                }
                let i = (z * d[1] + y) * d[0] + x;
                let old = level0.values[i];
                out.values[i] = match &edit.kind {
                    EditKind::Binary(op, term) => op.apply(old, term.sample(v), t),
                    EditKind::Unary(op) => op.apply(old, t),
                    // Paint leaves density as it is.
                    EditKind::Paint { .. } => old,
                };
            }
        }
    }
    out
}

/// Applies `req` to the head of `path` and returns the edit and its outcome.
fn run(
    path: &Path,
    req: &EditRequest,
    policy: CheckpointPolicy,
    volumes: &dyn VolumeResolver,
) -> (Edit, EditOutcome) {
    let vod = Vod2::open(path).unwrap();
    let snap = vod.head();
    let t = snap.layout().voxel_type();
    let mut edit = Edit::from_request(req, t, &TermLimits::default(), volumes).unwrap();
    let mut w = Vod2Writer::open_append(path, Compression::Zstd(5)).unwrap();
    let outcome = apply_edit(&mut w, &snap, &mut edit, policy, &CancelToken::never()).unwrap();
    (edit, outcome)
}

/// Applies an edit, checks the file against the reference, the outcome's changed bricks against
/// the bricks whose content differs, and the number of evaluated bricks against the bricks the
/// edit may touch. Returns the new reference and its version.
fn edit_and_check(
    path: &Path,
    before: &Grid,
    req: &EditRequest,
    policy: CheckpointPolicy,
) -> (Grid, u64, EditOutcome) {
    edit_and_check_with(path, before, req, policy, &NoVolumes)
}

/// [`edit_and_check`] with terms that may name stored volumes.
fn edit_and_check_with(
    path: &Path,
    before: &Grid,
    req: &EditRequest,
    policy: CheckpointPolicy,
    volumes: &dyn VolumeResolver,
) -> (Grid, u64, EditOutcome) {
    let (edit, outcome) = run(path, req, policy, volumes);
    let vod = Vod2::open(path).unwrap();
    let snap = vod.head();
    let layout = snap.layout().clone();
    let t = layout.voxel_type();
    let after = naive(before, &edit, t);
    let what = format!("after {req:?}");
    assert_eq!(snap.version, outcome.version, "{what}: head version");
    check_snapshot(&snap, &after, &what);
    // Changed bricks: exactly those whose content differs, at every level.
    let (old, new) = (
        pyramid(before, layout.levels()),
        pyramid(&after, layout.levels()),
    );
    assert_eq!(outcome.changed.len(), layout.levels() as usize);
    for level in 0..layout.levels() as usize {
        let want = differing_bricks(&old[level], &new[level], layout.brick() as usize);
        let got: BTreeSet<[u32; 3]> = outcome.changed[level].iter().copied().collect();
        assert_eq!(
            got.len(),
            outcome.changed[level].len(),
            "{what}: duplicates"
        );
        assert_eq!(got, want, "{what}: changed bricks of level {level}");
    }
    let changed: usize = outcome.changed.iter().map(Vec::len).sum();
    assert!(
        outcome.new_records as usize <= changed,
        "{what}: {} new records for {changed} changed bricks",
        outcome.new_records
    );
    // Evaluated bricks: at most those of the region (or the volume) that the edit can change;
    // for an identity-class operator with a bounded term, those the term's B-box meets.
    let vol = Box3::new([0; 3], layout.dims().map(|d| d as i64));
    let mut reach = edit.region.map_or(vol, |r| r.intersect(&vol));
    if let EditKind::Binary(op, term) = &edit.kind {
        if let (Outside::Identity, Some(bb)) = (op.outside(t), term.bbox) {
            reach = reach.intersect(&bb);
        }
    }
    let bricks_meeting = if reach.is_empty() {
        0
    } else {
        (0..3)
            .map(|a| {
                let e = layout.brick() as i64;
                ((reach.max[a] - 1) / e - reach.min[a] / e + 1) as usize
            })
            .product()
    };
    assert!(
        outcome.evaluated <= bricks_meeting,
        "{what}: evaluated {} bricks, the edit reaches {bricks_meeting}",
        outcome.evaluated
    );
    (after, outcome.version, outcome)
}

// ---------------------------------------------------------------------------------------------
// Random edits
// ---------------------------------------------------------------------------------------------

const BINARY_NAMES: [&str; 12] = [
    "union",
    "intersection",
    "trim",
    "cap",
    "difference",
    "difference_a",
    "difference_b",
    "add",
    "modulate",
    "product",
    "divide_a",
    "divide",
];

fn pos() -> impl Strategy<Value = [i64; 3]> + Clone {
    (-6i64..43, -6i64..35, -6i64..29).prop_map(|(x, y, z)| [x, y, z])
}

fn leaf() -> impl Strategy<Value = Term> {
    random_terms::leaf(pos(), 20)
}

fn small_term() -> impl Strategy<Value = Term> {
    leaf().prop_recursive(2, 6, 2, |inner| {
        prop_oneof![
            3 => (0u8..12, inner.clone(), inner.clone(), 1u32..=100)
                .prop_map(|(w, a, b, s)| random_terms::binary(w, a, b, f64::from(s) / 100.0)),
            1 => inner.clone().prop_map(|a| Term::Inverse(Box::new(a))),
            1 => (-200i32..200, inner).prop_map(|(k, a)| Term::AddScalar { k, arg: Box::new(a) }),
        ]
    })
}

fn region() -> impl Strategy<Value = Option<Box3>> {
    prop::option::of(
        (
            prop::array::uniform3(-5i64..36),
            prop::array::uniform3(1i64..30),
        )
            .prop_map(|(min, size)| Box3 {
                min,
                max: [0, 1, 2].map(|a| min[a] + size[a]),
            }),
    )
}

/// A random edit request for voxels with maximum `h`: one of the 12 binary operators with a
/// small term, or one of the 2 unary ones; optionally bounded by a region.
fn request(h: u16) -> impl Strategy<Value = EditRequest> {
    (
        0usize..14,
        small_term(),
        1u32..=100,
        -255i32..=255,
        region(),
    )
        .prop_map(move |(op, term, s_l, k, region)| {
            let scale = h as i32 / 255;
            match op {
                12 => EditRequest {
                    op: "inverse".into(),
                    term: None,
                    s_l: None,
                    k: None,
                    region,
                    message: None,
                    channel: None,
                    overwrite: None,
                },
                13 => EditRequest {
                    op: "add_scalar".into(),
                    term: None,
                    s_l: None,
                    k: Some(k * scale),
                    region,
                    message: None,
                    channel: None,
                    overwrite: None,
                },
                i => EditRequest {
                    op: BINARY_NAMES[i].into(),
                    term: Some(term),
                    s_l: (i == 11).then_some(s_l as f64 / 100.0),
                    k: None,
                    region,
                    message: None,
                    channel: None,
                    overwrite: None,
                },
            }
        })
}

fn random_edits(t: VoxelType, seed: u64, reqs: &[EditRequest]) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.vod2");
    let mut grid = initial(DIMS, t, seed);
    build(&path, &grid, t);
    let vod = Vod2::open(&path).unwrap();
    check_snapshot(&vod.head(), &grid, "as built");
    let mut history = vec![(vod.head().version, grid.clone())];
    drop(vod);
    for req in reqs {
        let (after, version, _) = edit_and_check(&path, &grid, req, CheckpointPolicy::default());
        grid = after;
        history.push((version, grid.clone()));
    }
    // Every older version still reads its own content.
    let vod = Vod2::open(&path).unwrap();
    for (version, level0) in &history {
        check_snapshot(
            &vod.version(*version).unwrap(),
            level0,
            &format!("version {version}"),
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn random_edits_u8(seed in any::<u64>(), reqs in prop::collection::vec(request(255), 4)) {
        random_edits(VoxelType::U8, seed, &reqs);
    }

    #[test]
    fn random_edits_u16(seed in any::<u64>(), reqs in prop::collection::vec(request(65535), 4)) {
        random_edits(VoxelType::U16, seed, &reqs);
    }
}

/// Every operator once, in sequence on one file, each with a term that covers part of the
/// volume (so every operator really runs over stored bricks, partial bricks included). The
/// second term's cuboid holds whole bricks of constant H ([0, 26) on every axis: level-0
/// bricks 0..=2 lie inside it), where the edit can decide bricks without touching voxels.
#[test]
fn every_operator_in_sequence() {
    let terms = [
        r#"{"union": [{"ellipsoid": {"center": [20, 14, 11], "radii": [9, 7, 6]}},
                      {"cuboid": {"origin": [28, 3, 12], "size": [12, 9, 14]}}]}"#,
        r#"{"cuboid": {"origin": [-2, -2, -2], "size": [30, 30, 30]}}"#,
    ];
    for (t, json) in [VoxelType::U8, VoxelType::U16]
        .into_iter()
        .flat_map(|t| terms.map(|j| (t, j)))
    {
        let term: Term = serde_json::from_str(json).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.vod2");
        let mut grid = initial(DIMS, t, 7);
        build(&path, &grid, t);
        let mut history = vec![(1u64, grid.clone())];
        let mut reqs: Vec<EditRequest> = BINARY_NAMES
            .iter()
            .map(|name| EditRequest {
                op: (*name).into(),
                term: Some(term.clone()),
                s_l: (*name == "divide").then_some(0.5),
                k: None,
                region: None,
                message: None,
                channel: None,
                overwrite: None,
            })
            .collect();
        reqs.push(EditRequest {
            op: "inverse".into(),
            term: None,
            s_l: None,
            k: None,
            region: Some(Box3 {
                min: [5, 5, 5],
                max: [30, 20, 17],
            }),
            message: None,
            channel: None,
            overwrite: None,
        });
        reqs.push(EditRequest {
            op: "add_scalar".into(),
            term: None,
            s_l: None,
            k: Some(-(t.high() as i32) / 3),
            region: None,
            message: None,
            channel: None,
            overwrite: None,
        });
        for req in reqs {
            let (after, version, _) =
                edit_and_check(&path, &grid, &req, CheckpointPolicy::default());
            grid = after;
            history.push((version, grid.clone()));
        }
        let vod = Vod2::open(&path).unwrap();
        assert_eq!(vod.head().version, 15, "1 build + 14 edits");
        for (version, level0) in &history {
            check_snapshot(
                &vod.version(*version).unwrap(),
                level0,
                &format!("{t} {json} version {version}"),
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Deduplication, skipped bricks, constant bricks, checkpoints
// ---------------------------------------------------------------------------------------------

fn difference_ellipsoid(center: [i64; 3], radius: u32) -> EditRequest {
    EditRequest {
        op: "difference".into(),
        term: Some(Term::Ellipsoid {
            center,
            radii: [radius; 3],
        }),
        s_l: None,
        k: None,
        region: None,
        message: None,
        channel: None,
        overwrite: None,
    }
}

/// A solid (all H) u8 volume of 128 x 16 x 16, brick 8: levels 0..=4 (brick spans 8, 16, 32, 64,
/// 128). Carving a sphere of radius 1 at (9, 9, 9) and then at (73, 9, 9) (64 = one level-3
/// brick further): every brick the second carve changes has the same content as one the first
/// carve made, so the second edit appends no record.
///
/// Hand computation of the carve (radius 1, u8; `difference(255, D2)`):
/// - centre: T = 0, H = 255: D2 >= S -> max(0, 0) = 0;
/// - 6 face neighbours: body(T - T^) = 0, body(T) = 1 -> D2 = 127 >= S -> 255 - 127 = 128;
/// - 12 edge neighbours: body 2 -> D2 = floor(63.5) = 63 < S -> max(192, 127) = 192;
/// - 8 corners: body 3 -> D2 = floor(42.3) = 42 -> max(213, 127) = 213.
///
/// Level 1 (2x2x2 groups {8,9}, {10,11} per axis; the carve covers 8..=10): the group holding
/// offsets {-1,0}³ loses 255 + 3*127 + 3*63 + 42 = 867: (2040 - 867 + 4) / 8 = 147; a group with
/// one axis at +1 loses 127 + 2*63 + 42 = 295: (1745 + 4) / 8 = 218; two axes at +1: 63 + 42 =
/// 105: (1935 + 4) / 8 = 242; three: 42: (1998 + 4) / 8 = 250.
/// Level 2 (one voxel over level-1 voxels 4..=5): (147 + 3*218 + 3*242 + 250 + 4) / 8 =
/// (1777 + 4) / 8 = 222. Level 3: (222 + 7*255 + 4) / 8 = 2011 / 8 = 251.
/// Level 4: (251 + 7*255 + 4) / 8 = 2040 / 8 = 255: unchanged, so the root is not rewritten.
#[test]
fn congruent_carves_deduplicate() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("solid.vod2");
    let t = VoxelType::U8;
    let dims = [128usize, 16, 16];
    let solid = Grid {
        dims,
        values: vec![255; dims.iter().product()],
    };
    let layout = build(&path, &solid, t);
    assert_eq!(layout.levels(), 5);

    let (after1, _, first) = edit_and_check(
        &path,
        &solid,
        &difference_ellipsoid([9, 9, 9], 1),
        CheckpointPolicy::default(),
    );
    // Changed: level-0 brick (1,1,1) ([8,16)³), then brick (0,0,0) of levels 1, 2, 3.
    assert_eq!(
        first.changed,
        vec![
            vec![[1, 1, 1]],
            vec![[0, 0, 0]],
            vec![[0, 0, 0]],
            vec![[0, 0, 0]],
            vec![]
        ]
    );
    assert_eq!(first.new_records, 4, "four bricks of new content");
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    let voxel = |level: u8, v: [u32; 3]| {
        let key = layout.key(level, v[0] / 8, v[1] / 8, v[2] / 8).unwrap();
        snap.read(key).unwrap()[(((v[2] % 8) * 8 + v[1] % 8) * 8 + v[0] % 8) as usize]
    };
    assert_eq!(voxel(0, [9, 9, 9]), 0);
    assert_eq!(voxel(0, [10, 9, 9]), 128);
    assert_eq!(voxel(0, [8, 10, 9]), 192);
    assert_eq!(voxel(0, [10, 10, 10]), 213);
    assert_eq!(voxel(0, [11, 9, 9]), 255);
    assert_eq!(voxel(1, [4, 4, 4]), 147);
    assert_eq!(voxel(1, [5, 4, 4]), 218);
    assert_eq!(voxel(1, [5, 5, 4]), 242);
    assert_eq!(voxel(1, [5, 5, 5]), 250);
    assert_eq!(voxel(2, [2, 2, 2]), 222);
    assert_eq!(voxel(3, [1, 1, 1]), 251);
    assert_eq!(voxel(4, [0, 0, 0]), 255);
    drop(snap);
    drop(vod);

    let (_, _, second) = edit_and_check(
        &path,
        &after1,
        &difference_ellipsoid([9 + 64, 9, 9], 1),
        CheckpointPolicy::default(),
    );
    assert_eq!(
        second.changed,
        vec![
            vec![[9, 1, 1]],
            vec![[4, 0, 0]],
            vec![[2, 0, 0]],
            vec![[1, 0, 0]],
            vec![]
        ]
    );
    assert_eq!(
        second.new_records, 0,
        "the second carve's bricks all exist already"
    );
}

/// A carve offset by one brick edge only (8): its level-0 brick deduplicates against the first
/// carve's, even though coarser levels differ.
#[test]
fn level0_brick_of_a_congruent_carve_deduplicates() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("solid.vod2");
    let t = VoxelType::U16;
    let dims = [40usize, 24, 24];
    let solid = Grid {
        dims,
        values: vec![65535; dims.iter().product()],
    };
    build(&path, &solid, t);
    let (after, _, first) = edit_and_check(
        &path,
        &solid,
        &difference_ellipsoid([11, 11, 12], 2),
        CheckpointPolicy::default(),
    );
    let (_, _, second) = edit_and_check(
        &path,
        &after,
        &difference_ellipsoid([11 + 16, 11, 12], 2),
        CheckpointPolicy::default(),
    );
    // Radius 2 around (11, 11, 12): voxels 9..=13 x 9..=13 x 10..=14, all in brick (1,1,1).
    assert_eq!(first.changed[0], vec![[1, 1, 1]]);
    assert_eq!(second.changed[0], vec![[3, 1, 1]]);
    // Level 1 (brick span 16): the carves sit at level-1 voxels 4..=6 of bricks 0 and 1, with
    // all-H surroundings: congruent too.
    assert_eq!(first.changed[1], vec![[0, 0, 0]]);
    assert_eq!(second.changed[1], vec![[1, 0, 0]]);
    // Coarser bricks hold both carves: new content. Level 0 and 1 are shared.
    let total: usize = second.changed.iter().map(Vec::len).sum();
    assert_eq!(
        second.new_records as usize,
        total - 2,
        "the level-0 and level-1 bricks are shared: {:?}",
        second.changed
    );
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    let l = snap.layout().clone();
    for (level, a, b) in [(0, [1, 1, 1], [3, 1, 1]), (1, [0, 0, 0], [1, 0, 0])] {
        let ea = snap.entry(l.key(level, a[0], a[1], a[2]).unwrap()).unwrap();
        let eb = snap.entry(l.key(level, b[0], b[1], b[2]).unwrap()).unwrap();
        assert_eq!(
            ea, eb,
            "level {level}: both carved bricks point at one record"
        );
    }
}

#[test]
fn term_outside_the_volume_changes_nothing() {
    for t in [VoxelType::U8, VoxelType::U16] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.vod2");
        let grid = initial(DIMS, t, 3);
        build(&path, &grid, t);
        let far = [[-40, 10, 10], [100, 10, 10], [10, -30, 10], [10, 10, 60]];
        let version = 1;
        for op in [
            "union",
            "difference",
            "difference_a",
            "difference_b",
            "add",
            "trim",
        ] {
            for center in far {
                let req = EditRequest {
                    op: op.into(),
                    term: Some(Term::Ellipsoid {
                        center,
                        radii: [6, 6, 6],
                    }),
                    s_l: None,
                    k: None,
                    region: None,
                    message: None,
                    channel: None,
                    overwrite: None,
                };
                let (after, v, out) =
                    edit_and_check(&path, &grid, &req, CheckpointPolicy::default());
                assert_eq!(after, grid, "reference unchanged");
                assert_eq!(out.evaluated, 0, "{op} at {center:?} evaluated bricks");
                assert!(
                    out.changed.iter().all(Vec::is_empty),
                    "{op}: {:?}",
                    out.changed
                );
                assert_eq!(out.new_records, 0);
                // Nothing to change, so nothing committed: the head stays at version 1 (an
                // empty version per such edit would only wake the change feed's followers).
                assert!(!out.committed, "{op} at {center:?} committed a version");
                assert_eq!(v, version);
            }
        }
        // A region wholly outside the volume: even constant-class and unary edits change
        // nothing.
        for (op, term) in [
            (
                "intersection",
                Some(Term::Ellipsoid {
                    center: [10, 10, 10],
                    radii: [3, 3, 3],
                }),
            ),
            (
                "divide_a",
                Some(Term::Ellipsoid {
                    center: [10, 10, 10],
                    radii: [3, 3, 3],
                }),
            ),
            ("inverse", None),
        ] {
            let req = EditRequest {
                op: op.into(),
                term,
                s_l: None,
                k: None,
                region: Some(Box3 {
                    min: [37, 0, 0],
                    max: [60, 29, 23],
                }),
                message: None,
                channel: None,
                overwrite: None,
            };
            let (after, v, out) = edit_and_check(&path, &grid, &req, CheckpointPolicy::default());
            assert_eq!(after, grid);
            assert_eq!(out.evaluated, 0, "{op} outside the volume");
            assert!(out.changed.iter().all(Vec::is_empty));
            assert!(
                !out.committed && v == version,
                "{op} outside the volume committed"
            );
        }
    }
}

/// An operator, its term, an optional region, and the level-0 bricks the edit may touch.
type BboxCase = (&'static str, Term, Option<Box3>, BTreeSet<[u32; 3]>);

#[test]
fn identity_edit_visits_only_bricks_in_the_bbox() {
    let t = VoxelType::U8;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.vod2");
    let mut grid = initial(DIMS, t, 11);
    build(&path, &grid, t);
    let cases: [BboxCase; 4] = [
        // Ellipsoid (20,10,12) radii (3,4,2): B-box [17,6,10]..[24,15,15): brick x 17/8 = 2 ..
        // 23/8 = 2, y 6/8 = 0 .. 14/8 = 1, z 10/8 = 1 .. 14/8 = 1: bricks (2,0,1), (2,1,1).
        (
            "union",
            Term::Ellipsoid {
                center: [20, 10, 12],
                radii: [3, 4, 2],
            },
            None,
            [[2, 0, 1], [2, 1, 1]].into(),
        ),
        // Ellipsoid (36,27,21) radius 5: B-box [31,22,16]..[42,33,27), within the volume
        // [31,22,16]..[37,29,23): bricks x 3..=4, y 2..=3, z 2.
        (
            "difference",
            Term::Ellipsoid {
                center: [36, 27, 21],
                radii: [5, 5, 5],
            },
            None,
            [[3, 2, 2], [4, 2, 2], [3, 3, 2], [4, 3, 2]].into(),
        ),
        // A cuboid over the whole volume, bounded by the region [0,0,0]..[8,8,8]: brick (0,0,0).
        (
            "add",
            Term::Cuboid {
                origin: [-5, -5, -5],
                size: [50, 40, 40],
            },
            Some(Box3 {
                min: [0, 0, 0],
                max: [8, 8, 8],
            }),
            [[0, 0, 0]].into(),
        ),
        // Cylinder base (9, 3, 30) radii (4, 4) height 10: B-box [5,3,26]..[14,13,35), within the
        // volume z < 23: empty -> no brick.
        (
            "trim",
            Term::Cylinder {
                base: [9, 3, 30],
                radii: [4, 4],
                height: 10,
            },
            None,
            BTreeSet::new(),
        ),
    ];
    for (op, term, region, allowed) in cases {
        let req = EditRequest {
            op: op.into(),
            term: Some(term),
            s_l: None,
            k: None,
            region,
            message: None,
            channel: None,
            overwrite: None,
        };
        let (after, _, out) = edit_and_check(&path, &grid, &req, CheckpointPolicy::default());
        assert!(
            out.evaluated <= allowed.len(),
            "{op}: evaluated {} bricks, the B-box meets {}",
            out.evaluated,
            allowed.len()
        );
        for b in &out.changed[0] {
            assert!(
                allowed.contains(b),
                "{op} changed brick {b:?} outside its B-box"
            );
        }
        grid = after;
    }
}

#[test]
fn intersection_makes_bricks_outside_the_bbox_constant_l() {
    for t in [VoxelType::U8, VoxelType::U16] {
        let dir = tempfile::tempdir().unwrap();
        let grid = initial(DIMS, t, 5);
        for op in ["intersection", "cap", "modulate", "product"] {
            let path = dir.path().join(format!("{op}.vod2"));
            let layout = build(&path, &grid, t);
            let req = EditRequest {
                op: op.into(),
                term: Some(Term::Ellipsoid {
                    center: [12, 12, 12],
                    radii: [5, 5, 5],
                }),
                s_l: None,
                k: None,
                region: None,
                message: None,
                channel: None,
                overwrite: None,
            };
            edit_and_check(&path, &grid, &req, CheckpointPolicy::default());
            // B-box [7,7,7]..[18,18,18): level-0 bricks 0..=2 on every axis meet it.
            let vod = Vod2::open(&path).unwrap();
            let snap = vod.head();
            let g = layout.grid(0);
            let mut outside = 0;
            for z in 0..g[2] {
                for y in 0..g[1] {
                    for x in 0..g[0] {
                        if x <= 2 && y <= 2 && z <= 2 {
                            continue;
                        }
                        outside += 1;
                        let key = layout.key(0, x, y, z).unwrap();
                        assert!(
                            matches!(snap.stored(key).unwrap(), StoredBrick::Constant(0)),
                            "{t} {op}: brick {x},{y},{z} outside the B-box is not the constant L"
                        );
                    }
                }
            }
            // 5 * 4 * 3 = 60 bricks, 27 meet the B-box.
            assert_eq!(outside, 60 - 27);
        }
    }
}

#[test]
fn checkpoint_every_commit() {
    let policy = CheckpointPolicy {
        max_overlay: 1,
        max_chain: 1,
    };
    for t in [VoxelType::U8, VoxelType::U16] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.vod2");
        let mut grid = initial(DIMS, t, 9);
        build(&path, &grid, t);
        let mut history = vec![(1u64, grid.clone())];
        let k = t.high() as i32 / 10;
        let reqs = [
            difference_ellipsoid([24, 16, 12], 6),
            EditRequest {
                op: "union".into(),
                term: Some(Term::Cuboid {
                    origin: [3, 12, 2],
                    size: [10, 10, 10],
                }),
                s_l: None,
                k: None,
                region: None,
                message: None,
                channel: None,
                overwrite: None,
            },
            EditRequest {
                op: "add_scalar".into(),
                term: None,
                s_l: None,
                k: Some(-k),
                region: Some(Box3 {
                    min: [0, 0, 0],
                    max: [20, 20, 20],
                }),
                message: None,
                channel: None,
                overwrite: None,
            },
            EditRequest {
                op: "inverse".into(),
                term: None,
                s_l: None,
                k: None,
                region: None,
                message: None,
                channel: None,
                overwrite: None,
            },
        ];
        for req in &reqs {
            let (after, version, out) = edit_and_check(&path, &grid, req, policy);
            assert!(
                out.checkpoint,
                "{t} {req:?}: max_chain 1 asks for a checkpoint"
            );
            grid = after;
            history.push((version, grid.clone()));
            // Reopened, the head builds on its own checkpoint.
            let vod = Vod2::open(&path).unwrap();
            assert_eq!(vod.head().chain_len(), 0);
            assert_eq!(vod.head().overlay_len(), 0);
        }
        let vod = Vod2::open(&path).unwrap();
        for (version, level0) in &history {
            check_snapshot(
                &vod.version(*version).unwrap(),
                level0,
                &format!("{t} version {version} (checkpointed)"),
            );
        }
        // The default policy, by contrast, writes a delta.
        let (_, _, out) = edit_and_check(
            &path,
            &grid,
            &difference_ellipsoid([10, 10, 10], 4),
            CheckpointPolicy::default(),
        );
        assert!(!out.checkpoint);
        let changed: usize = out.changed.iter().map(Vec::len).sum();
        let vod = Vod2::open(&path).unwrap();
        assert_eq!(vod.head().chain_len(), 1);
        assert_eq!(vod.head().overlay_len(), changed);
    }
}

/// A checkpoint written after deltas holds their changes too (the new checkpoint is the
/// previous one with the deltas' entries and the edit's own applied).
#[test]
fn checkpoint_after_deltas_keeps_their_changes() {
    let policy = CheckpointPolicy {
        max_overlay: 1 << 20,
        max_chain: 2,
    };
    let t = VoxelType::U8;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.vod2");
    let mut grid = initial(DIMS, t, 17);
    build(&path, &grid, t);
    let mut history = vec![(1u64, grid.clone())];
    let centers = [[24, 16, 12], [8, 20, 6], [16, 8, 17], [30, 6, 16]];
    let mut kinds = Vec::new();
    for c in centers {
        let (after, version, out) =
            edit_and_check(&path, &grid, &difference_ellipsoid(c, 5), policy);
        kinds.push(out.checkpoint);
        grid = after;
        history.push((version, grid.clone()));
    }
    // Two deltas, then the chain is full: the third edit checkpoints, the fourth is a delta.
    assert_eq!(kinds, [false, false, true, false]);
    let vod = Vod2::open(&path).unwrap();
    assert_eq!(vod.head().chain_len(), 1);
    for (version, level0) in &history {
        check_snapshot(
            &vod.version(*version).unwrap(),
            level0,
            &format!("version {version}"),
        );
    }
}

#[test]
fn overlay_limit_alone_triggers_a_checkpoint() {
    let t = VoxelType::U8;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.vod2");
    let grid = initial(DIMS, t, 13);
    build(&path, &grid, t);
    let policy = CheckpointPolicy {
        max_overlay: 3,
        max_chain: 1000,
    };
    // Inverse over the whole volume changes far more than 3 entries.
    let req = EditRequest {
        op: "inverse".into(),
        term: None,
        s_l: None,
        k: None,
        region: None,
        message: None,
        channel: None,
        overwrite: None,
    };
    let (after, _, out) = edit_and_check(&path, &grid, &req, policy);
    let changed: usize = out.changed.iter().map(Vec::len).sum();
    assert!(changed > 3);
    assert!(out.checkpoint);
    // A small edit (one level-0 brick, its ancestors: at most 4 entries) after the checkpoint:
    // 0 + changed <= 3 would be a delta; check whichever the count says.
    let (_, _, out) = edit_and_check(
        &path,
        &after,
        &difference_ellipsoid([12, 12, 12], 1),
        policy,
    );
    let changed: usize = out.changed.iter().map(Vec::len).sum();
    assert_eq!(out.checkpoint, changed > 3, "{changed} entries changed");
}

// ---------------------------------------------------------------------------------------------
// Stored volumes as operands
// ---------------------------------------------------------------------------------------------

/// Resolves volume names to the heads of real files.
#[derive(Debug)]
struct Files(Vec<(String, PathBuf)>);

impl VolumeResolver for Files {
    fn resolve(&self, name: &str) -> Result<Arc<Snapshot>, TermError> {
        let (_, path) = self
            .0
            .iter()
            .find(|(n, _)| n == name)
            .ok_or_else(|| TermError::Volume(format!("no volume {name:?}")))?;
        Ok(Vod2::open(path).unwrap().head())
    }
}

/// A stored volume placed in the world: its value at every voxel is the stored array's, L
/// outside; `eval` over boxes that straddle it equals that array; edits with it as the operand
/// equal the naive computation.
#[test]
fn stored_volume_operand() {
    for t in [VoxelType::U8, VoxelType::U16] {
        let dir = tempfile::tempdir().unwrap();
        // The operand: 13 x 9 x 11 of noise over half the range plus a solid core (brick 8, so
        // it spans 2 x 2 x 2 bricks with partial ones).
        let mut rng = XorShift(99);
        let bdims = [13usize, 9, 11];
        let mut values = Vec::new();
        for z in 0..bdims[2] {
            for y in 0..bdims[1] {
                for x in 0..bdims[0] {
                    let core = (3..10).contains(&x) && (2..7).contains(&y) && (3..8).contains(&z);
                    values.push(if core {
                        t.high()
                    } else {
                        (rng.next() % (t.high() as u64 / 2)) as u16
                    });
                }
            }
        }
        let boulder = Grid {
            dims: bdims,
            values,
        };
        let bpath = dir.path().join("boulder.vod2");
        build(&bpath, &boulder, t);
        let files = Files(vec![("boulder".into(), bpath)]);

        // eval over boxes equals the array (and sample).
        let origin = [5i64, -3, 7];
        let term = Term::Volume {
            name: "boulder".into(),
            origin,
            region: None,
        };
        let c = CompiledTerm::compile(&term, t, &TermLimits::default(), &files).unwrap();
        assert_eq!(
            c.bbox,
            Some(Box3::new(origin, [18, 6, 18])),
            "origin + dims (13, 9, 11)"
        );
        for b in [
            Box3::new([0, -5, 0], [25, 10, 25]),
            Box3::new([9, 0, 10], [14, 4, 16]),
            Box3::new([16, 4, 16], [20, 8, 20]),
            Box3::new([-10, -10, -10], [0, 0, 0]),
        ] {
            let mut out = vec![0u16; b.voxels() as usize];
            c.eval(&b, &mut out).unwrap();
            let mut i = 0;
            for z in b.min[2]..b.max[2] {
                for y in b.min[1]..b.max[1] {
                    for x in b.min[0]..b.max[0] {
                        let l = [x - origin[0], y - origin[1], z - origin[2]];
                        let want = if (0..3).all(|a| l[a] >= 0 && (l[a] as usize) < bdims[a]) {
                            boulder.at(l[0] as usize, l[1] as usize, l[2] as usize)
                        } else {
                            0
                        };
                        assert_eq!(out[i], want, "{t} eval at ({x},{y},{z})");
                        assert_eq!(c.sample([x, y, z]), want, "{t} sample at ({x},{y},{z})");
                        i += 1;
                    }
                }
            }
        }

        // A region of the volume: its min corner lands on `origin`, nothing outside it shows.
        let (rmin, rmax) = ([2i64, 1, 3], [10i64, 7, 9]);
        let part = Term::Volume {
            name: "boulder".into(),
            origin,
            region: Some(Box3 {
                min: rmin,
                max: rmax,
            }),
        };
        let c = CompiledTerm::compile(&part, t, &TermLimits::default(), &files).unwrap();
        assert_eq!(
            c.bbox,
            Some(Box3::new(origin, [13, 3, 13])),
            "origin + region size (8, 6, 6)"
        );
        let b = Box3::new([3, -5, 5], [16, 5, 16]);
        let mut out = vec![0u16; b.voxels() as usize];
        c.eval(&b, &mut out).unwrap();
        let mut i = 0;
        for z in b.min[2]..b.max[2] {
            for y in b.min[1]..b.max[1] {
                for x in b.min[0]..b.max[0] {
                    let s = [
                        x - origin[0] + rmin[0],
                        y - origin[1] + rmin[1],
                        z - origin[2] + rmin[2],
                    ];
                    let want = if (0..3).all(|a| s[a] >= rmin[a] && s[a] < rmax[a]) {
                        boulder.at(s[0] as usize, s[1] as usize, s[2] as usize)
                    } else {
                        0
                    };
                    assert_eq!(out[i], want, "{t} region eval at ({x},{y},{z})");
                    assert_eq!(
                        c.sample([x, y, z]),
                        want,
                        "{t} region sample at ({x},{y},{z})"
                    );
                    i += 1;
                }
            }
        }
        let outside = Term::Volume {
            name: "boulder".into(),
            origin,
            region: Some(Box3 {
                min: [0, 0, 0],
                max: [14, 1, 1],
            }),
        };
        assert!(
            CompiledTerm::compile(&outside, t, &TermLimits::default(), &files).is_err(),
            "a region beyond the volume is refused"
        );

        // Edits: union at one place, a difference partly outside the volume, a product in a
        // region.
        let path = dir.path().join("v.vod2");
        let mut grid = initial(DIMS, t, 21);
        build(&path, &grid, t);
        for (op, origin, region) in [
            ("union", [5, 10, 7], None),
            ("difference", [30, 22, 15], None),
            (
                "product",
                [10, 8, 4],
                Some(Box3 {
                    min: [8, 6, 2],
                    max: [26, 20, 15],
                }),
            ),
        ] {
            let req = EditRequest {
                op: op.into(),
                term: Some(Term::Volume {
                    name: "boulder".into(),
                    origin,
                    region: None,
                }),
                s_l: None,
                k: None,
                region,
                message: None,
                channel: None,
                overwrite: None,
            };
            let (after, _, _) =
                edit_and_check_with(&path, &grid, &req, CheckpointPolicy::default(), &files);
            assert_ne!(after, grid, "{op} changed something");
            grid = after;
        }
        // A volume of the other voxel type is refused.
        let other = if t == VoxelType::U8 {
            VoxelType::U16
        } else {
            VoxelType::U8
        };
        let e = CompiledTerm::compile(&term, other, &TermLimits::default(), &files).unwrap_err();
        assert!(e.to_string().contains("boulder"), "{e}");
    }
}
