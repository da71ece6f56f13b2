//! Crack-free meshes across levels, at the kernel level: tiles of a small volume held in
//! memory are meshed with `march`, `tile_moves` and `mesh_strip` the way a tile server gathers
//! them,
//! selected and masked by `isovox_proto::lod`, stitched by `isovox_proto::mesh::stitch`, and
//! the assembled mesh is checked: closed and 2-manifold after welding equal positions, no
//! degenerate triangles, no transition triangle crossing another, and the volume of a sphere.

use crate::common::XorShift;
use isovox_proto::lod::{balance, balanced_tiles, face_masks};
use isovox_proto::mesh::{apply_moves, stitch, TileMesh};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::mesh::check::{
    crossing_triangles, degenerate_triangles, enclosed_volume, open_edges,
};
use isovox_server::mesh::lattice::{lattice_field, LatticeScratch};
use isovox_server::mesh::level::weld_flagged;
use isovox_server::mesh::mc::{march, Field, Mesh, Scratch};
use isovox_server::mesh::transition::{
    mesh_strip, tile_moves, TileFaces, TransitionInput, TransitionScratch,
};
use isovox_server::store::pyramid::{downsample, BrickVoxels, Downsampling};
use std::collections::HashMap;

const ISO: f32 = 127.5;

/// Where a tile's samples come from.
trait Samples {
    /// The lattice values of `level` over the box `[lo, hi]` (inclusive), x fastest.
    fn lattice(&self, level: u8, lo: [i64; 3], hi: [i64; 3], out: &mut Vec<f32>);
}

/// A cubic volume in memory: level-0 voxels and the project's mean pyramid above them.
struct Pyramid {
    levels: Vec<(i64, Vec<u8>)>, // side, voxels x fastest
}

impl Pyramid {
    /// `side` is `brick` times a power of two.
    fn new(side: i64, brick: i64, voxel: impl Fn([i64; 3]) -> u8) -> Pyramid {
        assert!(side % brick == 0 && ((side / brick) as u64).is_power_of_two());
        let mut level0 = Vec::with_capacity((side * side * side) as usize);
        for z in 0..side {
            for y in 0..side {
                for x in 0..side {
                    level0.push(voxel([x, y, z]));
                }
            }
        }
        let mut levels = vec![(side, level0)];
        while levels.last().map(|l| l.0) != Some(brick) {
            let (s, v) = levels.last().cloned().unwrap_or_default();
            // The level as 8 children of side s/2, downsampled into one parent of side s/2.
            let h = (s / 2) as usize;
            let children: Vec<BrickVoxels> = (0..8)
                .map(|o| {
                    let mut c = Vec::with_capacity(h * h * h);
                    let off = [o & 1, o >> 1 & 1, o >> 2].map(|b| b * h);
                    for z in 0..h {
                        for y in 0..h {
                            for x in 0..h {
                                let i = ((off[2] + z) * s as usize + off[1] + y) * s as usize
                                    + off[0]
                                    + x;
                                c.push(v[i]);
                            }
                        }
                    }
                    BrickVoxels::Data(c)
                })
                .collect();
            let refs: [Option<&BrickVoxels>; 8] = std::array::from_fn(|i| Some(&children[i]));
            let mut out = vec![0u8; h * h * h];
            downsample(&refs, h as u32, VoxelType::U8, Downsampling::Mean, &mut out);
            levels.push((s / 2, out));
        }
        Pyramid { levels }
    }

    fn stored(&self, level: u8, p: [i64; 3]) -> f32 {
        let (s, v) = &self.levels[level as usize];
        if p.iter().any(|&c| c < 0 || c >= *s) {
            return 0.0;
        }
        v[((p[2] * s + p[1]) * s + p[0]) as usize] as f32
    }
}

impl Samples for Pyramid {
    fn lattice(&self, level: u8, lo: [i64; 3], hi: [i64; 3], out: &mut Vec<f32>) {
        // The stored voxels [lo - 2, hi + 1], resampled by the project's function.
        let origin = lo.map(|c| c - 2);
        let size = [0, 1, 2].map(|a| (hi[a] + 1 - origin[a] + 1) as usize);
        let mut stored = Vec::with_capacity(size[0] * size[1] * size[2]);
        for z in 0..size[2] as i64 {
            for y in 0..size[1] as i64 {
                for x in 0..size[0] as i64 {
                    stored.push(self.stored(level, [origin[0] + x, origin[1] + y, origin[2] + z]));
                }
            }
        }
        let field = Field {
            origin,
            size,
            values: &stored,
        };
        let mut values = Vec::new();
        let scratch = &mut LatticeScratch::default();
        let f = lattice_field(&field, (lo, hi), level, VoxelType::U8, scratch, &mut values);
        assert_eq!((f.origin, f.size[0]), (lo, (hi[0] - lo[0] + 1) as usize));
        out.clear();
        out.extend_from_slice(&values);
    }
}

/// Lattice values given point by point (the rest outside), so that every pattern of a
/// transition cell's 13 samples can be set up directly.
#[derive(Default)]
struct Explicit(HashMap<(u8, [i64; 3]), f32>);

impl Samples for Explicit {
    fn lattice(&self, level: u8, lo: [i64; 3], hi: [i64; 3], out: &mut Vec<f32>) {
        let size = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
        out.clear();
        out.resize(size[0] * size[1] * size[2], 0.0);
        for (&(l, p), &v) in &self.0 {
            if l == level && (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]) {
                let q = [0, 1, 2].map(|a| (p[a] - lo[a]) as usize);
                out[(q[2] * size[1] + q[1]) * size[0] + q[0]] = v;
            }
        }
    }
}

/// One tile, meshed as a tile server would: its regular mesh and moves, and the strip of each
/// face as drawn, in level-0 units (lattice point j of level k at 2^k j).
fn mesh_tile(samples: &dyn Samples, layout: &VolumeLayout, key: BrickKey) -> (TileMesh, [Mesh; 6]) {
    let b = layout.brick() as i64;
    let k = key.level;
    let pos = [key.x, key.y, key.z].map(|c| c as i64);
    let lo = pos.map(|c| c * b - i64::from(c == 0));
    let hi = pos.map(|c| (c + 1) * b);
    let frame = pos.map(|c| c * b);
    let mut fine_values = Vec::new();
    samples.lattice(k, lo.map(|c| c - 1), hi.map(|c| c + 1), &mut fine_values);
    let fine = Field {
        origin: lo.map(|c| c - 1),
        size: [0, 1, 2].map(|a| (hi[a] - lo[a] + 3) as usize),
        values: &fine_values,
    };
    let mut tile = TileMesh::default();
    let mut strips: [Mesh; 6] = Default::default();
    let mut scratch = Scratch::default();
    march(&fine, lo, frame, hi, ISO, &mut tile.mesh, &mut scratch);
    let mut faces = 0u8;
    if k + 1 < layout.levels() {
        for (f, d) in isovox_proto::lod::FACE_DIRECTIONS.iter().enumerate() {
            faces |= u8::from(layout.neighbour(key, *d).is_some()) << f;
        }
    }
    let where_ = TileFaces {
        lo,
        hi,
        frame,
        coarse_frame: pos.map(|c| c / 2 * b),
        faces,
    };
    tile_moves(&where_, &scratch, &mut tile.moves);
    // To level-0 units, one formula for every position of every tile.
    let step = (1u64 << k) as f32;
    let origin = frame.map(|c| c as f32);
    let world = |p: &mut [f32; 3]| {
        for a in 0..3 {
            p[a] = (p[a] + origin[a]) * step;
        }
    };
    let to_world = |t: &mut TileMesh| {
        t.mesh.positions.iter_mut().for_each(world);
        for m in &mut t.moves {
            m.distance *= step;
        }
    };
    if faces != 0 {
        let c = lo.map(|v| v.div_euclid(2) - 1);
        let d = hi.map(|v| v / 2 + 1);
        let mut coarse_values = Vec::new();
        samples.lattice(k + 1, c, d, &mut coarse_values);
        let coarse = Field {
            origin: c,
            size: [0, 1, 2].map(|a| (d[a] - c[a] + 1) as usize),
            values: &coarse_values,
        };
        let input = TransitionInput {
            tile: where_,
            fine: &fine,
            coarse: &coarse,
            iso: ISO,
        };
        let mut transitions = TransitionScratch::default();
        for (face, drawn) in strips.iter_mut().enumerate() {
            let mut strip = TileMesh::default();
            mesh_strip(
                &input,
                face,
                &tile.mesh,
                &scratch,
                &mut strip,
                &mut transitions,
            );
            assert!(strip.moves.iter().all(|m| usize::from(m.face) == face));
            to_world(&mut strip);
            apply_moves(&mut strip.mesh.positions, &strip.moves, 0x3f);
            *drawn = strip.mesh;
        }
    }
    to_world(&mut tile);
    (tile, strips)
}

/// The tiles stitched with their masks and concatenated; also, per triangle, whether it is a
/// transition triangle (the regular triangles of each tile's part come first).
fn assemble(samples: &dyn Samples, layout: &VolumeLayout, tiles: &[BrickKey]) -> (Mesh, Vec<bool>) {
    let masks = face_masks(layout, tiles);
    let parts: Vec<Option<(Mesh, Vec<bool>)>> = (0..tiles.len()).map(|_| None).collect();
    assemble_reusing(samples, layout, tiles, &masks, &parts)
}

/// One tile's part of [`assemble`]: the tile stitched by `mask`, and which of its triangles
/// are transition triangles.
fn tile_part(
    samples: &dyn Samples,
    layout: &VolumeLayout,
    key: BrickKey,
    mask: u8,
) -> (Mesh, Vec<bool>) {
    let (tile, strips) = mesh_tile(samples, layout, key);
    let mut part = Mesh::default();
    stitch(
        &tile,
        mask,
        std::array::from_fn(|f| Some(&strips[f])),
        &mut part,
    );
    let regular = tile.mesh.triangles();
    let transition = (0..part.triangles()).map(|t| t >= regular).collect();
    (part, transition)
}

/// [`assemble`], taking the part of tile `i` from `parts[i]` where it is given (a tile whose
/// samples are known not to change: meshing is a function of the samples it reads).
fn assemble_reusing(
    samples: &dyn Samples,
    layout: &VolumeLayout,
    tiles: &[BrickKey],
    masks: &[u8],
    parts: &[Option<(Mesh, Vec<bool>)>],
) -> (Mesh, Vec<bool>) {
    let mut out = Mesh::default();
    let mut transition = Vec::new();
    for ((&key, &mask), known) in tiles.iter().zip(masks).zip(parts) {
        let made;
        let (part, flags) = match known {
            Some(p) => p,
            None => {
                made = tile_part(samples, layout, key, mask);
                &made
            }
        };
        transition.extend_from_slice(flags);
        out.append(part);
    }
    (out, transition)
}

/// A lattice box read: level, lowest and highest point (inclusive).
type LatticeBox = (u8, [i64; 3], [i64; 3]);

/// Records the lattice boxes read through it (which samples a tile's meshing depends on).
struct Reads<'a> {
    inner: &'a dyn Samples,
    boxes: std::cell::RefCell<Vec<LatticeBox>>,
}

impl Samples for Reads<'_> {
    fn lattice(&self, level: u8, lo: [i64; 3], hi: [i64; 3], out: &mut Vec<f32>) {
        self.boxes.borrow_mut().push((level, lo, hi));
        self.inner.lattice(level, lo, hi, out);
    }
}

/// For each tile, its part when meshing it reads none of `points` (so that it is the same
/// whatever values they take), else `None`.
fn parts_without(
    samples: &dyn Samples,
    layout: &VolumeLayout,
    tiles: &[BrickKey],
    masks: &[u8],
    points: &[(u8, [i64; 3])],
) -> Vec<Option<(Mesh, Vec<bool>)>> {
    tiles
        .iter()
        .zip(masks)
        .map(|(&key, &mask)| {
            let reads = Reads {
                inner: samples,
                boxes: Default::default(),
            };
            let part = tile_part(&reads, layout, key, mask);
            let touched = reads.boxes.borrow().iter().any(|&(level, lo, hi)| {
                points
                    .iter()
                    .any(|&(l, p)| l == level && (0..3).all(|a| lo[a] <= p[a] && p[a] <= hi[a]))
            });
            (!touched).then_some(part)
        })
        .collect()
}

fn key(level: u8, x: u32, y: u32, z: u32) -> BrickKey {
    BrickKey { level, x, y, z }
}

fn children(layout: &VolumeLayout, k: BrickKey) -> Vec<BrickKey> {
    layout.children(k).into_iter().map(|(_, c)| c).collect()
}

/// Uniform numbers in [0, 1) from the tests' one generator, seeded.
fn rng(seed: u64) -> impl FnMut() -> f64 {
    let mut rng = XorShift(seed | 1);
    move || rng.unit()
}

/// The scenes of the exhaustive test: a volume of 8 x 8 x 8 bricks (grids 8, 4, 2, 1), a
/// selection, and the transition cell (tile, face, lower corner of its 2x2 block) the 13
/// samples go to. `collapsed`: how many of the cell's sides collapse onto its tile's edges
/// (where the coarse tile's face ends).
struct Scene {
    name: &'static str,
    tiles: Vec<BrickKey>,
    tile: BrickKey,
    face: usize,
    block: [i64; 3],
    collapsed: usize,
}

fn scenes(brick: i64) -> Vec<Scene> {
    let mut out = Vec::new();
    {
        let layout =
            VolumeLayout::new([8 * brick as u32; 3], brick as u32, VoxelType::U8).expect("layout");
        // Level 0 in some level-1 octants of level-2 tile (0,0,0); level 1 in its other
        // octants; level 2 elsewhere.
        let cover = |fine_octants: &[BrickKey]| {
            let mut tiles = Vec::new();
            for c in children(&layout, key(2, 0, 0, 0)) {
                if fine_octants.contains(&c) {
                    tiles.extend(children(&layout, c));
                } else {
                    tiles.push(c);
                }
            }
            tiles.extend(children(&layout, key(3, 0, 0, 0)).into_iter().skip(1));
            // Level 0 beside level 2 would break the 2:1 rule: refined where it does.
            balance(&layout, tiles)
        };
        let b = brick;
        let one = cover(&[key(1, 0, 0, 0)]);
        let concave = cover(&[key(1, 0, 0, 0), key(1, 0, 1, 0), key(1, 1, 1, 0)]);
        // Level-0 tile (1,0,0) meets level-1 tile (1,0,0) across +x; it is first on y and z,
        // so its face has blocks from -2. With brick 4 the block at y, z in [0, 2] is inside
        // the strip, the one at y in [2, 4] ends it on the tile's +y face, where the next
        // level-0 tile meets the same coarse tile: its side is shared with that tile's strip,
        // not collapsed; with brick 2 the block at [0, 2] ends the strip on +y and +z, where
        // the coarse tile goes on as well.
        let straight = Scene {
            name: "strip, level 0 against level 1 across +x",
            tiles: one.clone(),
            tile: key(0, 1, 0, 0),
            face: 1,
            block: [2 * b, 0, 0],
            collapsed: 0,
        };
        // Level-0 tile (1,1,1) has level 1 across +x, +y and +z; the block at its corner,
        // where the coarse tile's face ends on both sides: two collapsed sides, and the fine
        // square at the corner bent (three of its corners stay, one moves).
        let corner = Scene {
            name: "convex corner",
            tiles: one.clone(),
            tile: key(0, 1, 1, 1),
            face: 1,
            block: [2 * b, 2 * b - 2, 2 * b - 2],
            collapsed: 2,
        };
        // Octants (0,0,0), (0,1,0) and (1,1,0) refined: level-1 tile (1,0,0) sits in a
        // concave corner of level 0. Level-0 tile (1,1,0) meets it across +x, level-0 tile
        // (2,2,0) across -y, and level-0 tile (1,2,0) beside both meets nothing coarser there:
        // the cells next to the edge between them, one collapsed side each.
        let concave_x = Scene {
            name: "concave corner, +x strip",
            tiles: concave.clone(),
            tile: key(0, 1, 1, 0),
            face: 1,
            block: [2 * b, 2 * b - 2, 0],
            collapsed: 1,
        };
        let concave_y = Scene {
            name: "concave corner, -y strip",
            tiles: concave,
            tile: key(0, 2, 2, 0),
            face: 2,
            block: [2 * b, 2 * b, 0],
            collapsed: 1,
        };
        out.extend([straight, corner, concave_x, concave_y]);
        if b == 4 {
            out.push(Scene {
                name: "strip end, level 0 against level 1 across +x",
                tiles: one,
                tile: key(0, 1, 0, 0),
                face: 1,
                block: [2 * b, 2, 0],
                collapsed: 0,
            });
        }
    }
    out
}

/// The lattice points of a transition cell's samples: (level, point) for sample s of the
/// table's numbering, for the cell of `face` whose 2x2 block starts at `block` (fine lattice,
/// on the face plane).
fn cell_points(face: usize, block: [i64; 3]) -> Vec<(u8, [i64; 3])> {
    // The kernel's (u, v) axes of each face.
    const FRAMES: [(usize, usize); 6] = [(2, 1), (1, 2), (0, 2), (2, 0), (1, 0), (0, 1)];
    let (ua, va) = FRAMES[face];
    (0..13u8)
        .map(|s| {
            let c = isovox_server::mesh::transition_table::sample_position(s);
            let mut p = block;
            p[ua] += i64::from(c[0]);
            p[va] += i64::from(c[1]);
            if s < 9 {
                (0, p)
            } else {
                (1, p.map(|x| x / 2))
            }
        })
        .collect()
}

/// Every pattern of a transition cell's 13 samples (8192 cases) in the scenes of `brick`: with
/// values that put each vertex at its edge's middle (pass 0), then with random values on each
/// side of the iso value (pass 1). The assembled mesh is closed, without degenerate triangles.
/// Returns, per scene and pass, the number of cases where a transition triangle crosses
/// another triangle.
fn exhaustive(brick: i64) -> Vec<(Scene, [usize; 2])> {
    let mut next = rng(7 + brick as u64);
    let mut found = Vec::new();
    for scene in scenes(brick) {
        let side = 8 * brick as u32;
        let layout = VolumeLayout::new([side; 3], brick as u32, VoxelType::U8).expect("layout");
        let masks = face_masks(&layout, &scene.tiles);
        let i = scene
            .tiles
            .iter()
            .position(|k| *k == scene.tile)
            .expect("tile");
        assert!(
            masks[i] >> scene.face & 1 == 1,
            "{}: the face touches a coarser tile",
            scene.name
        );
        let points = cell_points(scene.face, scene.block);
        let mut samples = Explicit::default();
        // The tiles that read none of the cell's samples mesh alike in every case: meshed
        // once. (An assembly over freshly meshed tiles in every case checks the same meshes;
        // `a_tile_that_reads_none_of_a_cells_samples_is_reused_unchanged` shows it.)
        let parts = parts_without(&samples, &layout, &scene.tiles, &masks, &points);
        let mut crossing_cases = [0; 2];
        for case in 0..1u16 << 13 {
            for (pass, found) in crossing_cases.iter_mut().enumerate() {
                for (s, &p) in points.iter().enumerate() {
                    let inside = case >> s & 1 == 1;
                    let v = match (pass, inside) {
                        (0, true) => 191.0,
                        (0, false) => 64.0,
                        (_, true) => 128.0 + (next() * 127.0).floor(),
                        (_, false) => (next() * 127.0).floor(),
                    };
                    samples.0.insert(p, v as f32);
                }
                let (mesh, transition) =
                    assemble_reusing(&samples, &layout, &scene.tiles, &masks, &parts);
                let (welded, transition, collapsed) = weld_flagged(&mesh, &transition);
                let what = format!(
                    "{} (brick {brick}): case {case:#015b} pass {pass}",
                    scene.name
                );
                // Only a fine and a coarse crossing at one position collapse a triangle; at
                // 64 / 191 they never coincide.
                if pass == 0 {
                    assert_eq!(collapsed, 0, "{what}: a triangle collapsed");
                }
                assert_eq!(open_edges(&welded), 0, "{what}: not closed");
                let min_area = if pass == 0 { 1e-4 } else { 1e-12 };
                assert_eq!(
                    degenerate_triangles(&welded, min_area),
                    0,
                    "{what}: degenerate triangles"
                );
                if crossing_triangles(&welded, &transition) > 0 {
                    *found += 1;
                }
            }
        }
        eprintln!(
            "{} (brick {brick}, {} collapsed sides): cases with crossing triangles: {} of 8192 \
             at edge midpoints, {} of 8192 with random values",
            scene.name, scene.collapsed, crossing_cases[0], crossing_cases[1]
        );
        found.push((scene, crossing_cases));
    }
    found
}

/// The exhaustive tests mesh the tiles that read none of a cell's samples once
/// ([`parts_without`]): here, for every scene and a few random values of its cell, the
/// assembly that reuses them equals the one that meshes every tile again, and some tiles are
/// reused while the cell's own tile is not.
#[test]
fn a_tile_that_reads_none_of_a_cells_samples_is_reused_unchanged() {
    let mut next = rng(11);
    for brick in [2, 4] {
        for scene in scenes(brick) {
            let side = 8 * brick as u32;
            let layout = VolumeLayout::new([side; 3], brick as u32, VoxelType::U8).expect("layout");
            let masks = face_masks(&layout, &scene.tiles);
            let points = cell_points(scene.face, scene.block);
            let mut samples = Explicit::default();
            let parts = parts_without(&samples, &layout, &scene.tiles, &masks, &points);
            let i = scene.tiles.iter().position(|k| *k == scene.tile).unwrap();
            assert!(
                parts[i].is_none(),
                "{}: the cell's tile was reused",
                scene.name
            );
            assert!(
                parts.iter().any(Option::is_some),
                "{}: no tile was reused",
                scene.name
            );
            for _ in 0..8 {
                for &p in &points {
                    samples.0.insert(p, (next() * 255.0).floor() as f32);
                }
                let fresh = assemble(&samples, &layout, &scene.tiles);
                let reused = assemble_reusing(&samples, &layout, &scene.tiles, &masks, &parts);
                assert!(fresh == reused, "{} (brick {brick})", scene.name);
            }
        }
    }
}

#[test]
fn every_transition_case_closes_brick_4() {
    for (scene, crossing) in exhaustive(4) {
        // Inside a strip the cells are regular slabs: with vertices at their edges' middles
        // no triangle crosses another.
        if scene.collapsed == 0 {
            assert_eq!(crossing[0], 0, "{}: triangles cross", scene.name);
        }
    }
}

#[test]
fn every_transition_case_closes_brick_2() {
    // With brick 2 every cell of a strip ends it on two sides.
    for (scene, crossing) in exhaustive(2) {
        if scene.collapsed == 0 {
            assert_eq!(crossing[0], 0, "{}: triangles cross", scene.name);
        }
    }
}

/// A sphere of radius `r` around `c`: a linear ramp across the surface, 127.5 at distance r.
fn sphere(c: [f64; 3], r: f64) -> impl Fn([i64; 3]) -> u8 {
    move |p| {
        let d = (0..3)
            .map(|a| (p[a] as f64 - c[a]).powi(2))
            .sum::<f64>()
            .sqrt();
        (127.5 + 96.0 * (r - d)).round().clamp(0.0, 255.0) as u8
    }
}

/// Random cameras in and around a volume of `side`, with radii for levels 0, 1 and 2.
fn cameras(side: f64, n: usize, seed: u64) -> Vec<([f32; 3], Vec<f32>)> {
    let mut next = rng(seed);
    (0..n)
        .map(|_| {
            let camera = [0; 3].map(|_| ((next() * 1.4 - 0.2) * side) as f32);
            let r0 = (4.0 + next() * side * 0.3) as f32;
            let r1 = r0 * (1.2 + next() as f32 * 1.5);
            let r2 = r1 * (1.2 + next() as f32 * 1.5);
            (camera, vec![r0, r1, r2])
        })
        .collect()
}

/// What an assembled selection shows: levels used, and the checks.
struct Checked {
    levels: [usize; 4],
    triangles: usize,
    transition_triangles: usize,
    crossing: usize,
    volume: f64,
}

fn check(pyramid: &Pyramid, layout: &VolumeLayout, tiles: &[BrickKey], what: &str) -> Checked {
    let (mesh, transition) = assemble(pyramid, layout, tiles);
    let (welded, transition, _) = weld_flagged(&mesh, &transition);
    assert_eq!(open_edges(&welded), 0, "{what}: not closed");
    assert_eq!(
        degenerate_triangles(&welded, 1e-12),
        0,
        "{what}: degenerate triangles"
    );
    let mut levels = [0; 4];
    for t in tiles {
        levels[t.level as usize] += 1;
    }
    Checked {
        levels,
        triangles: welded.triangles(),
        transition_triangles: transition.iter().filter(|&&t| t).count(),
        crossing: crossing_triangles(&welded, &transition),
        volume: enclosed_volume(&welded),
    }
}

#[test]
fn stitched_sphere_is_closed_and_keeps_its_volume_at_every_level_mix() {
    // 128^3, brick 8: grids 16, 8, 4, 2, 1. A sphere of radius 40 voxels: 5 lattice cells at
    // level 3 (lattice step 8).
    let (side, r) = (128i64, 56.0);
    let c = [63.3, 64.6, 62.1];
    let pyramid = Pyramid::new(side, 8, sphere(c, r));
    let layout = VolumeLayout::new([side as u32; 3], 8, VoxelType::U8).expect("layout");
    let analytic = 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
    // Each level alone first.
    for level in 0..4u8 {
        let g = layout.grid(level);
        let tiles: Vec<BrickKey> = (0..g[0] * g[1] * g[2])
            .map(|i| key(level, i % g[0], i / g[0] % g[1], i / (g[0] * g[1])))
            .collect();
        let got = check(&pyramid, &layout, &tiles, &format!("level {level}"));
        let error = (got.volume - analytic).abs() / analytic;
        eprintln!(
            "level {level} alone: {} triangles, volume error {:.2}%",
            got.triangles,
            100.0 * error
        );
        assert!(
            error < 0.03,
            "level {level}: volume {} vs {analytic}",
            got.volume
        );
    }
    let mut mixes = 0;
    let mut crossing = 0;
    let mut transition_triangles = 0;
    for (camera, radii) in cameras(side as f64, 40, 3) {
        let tiles = balanced_tiles(&layout, [1.0; 3], camera, &radii);
        let what = format!("camera {camera:?} radii {radii:?}");
        let got = check(&pyramid, &layout, &tiles, &what);
        let error = (got.volume - analytic).abs() / analytic;
        assert!(error < 0.03, "{what}: volume {} vs {analytic}", got.volume);
        if got.levels.iter().filter(|&&n| n > 0).count() > 1 {
            mixes += 1;
        }
        crossing += got.crossing;
        transition_triangles += got.transition_triangles;
    }
    eprintln!(
        "{mixes} of 40 cameras mixed levels; {transition_triangles} transition triangles, \
         {crossing} crossing another triangle"
    );
    assert!(mixes >= 30, "the cameras mix levels");
}

#[test]
fn stitched_random_fields_are_closed() {
    // Random blobs, a field with thin parts and many small components, on a non-cubic
    // selection of a 64^3 volume with brick 4 (grids 16, 8, 4, 2, 1).
    let side = 64i64;
    let mut next = rng(11);
    let blobs: Vec<([f64; 3], f64)> = (0..60)
        .map(|_| ([0; 3].map(|_| next() * side as f64), 1.5 + next() * 7.0))
        .collect();
    let pyramid = Pyramid::new(side, 4, |p| {
        let v: f64 = blobs
            .iter()
            .map(|(c, r)| {
                let d2 = (0..3).map(|a| (p[a] as f64 - c[a]).powi(2)).sum::<f64>();
                255.0 * (-d2 / (r * r)).exp()
            })
            .sum();
        v.round().clamp(0.0, 255.0) as u8
    });
    let layout = VolumeLayout::new([side as u32; 3], 4, VoxelType::U8).expect("layout");
    let mut crossing = 0;
    let mut transition_triangles = 0;
    for (camera, radii) in cameras(side as f64, 30, 5) {
        let tiles = balanced_tiles(&layout, [1.0; 3], camera, &radii);
        let got = check(
            &pyramid,
            &layout,
            &tiles,
            &format!("camera {camera:?} radii {radii:?}"),
        );
        crossing += got.crossing;
        transition_triangles += got.transition_triangles;
    }
    eprintln!("{transition_triangles} transition triangles, {crossing} crossing another triangle");
}
