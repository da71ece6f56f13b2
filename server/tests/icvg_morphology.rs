//! Morphology terms (`dilate`, `erode`): golden values by reasoning, the fast path against the
//! voxel-by-voxel reference, and an edit that dilates a stored volume against a naive dilation.
//!
//! Golden rule used below: a cuboid is three nested boxes (L padding, S surface, H core), and the
//! maximum of nested boxes over a cube window of radius r is the same boxes grown by r; the
//! minimum is them shrunk by r. So dilate(cuboid(o, s), r) = cuboid(o - r, s + 2r) and
//! erode(cuboid(o, s), r) = cuboid(o + r, s - 2r), voxel for voxel.

#![allow(clippy::unwrap_used)]

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::{VolumeLayout, VoxelType};
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

#[test]
fn fast_path_equals_the_reference_on_curved_and_composite_terms() {
    let ellipsoid = Term::Ellipsoid {
        center: [10, 12, 9],
        radii: [7, 5, 6],
    };
    let composite = Term::Difference(
        Box::new(cuboid([0, 0, 0], [22, 20, 18])),
        Box::new(ellipsoid.clone()),
    );
    for arg in [ellipsoid, composite] {
        for r in 1..=3 {
            for dilate in [true, false] {
                let term = if dilate {
                    Term::Dilate {
                        radius: r,
                        arg: Box::new(arg.clone()),
                    }
                } else {
                    Term::Erode {
                        radius: r,
                        arg: Box::new(arg.clone()),
                    }
                };
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

/// Dilating a stored volume in place: union(volume, dilate(volume)) is the dilation, since the
/// maximum over a window holds the centre. Checked against a naive dilation of the array.
#[test]
fn an_edit_dilates_a_stored_volume() {
    let dims = [40usize, 24, 36];
    let mut level0 = vec![0u8; dims[0] * dims[1] * dims[2]];
    let mut seed = 0x9e37_79b9_u64;
    for v in level0.iter_mut() {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        // Sparse specks of varied values.
        *v = if seed.is_multiple_of(23) {
            (seed >> 8) as u8
        } else {
            0
        };
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.vod");
    let d32 = dims.map(|d| d as u32);
    let layout = VolumeLayout::new(d32, 8, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &DenseGrid::new(d32, VoxelType::U8, 8, &level0),
        &BuildOptions::default(),
    )
    .unwrap();
    let snap = Vod2::open(&path).unwrap().head();
    let r = 2i64;
    let request: EditRequest = serde_json::from_str(
        r#"{"op": "union", "term": {"dilate": {"radius": 2, "arg": {"volume": {"name": "v", "origin": [0, 0, 0]}}}}}"#,
    )
    .unwrap();
    let edit = Edit::from_request(
        &request,
        VoxelType::U8,
        &TermLimits::default(),
        &One(snap.clone()),
    )
    .unwrap();
    let mut writer = Vod2Writer::open_append(&path, Compression::default()).unwrap();
    apply_edit(&mut writer, &snap, &edit, CheckpointPolicy::default()).unwrap();
    let after = Vod2::open(&path).unwrap().head();
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
        isovox_server::store::raw::Region {
            min: [0; 3],
            max: d32,
        },
        &mut out,
        &isovox_server::progress::Silent,
    )
    .unwrap();
    for z in 0..dims[2] as i64 {
        for y in 0..dims[1] as i64 {
            for x in 0..dims[0] as i64 {
                let mut m = 0u8;
                for dz in -r..=r {
                    for dy in -r..=r {
                        for dx in -r..=r {
                            m = m.max(at(x + dx, y + dy, z + dz));
                        }
                    }
                }
                let got = out[(z as usize * dims[1] + y as usize) * dims[0] + x as usize];
                assert_eq!(got, m, "voxel ({x}, {y}, {z})");
            }
        }
    }
}
