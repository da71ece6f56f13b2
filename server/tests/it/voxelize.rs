//! The voxelizer (`isovox_server::voxelize`) against hand counts and an independent oracle.
//!
//! Golden values come from hand computation (boxes, placements, edge counts) or from methods
//! that share nothing with the code under test:
//! - the generalized winding number (sum of the triangles' signed solid angles, Van Oosterom
//!   and Strackee, over 4 pi) at a point: its parity is the paper's "inside" (Jordan theorem).
//!   Points on the surface (in a triangle's plane and inside it, where that triangle's solid
//!   angle jumps by 4 pi) are recognised and set aside, as are winding numbers far from an
//!   integer;
//! - the divergence theorem for a polyhedron's volume and its triangles' areas;
//! - the source voxels of a generated world (value >= S) for the world's marching-cubes mesh;
//! - for the parity pass and the box filter, their previous, simpler versions (kept in
//!   `voxelize::reference`; they share the fixed-point sampling helpers, not the binning, the
//!   stepped edge functions or the filter's loops), voxel for voxel on random closed meshes.
//!
//! The voxelizer rounds x and y to 16 fractional bits (module docs of `solid`). Shapes built in
//! grid coordinates are snapped to that lattice here, so they are voxelized without rounding
//! and every voxel must agree with the oracle. Shapes placed by `voxelize` (model units) are
//! not on the lattice: rounding moves each vertex by at most 2^-17 per axis, so the surface moves
//! by at most 2^-17 * sqrt(2) < 2^-16; a disagreement with the oracle is excused only where the
//! point lies within 2^-16 of the surface (and counted).
//!
//! Tie rules, derived from the module docs of `solid` (not from its code): triangles are turned
//! counter-clockwise in projection, so their inside lies left of each edge; an edge owns its
//! points when its direction d has d.y > 0 (an edge on the triangle's right, +x, side) or
//! d.y == 0 and d.x < 0 (an edge on its top, +y, side). A column centre on an edge or vertex is
//! thus covered exactly when the point moved by (-e, -e^2) (e -> 0) lies inside the projection.
//! In z a centre is toggled only by a triangle strictly above it, i.e. the point is moved up by
//! an amount that dominates e. Hence, for an axis-aligned box [x0, x1] x [y0, y1] x [z0, z1], a
//! centre c is inside iff x0 < cx <= x1, y0 < cy <= y1 and z0 <= cz < z1, and for any closed
//! mesh the voxelizer's answer at c is the winding number's parity at
//! c + (-e1, -e2, +e3) with e2 << e1 << e3 (the "perturbed oracle" below).

use crate::common::XorShift;
use isovox_proto::mesh::{encode_glb, Mesh};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};
use isovox_server::generate::WorldSource;
use isovox_server::mesh::check::{enclosed_volume, open_edges};
use isovox_server::mesh::level::{level_tiles, mesh_tiles, weld};
use isovox_server::mesh::tile::default_iso;
use isovox_server::store::{build_vod2, BrickSource, BuildOptions, DenseGrid, Vod2};
use isovox_server::voxelize::load::{load_model, LoadError};
use isovox_server::voxelize::reference::{voxelize_reference, voxelize_solid_reference};
use isovox_server::voxelize::solid::{voxelize_solid, BitGrid, TriMesh};
use isovox_server::voxelize::{density_value, voxelize, Fill, Options, VoxelizeError, Voxelized};
use proptest::prelude::*;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::ops::RangeInclusive;
use std::path::Path;

// ---------------------------------------------------------------------------------------------
// Vectors and shapes

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn mul(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}

/// A 3x3 rotation, rows.
type Rot = [V3; 3];

fn rotate(r: &Rot, p: V3) -> V3 {
    [dot(r[0], p), dot(r[1], p), dot(r[2], p)]
}

/// Rotation by `angle` about the unit `axis` (Rodrigues).
fn axis_angle(axis: V3, angle: f64) -> Rot {
    let k = mul(axis, 1.0 / norm(axis));
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    [
        [
            c + k[0] * k[0] * t,
            k[0] * k[1] * t - k[2] * s,
            k[0] * k[2] * t + k[1] * s,
        ],
        [
            k[1] * k[0] * t + k[2] * s,
            c + k[1] * k[1] * t,
            k[1] * k[2] * t - k[0] * s,
        ],
        [
            k[2] * k[0] * t - k[1] * s,
            k[2] * k[1] * t + k[0] * s,
            c + k[2] * k[2] * t,
        ],
    ]
}

/// A uniformly random rotation (Shoemake's quaternion).
fn rotation(rng: &mut XorShift) -> Rot {
    let (u1, u2, u3) = (rng.unit(), rng.unit(), rng.unit());
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    let (x, y, z, w) = (
        a * (2.0 * PI * u2).sin(),
        a * (2.0 * PI * u2).cos(),
        b * (2.0 * PI * u3).sin(),
        b * (2.0 * PI * u3).cos(),
    );
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// A triangle mesh under construction, in f64.
#[derive(Debug, Clone, Default)]
struct Shape {
    p: Vec<V3>,
    t: Vec<[u32; 3]>,
}

impl Shape {
    fn with(mut self, other: &Shape) -> Shape {
        let base = self.p.len() as u32;
        self.p.extend(&other.p);
        self.t.extend(other.t.iter().map(|t| t.map(|i| i + base)));
        self
    }

    fn map(&self, f: impl Fn(V3) -> V3) -> Shape {
        Shape {
            p: self.p.iter().map(|&p| f(p)).collect(),
            t: self.t.clone(),
        }
    }

    fn translated(&self, d: V3) -> Shape {
        self.map(|p| add(p, d))
    }

    /// The same surface wound the other way.
    fn flipped(&self) -> Shape {
        Shape {
            p: self.p.clone(),
            t: self.t.iter().map(|&[a, b, c]| [a, c, b]).collect(),
        }
    }

    /// Rotated by `r` about `centre`.
    fn rotated(&self, r: &Rot, centre: V3) -> Shape {
        self.map(|p| add(centre, rotate(r, sub(p, centre))))
    }

    /// Every coordinate rounded to a multiple of 2^-16 (the voxelizer's x/y lattice).
    fn snapped(&self) -> Shape {
        self.map(|p| p.map(|c| (c * 65536.0).round() / 65536.0))
    }

    /// Each triangle turned so that its normal points away from `centre` (convex shapes).
    fn outward_from(mut self, centre: V3) -> Shape {
        for t in &mut self.t {
            let [a, b, c] = t.map(|i| self.p[i as usize]);
            let n = cross(sub(b, a), sub(c, a));
            let g = mul(add(add(a, b), c), 1.0 / 3.0);
            if dot(n, sub(g, centre)) < 0.0 {
                t.swap(1, 2);
            }
        }
        self
    }

    fn tri_mesh(&self) -> TriMesh {
        TriMesh {
            positions: self.p.iter().map(|p| p.map(|c| c as f32)).collect(),
            triangles: self.t.clone(),
        }
    }
}

/// The triangles of `m` mapped by `f` (f32 positions taken exactly, as the voxelizer takes
/// them).
fn triangles_of(m: &TriMesh, f: impl Fn([f32; 3]) -> V3) -> Vec<[V3; 3]> {
    m.triangles
        .iter()
        .map(|t| t.map(|i| f(m.positions[i as usize])))
        .collect()
}

fn grid_coords(p: [f32; 3]) -> V3 {
    p.map(f64::from)
}

/// Signed volume (divergence theorem) and area of a triangle soup.
fn volume_and_area(tris: &[[V3; 3]]) -> (f64, f64) {
    let mut v = 0.0;
    let mut a = 0.0;
    for &[p, q, r] in tris {
        v += dot(p, cross(q, r)) / 6.0;
        a += norm(cross(sub(q, p), sub(r, p))) / 2.0;
    }
    (v, a)
}

/// An axis-aligned box, outward wound; `other_diagonal` splits each face along its other
/// diagonal.
fn cuboid(lo: V3, hi: V3, other_diagonal: bool) -> Shape {
    let p: Vec<V3> = (0..8)
        .map(|i| {
            [
                if i & 1 == 0 { lo[0] } else { hi[0] },
                if i & 2 == 0 { lo[1] } else { hi[1] },
                if i & 4 == 0 { lo[2] } else { hi[2] },
            ]
        })
        .collect();
    let quads = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let mut t = Vec::new();
    for [a, b, c, d] in quads {
        if other_diagonal {
            t.push([b, c, d]);
            t.push([b, d, a]);
        } else {
            t.push([a, b, c]);
            t.push([a, c, d]);
        }
    }
    Shape { p, t }.outward_from(mul(add(lo, hi), 0.5))
}

/// A cube of side `side` centred at `centre`, rotated by `r`.
fn rotated_cube(centre: V3, side: f64, r: &Rot) -> Shape {
    let h = side / 2.0;
    cuboid([-h; 3], [h; 3], false).map(|p| add(centre, rotate(r, p)))
}

/// An icosphere: the icosahedron subdivided `subdiv` times, vertices on the sphere.
fn icosphere(centre: V3, r: f64, subdiv: u32) -> Shape {
    let g = (1.0 + 5f64.sqrt()) / 2.0;
    let mut p: Vec<V3> = vec![
        [-1.0, g, 0.0],
        [1.0, g, 0.0],
        [-1.0, -g, 0.0],
        [1.0, -g, 0.0],
        [0.0, -1.0, g],
        [0.0, 1.0, g],
        [0.0, -1.0, -g],
        [0.0, 1.0, -g],
        [g, 0.0, -1.0],
        [g, 0.0, 1.0],
        [-g, 0.0, -1.0],
        [-g, 0.0, 1.0],
    ];
    for v in &mut p {
        *v = mul(*v, 1.0 / norm(*v));
    }
    let mut t: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdiv {
        let mut mid = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32, p: &mut Vec<V3>| -> u32 {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let m = add(p[a as usize], p[b as usize]);
                p.push(mul(m, 1.0 / norm(m)));
                (p.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(t.len() * 4);
        for [a, b, c] in t {
            let ab = midpoint(a, b, &mut p);
            let bc = midpoint(b, c, &mut p);
            let ca = midpoint(c, a, &mut p);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        t = next;
    }
    Shape {
        p: p.iter().map(|&v| add(centre, mul(v, r))).collect(),
        t,
    }
    .outward_from(centre)
}

/// A torus around the z axis through `centre`: major radius `big`, minor `small`, `nu` x `nv`
/// quads, each split into two triangles; outward wound.
fn torus(centre: V3, big: f64, small: f64, nu: u32, nv: u32) -> Shape {
    let mut p = Vec::new();
    for i in 0..nu {
        let u = 2.0 * PI * i as f64 / nu as f64;
        for j in 0..nv {
            let v = 2.0 * PI * j as f64 / nv as f64;
            let w = big + small * v.cos();
            p.push(add(centre, [w * u.cos(), w * u.sin(), small * v.sin()]));
        }
    }
    let id = |i: u32, j: u32| (i % nu) * nv + (j % nv);
    let mut t = Vec::new();
    for i in 0..nu {
        for j in 0..nv {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            t.push([a, b, c]);
            t.push([a, c, d]);
        }
    }
    let s = Shape { p, t };
    let tris: Vec<[V3; 3]> =
        s.t.iter()
            .map(|t| t.map(|i| sub(s.p[i as usize], centre)))
            .collect();
    if volume_and_area(&tris).0 < 0.0 {
        s.flipped()
    } else {
        s
    }
}

/// The octahedron |x| + |y| + |z| <= a around `centre`.
fn octahedron(centre: V3, a: f64) -> Shape {
    let p: Vec<V3> = [
        [a, 0.0, 0.0],
        [-a, 0.0, 0.0],
        [0.0, a, 0.0],
        [0.0, -a, 0.0],
        [0.0, 0.0, a],
        [0.0, 0.0, -a],
    ]
    .iter()
    .map(|&d| add(centre, d))
    .collect();
    let mut t = Vec::new();
    for x in [0, 1] {
        for y in [2, 3] {
            for z in [4, 5] {
                t.push([x, y, z]);
            }
        }
    }
    Shape { p, t }.outward_from(centre)
}

/// A prism over the convex polygon `poly` from z0 to z1, outward wound (caps fanned from the
/// first corner, sides split into two triangles).
fn prism(poly: &[[f64; 2]], z0: f64, z1: f64) -> Shape {
    let n = poly.len() as u32;
    let mut p = Vec::new();
    for z in [z0, z1] {
        for q in poly {
            p.push([q[0], q[1], z]);
        }
    }
    let mut t = Vec::new();
    for i in 1..n - 1 {
        t.push([0, i, i + 1]);
        t.push([n, n + i, n + i + 1]);
    }
    for i in 0..n {
        let j = (i + 1) % n;
        t.push([i, j, n + j]);
        t.push([i, n + j, n + i]);
    }
    let c = mul(
        p.iter().fold([0.0; 3], |a, &q| add(a, q)),
        1.0 / p.len() as f64,
    );
    Shape { p, t }.outward_from(c)
}

/// A tetrahedron, outward wound.
fn tetrahedron(v: [V3; 4]) -> Shape {
    let c = mul(add(add(v[0], v[1]), add(v[2], v[3])), 0.25);
    Shape {
        p: v.to_vec(),
        t: vec![[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]],
    }
    .outward_from(c)
}

// ---------------------------------------------------------------------------------------------
// The oracle: generalized winding number and distance to the surface

struct Oracle {
    tris: Vec<[V3; 3]>,
    lo: V3,
    hi: V3,
}

impl Oracle {
    fn new(tris: Vec<[V3; 3]>) -> Oracle {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for t in &tris {
            for p in t {
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
            }
        }
        Oracle { tris, lo, hi }
    }

    fn outside_bounds(&self, p: V3, margin: f64) -> bool {
        (0..3).any(|a| p[a] < self.lo[a] - margin || p[a] > self.hi[a] + margin)
    }

    /// The generalized winding number at `p` (0 outside the bounding box), and whether `p`
    /// lies on a triangle (in its plane, within 1e-12 relative, and inside or on its border,
    /// where the solid angle jumps by 4 pi and atan2 picks a side at random).
    fn winding_on(&self, p: V3) -> (f64, bool) {
        if self.outside_bounds(p, 0.0) {
            return (0.0, false);
        }
        let mut sum = 0.0;
        let mut on = false;
        for t in &self.tris {
            let (a, b, c) = (sub(t[0], p), sub(t[1], p), sub(t[2], p));
            let (la, lb, lc) = (norm(a), norm(b), norm(c));
            let num = dot(a, cross(b, c));
            let den = la * lb * lc + dot(a, b) * lc + dot(a, c) * lb + dot(b, c) * la;
            if num.abs() <= 1e-12 * la * lb * lc && den <= 0.0 {
                on = true;
                continue;
            }
            sum += 2.0 * num.atan2(den);
        }
        (sum / (4.0 * PI), on)
    }

    fn winding(&self, p: V3) -> f64 {
        self.winding_on(p).0
    }

    /// Inside by parity of the winding number; `None` on the surface (on a triangle, or the
    /// winding number more than 1/4 from an integer).
    fn inside(&self, p: V3) -> Option<bool> {
        let (w, on) = self.winding_on(p);
        let r = w.round();
        (!on && (w - r).abs() <= 0.25).then_some((r as i64).rem_euclid(2) == 1)
    }

    /// Distance from `p` to the surface.
    fn distance(&self, p: V3) -> f64 {
        self.tris
            .iter()
            .map(|t| norm(sub(p, closest_on_triangle(p, t))))
            .fold(f64::INFINITY, f64::min)
    }
}

/// The point of triangle `t` closest to `p` (Ericson, Real-Time Collision Detection, 5.1.5).
fn closest_on_triangle(p: V3, t: &[V3; 3]) -> V3 {
    let [a, b, c] = *t;
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return add(a, mul(ab, d1 / (d1 - d3)));
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return add(a, mul(ac, d2 / (d2 - d6)));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0 {
        return add(b, mul(sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6))));
    }
    let denom = va + vb + vc;
    if denom == 0.0 {
        return a;
    }
    add(a, add(mul(ab, vb / denom), mul(ac, vc / denom)))
}

/// 2^-16 grid units: how far the voxelizer's x/y rounding can move the surface (see the top).
const SNAP_BAND: f64 = 1.0 / 65536.0;

/// Perturbation of the "perturbed oracle": -e1 in x, -e2 in y, +e3 in z, e2 << e1 << e3. Valid
/// for shapes with vertices on multiples of 1/4 and extents of a few voxels: there every
/// non-zero distance from a centre to a face is far above e3, slopes are far below e3 / e1,
/// and no projected edge through a centre is closer to horizontal than e2 / e1.
const TIE_SHIFT: V3 = [-1e-8, -1e-11, 1e-3];

#[derive(Debug, Default, Clone, Copy)]
struct Tally {
    compared: usize,
    inside: usize,
    /// Centres on the surface (see `Oracle::inside`), not compared.
    on_surface: usize,
    /// Disagreements within `band` of the surface.
    excused: usize,
    mismatches: usize,
}

/// Compares `grid` voxel by voxel with the winding number's parity at the centres
/// `(i + 0.5) + shift` (grid units). A disagreement is excused only within `band` of the
/// surface; any other fails the test.
fn compare(name: &str, grid: &BitGrid, oracle: &Oracle, shift: V3, band: f64) -> Tally {
    let [nx, ny, nz] = grid.dims;
    let parts: Vec<(Tally, Vec<String>)> = (0..nz)
        .into_par_iter()
        .map(|z| {
            let mut t = Tally::default();
            let mut bad = Vec::new();
            for y in 0..ny {
                for x in 0..nx {
                    let p = add([x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5], shift);
                    let got = grid.get(x, y, z);
                    let Some(want) = oracle.inside(p) else {
                        t.on_surface += 1;
                        continue;
                    };
                    t.compared += 1;
                    t.inside += usize::from(want);
                    if got != want {
                        let d = oracle.distance(p);
                        if d <= band {
                            t.excused += 1;
                        } else {
                            t.mismatches += 1;
                            if bad.len() < 6 {
                                bad.push(format!(
                                    "voxel ({x}, {y}, {z}): voxelizer {}, winding number {:.6} at {p:?} (distance to the surface {d:.3e})",
                                    if got { "inside" } else { "outside" },
                                    oracle.winding(p)
                                ));
                            }
                        }
                    }
                }
            }
            (t, bad)
        })
        .collect();
    let mut total = Tally::default();
    let mut bad = Vec::new();
    for (t, b) in parts {
        total.compared += t.compared;
        total.inside += t.inside;
        total.on_surface += t.on_surface;
        total.excused += t.excused;
        total.mismatches += t.mismatches;
        bad.extend(b);
    }
    assert_eq!(
        total.mismatches,
        0,
        "{name}: {} voxels disagree with the winding number ({total:?}), e.g.\n{}",
        total.mismatches,
        bad.join("\n")
    );
    total
}

/// Voxelizes `shape` (grid coordinates, snapped to the 2^-16 lattice) with the identity
/// transform and compares every voxel with the winding number at the centres; generic
/// placements must have no centre on the surface.
fn check_generic(name: &str, shape: &Shape, dims: [usize; 3]) -> Tally {
    let m = shape.snapped().tri_mesh();
    let grid = voxelize_solid(&m, dims, grid_coords);
    let oracle = Oracle::new(triangles_of(&m, grid_coords));
    let t = compare(name, &grid, &oracle, [0.0; 3], 1e-9);
    assert!(t.inside > 0, "{name}: nothing inside ({t:?})");
    assert_eq!(t.on_surface, 0, "{name}: centres on the surface: {t:?}");
    assert_eq!(t.excused, 0, "{name}: {t:?}");
    assert_eq!(grid.count() as usize, t.inside, "{name}");
    t
}

/// Voxelizes `shape` (grid coordinates with vertices on multiples of 1/4, so many centres lie
/// on faces, edges and vertices) and compares every voxel with the perturbed oracle.
fn check_ties(name: &str, shape: &Shape, dims: [usize; 3]) -> Tally {
    for p in &shape.p {
        assert!(p.iter().all(|c| (c * 4.0).fract() == 0.0), "{name}: {p:?}");
    }
    let m = shape.tri_mesh();
    let grid = voxelize_solid(&m, dims, grid_coords);
    let oracle = Oracle::new(triangles_of(&m, grid_coords));
    let t = compare(name, &grid, &oracle, TIE_SHIFT, 0.0);
    assert_eq!(t.on_surface, 0, "{name}: {t:?}");
    assert_eq!(grid.count() as usize, t.inside, "{name}");
    t
}

/// Checks that `grid` holds exactly the voxels of the box of index ranges `x` x `y` x `z`.
fn assert_box(
    name: &str,
    grid: &BitGrid,
    x: RangeInclusive<usize>,
    y: RangeInclusive<usize>,
    z: RangeInclusive<usize>,
) {
    let [nx, ny, nz] = grid.dims;
    let mut wrong = Vec::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let want = x.contains(&i) && y.contains(&j) && z.contains(&k);
                if grid.get(i, j, k) != want {
                    wrong.push((i, j, k, want));
                }
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "{name}: {} voxels differ from the box {x:?} x {y:?} x {z:?}; first (x, y, z, expected): {:?}",
        wrong.len(),
        &wrong[..wrong.len().min(8)]
    );
}

/// Voxel `(x, y, z)` of a voxelized volume (u8 or u16).
fn value(v: &Voxelized, t: VoxelType, x: usize, y: usize, z: usize) -> u16 {
    let [nx, ny, _] = v.dims.map(|d| d as usize);
    let i = (z * ny + y) * nx + x;
    match t {
        VoxelType::U8 => u16::from(v.bytes[i]),
        _ => u16::from_le_bytes([v.bytes[2 * i], v.bytes[2 * i + 1]]),
    }
}

/// A binary voxelization (L or H only) as a bit grid.
fn binary(v: &Voxelized, t: VoxelType) -> BitGrid {
    let d = v.dims.map(|d| d as usize);
    let mut g = BitGrid::new(d);
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let a = value(v, t, x, y, z);
                assert!(a == 0 || a == t.high(), "binary fill gave {a}");
                g.set(x, y, z, a == t.high());
            }
        }
    }
    g
}

fn options(size: u32, fill: Fill) -> Options {
    Options {
        size,
        supersample: 2,
        padding: 2,
        fill,
        voxel_type: VoxelType::U8,
        allow_open: false,
    }
}

/// The oracle for a model voxelized by `voxelize`: triangles in `v`'s voxel coordinates.
fn placed_oracle(m: &TriMesh, v: &Voxelized) -> Oracle {
    let (o, s) = (v.origin, v.voxel_size);
    Oracle::new(triangles_of(m, |p| {
        std::array::from_fn(|a| (f64::from(p[a]) - o[a]) / s)
    }))
}

// ---------------------------------------------------------------------------------------------
// 1. Boxes counted by hand

#[test]
fn boxes_hold_the_centres_counted_by_hand() {
    let dims = [16; 3];
    let solid = |s: &Shape| voxelize_solid(&s.tri_mesh(), dims, grid_coords);
    // No ties: centres 2.5..=9.5 in x, 3.5..=7.5 in y, 1.5..=10.5 in z; the top face z = 11.5
    // lies on the centres of layer 11, which are outside (half-open [bottom, top)).
    let a = cuboid([2.25, 3.125, 1.25], [9.75, 7.875, 11.5], false);
    assert_box("fractional box", &solid(&a), 2..=9, 3..=7, 1..=10);
    assert_eq!(solid(&a).count(), 8 * 5 * 10);
    // Bottom and top on centres: z in [2.5, 6.5) holds the centres 2.5, 3.5, 4.5, 5.5.
    let b = cuboid([2.25, 3.125, 2.5], [9.75, 7.875, 6.5], false);
    assert_box("z faces on centres", &solid(&b), 2..=9, 3..=7, 2..=5);
    // Every face on centres: x in (2.5, 9.5] holds 3.5..=9.5, y in (3.5, 7.5] holds 4.5..=7.5.
    let c = cuboid([2.5, 3.5, 2.5], [9.5, 7.5, 6.5], false);
    assert_box("all faces on centres", &solid(&c), 3..=9, 4..=7, 2..=5);
    // Neither the winding nor the choice of diagonals changes anything.
    for (name, s) in [
        (
            "other diagonals",
            cuboid([2.5, 3.5, 2.5], [9.5, 7.5, 6.5], true),
        ),
        ("inward wound", c.flipped()),
        (
            "inward, other diagonals",
            cuboid([2.5, 3.5, 2.5], [9.5, 7.5, 6.5], true).flipped(),
        ),
    ] {
        assert_box(name, &solid(&s), 3..=9, 4..=7, 2..=5);
    }
    // Boxes leaving the grid are clipped: x centres 0.5..=3.5, y 10.5..=15.5, z 0.5..=3.5.
    let d = cuboid([-2.75, 10.25, -5.25], [3.75, 18.75, 4.5], false);
    assert_box("clipped below", &solid(&d), 0..=3, 10..=15, 0..=3);
    // A top face above the grid toggles whole columns; the bottom z = 10.25 leaves 10.5..=15.5.
    let e = cuboid([4.25, 4.25, 10.25], [6.75, 5.75, 20.5], false);
    assert_box("clipped above", &solid(&e), 4..=6, 4..=5, 10..=15);
}

#[test]
fn voxelize_places_a_box_as_computed_by_hand() {
    // A 10 x 6.5 x 3.25 box at (-3, 1.25, 7); size 20 gives voxels of 0.5 and 2 voxels of
    // padding: origin = lo - 1 = (-4, 0.25, 6), dims = (20, 13, ceil 6.5 = 7) + 4, and the box
    // spans [2, 22] x [2, 15] x [2, 8.5] in voxels. Centres inside: x 2.5..=21.5 (20), y
    // 2.5..=14.5 (13), z 2.5..=7.5 (6; the top face is on the centres of layer 8, outside).
    let m = cuboid([-3.0, 1.25, 7.0], [7.0, 7.75, 10.25], false).tri_mesh();
    let v = voxelize(&m, &options(20, Fill::Center)).unwrap();
    assert_eq!(v.dims, [24, 17, 11]);
    assert_eq!(v.voxel_size, 0.5);
    assert_eq!(v.origin, [-4.0, 0.25, 6.0]);
    assert_eq!(v.bytes.len(), 24 * 17 * 11);
    assert_eq!(v.report.triangles, 12);
    assert_eq!(v.report.samples, 24 * 17 * 11);
    assert_eq!(v.report.samples_inside, 20 * 13 * 6);
    assert_box(
        "placed box",
        &binary(&v, VoxelType::U8),
        2..=21,
        2..=14,
        2..=7,
    );
    // u16 holds the same voxels with H = 65535.
    let v16 = voxelize(
        &m,
        &Options {
            voxel_type: VoxelType::U16,
            ..options(20, Fill::Center)
        },
    )
    .unwrap();
    assert_eq!(v16.bytes.len(), 2 * 24 * 17 * 11);
    assert_box(
        "placed box, u16",
        &binary(&v16, VoxelType::U16),
        2..=21,
        2..=14,
        2..=7,
    );
}

// ---------------------------------------------------------------------------------------------
// 2. Voxel by voxel against the winding number

#[test]
fn sphere_and_torus_match_the_winding_number() {
    let sphere = icosphere([12.3, 11.7, 12.1], 9.3, 3);
    let t = check_generic("sphere", &sphere, [25, 24, 25]);
    eprintln!("sphere: {t:?}");
    let ring = torus([16.2, 15.9, 8.3], 10.1, 3.7, 48, 24);
    let t = check_generic("torus", &ring, [32, 32, 17]);
    eprintln!("torus: {t:?}");
    // Tilted, so that the rays cross the tube at every angle.
    let r = axis_angle([1.0, 0.3, 0.0], 0.9);
    let ring = torus([0.0; 3], 9.1, 3.3, 32, 16).rotated(&r, [0.0; 3]);
    let t = check_generic(
        "tilted torus",
        &ring.translated([14.3, 14.1, 14.2]),
        [29; 3],
    );
    eprintln!("tilted torus: {t:?}");
    // The same sphere placed by `voxelize` in model units (vertices off the 2^-16 lattice, so
    // disagreements within 2^-16 of the surface are excused and counted).
    let m = icosphere([0.31, -2.7, 5.05], 3.1, 3).tri_mesh();
    let v = voxelize(&m, &options(21, Fill::Center)).unwrap();
    let t = compare(
        "placed sphere",
        &binary(&v, VoxelType::U8),
        &placed_oracle(&m, &v),
        [0.0; 3],
        SNAP_BAND,
    );
    eprintln!("placed sphere: {t:?}");
    assert_eq!(t.on_surface, 0);
    assert!(t.excused <= 2, "{t:?}");
}

#[test]
fn rotated_cubes_and_grazing_faces_match_the_winding_number() {
    let mut rng = XorShift(7);
    for i in 0..64 {
        let r = rotation(&mut rng);
        let c = [
            rng.range(9.0, 11.0),
            rng.range(9.0, 11.0),
            rng.range(9.0, 11.0),
        ];
        let side = rng.range(3.0, 10.0);
        check_generic(
            &format!("rotated cube {i}"),
            &rotated_cube(c, side, &r),
            [20; 3],
        );
    }
    // Faces nearly parallel to z: tilts of the +-x and +-y faces down to a projected width of
    // a few lattice steps (8 * 1e-6 = 8e-6 voxels, half a step of 2^-16: snapped to 0 or 1
    // step), and tilts about a diagonal.
    for (k, angle) in [1e-2, 1e-3, 1e-4, 1e-5, 3e-6, 1e-6].into_iter().enumerate() {
        for (j, axis) in [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
            [1.0, -0.4, 0.0],
        ]
        .into_iter()
        .enumerate()
        {
            let r = axis_angle(axis, angle);
            let c = [10.1307, 9.8731, 10.3093];
            check_generic(
                &format!("grazing cube, axis {j}, tilt {angle:e}"),
                &rotated_cube(c, 8.0 + 0.3711 * k as f64, &r),
                [20; 3],
            );
            // Also tipped 90 degrees first, so the long axis of the tilt lies along x.
            let r2 = axis_angle([0.0, 0.0, 1.0], 0.5 * PI + angle);
            check_generic(
                &format!("grazing cube, axis {j}, tilt {angle:e}, turned"),
                &rotated_cube(c, 7.5, &r).rotated(&r2, c),
                [20; 3],
            );
        }
    }
}

#[test]
fn touching_objects_give_their_union() {
    let dims = [16; 3];
    let solid = |s: &Shape| voxelize_solid(&s.tri_mesh(), dims, grid_coords);
    // Shared faces on centres, by hand: the union box counts each shared centre once.
    // x = 6.5: union x in (2.5, 10.5] -> 3..=10; y in (3.25, 8.75] -> 3..=8; z [2.25, 9.75) -> 2..=9.
    let sx = cuboid([2.5, 3.25, 2.25], [6.5, 8.75, 9.75], false).with(&cuboid(
        [6.5, 3.25, 2.25],
        [10.5, 8.75, 9.75],
        true,
    ));
    assert_box("touching at x = 6.5", &solid(&sx), 3..=10, 3..=8, 2..=9);
    // y = 7.5: y in (3.5, 12.5] -> 4..=12.
    let sy = cuboid([2.25, 3.5, 2.25], [9.75, 7.5, 9.75], false).with(&cuboid(
        [2.25, 7.5, 2.25],
        [9.75, 12.5, 9.75],
        false,
    ));
    assert_box("touching at y = 7.5", &solid(&sy), 2..=9, 4..=12, 2..=9);
    // z = 6.5: z in [2.5, 11.5) -> 2..=10.
    let sz = cuboid([2.25, 3.25, 2.5], [9.75, 8.75, 6.5], true).with(&cuboid(
        [2.25, 3.25, 6.5],
        [9.75, 8.75, 11.5],
        false,
    ));
    assert_box("touching at z = 6.5", &solid(&sz), 2..=9, 3..=8, 2..=10);
    // The same with the perturbed oracle.
    for (name, s) in [("x", &sx), ("y", &sy), ("z", &sz)] {
        check_ties(&format!("touching at {name}, oracle"), s, dims);
    }
    // Generic placements: a small cube standing on a big one (its bottom inside the big top),
    // two rotated cubes sharing a face, two cubes sharing an edge.
    let big = cuboid([3.1, 2.9, 2.3], [15.7, 14.2, 9.6], false);
    let small = cuboid([6.3, 5.2, 9.6], [10.9, 11.3, 14.8], true);
    check_generic("cube on a cube", &big.with(&small), [19, 18, 18]);
    let mut rng = XorShift(11);
    for i in 0..6 {
        let r = rotation(&mut rng);
        let c = [12.2, 11.9, 12.1];
        let h = rng.range(2.0, 4.0);
        let a = cuboid([-2.0 * h, -h, -h], [0.0, h, h], false);
        let b = cuboid([0.0, -h, -h], [2.0 * h, h, h], true);
        let pair = a.clone().with(&b).rotated(&r, [0.0; 3]).translated(c);
        check_generic(&format!("rotated cubes sharing a face {i}"), &pair, [24; 3]);
        let e = cuboid([0.0, h, -h], [2.0 * h, 3.0 * h, h], false);
        let pair = a.with(&e).rotated(&r, [0.0; 3]).translated(c);
        check_generic(
            &format!("rotated cubes sharing an edge {i}"),
            &pair,
            [24; 3],
        );
    }
}

#[test]
fn nested_shells_give_the_hollow_shell() {
    let dims = [16; 3];
    // By hand: outer centres 1.5..=14.5 on each axis (14^3), inner 4..=9 x 5..=10 x 6..=11
    // (6^3) is left out: the XOR of the two solids.
    let outer = cuboid([1.25; 3], [14.75; 3], false);
    let inner = cuboid([4.25, 5.25, 6.25], [9.75, 10.75, 11.75], true);
    for (name, s) in [
        ("both outward", outer.clone().with(&inner)),
        ("inner inward", outer.clone().with(&inner.flipped())),
    ] {
        let grid = voxelize_solid(&s.tri_mesh(), dims, grid_coords);
        assert_eq!(grid.count(), 14 * 14 * 14 - 6 * 6 * 6, "{name}");
        for z in 0..16 {
            for y in 0..16 {
                for x in 0..16 {
                    let o = (1..=14).contains(&x) && (1..=14).contains(&y) && (1..=14).contains(&z);
                    let i = (4..=9).contains(&x) && (5..=10).contains(&y) && (6..=11).contains(&z);
                    assert_eq!(grid.get(x, y, z), o && !i, "{name}: ({x}, {y}, {z})");
                }
            }
        }
        // The winding number is 2 (or 0) in the hole: its parity agrees.
        check_generic(name, &s, dims);
    }
    // Three nested spheres: shell, then the innermost ball again.
    let c = [12.4, 12.2, 11.9];
    let s = icosphere(c, 10.3, 2)
        .with(&icosphere(c, 7.1, 2))
        .with(&icosphere(c, 3.9, 2).flipped());
    check_generic("nested spheres", &s, [25; 3]);
    // Nested rotated cubes.
    let r = rotation(&mut XorShift(3));
    let s = rotated_cube(c, 14.0, &r).with(&rotated_cube(c, 6.3, &rotation(&mut XorShift(4))));
    check_generic("nested rotated cubes", &s, [25; 3]);
}

#[test]
fn vertices_edges_and_faces_on_centres_follow_the_tie_rules() {
    let dims = [20; 3];
    let c = [9.5, 10.5, 9.5];
    // Vertices on centres; faces x +- y +- z = const through many centres; projected edges
    // from the poles are horizontal (d.y = 0) and pass through centres.
    for a in [1.0, 2.0, 3.0, 5.0, 7.0] {
        check_ties(&format!("octahedron {a}"), &octahedron(c, a), dims);
        check_ties(
            &format!("octahedron {a}, inward"),
            &octahedron(c, a).flipped(),
            dims,
        );
    }
    // Squares turned 45 degrees about z, corners on centres: projected edges of slope +-1
    // through centres, top and bottom faces on centres.
    for (b, h) in [(3.0, 4.0), (5.0, 7.0), (1.0, 1.0)] {
        let diamond =
            [[b, 0.0], [0.0, b], [-b, 0.0], [0.0, -b]].map(|q| [q[0] + c[0], q[1] + c[1]]);
        let s = prism(&diamond, c[2] - h, c[2] + h);
        check_ties(&format!("diamond prism {b}"), &s, dims);
    }
    // A hexagon-like prism with horizontal and slanted edges through centres.
    let hex = [
        [3.0, 0.0],
        [1.0, 2.0],
        [-1.0, 2.0],
        [-3.0, 0.0],
        [-1.0, -2.0],
        [1.0, -2.0],
    ]
    .map(|q| [q[0] + c[0], q[1] + c[1]]);
    check_ties(
        "hexagonal prism",
        &prism(&hex, c[2] - 3.0, c[2] + 2.0),
        dims,
    );
    // Boxes with every face on centres, nested and touching.
    let b = cuboid([2.5, 3.5, 1.5], [15.5, 16.5, 17.5], false)
        .with(&cuboid([5.5, 6.5, 4.5], [10.5, 11.5, 8.5], true))
        .with(&cuboid([10.5, 6.5, 4.5], [12.5, 11.5, 8.5], false));
    check_ties("nested and touching boxes on centres", &b, dims);
    // Random tetrahedra with vertices on centres (rays through vertices and along edges).
    let mut rng = XorShift(5);
    let mut made = 0;
    while made < 150 {
        let v: [V3; 4] = std::array::from_fn(|_| [0, 1, 2].map(|_| (rng.next() % 8) as f64 + 6.5));
        let vol = dot(sub(v[1], v[0]), cross(sub(v[2], v[0]), sub(v[3], v[0])));
        if vol.abs() < 1.0 {
            continue;
        }
        check_ties(&format!("tetrahedron {made} {v:?}"), &tetrahedron(v), dims);
        made += 1;
    }
}

// ---------------------------------------------------------------------------------------------
// 3. Volumes

#[test]
fn inside_counts_match_the_volume() {
    let (big, small) = (1.0, 0.375);
    for (name, shape, analytic) in [
        (
            "sphere",
            icosphere([0.2, -0.1, 0.05], 1.0, 5),
            4.0 / 3.0 * PI,
        ),
        (
            "torus",
            torus([0.0; 3], big, small, 256, 96),
            2.0 * PI * PI * big * small * small,
        ),
    ] {
        let m = shape.tri_mesh();
        let v = voxelize(&m, &options(64, Fill::Center)).unwrap();
        let count = binary(&v, VoxelType::U8).count() as f64;
        let s = v.voxel_size;
        // The polyhedron, in voxel units.
        let (poly, area) = volume_and_area(&triangles_of(&m, |p| p.map(|c| f64::from(c) / s)));
        let analytic = analytic / (s * s * s);
        // Each voxel's centre sample is off its share of the volume only near the surface. A
        // plane parallel to a grid plane at t in [-1/2, 1/2] voxel from the centres errs by
        // |t| per unit of area, the worst case for a plane: half a voxel times the area bounds
        // the error (the surfaces here are planes at the scale of a voxel).
        let bound = area / 2.0;
        eprintln!(
            "{name}: {count} voxels inside, polyhedron {poly:.1}, analytic {analytic:.1}, area {area:.0}: error {:.1} ({:.3}%) against a bound of {bound:.0}",
            count - poly,
            100.0 * (count - poly) / poly
        );
        assert!((count - poly).abs() <= bound, "{name}");
        assert!(
            (count - analytic).abs() <= bound + (analytic - poly).abs(),
            "{name}"
        );
        assert_eq!(v.report.samples_inside as f64, count);
    }
}

/// Builds a VOD 2 of `v`, meshes level 0 and returns the welded mesh's open edges, the volume
/// it encloses (model units) and its triangles.
fn mesh_of(v: &Voxelized, dir: &Path) -> (usize, f64, usize) {
    let t = VoxelType::U8;
    let path = dir.join("v.vod");
    let layout = VolumeLayout::new(v.dims, 16, t).unwrap();
    let grid = DenseGrid::new(v.dims, t, 16, &v.bytes);
    let scale = [v.voxel_size as f32; 3];
    build_vod2(&path, &layout, scale, &grid, &BuildOptions::default()).unwrap();
    let snap = Vod2::open(&path).unwrap().head();
    let raw = mesh_tiles(
        &snap,
        &level_tiles(&snap, 0),
        default_iso(t),
        &isovox_server::progress::Silent,
    )
    .unwrap();
    let mesh = weld(&raw);
    (open_edges(&mesh), enclosed_volume(&mesh), mesh.triangles())
}

#[test]
fn density_meshes_enclose_the_volume() {
    let dir = tempfile::tempdir().unwrap();
    let (big, small) = (1.0, 0.4);
    for (name, shape, analytic) in [
        ("sphere", icosphere([0.0; 3], 1.0, 5), 4.0 / 3.0 * PI),
        (
            "torus",
            torus([0.0; 3], big, small, 192, 96),
            2.0 * PI * PI * big * small * small,
        ),
    ] {
        let v = voxelize(&shape.tri_mesh(), &options(48, Fill::Density)).unwrap();
        let (open, enclosed, triangles) = mesh_of(&v, dir.path());
        let err = (enclosed - analytic) / analytic;
        eprintln!(
            "{name}: {triangles} triangles, encloses {enclosed:.4}, analytic {analytic:.4}, error {:.2}%",
            100.0 * err
        );
        assert!(triangles > 1000, "{name}");
        assert_eq!(open, 0, "{name}: the mesh of the density is not closed");
        assert!(err.abs() < 0.03, "{name}: error {:.2}%", 100.0 * err);
    }
}

// ---------------------------------------------------------------------------------------------
// 5. A closed model of a few hundred thousand triangles

#[test]
fn a_generated_world_mesh_voxelizes_back_to_the_world() {
    let dir = tempfile::tempdir().unwrap();
    let t = VoxelType::U8;
    let d = [176u32, 88, 176];
    let layout = VolumeLayout::new(d, 16, t).unwrap();
    let source = WorldSource::new(layout.clone(), 5);
    let path = dir.path().join("world.vod");
    build_vod2(&path, &layout, [1.0; 3], &source, &BuildOptions::default()).unwrap();
    // The source's own voxels: inside where value >= S.
    let [dx, dy, dz] = d.map(|c| c as usize);
    let mut inside = vec![false; dx * dy * dz];
    let b = layout.brick() as usize;
    let g = layout.grid(0);
    let mut buf = vec![0u8; layout.brick_bytes()];
    for bz in 0..g[2] {
        for by in 0..g[1] {
            for bx in 0..g[0] {
                buf.fill(0);
                source.fill(
                    BrickKey {
                        level: 0,
                        x: bx,
                        y: by,
                        z: bz,
                    },
                    &mut buf,
                );
                for k in 0..b {
                    for j in 0..b {
                        for i in 0..b {
                            let (x, y, z) = (
                                bx as usize * b + i,
                                by as usize * b + j,
                                bz as usize * b + k,
                            );
                            if x < dx && y < dy && z < dz {
                                inside[(z * dy + y) * dx + x] =
                                    u16::from(buf[(k * b + j) * b + i]) >= t.surface();
                            }
                        }
                    }
                }
            }
        }
    }
    let count = inside.iter().filter(|&&i| i).count();
    // The project's mesh of it: marching cubes at S - 0.5, welded, closed.
    let snap = Vod2::open(&path).unwrap().head();
    let raw = mesh_tiles(
        &snap,
        &level_tiles(&snap, 0),
        default_iso(t),
        &isovox_server::progress::Silent,
    )
    .unwrap();
    let mesh = weld(&raw);
    assert_eq!(open_edges(&mesh), 0);
    let model = TriMesh {
        positions: mesh.positions.clone(),
        triangles: mesh
            .indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect(),
    };
    let triangles = model.triangles.len();
    assert!(triangles > 200_000, "{triangles} triangles");
    let enclosed = enclosed_volume(&mesh);
    // Voxel (x, y, z) sits at mesh coordinates (x, y, z): in a grid with 2 voxels of padding
    // its centre is at p + 2.5. Once with the rays along the world's z (through the cliffs),
    // once along its y (through the ground), by swapping the axes.
    let start = std::time::Instant::now();
    let grid_z = voxelize_solid(&model, [dx + 4, dy + 4, dz + 4], |p| {
        p.map(|c| f64::from(c) + 2.5)
    });
    let solid_time = start.elapsed();
    let grid_y = voxelize_solid(&model, [dx + 4, dz + 4, dy + 4], |p| {
        [p[0], p[2], p[1]].map(|c| f64::from(c) + 2.5)
    });
    let v = voxelize(&model, &options(176, Fill::Center)).unwrap();
    for (name, grid, swap) in [
        ("rays along z", &grid_z, false),
        ("rays along y", &grid_y, true),
    ] {
        let mut differ = 0usize;
        let mut first = Vec::new();
        for z in 0..dz {
            for y in 0..dy {
                for x in 0..dx {
                    let got = if swap {
                        grid.get(x + 2, z + 2, y + 2)
                    } else {
                        grid.get(x + 2, y + 2, z + 2)
                    };
                    if got != inside[(z * dy + y) * dx + x] {
                        differ += 1;
                        if first.len() < 6 {
                            first.push((x, y, z));
                        }
                    }
                }
            }
        }
        eprintln!(
            "world {d:?}: {triangles} triangles, {count} voxels >= S, voxelized {} ({name}), {differ} voxels differ, mesh encloses {enclosed:.0}; parity pass {:.0} ms",
            grid.count(),
            solid_time.as_secs_f64() * 1e3
        );
        // Marching cubes puts the surface between samples of opposite sides, so every sample
        // (a voxel centre here) lies on its own side: the counts agree exactly, voxel by voxel.
        assert_eq!(differ, 0, "{name}: e.g. (x, y, z) {first:?}");
        assert_eq!(grid.count() as usize, count, "{name}");
    }
    // Through `voxelize` (its own placement, not aligned with the samples): the count agrees
    // within the discretisation error, half a voxel times the area.
    let s = v.voxel_size;
    let (_, area) = volume_and_area(&triangles_of(&model, |p| p.map(|c| f64::from(c) / s)));
    let placed = binary(&v, t).count() as f64 * s * s * s;
    eprintln!("world via voxelize: {placed:.0} (voxel size {s}), area {area:.0}");
    assert!((placed - count as f64).abs() <= area / 2.0);
    assert!((enclosed - count as f64).abs() <= area / 2.0);
}

// ---------------------------------------------------------------------------------------------
// 6. Files

fn write_binary_stl(path: &Path, m: &TriMesh, header: &[u8]) {
    let mut out = vec![0u8; 80];
    out[..header.len()].copy_from_slice(header);
    out.extend_from_slice(&(m.triangles.len() as u32).to_le_bytes());
    for t in &m.triangles {
        out.extend_from_slice(&[0u8; 12]);
        for &i in t {
            for c in m.positions[i as usize] {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        out.extend_from_slice(&[0, 0]);
    }
    std::fs::write(path, out).unwrap();
}

fn write_ascii_stl(path: &Path, m: &TriMesh) {
    let mut s = String::from("solid test\n");
    for t in &m.triangles {
        s.push_str("  facet normal 0 0 0\n    outer loop\n");
        for &i in t {
            let p = m.positions[i as usize];
            s.push_str(&format!("      vertex {} {} {}\n", p[0], p[1], p[2]));
        }
        s.push_str("    endloop\n  endfacet\n");
    }
    s.push_str("endsolid test\n");
    std::fs::write(path, s).unwrap();
}

fn write_obj(path: &Path, positions: &[[f32; 3]], faces: &[Vec<u32>]) {
    let mut s = String::from("# test\no test\n");
    for p in positions {
        s.push_str(&format!("v {} {} {}\n", p[0], p[1], p[2]));
    }
    for f in faces {
        let ids: Vec<String> = f.iter().map(|i| (i + 1).to_string()).collect();
        s.push_str(&format!("f {}\n", ids.join(" ")));
    }
    std::fs::write(path, s).unwrap();
}

fn write_ply_ascii(path: &Path, positions: &[[f32; 3]], faces: &[Vec<u32>]) {
    let mut s = format!(
        "ply\nformat ascii 1.0\ncomment test\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        positions.len(),
        faces.len()
    );
    for p in positions {
        s.push_str(&format!("{} {} {}\n", p[0], p[1], p[2]));
    }
    for f in faces {
        let ids: Vec<String> = f.iter().map(u32::to_string).collect();
        s.push_str(&format!("{} {}\n", f.len(), ids.join(" ")));
    }
    std::fs::write(path, s).unwrap();
}

fn write_ply_binary(path: &Path, positions: &[[f32; 3]], faces: &[Vec<u32>]) {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        positions.len(),
        faces.len()
    )
    .into_bytes();
    for p in positions {
        for c in p {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    for f in faces {
        out.push(f.len() as u8);
        for i in f {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    std::fs::write(path, out).unwrap();
}

fn glb_of(m: &TriMesh) -> Vec<u8> {
    encode_glb(&Mesh {
        positions: m.positions.clone(),
        normals: vec![[0.0, 0.0, 1.0]; m.positions.len()],
        indices: m.triangles.iter().flatten().copied().collect(),
        materials: vec![],
    })
}

/// A .gltf with its buffer in a .bin beside it and two nested nodes: the parent turns by 90
/// degrees about z and moves by (3, -5, 7) (a matrix), the child scales x by 2. World:
/// (x, y, z) -> (-y + 3, 2x - 5, z + 7).
fn write_gltf(path: &Path, m: &TriMesh) {
    let mut bin = Vec::new();
    for p in &m.positions {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let at = bin.len();
    for i in m.triangles.iter().flatten() {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let (lo, hi) = m.bounds().unwrap();
    let json = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [
            {"matrix": [0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1, 0, 3, -5, 7, 1], "children": [1]},
            {"scale": [2, 1, 1], "mesh": 0}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": m.positions.len(), "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5125, "count": 3 * m.triangles.len(), "type": "SCALAR"}
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": at},
            {"buffer": 0, "byteOffset": at, "byteLength": bin.len() - at}
        ],
        "buffers": [{"uri": "m.bin", "byteLength": bin.len()}]
    });
    std::fs::write(path.with_file_name("m.bin"), &bin).unwrap();
    std::fs::write(path, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
}

/// The positions of each triangle's corners, in order.
fn corners(m: &TriMesh) -> Vec<[[f32; 3]; 3]> {
    m.triangles
        .iter()
        .map(|t| t.map(|i| m.positions[i as usize]))
        .collect()
}

#[test]
fn every_file_format_gives_the_same_voxels() {
    let dir = tempfile::tempdir().unwrap();
    let r = axis_angle([0.3, 1.0, 0.2], 0.7);
    let shape = torus([0.0; 3], 1.3, 0.45, 24, 12)
        .rotated(&r, [0.0; 3])
        .translated([10.1, -3.7, 2.9]);
    let m = shape.tri_mesh();
    let opts = options(28, Fill::Density);
    let want = voxelize(&m, &opts).unwrap();
    let faces: Vec<Vec<u32>> = m.triangles.iter().map(|t| t.to_vec()).collect();
    let files = [
        "binary.stl",
        "ascii.stl",
        "mesh.obj",
        "ascii.ply",
        "binary.ply",
        "mesh.glb",
    ];
    write_binary_stl(&dir.path().join(files[0]), &m, b"isovox test, binary");
    write_ascii_stl(&dir.path().join(files[1]), &m);
    write_obj(&dir.path().join(files[2]), &m.positions, &faces);
    write_ply_ascii(&dir.path().join(files[3]), &m.positions, &faces);
    write_ply_binary(&dir.path().join(files[4]), &m.positions, &faces);
    std::fs::write(dir.path().join(files[5]), glb_of(&m)).unwrap();
    for f in files {
        let loaded = load_model(&dir.path().join(f)).unwrap();
        assert_eq!(corners(&loaded), corners(&m), "{f}: triangles differ");
        let got = voxelize(&loaded, &opts).unwrap();
        assert_eq!(got.dims, want.dims, "{f}");
        assert_eq!(got.origin, want.origin, "{f}");
        assert!(got.bytes == want.bytes, "{f}: voxels differ");
    }
    // Upper-case extensions are recognised too.
    std::fs::copy(dir.path().join("mesh.obj"), dir.path().join("UPPER.OBJ")).unwrap();
    assert_eq!(
        corners(&load_model(&dir.path().join("UPPER.OBJ")).unwrap()),
        corners(&m)
    );
    // glTF with a .bin and node transforms: each position goes to (-y + 3, 2x - 5, z + 7)
    // (exact in f32: one rounding, as the matrix product has entries 0, +-1 and 2).
    let gltf = dir.path().join("mesh.gltf");
    write_gltf(&gltf, &m);
    let moved = TriMesh {
        positions: m
            .positions
            .iter()
            .map(|p| [-p[1] + 3.0, 2.0 * p[0] - 5.0, p[2] + 7.0])
            .collect(),
        triangles: m.triangles.clone(),
    };
    let loaded = load_model(&gltf).unwrap();
    assert_eq!(corners(&loaded), corners(&moved), "gltf node transforms");
    assert!(voxelize(&loaded, &opts).unwrap().bytes == voxelize(&moved, &opts).unwrap().bytes);
}

#[test]
fn polygons_are_fanned_into_the_same_solid() {
    // A hexagonal prism with hexagon caps and quad sides (OBJ and PLY), against its
    // triangulation fanned from other corners: planar convex polygons, the same solid.
    let dir = tempfile::tempdir().unwrap();
    let mut positions = Vec::new();
    for z in [0.3f32, 4.55] {
        for k in 0..6 {
            let a = PI / 3.0 * k as f64 + 0.1;
            positions.push([
                (3.2 * a.cos()) as f32 + 1.25,
                (3.2 * a.sin()) as f32 - 0.5,
                z,
            ]);
        }
    }
    let mut faces: Vec<Vec<u32>> = vec![(0..6).rev().collect(), (6..12).collect()];
    for k in 0..6u32 {
        let n = (k + 1) % 6;
        faces.push(vec![k, n, n + 6, k + 6]);
    }
    let mut triangles = Vec::new();
    for f in &faces {
        // Fanned from the polygon's last corner (the readers fan from the first).
        let l = f.len();
        for i in 0..l - 2 {
            triangles.push([f[l - 1], f[i], f[i + 1]]);
        }
    }
    let m = TriMesh {
        positions: positions.clone(),
        triangles,
    };
    let opts = options(24, Fill::Density);
    let want = voxelize(&m, &opts).unwrap();
    assert!(want.report.samples_inside > 1000);
    write_obj(&dir.path().join("p.obj"), &positions, &faces);
    write_ply_ascii(&dir.path().join("p.ply"), &positions, &faces);
    for f in ["p.obj", "p.ply"] {
        let loaded = load_model(&dir.path().join(f)).unwrap();
        assert_eq!(loaded.triangles.len(), 2 * 4 + 6 * 2, "{f}");
        let got = voxelize(&loaded, &opts).unwrap();
        assert!(got.bytes == want.bytes, "{f}: voxels differ");
    }
}

#[test]
fn binary_stl_whose_header_starts_with_solid_loads() {
    // Many exporters write "solid <name>" into the 80-byte header of binary STL files; the file
    // is binary all the same (its size is exactly 84 + 50 * triangles).
    let dir = tempfile::tempdir().unwrap();
    // A box (12 triangles) and a pentagonal bipyramid (10 triangles: the count's first byte is
    // 0x0a, a line feed, so the header and count read as one valid text line).
    let pentagon: Vec<V3> = (0..5)
        .map(|k| {
            let a = 0.4 * PI * k as f64;
            [a.cos(), a.sin(), 0.0]
        })
        .collect();
    let mut p = pentagon.clone();
    p.push([0.0, 0.0, 1.0]);
    p.push([0.0, 0.0, -1.0]);
    let mut t = Vec::new();
    for k in 0..5u32 {
        t.push([k, (k + 1) % 5, 5]);
        t.push([k, (k + 1) % 5, 6]);
    }
    let bipyramid = Shape { p, t }.outward_from([0.0; 3]);
    let mut failures = Vec::new();
    for (name, shape) in [
        ("box", cuboid([0.0; 3], [1.0, 2.0, 3.0], false)),
        ("bipyramid", bipyramid),
    ] {
        let m = shape.tri_mesh();
        let path = dir.path().join(format!("{name}.stl"));
        write_binary_stl(&path, &m, b"solid part, exported as binary");
        assert_eq!(
            std::fs::metadata(&path).unwrap().len(),
            84 + 50 * m.triangles.len() as u64
        );
        match load_model(&path) {
            Ok(loaded) => assert_eq!(corners(&loaded), corners(&m), "{name}"),
            Err(e) => failures.push(format!("{name} ({} triangles): {e}", m.triangles.len())),
        }
    }
    // Regression (found by this test, now fixed): the STL reader (stl_io's probe, used as is by `load_stl`) takes a file for ASCII
    // when its first line is valid UTF-8 and starts with "solid "; a binary STL with such a
    // header whose bytes up to the first 0x0a are valid UTF-8 (here: 10 triangles) then fails
    // to load. The file's size (84 + 50 n) identifies it as binary.
    assert!(
        failures.is_empty(),
        "binary STL with a \"solid\" header refused: {failures:?}"
    );
}

/// Loads and voxelizes `path`, catching panics: the outcome as text, or "panic".
fn load_and_voxelize(path: &Path) -> Result<String, String> {
    let p = path.to_path_buf();
    let outcome = std::panic::catch_unwind(move || -> Result<String, String> {
        let m = load_model(&p).map_err(|e| format!("load: {e}"))?;
        let v = voxelize(&m, &options(16, Fill::Center)).map_err(|e| format!("voxelize: {e}"))?;
        Ok(format!("{} voxels", v.report.samples_inside))
    });
    match outcome {
        Ok(r) => r,
        Err(_) => Err("panic".into()),
    }
}

#[test]
fn damaged_files_are_errors_not_panics() {
    let dir = tempfile::tempdir().unwrap();
    let m = torus([0.0; 3], 1.0, 0.4, 12, 8).tri_mesh();
    let faces: Vec<Vec<u32>> = m.triangles.iter().map(|t| t.to_vec()).collect();
    let d = dir.path();
    write_binary_stl(&d.join("good.stl"), &m, b"binary");
    write_ascii_stl(&d.join("good_ascii.stl"), &m);
    write_obj(&d.join("good.obj"), &m.positions, &faces);
    write_ply_ascii(&d.join("good.ply"), &m.positions, &faces);
    write_ply_binary(&d.join("good_binary.ply"), &m.positions, &faces);
    std::fs::write(d.join("good.glb"), glb_of(&m)).unwrap();
    // (name, bytes, whether it must be refused): truncated files, noise and bad indices must
    // be; a file damaged in the middle may still be a valid closed model (the damage may fall
    // on normals, say), so it must only not panic.
    let mut cases: Vec<(String, Vec<u8>, bool)> = Vec::new();
    for (good, ext) in [
        ("good.stl", "stl"),
        ("good_ascii.stl", "stl"),
        ("good.obj", "obj"),
        ("good.ply", "ply"),
        ("good_binary.ply", "ply"),
        ("good.glb", "glb"),
    ] {
        let bytes = std::fs::read(d.join(good)).unwrap();
        assert!(load_and_voxelize(&d.join(good)).is_ok(), "{good}");
        let n = bytes.len();
        for cut in [0, 1, 7, 40, 83, 84, 100, n / 3, n / 2, n - 60] {
            let name = format!("{good} cut to {cut}.{ext}");
            cases.push((name, bytes[..cut].to_vec(), true));
        }
        let mut junk = bytes.clone();
        for (k, b) in junk[n / 2..n / 2 + 64].iter_mut().enumerate() {
            *b = (k as u8).wrapping_mul(37).wrapping_add(0x9c);
        }
        cases.push((format!("{good} damaged.{ext}"), junk, false));
    }
    let mut rng = XorShift(9);
    for ext in ["stl", "obj", "ply", "glb", "gltf"] {
        let noise: Vec<u8> = (0..3000).map(|_| rng.next() as u8).collect();
        cases.push((format!("noise.{ext}"), noise, true));
        let text = b"this is not a model\n".to_vec();
        cases.push((format!("text.{ext}"), text, true));
    }
    // Indices out of range, a vertex without y and z, a lying triangle count.
    let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n".to_vec();
    cases.push(("bad index.obj".into(), obj, true));
    let head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
    let ply = format!("{head}0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n").into_bytes();
    cases.push(("bad index.ply".into(), ply, true));
    let ply = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n0\n1\n2\n";
    cases.push(("bad ply header.ply".into(), ply.to_vec(), true));
    let mut lying = std::fs::read(d.join("good.stl")).unwrap();
    lying[80..84].copy_from_slice(&1_000_000u32.to_le_bytes());
    cases.push(("lying count.stl".into(), lying, true));
    cases.push(("unknown.xyz".into(), b"1 2 3\n".to_vec(), true));
    let mut failures = Vec::new();
    for (name, bytes, refuse) in &cases {
        let path = d.join(name);
        std::fs::write(&path, bytes).unwrap();
        match load_and_voxelize(&path) {
            Err(e) if e == "panic" => failures.push(format!("{name}: panicked")),
            Err(_) => {}
            Ok(r) if *refuse => failures.push(format!("{name}: accepted ({r})")),
            Ok(_) => {}
        }
    }
    assert!(
        failures.is_empty(),
        "damaged files not reported as errors:\n{}",
        failures.join("\n")
    );
    assert!(matches!(
        load_model(&d.join("unknown.xyz")),
        Err(LoadError::UnknownFormat(_))
    ));
    assert!(matches!(
        load_model(&d.join("missing.stl")),
        Err(LoadError::Read { .. })
    ));
}

#[test]
fn gltf_triangle_strips_and_fans_are_not_dropped() {
    // glTF has three triangle modes: 4 (list), 5 (strip), 6 (fan). One primitive per mode, each
    // a closed, disjoint solid: a box as a list, a tetrahedron as the strip 0 1 2 3 0 1 (its 4
    // faces), a square bipyramid's upper half as a fan around the apex plus the lower half as a
    // second fan. Loading must give 12 + 4 + 4 + 4 triangles, or refuse the file; silently dropping
    // primitives would voxelize a different model.
    let dir = tempfile::tempdir().unwrap();
    let cube = cuboid([0.0; 3], [1.0; 3], false).tri_mesh();
    let tet: Vec<[f32; 3]> = vec![
        [3.0, 0.0, 0.0],
        [4.0, 0.0, 0.0],
        [3.0, 1.0, 0.0],
        [3.0, 0.0, 1.0],
    ];
    let square = |z: f32| -> Vec<[f32; 3]> {
        vec![
            [6.5, 0.5, z],
            [7.0, 0.0, 0.5],
            [7.0, 1.0, 0.5],
            [6.0, 1.0, 0.5],
            [6.0, 0.0, 0.5],
        ]
    };
    let prims: Vec<(Vec<[f32; 3]>, Vec<u32>, u32)> = vec![
        (
            cube.positions.clone(),
            cube.triangles.iter().flatten().copied().collect(),
            4,
        ),
        (tet, vec![0, 1, 2, 3, 0, 1], 5),
        (square(1.0), vec![0, 1, 2, 3, 4, 1], 6),
        (square(0.0), vec![0, 1, 4, 3, 2, 1], 6),
    ];
    let mut bin = Vec::new();
    let mut accessors = Vec::new();
    let mut views = Vec::new();
    let mut primitives = Vec::new();
    for (positions, indices, mode) in &prims {
        let at = bin.len();
        for p in positions {
            for c in p {
                bin.extend_from_slice(&c.to_le_bytes());
            }
        }
        let lo: Vec<f32> = (0..3)
            .map(|a| positions.iter().map(|p| p[a]).fold(f32::INFINITY, f32::min))
            .collect();
        let hi: Vec<f32> = (0..3)
            .map(|a| {
                positions
                    .iter()
                    .map(|p| p[a])
                    .fold(f32::NEG_INFINITY, f32::max)
            })
            .collect();
        views
            .push(serde_json::json!({"buffer": 0, "byteOffset": at, "byteLength": bin.len() - at}));
        accessors.push(serde_json::json!({"bufferView": views.len() - 1, "componentType": 5126, "count": positions.len(), "type": "VEC3", "min": lo, "max": hi}));
        let at = bin.len();
        for i in indices {
            bin.extend_from_slice(&i.to_le_bytes());
        }
        views
            .push(serde_json::json!({"buffer": 0, "byteOffset": at, "byteLength": bin.len() - at}));
        accessors.push(serde_json::json!({"bufferView": views.len() - 1, "componentType": 5125, "count": indices.len(), "type": "SCALAR"}));
        primitives.push(serde_json::json!({"attributes": {"POSITION": accessors.len() - 2}, "indices": accessors.len() - 1, "mode": mode}));
    }
    let json = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": primitives}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"uri": "m.bin", "byteLength": bin.len()}]
    });
    let path = dir.path().join("modes.gltf");
    std::fs::write(dir.path().join("m.bin"), &bin).unwrap();
    std::fs::write(&path, serde_json::to_vec(&json).unwrap()).unwrap();
    match load_model(&path) {
        // Regression (found by this test, now fixed): `load_gltf` skips every primitive whose
        // mode is not 4 without a word; here only the box's 12 triangles arrive.
        Ok(m) => assert_eq!(
            m.triangles.len(),
            12 + 4 + 4 + 4,
            "triangles loaded from list, strip and fan primitives"
        ),
        Err(e) => eprintln!("refused: {e}"),
    }
}

// ---------------------------------------------------------------------------------------------
// 7. Non-watertight input

/// A box [0, 4] x [0, 2] x [0, 3] with its top (z = 3) removed: 10 triangles, 17 edges (12
/// sides and 5 diagonals), of which the 4 around the hole are used once.
fn open_box() -> Shape {
    let mut s = cuboid([0.0; 3], [4.0, 2.0, 3.0], false);
    let top: Vec<usize> = (0..s.t.len())
        .filter(|&i| s.t[i].iter().all(|&v| s.p[v as usize][2] == 3.0))
        .collect();
    assert_eq!(top.len(), 2);
    s.t.remove(top[1]);
    s.t.remove(top[0]);
    s
}

/// The box [0, 4] x [0, 2] x [0, 2] with an inner wall at x = 2 meeting the hull along edges
/// shared by the hull: 12 vertices, 2 + 2 + 16 hull triangles and 2 wall triangles; 20 edges
/// along the axes and 11 diagonals = 31 edges; the wall's 4 sides are used by two hull
/// triangles and the wall, 3 times.
fn walled_box() -> Shape {
    let left = cuboid([0.0; 3], [2.0, 2.0, 2.0], false);
    let right = cuboid([2.0, 0.0, 0.0], [4.0, 2.0, 2.0], false);
    let mut s = left.with(&right);
    // Keep one copy of the shared face x = 2: drop the right box's.
    s.t.retain(|t| !(t.iter().all(|&v| s.p[v as usize][0] == 2.0) && t.iter().all(|&v| v >= 8)));
    // Weld the right box's vertices at x = 2 onto the left box's (same positions anyway).
    s
}

#[test]
fn open_models_are_refused_with_the_reason() {
    let check = |name: &str, s: &Shape, odd: usize, edges: usize| {
        let e = voxelize(&s.tri_mesh(), &options(8, Fill::Center)).unwrap_err();
        match e {
            VoxelizeError::NotWatertight { odd: o, edges: n } => {
                assert_eq!((o, n), (odd, edges), "{name}");
            }
            other => panic!("{name}: {other}"),
        }
        let text = e.to_string();
        assert!(text.contains("not watertight"), "{name}: {text}");
        assert!(text.contains("--allow-open"), "{name}: {text}");
    };
    check("open box", &open_box(), 4, 17);
    check("walled box", &walled_box(), 4, 31);
    // A wall whose sides are not hull edges (the hull is not split): used once each; 18 hull
    // edges + 4 wall sides + 1 wall diagonal.
    let wall = Shape {
        p: vec![
            [2.0, 0.0, 0.0],
            [2.0, 2.0, 0.0],
            [2.0, 2.0, 2.0],
            [2.0, 0.0, 2.0],
        ],
        t: vec![[0, 1, 2], [0, 2, 3]],
    };
    check(
        "wall through a box",
        &cuboid([0.0; 3], [4.0, 2.0, 2.0], false).with(&wall),
        4,
        23,
    );
    // A wall on the hull (the top face doubled): its 4 sides are used 3 times.
    let s = cuboid([0.0; 3], [4.0, 2.0, 3.0], false);
    let top: Vec<[u32; 3]> =
        s.t.iter()
            .filter(|t| t.iter().all(|&v| s.p[v as usize][2] == 3.0))
            .copied()
            .collect();
    let mut doubled = s.clone();
    doubled.t.extend(top);
    check("doubled top", &doubled, 4, 18);
    // A hole that vertices merely meet (a separate vertex at the same position) is no hole: the
    // check welds by position.
    let mut split = cuboid([0.0; 3], [4.0, 2.0, 3.0], false);
    split.p.push(split.p[7]);
    let n = split.p.len() as u32 - 1;
    for t in &mut split.t[..3] {
        for v in t.iter_mut() {
            if *v == 7 {
                *v = n;
            }
        }
    }
    assert!(voxelize(&split.tri_mesh(), &options(8, Fill::Center)).is_ok());
    // With allow_open parity decides. The open box (size 8: voxels of 0.5, the box at
    // [2, 10] x [2, 6] x [2, 8]) keeps only its bottom as a horizontal face, which toggles the
    // centres below it: layers 0 and 1 under the box (x 2..=9, y 2..=5), nothing above.
    let allow = Options {
        allow_open: true,
        ..options(8, Fill::Center)
    };
    let v = voxelize(&open_box().tri_mesh(), &allow).unwrap();
    assert_eq!(v.dims, [12, 8, 10]);
    assert_box(
        "open box, allowed",
        &binary(&v, VoxelType::U8),
        2..=9,
        2..=5,
        0..=1,
    );
    // The walled box: the wall is parallel to the rays and toggles nothing: the plain box,
    // [2, 10] x [2, 6] x [2, 6] in voxels.
    let v = voxelize(&walled_box().tri_mesh(), &allow).unwrap();
    assert_box(
        "walled box, allowed",
        &binary(&v, VoxelType::U8),
        2..=9,
        2..=5,
        2..=5,
    );
    // Nothing to voxelize, or out-of-range options.
    assert!(matches!(
        voxelize(&TriMesh::default(), &options(8, Fill::Center)),
        Err(VoxelizeError::Empty)
    ));
    let cube = cuboid([0.0; 3], [1.0; 3], false).tri_mesh();
    for o in [
        options(0, Fill::Center),
        options(5000, Fill::Center),
        Options {
            supersample: 0,
            ..options(8, Fill::Density)
        },
        Options {
            supersample: 5,
            ..options(8, Fill::Density)
        },
    ] {
        assert!(matches!(
            voxelize(&cube, &o),
            Err(VoxelizeError::Invalid(_))
        ));
    }
    let flat = Shape {
        p: vec![[0.0; 3], [0.0; 3], [0.0; 3]],
        t: vec![[0, 1, 2]],
    };
    assert!(matches!(
        voxelize(&flat.tri_mesh(), &options(8, Fill::Center)),
        Err(VoxelizeError::Invalid(_))
    ));
}

/// The faces of a tetrahedron over points 0..4, each edge used twice.
const TETRA: [[u32; 3]; 4] = [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]];

#[test]
fn models_that_enclose_no_volume_are_refused() {
    // Edge counting alone takes these for closed: every edge is used twice. None has an inside.
    let cases = [
        // Four points on a line: four triangles of zero area.
        (
            "zero-area triangles",
            Shape {
                p: vec![[0.0; 3], [1.0; 3], [2.0; 3], [3.0; 3]],
                t: TETRA.to_vec(),
            },
        ),
        // Four points in one plane: triangles of positive area folded onto each other.
        (
            "coplanar tetrahedron",
            Shape {
                p: vec![[0.0; 3], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [1.0, 1.0, 0.0]],
                t: TETRA.to_vec(),
            },
        ),
        // One triangle and its back face, tilted so no bounding-box side is 0.
        (
            "two faces back to back",
            Shape {
                p: vec![[0.0; 3], [4.0, 0.0, 1.0], [0.0, 4.0, 2.0]],
                t: vec![[0, 1, 2], [0, 2, 1]],
            },
        ),
    ];
    for (name, shape) in &cases {
        let e = voxelize(&shape.tri_mesh(), &options(8, Fill::Center)).unwrap_err();
        assert!(
            matches!(e, VoxelizeError::Flat { triangles } if triangles == shape.t.len()),
            "{name}: {e:?}"
        );
        let text = e.to_string();
        assert!(
            text.contains("not watertight") && text.contains("no volume"),
            "{name}: {text}"
        );
    }
    // The same faces over four points in general position bound a solid: accepted, and the
    // check does not depend on the winding.
    let tetra = Shape {
        p: vec![[0.0; 3], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 4.0]],
        t: TETRA.to_vec(),
    };
    assert!(voxelize(&tetra.tri_mesh(), &options(8, Fill::Center)).is_ok());
    assert!(voxelize(&tetra.flipped().tri_mesh(), &options(8, Fill::Center)).is_ok());
    // A thin solid is still a solid: a slab 1/1000 as thick as it is wide.
    let slab = cuboid([0.0; 3], [1000.0, 1000.0, 1.0], false);
    assert!(isovox_server::voxelize::check_closed(&slab.tri_mesh()).is_ok());
}

#[test]
fn out_of_range_padding_is_an_error() {
    // Options are validated (size, supersample): so must the padding be. u32::MAX voxels of
    // padding on each side cannot be placed (2 * padding overflows u32); the answer must be an
    // error, not an arithmetic overflow (a panic with debug assertions, a silently empty volume
    // without them).
    let cube = cuboid([0.0; 3], [1.0; 3], false).tri_mesh();
    let o = Options {
        padding: u32::MAX,
        ..options(8, Fill::Center)
    };
    let r = std::panic::catch_unwind(|| voxelize(&cube, &o).map(|v| v.dims));
    // Regression (found by this test, now fixed): `voxelize` validates size and supersample but
    // not padding, and computes `2 * padding` in u32 unchecked (mod.rs, `dims`).
    assert!(
        matches!(r, Ok(Err(VoxelizeError::Invalid(_)))),
        "padding u32::MAX: {}",
        match &r {
            Ok(Ok(d)) => format!("accepted, dims {d:?}"),
            Ok(Err(e)) => format!("error {e}"),
            Err(_) => "panicked".into(),
        }
    );
}

#[test]
fn triangles_far_larger_than_the_grid_are_clipped() {
    // `voxelize_solid` takes any transform, so a model may extend far beyond the grid (a ground
    // slab under a small window of a scene). A slab 200,000 voxels wide, z in [2.25, 5.75]:
    // every column of a 16^3 grid holds layers 2..=5.
    let slab = cuboid([-1e5, -1e5, 2.25], [1e5, 1e5, 5.75], false).tri_mesh();
    let r = std::panic::catch_unwind(|| voxelize_solid(&slab, [16; 3], grid_coords));
    // Regression (found by this test, now fixed): the fixed-point edge functions (solid.rs, `edge`)
    // multiply two 16.16 differences in i64, which overflows once a projected triangle spans
    // more than sqrt(2^63) / 2^16 = 46,341 voxels.
    let grid =
        r.unwrap_or_else(|_| panic!("voxelize_solid panicked on a slab 200,000 voxels wide"));
    assert_box("wide slab", &grid, 0..=15, 0..=15, 2..=5);
    // 40,000 voxels wide (below the limit) is fine.
    let slab = cuboid([-2e4, -2e4, 2.25], [2e4, 2e4, 5.75], false).tri_mesh();
    assert_box(
        "slab 40,000 wide",
        &voxelize_solid(&slab, [16; 3], grid_coords),
        0..=15,
        0..=15,
        2..=5,
    );
}

#[test]
fn the_command_refuses_an_open_model() {
    let dir = tempfile::tempdir().unwrap();
    let open = dir.path().join("open.stl");
    write_binary_stl(&open, &open_box().tri_mesh(), b"open box");
    let out = dir.path().join("x.vod");
    let run = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_isovox"))
            .args(args)
            .env_remove("ISOVOX_LOG")
            .output()
            .unwrap()
    };
    let o = run(&[
        "voxelize",
        open.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--size",
        "32",
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(stderr.contains("error:"), "{stderr}");
    assert!(stderr.contains("not watertight"), "{stderr}");
    assert!(stderr.contains("4 of its 17 edges"), "{stderr}");
    assert!(stderr.contains("--allow-open"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(!out.exists(), "a file was written");
    // With --allow-open it is written.
    let o = run(&[
        "voxelize",
        open.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--size",
        "32",
        "--allow-open",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.exists());
    // A closed box: the VOD has the dimensions computed by hand (size 8, padding 2: a 4 x 2 x 3
    // box in voxels of 0.5 -> 8 x 4 x 6 + 4) and the voxel size as its scale.
    let closed = dir.path().join("closed.obj");
    let cube = cuboid([0.0; 3], [4.0, 2.0, 3.0], false).tri_mesh();
    let faces: Vec<Vec<u32>> = cube.triangles.iter().map(|t| t.to_vec()).collect();
    write_obj(&closed, &cube.positions, &faces);
    let out = dir.path().join("closed.vod");
    let o = run(&[
        "voxelize",
        closed.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--size",
        "8",
        "--fill",
        "center",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let vod = Vod2::open(&out).unwrap();
    assert_eq!(vod.head().layout().dims(), [12, 8, 10]);
    assert_eq!(vod.header().voxel_scale, [0.5; 3]);
}

// ---------------------------------------------------------------------------------------------
// 8. Conservative fills

#[test]
fn conservative_fills_match_hand_counts() {
    // The placed box of `voxelize_places_a_box_as_computed_by_hand`: [2, 22] x [2, 15] x
    // [2, 8.5] in voxels. Wholly inside (the closed voxel [i, i + 1] strictly inside, as a
    // voxel touching the surface is not): x 3..=20, y 3..=13, z 3..=7. Touched (the closed voxel
    // meets the closed box): x 1..=22, y 1..=15, z 1..=8.
    let m = cuboid([-3.0, 1.25, 7.0], [7.0, 7.75, 10.25], false).tri_mesh();
    let inside = voxelize(&m, &options(20, Fill::Inside)).unwrap();
    assert_box(
        "inside",
        &binary(&inside, VoxelType::U8),
        3..=20,
        3..=13,
        3..=7,
    );
    let touched = voxelize(&m, &options(20, Fill::Touched)).unwrap();
    assert_box(
        "touched",
        &binary(&touched, VoxelType::U8),
        1..=22,
        1..=15,
        1..=8,
    );
    // A box with no face on a voxel boundary or centre: a 10 x 6.3 x 3.7 box, size 20 ->
    // [2, 22] x [2, 14.6] x [2, 9.4]. Inside: x 3..=20, y 3..=13, z 3..=8; touched: x 1..=22,
    // y 1..=14, z 1..=9; centres: x 2..=21, y 2..=14, z 2..=8.
    let m = cuboid([0.0; 3], [10.0, 6.3, 3.7], true).tri_mesh();
    let g = |f| binary(&voxelize(&m, &options(20, f)).unwrap(), VoxelType::U8);
    assert_box("inside 2", &g(Fill::Inside), 3..=20, 3..=13, 3..=8);
    assert_box("centre 2", &g(Fill::Center), 2..=21, 2..=14, 2..=8);
    assert_box("touched 2", &g(Fill::Touched), 1..=22, 1..=14, 1..=9);
}

#[test]
fn conservative_fills_bracket_the_solid() {
    let mut rng = XorShift(21);
    let mut shapes = vec![
        ("sphere", icosphere([0.3, 0.1, -0.2], 1.0, 2)),
        ("torus", torus([0.0; 3], 1.0, 0.35, 24, 12)),
        (
            "nested cubes",
            rotated_cube([0.0; 3], 2.0, &rotation(&mut rng)).with(&rotated_cube(
                [0.0; 3],
                0.9,
                &rotation(&mut rng),
            )),
        ),
    ];
    for i in 0..4 {
        shapes.push((
            ["cube a", "cube b", "cube c", "cube d"][i],
            rotated_cube([0.0; 3], 1.0, &rotation(&mut rng)),
        ));
    }
    let half_diagonal = 3f64.sqrt() / 2.0;
    for (name, shape) in shapes {
        let m = shape.tri_mesh();
        let get = |f| voxelize(&m, &options(22, f)).unwrap();
        let (vi, vc, vt) = (get(Fill::Inside), get(Fill::Center), get(Fill::Touched));
        assert_eq!((vi.dims, vi.origin), (vc.dims, vc.origin));
        assert_eq!((vt.dims, vt.origin), (vc.dims, vc.origin));
        let t = VoxelType::U8;
        let (gi, gc, gt) = (binary(&vi, t), binary(&vc, t), binary(&vt, t));
        let oracle = placed_oracle(&m, &vc);
        let [nx, ny, nz] = gc.dims;
        let problems: Vec<String> = (0..nz)
            .into_par_iter()
            .flat_map_iter(|z| {
                let (gi, gc, gt, oracle) = (&gi, &gc, &gt, &oracle);
                (0..ny).flat_map(move |y| {
                    (0..nx).filter_map(move |x| {
                        let (i, c, t) = (gi.get(x, y, z), gc.get(x, y, z), gt.get(x, y, z));
                        if (i && !c) || (c && !t) {
                            return Some(format!(
                                "({x}, {y}, {z}): inside {i}, centre {c}, touched {t}"
                            ));
                        }
                        let p = [x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5];
                        if oracle.outside_bounds(p, 1.0) {
                            return t
                                .then(|| format!("({x}, {y}, {z}): touched, far from the model"));
                        }
                        let d = oracle.distance(p);
                        let w = oracle.inside(p);
                        // Wholly inside: the centre is inside and the ball of radius 1/2
                        // around it misses the surface.
                        if i && (w != Some(true) || d < 0.5 - 1e-9) {
                            return Some(format!(
                                "({x}, {y}, {z}): inside, but centre {w:?} at {d:.4}"
                            ));
                        }
                        // Not touched: outside, and again the inscribed ball misses the surface.
                        if !t && (w != Some(false) || d < 0.5 - 1e-9) {
                            return Some(format!(
                                "({x}, {y}, {z}): not touched, but centre {w:?} at {d:.4}"
                            ));
                        }
                        // Touched: inside, or the surface within the half diagonal.
                        if t && w != Some(true) && d > half_diagonal + 1e-9 {
                            return Some(format!(
                                "({x}, {y}, {z}): touched, but outside at {d:.4}"
                            ));
                        }
                        // Far from the surface all three agree.
                        if d > half_diagonal + 1e-9 && !(i == c && c == t) {
                            return Some(format!("({x}, {y}, {z}): far ({d:.4}) but {i} {c} {t}"));
                        }
                        None
                    })
                })
            })
            .collect();
        assert!(
            problems.is_empty(),
            "{name}: {} voxels, e.g. {:?}",
            problems.len(),
            &problems[..problems.len().min(6)]
        );
        let (ci, cc, ct) = (gi.count(), gc.count(), gt.count());
        eprintln!("{name}: inside {ci}, centre {cc}, touched {ct}");
        assert!(ci < cc && cc < ct, "{name}");
    }
}

// ---------------------------------------------------------------------------------------------
// 9. Density

/// The value of `c` of `total` samples inside: H c / total rounded half up, computed in f64
/// (the rounding is decided correctly: where H c / total is a half-integer, total is 8 or 64
/// and the quotient is exact).
fn expected_density(c: u32, total: u32, t: VoxelType) -> u16 {
    (f64::from(t.high()) * f64::from(c) / f64::from(total) + 0.5).floor() as u16
}

#[test]
fn density_values_are_the_box_filter_of_the_samples() {
    // The paper's 0..8 for u8, by hand: 255 c / 8 rounded half up.
    let table: Vec<u16> = (0..=8)
        .map(|c| density_value(c, 8, VoxelType::U8))
        .collect();
    assert_eq!(table, [0, 32, 64, 96, 128, 159, 191, 223, 255]);
    // Half the samples inside is inside (>= S = 127), three eighths is not.
    assert!(table[4] >= VoxelType::U8.surface() && table[3] < VoxelType::U8.surface());
    for t in [VoxelType::U8, VoxelType::U16] {
        for total in [1, 8, 27, 64] {
            for c in 0..=total {
                assert_eq!(density_value(c, total, t), expected_density(c, total, t));
            }
        }
    }
    let mut rng = XorShift(33);
    let cases = [
        // More than 64 layers: several words per fine column and several 32-layer slabs.
        (
            "cube, s = 2",
            rotated_cube([0.0; 3], 1.0, &rotation(&mut rng)),
            66,
            2,
            VoxelType::U8,
        ),
        (
            "sphere, s = 2",
            icosphere([0.1, 0.2, 0.3], 1.0, 2),
            22,
            2,
            VoxelType::U8,
        ),
        (
            "sphere, s = 2, u16",
            icosphere([0.0; 3], 1.0, 2),
            14,
            2,
            VoxelType::U16,
        ),
        (
            "cube, s = 3",
            rotated_cube([0.0; 3], 1.0, &rotation(&mut rng)),
            30,
            3,
            VoxelType::U8,
        ),
        (
            "torus, s = 4, u16",
            torus([0.0; 3], 1.0, 0.4, 16, 8),
            16,
            4,
            VoxelType::U16,
        ),
        (
            "cube, s = 1",
            rotated_cube([0.0; 3], 1.0, &rotation(&mut rng)),
            20,
            1,
            VoxelType::U8,
        ),
    ];
    for (name, shape, size, s, t) in cases {
        let m = shape.tri_mesh();
        let opts = Options {
            supersample: s,
            voxel_type: t,
            ..options(size, Fill::Density)
        };
        let v = voxelize(&m, &opts).unwrap();
        let total = s * s * s;
        let table: Vec<u16> = (0..=total).map(|c| expected_density(c, total, t)).collect();
        assert_eq!(
            v.report.samples,
            v.dims.iter().map(|&d| u64::from(d * s)).product::<u64>(),
            "{name}"
        );
        let oracle = placed_oracle(&m, &v);
        let [nx, ny, nz] = v.dims.map(|d| d as usize);
        let n = s as usize;
        // Per voxel: the number of its s^3 sample centres (i + (a + 1/2) / s) inside, by the
        // winding number; a sample within 2^-16 fine voxels of the surface may go either way.
        let results: Vec<(u64, usize, usize, Vec<String>)> = (0..nz)
            .into_par_iter()
            .map(|z| {
                let (mut inside, mut excused, mut far) = (0u64, 0usize, 0usize);
                let mut bad = Vec::new();
                for y in 0..ny {
                    for x in 0..nx {
                        let got = value(&v, t, x, y, z);
                        let Some(c) = table.iter().position(|&e| e == got) else {
                            bad.push(format!("({x}, {y}, {z}): {got} is no density"));
                            continue;
                        };
                        let centre = [x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5];
                        if oracle.outside_bounds(centre, 1.0) {
                            if got != 0 {
                                bad.push(format!("({x}, {y}, {z}): {got} far outside"));
                            }
                            continue;
                        }
                        let mut sure = 0;
                        let mut unsure = 0;
                        let mut points = Vec::new();
                        for k in 0..n {
                            for j in 0..n {
                                for i in 0..n {
                                    let f = |q: usize| (q as f64 + 0.5) / s as f64;
                                    let p = [x as f64 + f(i), y as f64 + f(j), z as f64 + f(k)];
                                    points.push(p);
                                    match oracle.inside(p) {
                                        Some(true) => sure += 1,
                                        Some(false) => {}
                                        None => unsure += 1,
                                    }
                                }
                            }
                        }
                        inside += sure as u64;
                        if c != sure || unsure > 0 {
                            // Which samples may go either way?
                            let near = points
                                .iter()
                                .filter(|&&p| oracle.distance(p) * s as f64 <= SNAP_BAND)
                                .count();
                            let ok = c + near >= sure && c <= sure + near + unsure;
                            if ok && near + unsure > 0 {
                                excused += 1;
                            } else {
                                bad.push(format!(
                                    "({x}, {y}, {z}): value {got} = {c} samples, the winding number says {sure} (+{unsure} on the surface, {near} within 2^-16)"
                                ));
                            }
                        }
                        // Far inside H, far outside L.
                        let d = oracle.distance(centre);
                        if d > 3f64.sqrt() / 2.0 {
                            far += 1;
                            let want = if oracle.inside(centre) == Some(true) { t.high() } else { 0 };
                            if got != want {
                                bad.push(format!("({x}, {y}, {z}): {got} at {d:.3} from the surface"));
                            }
                        }
                    }
                }
                (inside, excused, far, bad)
            })
            .collect();
        let inside: u64 = results.iter().map(|r| r.0).sum();
        let excused: usize = results.iter().map(|r| r.1).sum();
        let far: usize = results.iter().map(|r| r.2).sum();
        let bad: Vec<&String> = results.iter().flat_map(|r| &r.3).collect();
        eprintln!(
            "{name}: dims {:?}, {inside} samples inside, {excused} voxels excused, {far} far from the surface",
            v.dims
        );
        assert!(
            bad.is_empty(),
            "{name}: {} voxels, e.g. {:?}",
            bad.len(),
            &bad[..bad.len().min(6)]
        );
        assert!(excused <= 2, "{name}: {excused}");
        assert!(far > 0);
        let diff = (v.report.samples_inside as i64 - inside as i64).unsigned_abs();
        assert!(diff <= 2 * excused as u64 * u64::from(total), "{name}");
    }
}

// ---------------------------------------------------------------------------------------------
// 10. The binned parity pass and the cache-aware box filter against the previous ones

/// A union of closed parts placed at random in (and around) a grid of `dims`: jittered
/// icospheres, tori at any orientation, tetrahedra and boxes with vertices on the quarter
/// lattice (many centres on faces, edges and vertices), and now and then a slab reaching far
/// beyond the grid or a part wound inside out. Every part is closed, so the union is.
fn random_closed_mesh(rng: &mut XorShift, dims: [usize; 3]) -> Shape {
    let extent = dims.map(|d| d as f64);
    let size = extent.iter().copied().fold(1.0, f64::max);
    let mut shape = Shape::default();
    for _ in 0..1 + rng.below(4) {
        let centre: V3 = std::array::from_fn(|a| rng.range(-0.2, 1.2) * extent[a]);
        let quarter = |p: V3| p.map(|c| (c * 4.0).round() / 4.0);
        let part = match rng.below(5) {
            0 => {
                let r = rng.range(0.5, size / 2.0);
                let jitter = rng.range(0.0, 0.3) * r;
                let mut sphere = icosphere(centre, r, rng.below(3) as u32);
                for c in sphere.p.iter_mut().flatten() {
                    *c += rng.range(-jitter, jitter);
                }
                sphere
            }
            1 => {
                let big = rng.range(1.0, size / 2.0);
                let small = rng.range(0.2, 0.9) * big;
                torus([0.0; 3], big, small, 12, 8)
                    .rotated(&rotation(rng), [0.0; 3])
                    .translated(centre)
            }
            2 => {
                let v: [V3; 4] = std::array::from_fn(|_| {
                    quarter(add(
                        centre,
                        std::array::from_fn(|_| rng.range(-size, size) / 2.0),
                    ))
                });
                tetrahedron(v)
            }
            3 => {
                let half: V3 = std::array::from_fn(|_| rng.range(0.25, size / 2.0));
                cuboid(
                    quarter(sub(centre, half)),
                    quarter(add(centre, half)),
                    rng.below(2) == 0,
                )
            }
            _ => {
                let (z0, z1) = (rng.range(-2.0, extent[2]), rng.range(-2.0, extent[2] + 2.0));
                // Some so wide that their edge functions outgrow an i64.
                let far = size * if rng.below(2) == 0 { 50.0 } else { 5000.0 };
                cuboid(
                    [-far, -0.8 * far, z0.min(z1)],
                    [1.2 * far, 1.4 * far, z0.max(z1) + 0.25],
                    false,
                )
            }
        };
        shape = shape.with(&if rng.below(6) == 0 {
            part.flipped()
        } else {
            part
        });
    }
    shape
}

/// Where two grids differ: their count and the first few voxels.
fn differences(a: &BitGrid, b: &BitGrid) -> (usize, Vec<[usize; 3]>) {
    let [nx, ny, nz] = a.dims;
    let mut first = Vec::new();
    let mut count = 0;
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                if a.get(x, y, z) != b.get(x, y, z) {
                    count += 1;
                    if first.len() < 6 {
                        first.push([x, y, z]);
                    }
                }
            }
        }
    }
    (count, first)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, failure_persistence: None, ..ProptestConfig::default() })]

    /// The parity pass gives exactly the voxels of the previous one (each band of rows scanning
    /// every triangle), on grids of several bands of rows and several words per column.
    #[test]
    fn binned_parity_pass_matches_the_previous_one(
        seed in any::<u64>(),
        dims in (1usize..70, 1usize..90, 1usize..200),
    ) {
        let dims = [dims.0, dims.1, dims.2];
        let m = random_closed_mesh(&mut XorShift(seed | 1), dims).tri_mesh();
        let want = voxelize_solid_reference(&m, dims, grid_coords);
        let got = voxelize_solid(&m, dims, grid_coords);
        let (count, first) = differences(&got, &want);
        prop_assert!(count == 0, "{count} voxels differ, e.g. {first:?} ({} triangles)", m.triangles.len());
    }

    /// `voxelize` gives exactly the values of the previous passes, for every fill, supersampling
    /// and voxel type (the 2x2x2 density goes through the new box filter).
    #[test]
    fn voxelize_matches_the_previous_passes(
        seed in any::<u64>(),
        size in 1u32..48,
        supersample in 1u32..=3,
        padding in 0u32..3,
        fill in prop_oneof![Just(Fill::Density), Just(Fill::Center), Just(Fill::Inside), Just(Fill::Touched)],
        voxel_type in prop_oneof![Just(VoxelType::U8), Just(VoxelType::U16)],
    ) {
        let m = random_closed_mesh(&mut XorShift(seed | 1), [32; 3]).tri_mesh();
        let options = Options { size, supersample, padding, fill, voxel_type, allow_open: true };
        let want = voxelize_reference(&m, &options).map_err(|e| TestCaseError::fail(e.to_string()))?;
        let got = voxelize(&m, &options).map_err(|e| TestCaseError::fail(e.to_string()))?;
        prop_assert_eq!(got.dims, want.dims);
        let differ = got.bytes.iter().zip(&want.bytes).filter(|(a, b)| a != b).count();
        prop_assert!(got.bytes == want.bytes, "{differ} of {} bytes differ (dims {:?})", want.bytes.len(), want.dims);
    }
}
