//! Morphology terms (`dilate`, `erode`): golden values by reasoning, the fast path against the
//! voxel-by-voxel reference, and an edit that dilates a stored volume against a naive dilation.
//!
//! Golden rule used below: a cuboid is three nested boxes (L padding, S surface, H core), and the
//! maximum of nested boxes over a cube window of radius r is the same boxes grown by r; the
//! minimum is them shrunk by r. So dilate(cuboid(o, s), r) = cuboid(o - r, s + 2r) and
//! erode(cuboid(o, s), r) = cuboid(o + r, s - 2r), voxel for voxel.

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::cancel::CancelToken;
use isovox_server::geometry::Box3;
use isovox_server::icvg::edit::{apply_edit, Edit};
use isovox_server::icvg::term::{CompiledTerm, NoVolumes, TermError, TermLimits, VolumeResolver};
use isovox_server::store::codec::Compression;
use isovox_server::store::CheckpointPolicy;
use isovox_server::store::{build_vod2, BuildOptions, DenseGrid, Snapshot, Vod2, Vod2Writer};
use std::sync::Arc;

fn compile(term: &Term) -> CompiledTerm {
    CompiledTerm::compile(term, VoxelType::U8, &TermLimits::default(), &NoVolumes).unwrap()
}

fn cuboid(origin: [i64; 3], size: [u32; 3]) -> Term {
    Term::Cuboid { origin, size }
}

fn values(t: &CompiledTerm, b: &Box3) -> Vec<u16> {
    let mut out = vec![0u16; b.voxels() as usize];
    t.eval(b, &mut out).unwrap();
    out
}

fn samples(t: &CompiledTerm, b: &Box3) -> Vec<u16> {
    let mut out = Vec::new();
    for z in b.min[2]..b.max[2] {
        for y in b.min[1]..b.max[1] {
            for x in b.min[0]..b.max[0] {
                out.push(t.sample([x, y, z]));
            }
        }
    }
    out
}

#[test]
fn dilated_and_eroded_cuboids_are_grown_and_shrunk_cuboids() {
    let frame = Box3::new([-12, -12, -12], [40, 36, 44]);
    for (origin, size, r) in [
        ([3, 4, 5], [10, 12, 9], 1u32),
        ([0, -3, 7], [14, 9, 20], 2),
        ([5, 5, 5], [16, 16, 16], 3),
    ] {
        let dilated = compile(&Term::Dilate {
            radius: r,
            arg: Box::new(cuboid(origin, size)),
        });
        let r64 = r as i64;
        let grown = compile(&cuboid(origin.map(|c| c - r64), size.map(|s| s + 2 * r)));
        assert_eq!(
            values(&dilated, &frame),
            values(&grown, &frame),
            "dilate {origin:?} {size:?} {r}"
        );
        assert_eq!(samples(&dilated, &frame), values(&grown, &frame));
        let eroded = compile(&Term::Erode {
            radius: r,
            arg: Box::new(cuboid(origin, size)),
        });
        let shrunk = compile(&cuboid(origin.map(|c| c + r64), size.map(|s| s - 2 * r)));
        assert_eq!(
            values(&eroded, &frame),
            values(&shrunk, &frame),
            "erode {origin:?} {size:?} {r}"
        );
        assert_eq!(samples(&eroded, &frame), values(&shrunk, &frame));
    }
}

/// An ellipsoid, and a cuboid with it carved out.
fn curved_and_composite() -> [Term; 2] {
    let ellipsoid = Term::Ellipsoid {
        center: [10, 12, 9],
        radii: [7, 5, 6],
    };
    let composite = Term::Difference(
        Box::new(cuboid([0, 0, 0], [22, 20, 18])),
        Box::new(ellipsoid.clone()),
    );
    [ellipsoid, composite]
}

fn morphology(dilate: bool, radius: u32, arg: &Term) -> Term {
    let arg = Box::new(arg.clone());
    if dilate {
        Term::Dilate { radius, arg }
    } else {
        Term::Erode { radius, arg }
    }
}

#[test]
fn fast_path_equals_the_reference_on_curved_and_composite_terms() {
    for arg in curved_and_composite() {
        for r in 1..=3 {
            for dilate in [true, false] {
                let term = morphology(dilate, r, &arg);
                let t = compile(&term);
                // Boxes that cut through the surface, the inside and the outside.
                for b in [
                    Box3::new([-4, -4, -4], [26, 24, 22]),
                    Box3::new([3, 5, 2], [11, 9, 17]),
                    Box3::new([15, -2, 8], [20, 30, 9]),
                ] {
                    assert_eq!(values(&t, &b), samples(&t, &b), "{term:?} over {b:?}");
                }
            }
        }
    }
}

#[test]
fn morphology_arguments_are_validated() {
    let err = CompiledTerm::compile(
        &Term::Dilate {
            radius: 0,
            arg: Box::new(cuboid([0; 3], [5; 3])),
        },
        VoxelType::U8,
        &TermLimits::default(),
        &NoVolumes,
    )
    .unwrap_err();
    assert!(err.to_string().contains("radius"), "{err}");
    let json =
        r#"{"dilate": {"radius": 2, "arg": {"cuboid": {"origin": [0, 0, 0], "size": [5, 5, 5]}}}}"#;
    let term: Term = serde_json::from_str(json).unwrap();
    assert!(matches!(term, Term::Dilate { radius: 2, .. }));
}

struct One(Arc<Snapshot>);

impl VolumeResolver for One {
    fn resolve(&self, _: &str) -> Result<Arc<Snapshot>, TermError> {
        Ok(self.0.clone())
    }
}

/// A volume of `dims` (brick 8) whose voxels are drawn by `value` from a deterministic noise.
fn noise_volume(dir: &std::path::Path, dims: [usize; 3], value: impl Fn(u64) -> u8) -> Vec<u8> {
    let mut level0 = vec![0u8; dims[0] * dims[1] * dims[2]];
    let mut seed = 0x9e37_79b9_u64;
    for v in level0.iter_mut() {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        *v = value(seed);
    }
    let d32 = dims.map(|d| d as u32);
    let layout = VolumeLayout::new(d32, 8, VoxelType::U8).unwrap();
    build_vod2(
        &dir.join("v.vod"),
        &layout,
        [1.0; 3],
        &DenseGrid::new(d32, VoxelType::U8, 8, &level0),
        &BuildOptions::default(),
    )
    .unwrap();
    level0
}

/// Dilates (`union` with `dilate`) or erodes (`intersection` with `erode`) the stored volume in
/// place, through `Edit::for_volume` as a server does, and checks every voxel against a naive
/// maximum or minimum over the window of the original array (L outside the volume). The
/// maximum over a window holds the centre, so the union is the dilation; the minimum likewise
/// makes the intersection the erosion.
fn morph_edit_matches_naive(dims: [usize; 3], r: i64, dilate: bool, value: impl Fn(u64) -> u8) {
    let dir = tempfile::tempdir().unwrap();
    let level0 = noise_volume(dir.path(), dims, value);
    let path = dir.path().join("v.vod");
    let snap = Vod2::open(&path).unwrap().head();
    let (op, filter) = if dilate {
        ("union", "dilate")
    } else {
        ("intersection", "erode")
    };
    let request: EditRequest = serde_json::from_str(&format!(
        r#"{{"op": "{op}", "term": {{"{filter}": {{"radius": {r}, "arg": {{"volume": {{"name": "v", "origin": [0, 0, 0]}}}}}}}}}}"#
    ))
    .unwrap();
    let never = CancelToken::never();
    let mut edit = Edit::for_volume(
        &request,
        snap.header(),
        &TermLimits::default(),
        &One(snap.clone()),
        Some(1 << 28),
        &never,
    )
    .unwrap();
    let mut writer = Vod2Writer::open_append(&path, Compression::default()).unwrap();
    apply_edit(
        &mut writer,
        &snap,
        &mut edit,
        CheckpointPolicy::default(),
        &never,
    )
    .unwrap();
    let after = Vod2::open(&path).unwrap().head();
    let d32 = dims.map(|d| d as u32);
    let at = |x: i64, y: i64, z: i64| -> u8 {
        if x < 0
            || y < 0
            || z < 0
            || x >= dims[0] as i64
            || y >= dims[1] as i64
            || z >= dims[2] as i64
        {
            0
        } else {
            level0[(z as usize * dims[1] + y as usize) * dims[0] + x as usize]
        }
    };
    let mut out = Vec::new();
    isovox_server::store::raw::export_raw(
        &after,
        0,
        isovox_server::geometry::Box3::new([0; 3], d32.map(i64::from)),
        &mut out,
        &isovox_server::progress::Silent,
    )
    .unwrap();
    let mut nonzero = 0;
    for z in 0..dims[2] as i64 {
        for y in 0..dims[1] as i64 {
            for x in 0..dims[0] as i64 {
                let mut m = if dilate { 0u8 } else { 255 };
                for dz in -r..=r {
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let v = at(x + dx, y + dy, z + dz);
                            m = if dilate { m.max(v) } else { m.min(v) };
                        }
                    }
                }
                let got = out[(z as usize * dims[1] + y as usize) * dims[0] + x as usize];
                assert_eq!(got, m, "{filter} {r}: voxel ({x}, {y}, {z})");
                nonzero += usize::from(m != 0);
            }
        }
    }
    // The case says something: neither all L nor (for dilation) all one value.
    assert!(nonzero > 0, "{filter} {r}: everything is L");
}

/// Sparse specks of varied values: dilation spreads each over its window.
fn specks(seed: u64) -> u8 {
    if seed.is_multiple_of(23) {
        (seed >> 8) as u8
    } else {
        0
    }
}

/// Dense values in 1..=255: erosion keeps the window's minimum, L within `r` of the faces.
fn dense(seed: u64) -> u8 {
    1 + ((seed >> 8) % 255) as u8
}

#[test]
fn an_edit_dilates_a_stored_volume() {
    morph_edit_matches_naive([40, 24, 36], 2, true, specks);
}

#[test]
fn an_edit_dilates_and_erodes_with_windows_wider_than_bricks_and_volume() {
    // Brick 8: radius 7 and 13 windows span two and four bricks; on a 26 x 18 x 22 volume the
    // radius-13 window also reaches past every face.
    for r in [7, 13] {
        morph_edit_matches_naive([26, 18, 22], r, true, specks);
    }
    morph_edit_matches_naive([34, 18, 30], 7, false, dense);
}

/// The filter's values against the brute-force maximum or minimum over each window of the
/// argument's samples (the voxel-by-voxel reference of each primitive).
#[test]
fn large_radii_equal_the_brute_force_filter() {
    for arg in curved_and_composite() {
        let a = compile(&arg);
        for (r, b) in [
            // Across the argument's B-box faces, and beyond them.
            (5u32, Box3::new([-9, 6, 3], [8, 14, 9])),
            (9, Box3::new([12, -12, 5], [20, 4, 11])),
            (9, Box3::new([-20, -20, -20], [-14, -14, -14])),
        ] {
            for dilate in [true, false] {
                let term = morphology(dilate, r, &arg);
                let grown = b.grow(r as i64);
                let field = samples(&a, &grown);
                let n = [0, 1, 2].map(|i| (grown.max[i] - grown.min[i]) as usize);
                let ri = r as usize;
                let mut want = Vec::new();
                for z in 0..(b.max[2] - b.min[2]) as usize {
                    for y in 0..(b.max[1] - b.min[1]) as usize {
                        for x in 0..(b.max[0] - b.min[0]) as usize {
                            let mut m = if dilate { 0u16 } else { 255 };
                            for wz in z..=z + 2 * ri {
                                for wy in y..=y + 2 * ri {
                                    for wx in x..=x + 2 * ri {
                                        let v = field[(wz * n[1] + wy) * n[0] + wx];
                                        m = if dilate { m.max(v) } else { m.min(v) };
                                    }
                                }
                            }
                            want.push(m);
                        }
                    }
                }
                assert_eq!(values(&compile(&term), &b), want, "{term:?} over {b:?}");
            }
        }
    }
}

#[test]
fn what_morphology_samples_is_counted_against_the_budget_before_it_runs() {
    let sphere = Term::Ellipsoid {
        center: [128, 128, 128],
        radii: [10, 10, 10],
    };
    let within = Box3::new([0; 3], [256; 3]);
    let scope = |max_voxels| isovox_server::icvg::term::Scope {
        within: Some(within),
        max_voxels,
        cancel: CancelToken::never(),
    };
    let compile_in = |term: &Term, max| {
        CompiledTerm::compile_in(
            term,
            VoxelType::U8,
            &TermLimits::default(),
            &NoVolumes,
            &scope(max),
        )
    };
    // Dilating a bounded argument reads it only over its B-box (the sphere's 21^3 voxels) and
    // keeps a 256^2 plane for each of its 21 layers for the last pass.
    let dilated = Term::Dilate {
        radius: 200,
        arg: Box::new(sphere.clone()),
    };
    let (_, sampled) = compile_in(&dilated, Some(1 << 28)).unwrap();
    assert_eq!(sampled, 21 * 21 * 21 + 256 * 256 * 21);
    // An unbounded argument (the inverse is H far away) is read over the whole volume grown by
    // 200 (656^3 voxels, and 656 planes of 256^2): over a budget of 2^28.
    let unbounded = Term::Dilate {
        radius: 200,
        arg: Box::new(Term::Inverse(Box::new(sphere.clone()))),
    };
    let heavy = 656 * 656 * 656 + 256 * 256 * 656;
    assert_eq!(compile_in(&unbounded, None).unwrap().1, heavy);
    match compile_in(&unbounded, Some(1 << 28)) {
        Err(TermError::OverBudget { voxels, limit, .. }) => {
            assert_eq!((voxels, limit), (heavy, 1 << 28));
        }
        other => panic!("expected OverBudget, got {other:?}"),
    }
    // Erosion is L wherever its window leaves the argument's B-box: it reaches no voxel when
    // the radius exceeds the sphere's, and samples nothing.
    let eroded = Term::Erode {
        radius: 11,
        arg: Box::new(sphere),
    };
    let (term, sampled) = compile_in(&eroded, Some(1 << 28)).unwrap();
    assert_eq!(sampled, 0);
    assert_eq!(term.constant_over(&within), Some(0));
}
