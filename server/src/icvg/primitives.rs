//! Virtual volume sampling functions (`docs/icvg.md`, "Virtual volume sampling functions").
//!
//! Each primitive lives in its own extension space, placed in the world (level-0 voxel
//! coordinates) by an integer offset; outside it the value is L. Bodies, unit vectors and
//! quotients are computed in f64, then floored and clamped, so that independent implementations
//! agree voxel for voxel.
//!
//! Curved faces follow one rule (the ellipsoid's): with `body` equal to 1 on the surface and
//! `u` the unit step outwards, a voxel is H when `body(T + u) < 1` (one step further out is
//! still inside), L when `body(T - u) > 1` (one step further in is still outside), and
//! `min(H, floor(S / body(T)))` in the one-voxel band between. Flat axis-aligned faces get an L
//! padding layer and an S surface layer, as the cuboid does. Slanted flat faces (prism, pyramid)
//! use the curved rule with `body = 1 - s`, `s` the signed distance inside the face's plane.

use crate::geometry::Box3;
use isovox_proto::VoxelType;

/// A primitive: a value for every world voxel, L outside its extension space.
pub trait Primitive: std::fmt::Debug + Send + Sync {
    /// The extension space in the world.
    fn bbox(&self) -> Box3;
    /// The value at world voxel `v` inside [`Primitive::bbox`].
    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16;
    /// The values of the voxels `(x0 + i, y, z)` for every `i < out.len()`, all inside
    /// [`Primitive::bbox`]. Primitives with a cheaper per-row form override it.
    fn sample_row(&self, x0: i64, y: i64, z: i64, t: VoxelType, out: &mut [u16]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = self.sample_inside([x0 + i as i64, y, z], t);
        }
    }
    /// The one value of every voxel of `b` (a sub-box of the extension space), when that is
    /// certain without sampling; `None` when unsure.
    fn constant_inside(&self, _b: &Box3, _t: VoxelType) -> Option<u16> {
        None
    }

    /// The one value of every voxel of `b` (any box), when certain without sampling.
    fn constant_over(&self, b: &Box3, t: VoxelType) -> Option<u16> {
        crate::geometry::constant_over(&self.bbox(), b, t.low(), |inside| {
            self.constant_inside(inside, t)
        })
    }

    /// The value at any world voxel.
    fn sample(&self, v: [i64; 3], t: VoxelType) -> u16 {
        if self.bbox().contains(v) {
            self.sample_inside(v, t)
        } else {
            t.low()
        }
    }
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn unit(t: [f64; 3]) -> [f64; 3] {
    let len = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
    if len == 0.0 {
        [0.0; 3]
    } else {
        t.map(|c| c / len)
    }
}

/// The band value `min(H, floor(S / body))`.
fn band(body: f64, t: VoxelType) -> u16 {
    (t.surface() as f64 / body).floor().min(t.high() as f64) as u16
}

/// The curved-face rule shared by every curved primitive.
fn curved(body: impl Fn([f64; 3]) -> f64, p: [f64; 3], u: [f64; 3], t: VoxelType) -> u16 {
    if body(add(p, u)) < 1.0 {
        t.high()
    } else if body(sub(p, u)) > 1.0 {
        t.low()
    } else {
        band(body(p), t)
    }
}

/// Bounds of `|p|_R = sqrt(sum p_i^2 / R_i^2)` (only the axes with a radius) over the box of
/// offsets `lo..=hi` from the centre: the norm is convex, so its maximum is at a corner, and its
/// minimum is found axis by axis.
fn norm_range(lo: [f64; 3], hi: [f64; 3], r: [Option<f64>; 3]) -> (f64, f64) {
    let (mut min_sq, mut max_sq) = (0.0, 0.0);
    for a in 0..3 {
        if let Some(ra) = r[a] {
            let far = lo[a].abs().max(hi[a].abs());
            let near = if lo[a] <= 0.0 && hi[a] >= 0.0 {
                0.0
            } else {
                lo[a].abs().min(hi[a].abs())
            };
            max_sq += far * far / (ra * ra);
            min_sq += near * near / (ra * ra);
        }
    }
    (min_sq.sqrt(), max_sq.sqrt())
}

const MARGIN: f64 = 1e-9;

/// Offsets of a box's corners from `centre`, as f64.
fn offsets(b: &Box3, centre: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    (
        [0, 1, 2].map(|a| b.min[a] as f64 - centre[a]),
        [0, 1, 2].map(|a| (b.max[a] - 1) as f64 - centre[a]),
    )
}

/// Cuboid: L on the outer layer, S on the next, H inside (B > 2 on every axis).
#[derive(Debug, Clone, PartialEq)]
pub struct Cuboid {
    /// The first voxel of the extension space.
    pub origin: [i64; 3],
    /// The extension space's size.
    pub size: [u32; 3],
}

impl Primitive for Cuboid {
    fn bbox(&self) -> Box3 {
        Box3::new(
            self.origin,
            [0, 1, 2].map(|a| self.origin[a] + self.size[a] as i64),
        )
    }

    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
        let local = [0, 1, 2].map(|a| v[a] - self.origin[a]);
        let last = self.size.map(|s| s as i64 - 1);
        if (0..3).any(|a| local[a] == 0 || local[a] == last[a]) {
            t.low()
        } else if (0..3).any(|a| local[a] == 1 || local[a] == last[a] - 1) {
            t.surface()
        } else {
            t.high()
        }
    }

    fn constant_inside(&self, b: &Box3, t: VoxelType) -> Option<u16> {
        let inner = Box3::new(
            [0, 1, 2].map(|a| self.origin[a] + 2),
            [0, 1, 2].map(|a| self.origin[a] + self.size[a] as i64 - 2),
        );
        (b.intersect(&inner) == *b).then_some(t.high())
    }
}

/// Ellipsoid: radii `R`, centre `C = R` in its extension space `2R + 1`.
#[derive(Debug, Clone, PartialEq)]
pub struct Ellipsoid {
    /// The centre voxel.
    pub center: [i64; 3],
    /// The radii along x, y, z.
    pub radii: [u32; 3],
}

impl Ellipsoid {
    fn body(&self, p: [f64; 3]) -> f64 {
        let r = self.radii.map(|r| r as f64);
        p[0] * p[0] / (r[0] * r[0]) + p[1] * p[1] / (r[1] * r[1]) + p[2] * p[2] / (r[2] * r[2])
    }
}

impl Ellipsoid {
    /// The spec's rule computed literally: the reference the fast path falls back to.
    fn sample_literal(&self, p: [f64; 3], t: VoxelType) -> u16 {
        curved(|q| self.body(q), p, unit(p), t)
    }
}

/// How close to a threshold the fast path must not decide on its own.
const FAST_EPS: f64 = 1e-9;

impl Primitive for Ellipsoid {
    fn bbox(&self) -> Box3 {
        Box3::new(
            [0, 1, 2].map(|a| self.center[a] - self.radii[a] as i64),
            [0, 1, 2].map(|a| self.center[a] + self.radii[a] as i64 + 1),
        )
    }

    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
        let mut out = [0u16];
        self.sample_row(v[0], v[1], v[2], t, &mut out);
        out[0]
    }

    /// Fast path: with `u = T / |T|`, `body(T +- u) = body(T) (1 +- 1/|T|)^2` exactly in real
    /// arithmetic, so one body (with precomputed 1/R^2), one square root and one division decide
    /// almost every voxel. Where a comparison or the floor lands within 1e-9 of its threshold
    /// (float rounding could tip it), the literal formula decides, so the result is always the
    /// spec's.
    fn sample_row(&self, x0: i64, y: i64, z: i64, t: VoxelType, out: &mut [u16]) {
        let inv = self.radii.map(|r| 1.0 / (r as f64 * r as f64));
        let (py, pz) = ((y - self.center[1]) as f64, (z - self.center[2]) as f64);
        let yz2 = py * py + pz * pz;
        let body_yz = py * py * inv[1] + pz * pz * inv[2];
        let (high, low, s) = (t.high(), t.low(), t.surface() as f64);
        for (i, o) in out.iter_mut().enumerate() {
            let px = (x0 + i as i64 - self.center[0]) as f64;
            let len2 = px * px + yz2;
            if len2 == 0.0 {
                *o = high;
                continue;
            }
            let body = px * px * inv[0] + body_yz;
            let inv_len = 1.0 / len2.sqrt();
            let outer = body * (1.0 + inv_len) * (1.0 + inv_len);
            if outer < 1.0 - FAST_EPS {
                *o = high;
                continue;
            }
            if outer > 1.0 + FAST_EPS {
                let inner = body * (1.0 - inv_len) * (1.0 - inv_len);
                if inner > 1.0 + FAST_EPS {
                    *o = low;
                    continue;
                }
                if inner < 1.0 - FAST_EPS {
                    let q = s / body;
                    if q >= high as f64 + FAST_EPS {
                        *o = high;
                        continue;
                    }
                    let frac = q - q.floor();
                    if frac > FAST_EPS && frac < 1.0 - FAST_EPS {
                        *o = q.floor() as u16;
                        continue;
                    }
                }
            }
            *o = self.sample_literal([px, py, pz], t);
        }
    }

    /// `|T^|_R <= 1 / min(R)` bounds how far one unit step moves the norm.
    fn constant_inside(&self, b: &Box3, t: VoxelType) -> Option<u16> {
        let r = self.radii.map(|r| Some(r as f64));
        let step = 1.0 / self.radii.iter().min().copied().unwrap_or(1) as f64;
        let (lo, hi) = offsets(b, self.center.map(|c| c as f64));
        let (min, max) = norm_range(lo, hi, r);
        if max + step < 1.0 - MARGIN {
            Some(t.high())
        } else if min - step > 1.0 + MARGIN {
            Some(t.low())
        } else {
            None
        }
    }
}

/// The extension space of a solid along +y (cylinder, cone): `(2 rx + 1, height, 2 rz + 1)`
/// with `base` the centre of its bottom layer.
fn axial_box(base: [i64; 3], radii: [u32; 2], height: u32) -> Box3 {
    let [rx, rz] = radii.map(|r| r as i64);
    Box3::new(
        [base[0] - rx, base[1], base[2] - rz],
        [base[0] + rx + 1, base[1] + height as i64, base[2] + rz + 1],
    )
}

/// Cylinder along +y: elliptic cross-section `radii = (rx, rz)`, L padding and S surface layers
/// at the bottom and top.
#[derive(Debug, Clone, PartialEq)]
pub struct Cylinder {
    /// The centre of the bottom padding layer.
    pub base: [i64; 3],
    /// The radii along x and z.
    pub radii: [u32; 2],
    /// The height along +y.
    pub height: u32,
}

impl Cylinder {
    fn ebody(&self, p: [f64; 3]) -> f64 {
        let (rx, rz) = (self.radii[0] as f64, self.radii[1] as f64);
        p[0] * p[0] / (rx * rx) + p[2] * p[2] / (rz * rz)
    }
}

impl Primitive for Cylinder {
    fn bbox(&self) -> Box3 {
        axial_box(self.base, self.radii, self.height)
    }

    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
        let vy = v[1] - self.base[1];
        let last = self.height as i64 - 1;
        let p = [
            (v[0] - self.base[0]) as f64,
            0.0,
            (v[2] - self.base[2]) as f64,
        ];
        let u = unit(p);
        if self.ebody(sub(p, u)) > 1.0 || vy == 0 || vy == last {
            return t.low();
        }
        let inside = self.ebody(add(p, u)) < 1.0;
        if (vy == 1 || vy == last - 1) && inside {
            t.surface()
        } else if inside {
            t.high()
        } else {
            band(self.ebody(p), t)
        }
    }

    fn constant_inside(&self, b: &Box3, t: VoxelType) -> Option<u16> {
        let r = [Some(self.radii[0] as f64), None, Some(self.radii[1] as f64)];
        let step = 1.0 / self.radii.iter().min().copied().unwrap_or(1) as f64;
        let (lo, hi) = offsets(b, self.base.map(|c| c as f64));
        let (min, max) = norm_range(lo, hi, r);
        if min - step > 1.0 + MARGIN {
            return Some(t.low());
        }
        let (y0, y1) = (b.min[1] - self.base[1], b.max[1] - 1 - self.base[1]);
        if max + step < 1.0 - MARGIN && y0 >= 2 && y1 <= self.height as i64 - 3 {
            return Some(t.high());
        }
        None
    }
}

/// Cone along +y, apex up on the axis column: the cross-section shrinks linearly with
/// `h = 1 - Vy / (By - 1)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Cone {
    /// The centre of the bottom padding layer.
    pub base: [i64; 3],
    /// The base's radii along x and z.
    pub radii: [u32; 2],
    /// The height along +y.
    pub height: u32,
}

impl Cone {
    fn cbody(&self, p: [f64; 3], h: f64) -> f64 {
        if h <= 0.0 {
            return if p[0] == 0.0 && p[2] == 0.0 {
                0.0
            } else {
                f64::INFINITY
            };
        }
        let (rx, rz) = (self.radii[0] as f64 * h, self.radii[1] as f64 * h);
        p[0] * p[0] / (rx * rx) + p[2] * p[2] / (rz * rz)
    }
}

impl Primitive for Cone {
    fn bbox(&self) -> Box3 {
        axial_box(self.base, self.radii, self.height)
    }

    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
        let vy = v[1] - self.base[1];
        if vy == 0 {
            return t.low();
        }
        let h = 1.0 - vy as f64 / (self.height as f64 - 1.0);
        let p = [
            (v[0] - self.base[0]) as f64,
            0.0,
            (v[2] - self.base[2]) as f64,
        ];
        let u = unit(p);
        if self.cbody(sub(p, u), h) > 1.0 {
            return t.low();
        }
        let inside = self.cbody(add(p, u), h) < 1.0;
        if vy == 1 && inside {
            t.surface()
        } else if inside {
            t.high()
        } else {
            band(self.cbody(p, h), t)
        }
    }
}

/// Torus around the +y axis through `center`.
#[derive(Debug, Clone, PartialEq)]
pub struct Torus {
    /// The centre of the ring.
    pub center: [i64; 3],
    /// The radius of the tube's centre circle.
    pub major: u32,
    /// The tube's radius.
    pub minor: u32,
}

impl Torus {
    /// Offset from the nearest point of the tube's centre circle.
    fn offset_from_core(&self, p: [f64; 3]) -> [f64; 3] {
        let ring = (p[0] * p[0] + p[2] * p[2]).sqrt();
        let major = self.major as f64;
        if ring == 0.0 {
            // On the axis every point of the circle is nearest: step along x.
            return [-major, p[1], 0.0];
        }
        [p[0] - p[0] / ring * major, p[1], p[2] - p[2] / ring * major]
    }

    fn body(&self, p: [f64; 3]) -> f64 {
        let d = self.offset_from_core(p);
        let r = self.minor as f64;
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (r * r)
    }
}

impl Primitive for Torus {
    fn bbox(&self) -> Box3 {
        let (o, m) = ((self.major + self.minor) as i64, self.minor as i64);
        Box3::new(
            [self.center[0] - o, self.center[1] - m, self.center[2] - o],
            [
                self.center[0] + o + 1,
                self.center[1] + m + 1,
                self.center[2] + o + 1,
            ],
        )
    }

    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
        let p = [0, 1, 2].map(|a| (v[a] - self.center[a]) as f64);
        curved(|q| self.body(q), p, unit(self.offset_from_core(p)), t)
    }
}

/// Capsule: a segment of `length` voxels along +y centred on `center`, swept by a ball; its
/// extension is `(2 r + 1, 2 ceil(length / 2) + 2 r + 1, 2 r + 1)`, symmetric about `center`.
#[derive(Debug, Clone, PartialEq)]
pub struct Capsule {
    /// The centre of the segment.
    pub center: [i64; 3],
    /// The ball's radius.
    pub radius: u32,
    /// The segment's length along +y.
    pub length: u32,
}

impl Capsule {
    fn offset_from_axis(&self, p: [f64; 3]) -> [f64; 3] {
        let half = self.length as f64 / 2.0;
        [p[0], p[1] - p[1].clamp(-half, half), p[2]]
    }

    fn body(&self, p: [f64; 3]) -> f64 {
        let d = self.offset_from_axis(p);
        let r = self.radius as f64;
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (r * r)
    }
}

impl Primitive for Capsule {
    fn bbox(&self) -> Box3 {
        let r = self.radius as i64;
        // Symmetric about the centre: the segment reaches length / 2 either way (x.5 for an odd
        // length), so the extension reaches ceil(length / 2) + r.
        let half_lo = (self.length as i64 + 1) / 2;
        let half_hi = half_lo;
        Box3::new(
            [
                self.center[0] - r,
                self.center[1] - half_lo - r,
                self.center[2] - r,
            ],
            [
                self.center[0] + r + 1,
                self.center[1] + half_hi + r + 1,
                self.center[2] + r + 1,
            ],
        )
    }

    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
        let p = [0, 1, 2].map(|a| (v[a] - self.center[a]) as f64);
        curved(|q| self.body(q), p, unit(self.offset_from_axis(p)), t)
    }
}

/// A slanted face: the half-space `n . (p - o) <= 0` with `n` the unit outward normal.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Plane {
    n: [f64; 3],
    o: [f64; 3],
}

impl Plane {
    fn through(o: [f64; 3], outward: [f64; 3]) -> Plane {
        Plane {
            n: unit(outward),
            o,
        }
    }

    /// `1 - s`, `s` the signed distance inside: 1 on the plane, < 1 inside.
    fn body(&self, p: [f64; 3]) -> f64 {
        let d = sub(p, self.o);
        1.0 + self.n[0] * d[0] + self.n[1] * d[1] + self.n[2] * d[2]
    }

    fn sample(&self, p: [f64; 3], t: VoxelType) -> u16 {
        curved(|q| self.body(q), p, self.n, t)
    }
}

/// A convex solid: an axis-aligned cuboid (with its L and S layers) cut by slanted planes; the
/// value is the minimum over the cuboid's and the planes' values (an intersection). The planes
/// are computed once, when the term is compiled.
#[derive(Debug, Clone, PartialEq)]
pub struct CutCuboid {
    cuboid: Cuboid,
    planes: Vec<Plane>,
}

impl Primitive for CutCuboid {
    fn bbox(&self) -> Box3 {
        self.cuboid.bbox()
    }

    fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
        let mut value = self.cuboid.sample_inside(v, t);
        let p = v.map(|c| c as f64);
        for plane in &self.planes {
            if value == t.low() {
                break;
            }
            value = value.min(plane.sample(p, t));
        }
        value
    }
}

/// Wedge: the cuboid cut by the plane through its top-left edge (x = 0, y = top) and its
/// bottom-right edge (x = right, y = 0), measured between the S layers.
#[derive(Debug, Clone, PartialEq)]
pub struct Prism {
    /// The first voxel of the bounding cuboid.
    pub origin: [i64; 3],
    /// The bounding cuboid's size.
    pub size: [u32; 3],
}

impl Prism {
    /// The wedge as a cuboid and its one slanted plane.
    pub fn solid(&self) -> CutCuboid {
        let o = self.origin.map(|x| x as f64);
        let (w, h) = (self.size[0] as f64 - 3.0, self.size[1] as f64 - 3.0);
        // Through (o.x + 1, o.y + 1 + h) and (o.x + 1 + w, o.y + 1); outward normal (h, w, 0).
        let plane = Plane::through([o[0] + 1.0, o[1] + 1.0 + h, o[2]], [h, w, 0.0]);
        CutCuboid {
            cuboid: Cuboid {
                origin: self.origin,
                size: self.size,
            },
            planes: vec![plane],
        }
    }
}

/// Square pyramid: base on the cuboid's bottom S layer, apex at the centre of its top S layer.
#[derive(Debug, Clone, PartialEq)]
pub struct Pyramid {
    /// The first voxel of the bounding cuboid.
    pub origin: [i64; 3],
    /// The bounding cuboid's size.
    pub size: [u32; 3],
}

impl Pyramid {
    /// The pyramid as a cuboid and its four slanted planes.
    pub fn solid(&self) -> CutCuboid {
        let o = self.origin.map(|x| x as f64);
        let (w, h, d) = (
            self.size[0] as f64 - 3.0,
            self.size[1] as f64 - 3.0,
            self.size[2] as f64 - 3.0,
        );
        let apex = [o[0] + 1.0 + w / 2.0, o[1] + 1.0 + h, o[2] + 1.0 + d / 2.0];
        let (hx, hz) = (w / 2.0, d / 2.0);
        let planes = vec![
            Plane::through(apex, [h, hx, 0.0]),
            Plane::through(apex, [-h, hx, 0.0]),
            Plane::through(apex, [0.0, hz, h]),
            Plane::through(apex, [0.0, hz, -h]),
        ];
        CutCuboid {
            cuboid: Cuboid {
                origin: self.origin,
                size: self.size,
            },
            planes,
        }
    }
}

/// The wedge and the pyramid sample through their solids (the engine compiles them to
/// [`CutCuboid`]s directly, so the planes are not rebuilt per voxel there).
macro_rules! via_solid {
    ($t:ty) => {
        impl Primitive for $t {
            fn bbox(&self) -> Box3 {
                Cuboid {
                    origin: self.origin,
                    size: self.size,
                }
                .bbox()
            }

            fn sample_inside(&self, v: [i64; 3], t: VoxelType) -> u16 {
                self.solid().sample_inside(v, t)
            }
        }
    };
}
via_solid!(Prism);
via_solid!(Pyramid);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ellipsoid_golden_values() {
        // Sphere of radius 4 centred at (4,4,4), u8: S = 127.
        let e = Ellipsoid {
            center: [4, 4, 4],
            radii: [4, 4, 4],
        };
        let t = VoxelType::U8;
        // Centre: T = 0, T^ = 0, body(0) = 0 < 1 -> H.
        assert_eq!(e.sample([4, 4, 4], t), 255);
        // (7,4,4): T = (3,0,0), body(T+T^) = 16/16 = 1, not < 1; body(T-T^) = 4/16 <= 1;
        // band: floor(127 / (9/16)) = floor(225.77) = 225.
        assert_eq!(e.sample([7, 4, 4], t), 225);
        // (8,4,4): T = (4,0,0): body(T-T^) = 9/16 <= 1 -> band: floor(127 / 1) = 127 = S.
        assert_eq!(e.sample([8, 4, 4], t), 127);
        // (6,4,4): T = (2,0,0): body(T+T^) = 9/16 < 1 -> H.
        assert_eq!(e.sample([6, 4, 4], t), 255);
        // (8,8,4): T = (4,4,0), |T| = 5.657, T - T^ = (3.293, 3.293, 0): body = 1.355 > 1 -> L.
        assert_eq!(e.sample([8, 8, 4], t), 0);
        // Outside the extension space [0, 8]: L.
        assert_eq!(e.sample([9, 4, 4], t), 0);
        assert_eq!(e.sample([-1, 4, 4], t), 0);
        // u16: (8,4,4) is floor(32767 / 1) = 32767; (7,4,4) floor(32767 * 16 / 9) = 58252.
        assert_eq!(e.sample([8, 4, 4], VoxelType::U16), 32767);
        assert_eq!(e.sample([7, 4, 4], VoxelType::U16), 58252);
    }

    #[test]
    fn ellipsoid_fast_path_equals_the_literal_formula() {
        // Every voxel of many ellipsoids, u8 and u16: the fast path must give exactly the
        // spec's literal computation (it defers to it near every threshold).
        let mut checked = 0;
        for radii in [
            [1, 1, 1],
            [1, 2, 3],
            [3, 3, 3],
            [4, 4, 4],
            [5, 3, 8],
            [7, 7, 2],
            [12, 9, 10],
            [16, 16, 16],
            [25, 6, 13],
        ] {
            let e = Ellipsoid {
                center: [3, -2, 5],
                radii,
            };
            let b = e.bbox();
            for t in [VoxelType::U8, VoxelType::U16] {
                for z in b.min[2]..b.max[2] {
                    for y in b.min[1]..b.max[1] {
                        for x in b.min[0]..b.max[0] {
                            let p = [x - 3, y + 2, z - 5].map(|c| c as f64);
                            assert_eq!(
                                e.sample_inside([x, y, z], t),
                                e.sample_literal(p, t),
                                "{radii:?} at {x},{y},{z} {t}"
                            );
                            checked += 1;
                        }
                    }
                }
            }
        }
        assert!(checked > 100_000);
    }

    fn check_constant_shortcut(p: &dyn Primitive, t: VoxelType) -> usize {
        let bb = p.bbox();
        let mut decided = 0;
        let step = 4;
        let mut z = bb.min[2];
        while z < bb.max[2] {
            let mut y = bb.min[1];
            while y < bb.max[1] {
                let mut x = bb.min[0];
                while x < bb.max[0] {
                    let b = Box3::new([x, y, z], [x + step, y + step, z + step]).intersect(&bb);
                    if let Some(v) = p.constant_inside(&b, t) {
                        decided += 1;
                        for vz in b.min[2]..b.max[2] {
                            for vy in b.min[1]..b.max[1] {
                                for vx in b.min[0]..b.max[0] {
                                    assert_eq!(
                                        p.sample_inside([vx, vy, vz], t),
                                        v,
                                        "{p:?} box {b:?} voxel {vx},{vy},{vz}"
                                    );
                                }
                            }
                        }
                    }
                    x += step;
                }
                y += step;
            }
            z += step;
        }
        decided
    }

    #[test]
    fn constant_shortcuts_agree_with_sampling() {
        let t = VoxelType::U8;
        assert!(
            check_constant_shortcut(
                &Ellipsoid {
                    center: [40, 30, 35],
                    radii: [33, 25, 29]
                },
                t
            ) > 100
        );
        assert!(
            check_constant_shortcut(
                &Cuboid {
                    origin: [-3, 5, 7],
                    size: [30, 21, 17]
                },
                t
            ) > 20
        );
        assert!(
            check_constant_shortcut(
                &Cylinder {
                    base: [10, -4, 3],
                    radii: [17, 12],
                    height: 30
                },
                t
            ) > 20
        );
    }
}
