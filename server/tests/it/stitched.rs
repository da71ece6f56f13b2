//! Crack-free meshes across levels, on real files through the real tile pipeline: every ICVG
//! primitive, an ellipsoid, the demo world and an MRI-like scan are meshed tile by tile with
//! their moves (`mesh_tile_with_moves`) and the transition strips their masks need (`mesh_strip_world`), selected for many random cameras and
//! radii (`balanced_tiles`, levels 0-3 mixed), stitched with `face_masks` and `stitch`, welded,
//! and checked: closed and 2-manifold (every edge in exactly two triangles, once each way), no
//! triangle without area, no transition triangle crossing another triangle; and the enclosed
//! volume of a stitched ball within 3% of the analytic one at every level mix.

use crate::common::XorShift;
use isovox_proto::icvg::{EditRequest, Term};
use isovox_proto::lod::face_masks;
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::cancel::CancelToken;
use isovox_server::generate::{build_demo, EllipsoidSource};
use isovox_server::icvg::edit::{apply_edit, Edit};
use isovox_server::icvg::term::{NoVolumes, TermLimits};
use isovox_server::mesh::check::{
    crossing_triangles, degenerate_triangles, enclosed_volume, open_edges,
};
use isovox_server::mesh::level::{balanced_tiles, mesh_stitchable_parts, weld_flagged};
use isovox_server::mesh::mc::Mesh;
use isovox_server::mesh::tile::{default_iso, mesh_strip_world, mesh_tile_with_moves, TileScratch};
use isovox_server::progress::Silent;
use isovox_server::store::codec::Compression;
use isovox_server::store::{
    build_vod2, BuildOptions, CheckpointPolicy, DenseGrid, Snapshot, Vod2, Vod2Writer,
};
use std::f64::consts::PI;
use std::path::Path;

/// Uniform numbers in [0, 1) from the tests' one generator, seeded.
fn rng(seed: u64) -> impl FnMut() -> f64 {
    let mut rng = XorShift(seed | 1);
    move || rng.unit()
}

/// Random cameras in and around a volume of `dims` (world units), with radii for levels 0, 1
/// and 2 (level 3 beyond).
fn cameras(dims: [f64; 3], n: usize, seed: u64) -> Vec<([f32; 3], Vec<f32>)> {
    let mut next = rng(seed);
    let side = dims.iter().copied().fold(0.0, f64::max);
    (0..n)
        .map(|_| {
            let camera = [0, 1, 2].map(|a| ((next() * 1.4 - 0.2) * dims[a]) as f32);
            let r0 = (4.0 + next() * side * 0.3) as f32;
            let r1 = r0 * (1.2 + next() as f32 * 1.5);
            let r2 = r1 * (1.2 + next() as f32 * 1.5);
            (camera, vec![r0, r1, r2])
        })
        .collect()
}

/// A few open edges of `mesh`, as positions, for a failure's message.
fn first_open_edges(mesh: &Mesh) -> Vec<([f32; 3], [f32; 3])> {
    let mut count = std::collections::HashMap::new();
    for t in mesh.indices.chunks_exact(3) {
        for k in 0..3 {
            *count.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
        }
    }
    let mut open: Vec<([f32; 3], [f32; 3])> = count
        .iter()
        .filter(|(&(a, b), &n)| n != 1 || count.get(&(b, a)) != Some(&1))
        .map(|(&(a, b), _)| (mesh.positions[a as usize], mesh.positions[b as usize]))
        .collect();
    open.sort_by(|x, y| x.0.partial_cmp(&y.0).unwrap_or(std::cmp::Ordering::Equal));
    open.truncate(8);
    open
}

/// What one stitched selection shows.
struct Stitched {
    levels: [usize; 8],
    triangles: usize,
    transition_triangles: usize,
    crossing: usize,
    volume: f64,
}

/// Meshes, stitches and welds the balanced selection for `camera` and `radii`, and checks it
/// is closed, 2-manifold and without degenerate triangles.
fn stitched(snap: &Snapshot, camera: [f32; 3], radii: &[f32], what: &str) -> Stitched {
    let iso = default_iso(snap.layout().voxel_type());
    let tiles = balanced_tiles(snap, camera, radii);
    let parts = mesh_stitchable_parts(snap, &tiles, iso, &Silent).unwrap();
    assert_eq!(parts.masks, face_masks(snap.layout(), &tiles));
    let mut mesh = Mesh::default();
    let mut transition = Vec::new();
    let mut drawn = Mesh::default();
    for (i, tile) in parts.tiles.iter().enumerate() {
        parts.drawn(i, &mut drawn);
        let regular = tile.mesh.triangles();
        transition.extend((0..drawn.triangles()).map(|t| t >= regular));
        mesh.append(&drawn);
    }
    let (welded, transition, _) = weld_flagged(&mesh, &transition);
    assert_eq!(
        open_edges(&welded),
        0,
        "{what}: not closed, first open edges {:?}",
        first_open_edges(&welded)
    );
    assert_eq!(
        degenerate_triangles(&welded, 1e-12),
        0,
        "{what}: triangles without area"
    );
    let mut levels = [0; 8];
    for t in &tiles {
        levels[t.level as usize] += 1;
    }
    Stitched {
        levels,
        triangles: welded.triangles(),
        transition_triangles: transition.iter().filter(|&&t| t).count(),
        crossing: crossing_triangles(&welded, &transition),
        volume: enclosed_volume(&welded),
    }
}

/// Checks `cameras` on `snap`; returns (selections mixing levels, transition triangles,
/// crossing ones).
fn check_cameras(
    name: &str,
    snap: &Snapshot,
    cameras: &[([f32; 3], Vec<f32>)],
    analytic: Option<f64>,
) -> (usize, usize, usize) {
    let (mut mixes, mut transition, mut crossing) = (0, 0, 0);
    for (camera, radii) in cameras {
        let what = format!("{name}, camera {camera:?} radii {radii:?}");
        let got = stitched(snap, *camera, radii, &what);
        assert!(got.triangles > 0, "{what}: nothing meshed");
        if let Some(analytic) = analytic {
            let error = (got.volume - analytic).abs() / analytic;
            assert!(
                error < 0.03,
                "{what}: enclosed {:.0}, analytic {analytic:.0} ({:.2}%)",
                got.volume,
                100.0 * error
            );
        }
        mixes += usize::from(got.levels.iter().filter(|&&n| n > 0).count() > 1);
        transition += got.transition_triangles;
        crossing += got.crossing;
    }
    eprintln!(
        "{name}: {mixes} of {} selections mix levels; {transition} transition triangles, \
         {crossing} crossing another triangle",
        cameras.len()
    );
    (mixes, transition, crossing)
}

/// An empty volume of `dims` with `term` unioned in.
fn volume_with(dir: &Path, dims: [u32; 3], brick: u32, term: Term) -> Vod2 {
    let path = dir.join("v.vod");
    let t = VoxelType::U8;
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
    let vod = Vod2::open(&path).unwrap();
    let req = EditRequest {
        op: "union".to_string(),
        term: Some(term),
        s_l: None,
        k: None,
        region: None,
        message: None,
        channel: None,
        overwrite: None,
    };
    let mut edit = Edit::from_request(&req, t, &TermLimits::default(), &NoVolumes).unwrap();
    let mut w = Vod2Writer::open_append(&path, Compression::Zstd(3)).unwrap();
    apply_edit(
        &mut w,
        &vod.head(),
        &mut edit,
        CheckpointPolicy::default(),
        &CancelToken::never(),
    )
    .unwrap();
    Vod2::open(&path).unwrap()
}

#[test]
fn every_primitive_stitches_closed() {
    // 64^3, brick 8: grids 8, 4, 2, 1, levels 0-3.
    let primitives = [
        Term::Ellipsoid {
            center: [31, 30, 33],
            radii: [22, 15, 19],
        },
        Term::Cuboid {
            origin: [9, 11, 7],
            size: [41, 37, 45],
        },
        Term::Cylinder {
            base: [32, 6, 30],
            radii: [20, 17],
            height: 50,
        },
        Term::Cone {
            base: [32, 6, 30],
            radii: [24, 22],
            height: 52,
        },
        Term::Torus {
            center: [32, 31, 32],
            major: 18,
            minor: 8,
        },
        Term::Capsule {
            center: [32, 33, 31],
            radius: 13,
            length: 22,
        },
        Term::Prism {
            origin: [7, 8, 9],
            size: [49, 45, 40],
        },
        Term::Pyramid {
            origin: [6, 5, 7],
            size: [51, 47, 50],
        },
    ];
    let (mut transition, mut crossing) = (0, 0);
    for (i, term) in primitives.into_iter().enumerate() {
        let name = format!("{term:?}");
        let name = name
            .split([' ', '{'])
            .next()
            .unwrap_or("primitive")
            .to_string();
        let dir = tempfile::tempdir().unwrap();
        let vod = volume_with(dir.path(), [64; 3], 8, term);
        let (mixes, t, c) = check_cameras(
            &name,
            &vod.head(),
            &cameras([64.0; 3], 12, 100 + i as u64),
            None,
        );
        assert!(mixes >= 8, "{name}: the cameras mix levels");
        transition += t;
        crossing += c;
    }
    eprintln!("all primitives: {transition} transition triangles, {crossing} crossing");
    assert_eq!(crossing, 0, "transition triangles cross other triangles");
}

#[test]
fn a_stitched_ball_keeps_its_volume_at_every_level_mix() {
    // The generator's ellipsoid of a 96^3 volume (brick 8: levels 0-3).
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("e.vod");
    let layout = VolumeLayout::new([96; 3], 8, VoxelType::U8).unwrap();
    build_vod2(
        &path,
        &layout,
        [1.0; 3],
        &EllipsoidSource::new(layout.clone()),
        &BuildOptions::default(),
    )
    .unwrap();
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    // The generator's ball: radii (96 - 1) / 2 = 47 voxels.
    let analytic = 4.0 / 3.0 * PI * 47.0f64.powi(3);
    let level0 = stitched(&snap, [48.0; 3], &[1e6, 1e6, 1e6], "level 0");
    assert!((level0.volume - analytic).abs() / analytic < 0.01);
    let (mixes, _, crossing) = check_cameras(
        "ellipsoid",
        &snap,
        &cameras([96.0; 3], 16, 7),
        Some(analytic),
    );
    assert!(mixes >= 12, "the cameras mix levels");
    assert_eq!(crossing, 0, "transition triangles cross other triangles");
}

#[test]
fn the_demo_world_stitches_closed() {
    let dir = tempfile::tempdir().unwrap();
    let path = build_demo(dir.path(), &BuildOptions::default()).unwrap();
    let vod = Vod2::open(&path).unwrap();
    let snap = vod.head();
    // 512 x 256 x 512, brick 32: levels 0-4. Radii in world units, from the ground up.
    let dims = [512.0, 256.0, 512.0];
    let mut next = rng(3);
    let views: Vec<([f32; 3], Vec<f32>)> = (0..6)
        .map(|_| {
            let camera = [0, 1, 2].map(|a| (next() * dims[a]) as f32);
            let r0 = (40.0 + next() * 80.0) as f32;
            (camera, vec![r0, r0 * 2.0, r0 * 4.0])
        })
        .collect();
    let (mixes, _, crossing) = check_cameras("demo world", &snap, &views, None);
    assert_eq!(mixes, views.len());
    assert_eq!(crossing, 0, "transition triangles cross other triangles");
}

/// An MRI-like scan: a head of nested tissue shells with noise, u16, odd dimensions (partial
/// bricks on the high faces) and anisotropic voxels.
#[test]
fn an_mri_like_scan_stitches_closed() {
    let dims = [99u32, 117, 95];
    let t = VoxelType::U16;
    let mut noise = rng(11);
    let mut bytes = Vec::with_capacity((dims[0] * dims[1] * dims[2] * 2) as usize);
    let c = [49.0, 58.0, 47.0];
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                // Normalized radius of an ellipsoidal head; skull, cortex folds, ventricles.
                let p = [x as f64, y as f64, z as f64];
                let r = ((p[0] - c[0]).powi(2) / 42.0f64.powi(2)
                    + (p[1] - c[1]).powi(2) / 52.0f64.powi(2)
                    + (p[2] - c[2]).powi(2) / 40.0f64.powi(2))
                .sqrt();
                let folds = (p[0] * 0.45).sin() * (p[1] * 0.38).cos() * (p[2] * 0.41).sin();
                // Intensities around the surface value S = 32768 of u16: skull and tissue
                // above it, the fluid between them and in the ventricles below.
                let mut v = if r > 1.0 {
                    0.0
                } else if r > 0.92 {
                    52000.0
                } else if r > 0.86 {
                    14000.0
                } else {
                    36000.0 + 18000.0 * folds
                };
                let ventricle = ((p[0] - c[0]).powi(2) / 64.0
                    + (p[1] - c[1] - 6.0).powi(2) / 225.0
                    + (p[2] - c[2]).powi(2) / 100.0)
                    .sqrt();
                if ventricle < 1.0 {
                    v = 6000.0;
                }
                v += (noise() - 0.5) * 6000.0;
                let v = v.clamp(0.0, 65535.0) as u16;
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mri.vod");
    let layout = VolumeLayout::new(dims, 8, t).unwrap();
    assert_eq!(layout.levels(), 5);
    build_vod2(
        &path,
        &layout,
        [1.0, 1.0, 1.25],
        &DenseGrid::new(dims, t, 8, &bytes),
        &BuildOptions::default(),
    )
    .unwrap();
    let vod = Vod2::open(&path).unwrap();
    let world = [99.0, 117.0, 95.0 * 1.25];
    check_cameras("mri", &vod.head(), &cameras(world, 10, 5), None);
}

#[test]
fn stitching_a_single_level_changes_nothing() {
    // With every tile at one level no face touches a coarser tile: the stitched mesh is the
    // regular meshes, and welding closes them as before.
    let dir = tempfile::tempdir().unwrap();
    let vod = volume_with(
        dir.path(),
        [32; 3],
        8,
        Term::Torus {
            center: [16, 15, 16],
            major: 9,
            minor: 4,
        },
    );
    let snap = vod.head();
    for level in 0..3u8 {
        let g = snap.layout().grid(level);
        let tiles: Vec<BrickKey> = (0..g[0] * g[1] * g[2])
            .map(|i| BrickKey {
                level,
                x: i % g[0],
                y: i / g[0] % g[1],
                z: i / (g[0] * g[1]),
            })
            .collect();
        assert!(face_masks(snap.layout(), &tiles).iter().all(|&m| m == 0));
    }
    let got = stitched(&snap, [16.0; 3], &[1e6, 1e6, 1e6], "level 0");
    assert_eq!(got.transition_triangles, 0);
    assert!((got.volume - 2.0 * PI * PI * 9.0 * 16.0).abs() / got.volume < 0.08);
}

/// At the iso value L every voxel, and the padding outside the volume, is inside: no tile has a
/// surface, and none fails. (A bright solid against the volume's low faces makes the coarser
/// lattice dip below L in the padding; strips once met that and reached past the finer field.)
#[test]
fn at_the_lowest_iso_value_every_tile_is_empty() {
    let dir = tempfile::tempdir().unwrap();
    // 64^3, brick 8: levels 0-3; the cuboid fills the low corner up to the volume's faces.
    let term = Term::Cuboid {
        origin: [0, 0, 0],
        size: [40, 40, 40],
    };
    let vod = volume_with(dir.path(), [64, 64, 64], 8, term);
    let snap = vod.head();
    let layout = snap.layout().clone();
    let mut scratch = TileScratch::default();
    let mut out = isovox_proto::mesh::TileMesh::default();
    let mut strip = Mesh::default();
    for level in 0..layout.levels() {
        let grid = layout.grid(level);
        for z in 0..grid[2] {
            for y in 0..grid[1] {
                for x in 0..grid[0] {
                    let key = BrickKey { level, x, y, z };
                    mesh_tile_with_moves(&snap, key, 0.0, &mut out, &mut scratch).unwrap();
                    assert_eq!(out.mesh.triangles(), 0, "tile {key} at iso 0");
                    assert!(out.moves.is_empty(), "tile {key} at iso 0");
                    for face in 0..6 {
                        mesh_strip_world(&snap, key, face, 0.0, &mut strip, &mut scratch).unwrap();
                        assert!(
                            strip.positions.is_empty(),
                            "tile {key} face {face} at iso 0"
                        );
                    }
                    // Just above L the cuboid's faces are a surface, inside the volume and on
                    // its low faces (against the padding).
                    mesh_tile_with_moves(&snap, key, 0.5, &mut out, &mut scratch).unwrap();
                    for face in 0..6 {
                        mesh_strip_world(&snap, key, face, 0.5, &mut strip, &mut scratch).unwrap();
                    }
                }
            }
        }
    }
}
