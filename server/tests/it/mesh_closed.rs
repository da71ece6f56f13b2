//! Closed surfaces: each ICVG primitive, and a carved compound, unioned into an empty volume and
//! meshed tile by tile, welds into a watertight, 2-manifold mesh whose enclosed volume is close to
//! the analytic one; vertices on shared tile faces are bit-identical from both sides.

use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::cancel::CancelToken;
use isovox_server::icvg::edit::{apply_edit, Edit};
use isovox_server::icvg::term::{NoVolumes, TermLimits};
use isovox_server::mesh::check::{enclosed_volume, open_edges};
use isovox_server::mesh::level::{level_tiles, mesh_tiles, weld};
use isovox_server::mesh::tile::default_iso;
use isovox_server::store::codec::Compression;
use isovox_server::store::CheckpointPolicy;
use isovox_server::store::{build_vod2, BuildOptions, DenseGrid, Vod2, Vod2Writer};
use std::f64::consts::PI;

/// An empty volume of `dims` with the edits applied in turn.
fn volume_with(
    dims: [u32; 3],
    brick: u32,
    t: VoxelType,
    edits: &[(&str, Term)],
) -> (tempfile::TempDir, Vod2) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.vod");
    let layout = VolumeLayout::new(dims, brick, t).unwrap();
    let zeros = vec![0u8; layout.raw_bytes() as usize];
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &DenseGrid::new(dims, t, brick, &zeros),
        &BuildOptions::default(),
    )
    .unwrap();
    for (op, term) in edits {
        let vod = Vod2::open(&path).unwrap();
        let req = EditRequest {
            op: op.to_string(),
            term: Some(term.clone()),
            s_l: None,
            k: None,
            region: None,
            message: None,
            channel: None,
            overwrite: None,
        };
        let mut edit = Edit::from_request(&req, t, &TermLimits::default(), &NoVolumes).unwrap();
        let mut w = Vod2Writer::open_append(&path, Compression::Zstd(3)).unwrap();
        let never = CancelToken::never();
        apply_edit(
            &mut w,
            &vod.head(),
            &mut edit,
            CheckpointPolicy::default(),
            &never,
        )
        .unwrap();
    }
    let vod = Vod2::open(&path).unwrap();
    (dir, vod)
}

fn check_closed(name: &str, vod: &Vod2, analytic: f64, tolerance: f64) {
    let snap = vod.head();
    let t = snap.layout().voxel_type();
    let raw = mesh_tiles(
        &snap,
        &level_tiles(&snap, 0),
        default_iso(t),
        &isovox_server::progress::Silent,
    )
    .unwrap();
    assert!(
        raw.triangles() > 100,
        "{name}: {} triangles",
        raw.triangles()
    );
    let mesh = weld(&raw);
    assert_eq!(
        open_edges(&mesh),
        0,
        "{name}: the welded mesh has open or non-manifold edges"
    );
    let v = enclosed_volume(&mesh);
    let err = (v - analytic).abs() / analytic;
    assert!(
        err < tolerance,
        "{name}: enclosed {v:.0}, analytic {analytic:.0}, error {:.2}%",
        err * 100.0
    );
}

#[test]
fn every_primitive_meshes_closed_with_the_right_volume() {
    let t = VoxelType::U8;
    let r = 12.0;
    let cases: Vec<(&str, Term, f64)> = vec![
        (
            "ellipsoid",
            Term::Ellipsoid {
                center: [24, 24, 24],
                radii: [12, 12, 12],
            },
            4.0 / 3.0 * PI * r * r * r,
        ),
        (
            "flat ellipsoid",
            Term::Ellipsoid {
                center: [24, 24, 24],
                radii: [16, 9, 12],
            },
            4.0 / 3.0 * PI * 16.0 * 9.0 * 12.0,
        ),
        // Flat faces: between the L layer (0) and the S layer (127) iso 126.5 sits at
        // t = 126.5 / 127 = 0.996, so the surface is (almost) on the S layers, local 1 and
        // size - 2: an extent of size - 3 per axis.
        (
            "cuboid",
            Term::Cuboid {
                origin: [4, 5, 6],
                size: [30, 20, 25],
            },
            27.0 * 17.0 * 22.0,
        ),
        (
            "cylinder",
            Term::Cylinder {
                base: [24, 4, 24],
                radii: [12, 12],
                height: 30,
            },
            PI * r * r * 27.0,
        ),
        // From the S layer at Vy = 1 (radius r (1 - 1/29)) to the apex at Vy = 29: height 28.
        (
            "cone",
            Term::Cone {
                base: [24, 4, 24],
                radii: [12, 12],
                height: 30,
            },
            PI * (r * 28.0 / 29.0).powi(2) * 28.0 / 3.0,
        ),
        (
            "torus",
            Term::Torus {
                center: [24, 24, 24],
                major: 14,
                minor: 6,
            },
            2.0 * PI * PI * 14.0 * 36.0,
        ),
        (
            "capsule",
            Term::Capsule {
                center: [24, 24, 24],
                radius: 10,
                length: 16,
            },
            PI * 100.0 * 16.0 + 4.0 / 3.0 * PI * 1000.0,
        ),
        // Legs and depth between the S layers: size - 3.
        (
            "prism",
            Term::Prism {
                origin: [4, 4, 4],
                size: [32, 30, 20],
            },
            0.5 * 29.0 * 27.0 * 17.0,
        ),
        (
            "pyramid",
            Term::Pyramid {
                origin: [4, 4, 4],
                size: [33, 30, 33],
            },
            30.0 * 30.0 * 27.0 / 3.0,
        ),
    ];
    for (name, term, analytic) in cases {
        let (_dir, vod) = volume_with([48, 48, 48], 8, t, &[("union", term)]);
        check_closed(name, &vod, analytic, 0.06);
    }
}

#[test]
fn carved_compound_is_closed() {
    // A cuboid minus an ellipsoid that breaks through one face: a closed cup.
    let cuboid = Term::Cuboid {
        origin: [4, 4, 4],
        size: [40, 40, 40],
    };
    let hole = Term::Ellipsoid {
        center: [24, 42, 24],
        radii: [12, 12, 12],
    };
    let (_dir, vod) = volume_with(
        [48, 48, 48],
        16,
        VoxelType::U16,
        &[("union", cuboid), ("difference", hole)],
    );
    // Cube of 38^3 (between the S layers, the surface half a voxel beyond), minus the part of
    // the ball inside it: the ball's centre is 42 - 24 = ... checked only for closedness and a
    // positive volume smaller than the cube.
    let snap = vod.head();
    let raw = mesh_tiles(
        &snap,
        &level_tiles(&snap, 0),
        default_iso(VoxelType::U16),
        &isovox_server::progress::Silent,
    )
    .unwrap();
    let mesh = weld(&raw);
    assert_eq!(open_edges(&mesh), 0);
    let v = enclosed_volume(&mesh);
    assert!(v > 38.0f64.powi(3) * 0.8 && v < 39.0f64.powi(3), "{v}");
}
