//! The marching-cubes kernel: a pure function of a sample grid, writing into reusable buffers.
//!
//! Cells run between integer grid points. A vertex lies on a cell edge where the field crosses
//! `iso`, interpolated linearly from the edge's lower endpoint to its upper one, so two cells (or
//! two tiles) that share an edge compute the bit-identical vertex from the same two samples. A
//! corner is inside when its value is >= `iso`; with integer voxels and the default
//! `iso = S - 0.5` that is exactly the algebra's `>= S`, and no vertex ever lands on a sample.
//! Normals are the negated, interpolated central-difference gradient (they point from inside to
//! outside, as the triangles' winding does).

use super::inside;
use super::mc_reference::{self, ReferenceScratch};
use super::mc_rows::{self, RowsScratch};

/// A sample the kernel marches: `f32` (the lattice values of coarser levels, resampled), or a
/// level's stored voxels as they are (`u8`, `u16`), so that level 0 needs no conversion pass.
/// Every formula reads samples through [`Sample::to_f32`], which is exact for integer voxels
/// (they fit f32's 24-bit mantissa): a vertex made from `u8` samples is bit for bit the one
/// made from the same values as `f32`.
pub trait Sample: Copy + Send + Sync + 'static {
    /// What [`Sample::inside_bits`] compares with, prepared once per call from `iso`.
    type Cut: Copy;

    /// The sample's value.
    fn to_f32(self) -> f32;

    /// The cut for `iso`: a sample is inside exactly when `sample.to_f32() >= iso`.
    fn cut(iso: f32) -> Self::Cut;

    /// Bit i: `values[i]` is inside (at most 64 values).
    fn inside_bits(values: &[Self], cut: Self::Cut) -> u64;
}

impl Sample for f32 {
    type Cut = f32;

    #[inline]
    fn to_f32(self) -> f32 {
        self
    }

    fn cut(iso: f32) -> f32 {
        iso
    }

    #[inline]
    fn inside_bits(values: &[f32], iso: f32) -> u64 {
        inside::f32_at_least(values, iso)
    }
}

/// The least integer voxel value that is inside for `iso` (`v >= iso` exactly when
/// `v >= threshold`), as a u32 in `[0, max + 1]`: `max + 1` when no voxel is (`iso` above `max`,
/// or NaN, which no value reaches).
fn integer_threshold(iso: f32, max: u32) -> u32 {
    let up = iso.ceil();
    if up <= 0.0 {
        0
    } else if up <= max as f32 {
        up as u32
    } else {
        // Above every voxel, or NaN.
        max + 1
    }
}

impl Sample for u8 {
    /// The threshold, `256` when nothing is inside.
    type Cut = u32;

    #[inline]
    fn to_f32(self) -> f32 {
        f32::from(self)
    }

    fn cut(iso: f32) -> u32 {
        integer_threshold(iso, u32::from(u8::MAX))
    }

    #[inline]
    fn inside_bits(values: &[u8], threshold: u32) -> u64 {
        u8::try_from(threshold).map_or(0, |t| inside::u8_at_least(values, t))
    }
}

impl Sample for u16 {
    /// The threshold, `65536` when nothing is inside.
    type Cut = u32;

    #[inline]
    fn to_f32(self) -> f32 {
        f32::from(self)
    }

    fn cut(iso: f32) -> u32 {
        integer_threshold(iso, u32::from(u16::MAX))
    }

    #[inline]
    fn inside_bits(values: &[u16], threshold: u32) -> u64 {
        u16::try_from(threshold).map_or(0, |t| inside::u16_at_least(values, t))
    }
}

/// A scalar field sampled on integer grid points: the value of point `origin + (x, y, z)` is
/// `values[(z * size[1] + y) * size[0] + x]`.
#[derive(Debug, Clone, Copy)]
pub struct Field<'a, S = f32> {
    /// The grid position of the first sample.
    pub origin: [i64; 3],
    /// Samples along x, y, z.
    pub size: [usize; 3],
    /// The samples, x fastest.
    pub values: &'a [S],
}

impl<S: Sample> Field<'_, S> {
    /// The index in `values` of point `p` (inside the field).
    pub fn index(&self, p: [i64; 3]) -> usize {
        let l = [0, 1, 2].map(|a| (p[a] - self.origin[a]) as usize);
        (l[2] * self.size[1] + l[1]) * self.size[0] + l[0]
    }

    /// Whether point `p` lies in the field.
    pub fn contains(&self, p: [i64; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.origin[a] && p[a] < self.origin[a] + self.size[a] as i64)
    }

    /// The value at point `p`. Panics if `p` is outside the field.
    pub fn value(&self, p: [i64; 3]) -> f32 {
        assert!(self.contains(p), "point {p:?} outside the field");
        self.values[self.index(p)].to_f32()
    }

    /// The negated central-difference gradient at `p` (pointing from inside to outside), not
    /// normalized. `p` and its six neighbours must lie in the field.
    pub fn outward_gradient(&self, p: [i64; 3]) -> [f32; 3] {
        self.gradient_at(self.index(p)).map(|c| -c)
    }

    /// Where the iso-surface crosses the grid edge from `p0` along `axis` (its endpoint values
    /// straddle `iso`): the parameter t from `p0`, and the unit normal, computed exactly as
    /// [`march`] computes them, so a caller meshing the same edge from the same field gets the
    /// same bits. `p0`, `p0 + axis` and their neighbours must lie in the field.
    pub fn crossing(&self, p0: [i64; 3], axis: usize, iso: f32) -> (f32, [f32; 3]) {
        let i0 = self.index(p0);
        let stride = [1, self.size[0], self.size[0] * self.size[1]][axis];
        let (v0, v1) = (self.values[i0].to_f32(), self.values[i0 + stride].to_f32());
        let t = (iso - v0) / (v1 - v0);
        (t, self.crossing_normal(i0, axis, t, v1 >= iso))
    }

    /// The unit normal of a crossing at parameter `t` on the edge from flat index `i0` along
    /// `axis` (see [`Field::crossing`]).
    #[inline]
    pub(super) fn crossing_normal(
        &self,
        i0: usize,
        axis: usize,
        t: f32,
        upper_inside: bool,
    ) -> [f32; 3] {
        let stride = [1, self.size[0], self.size[0] * self.size[1]][axis];
        let (g0, g1) = (self.gradient_at(i0), self.gradient_at(i0 + stride));
        let g = [0, 1, 2].map(|a| g0[a] + t * (g1[a] - g0[a]));
        let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
        if len > 0.0 {
            g.map(|c| -c / len)
        } else {
            // Flat gradient: point along the edge, from inside to outside.
            let mut d = [0f32; 3];
            d[axis] = if upper_inside { -1.0 } else { 1.0 };
            d
        }
    }

    /// Central differences at the point with flat index `i` (strides 1, size x, size x * y).
    #[inline]
    fn gradient_at(&self, i: usize) -> [f32; 3] {
        let (sy, sz) = (self.size[0], self.size[0] * self.size[1]);
        let v = |i: usize| self.values[i].to_f32();
        [
            (v(i + 1) - v(i - 1)) * 0.5,
            (v(i + sy) - v(i - sy)) * 0.5,
            (v(i + sz) - v(i - sz)) * 0.5,
        ]
    }
}

pub use isovox_proto::mesh::Mesh;

/// Reusable per-call memory, and what the last [`march`] left for the transition strips: the
/// vertex on each crossed edge, and the vertices on edges that touch the boundary of its cells
/// (the transition kernel moves them).
#[derive(Debug, Default)]
pub struct Scratch {
    /// The implementation [`march`] runs with this scratch.
    pub kernel: Kernel,
    /// The kernel that made the last [`march`]'s mesh; `None` before one, or after
    /// [`Scratch::forget`].
    last: Option<Kernel>,
    rows: RowsScratch,
    reference: ReferenceScratch,
    /// Vertices of the last call whose edge has an endpoint on the boundary of `[lo, hi]`.
    pub border: Vec<BorderVertex>,
}

/// A vertex on a grid edge with an endpoint on the boundary of the marched cells.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BorderVertex {
    /// Its index in the mesh.
    pub id: u32,
    /// The edge's lower endpoint.
    pub p0: [i64; 3],
    /// The edge's direction (0, 1, 2: x, y, z).
    pub axis: u8,
    /// Where the vertex lies on the edge, from `p0`.
    pub t: f32,
    /// The faces of `[lo, hi]` each endpoint lies on (bit 2a: the face at `lo[a]`, bit 2a + 1:
    /// the face at `hi[a]`).
    pub faces: [u8; 2],
}

impl Scratch {
    /// Scratch for marching with `kernel`.
    pub fn new(kernel: Kernel) -> Self {
        Scratch {
            kernel,
            ..Scratch::default()
        }
    }

    /// Forgets the last [`march`]: as if it had marched cells without a surface.
    pub fn forget(&mut self) {
        self.last = None;
        self.border.clear();
    }

    /// The id of the vertex the last [`march`] made on the grid edge from `p0` along `axis`, if
    /// it made one (the edge is crossed and lies within the cells it marched).
    pub fn vertex_on_edge(&self, p0: [i64; 3], axis: usize) -> Option<u32> {
        match self.last? {
            Kernel::Rows => self.rows.vertex_on_edge(p0, axis),
            Kernel::Reference => self.reference.vertex_on_edge(p0, axis),
        }
    }
}

/// Point `p` relative to `lo`, if it lies in the box `[lo, lo + n]`.
pub(super) fn local_point(p: [i64; 3], lo: [i64; 3], n: [usize; 3]) -> Option<[usize; 3]> {
    let l = [0, 1, 2].map(|a| p[a] - lo[a]);
    (0..3)
        .all(|a| l[a] >= 0 && l[a] as usize <= n[a])
        .then(|| l.map(|c| c as usize))
}

/// The faces of the box `[lo, hi]` that point `p` lies on (bit 2a: `p[a] == lo[a]`, bit 2a + 1:
/// `p[a] == hi[a]`).
pub fn faces_of(p: [i64; 3], lo: [i64; 3], hi: [i64; 3]) -> u8 {
    let mut f = 0;
    for a in 0..3 {
        f |= u8::from(p[a] == lo[a]) << (2 * a) | u8::from(p[a] == hi[a]) << (2 * a + 1);
    }
    f
}

/// Which implementation [`march`] runs. Both give the same mesh: the same vertices (bit for
/// bit), the same triangles and border vertices; only the order of the vertices differs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Kernel {
    /// Rows of cells classified 63 at a time, vertices made once per crossed edge
    /// ([`super::mc_rows`]).
    #[default]
    Rows,
    /// Cell by cell, as before ([`super::mc_reference`]): the tests' oracle and the
    /// benchmark's baseline.
    Reference,
}

/// Marches the cells whose lower corners lie in `[lo, hi)` and appends their triangles to `out`,
/// with positions in grid coordinates relative to `frame` (so a tile's mesh does not depend on
/// where the tile is, and identical tiles can share one cached mesh). Every crossed grid edge
/// between the points of `[lo, hi]` gets one vertex; [`Scratch::vertex_on_edge`] finds it and
/// [`Scratch::border`] lists those on the boundary.
///
/// The field must cover `[lo - 1, hi + 1]` on every axis (inclusive): `hi` for the cells' upper
/// corners, one more on each side for the central differences of the normals. Checked once up
/// front.
///
/// # Panics
/// The field does not cover that range.
pub fn march<S: Sample>(
    field: &Field<'_, S>,
    lo: [i64; 3],
    frame: [i64; 3],
    hi: [i64; 3],
    iso: f32,
    out: &mut Mesh,
    scratch: &mut Scratch,
) {
    for a in 0..3 {
        assert!(
            field.origin[a] < lo[a]
                && lo[a] <= hi[a]
                && hi[a] + 1 < field.origin[a] + field.size[a] as i64,
            "the field does not cover the cells and their gradient halo on axis {a}"
        );
    }
    assert_eq!(field.values.len(), field.size.iter().product::<usize>());
    let border = &mut scratch.border;
    match scratch.kernel {
        Kernel::Rows => mc_rows::march(
            field,
            (lo, hi),
            frame,
            iso,
            out,
            (&mut scratch.rows, border),
        ),
        Kernel::Reference => mc_reference::march(
            field,
            (lo, hi),
            frame,
            iso,
            out,
            (&mut scratch.reference, border),
        ),
    }
    scratch.last = Some(scratch.kernel);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn single_voxel_gives_a_closed_octahedron() {
        // One inside sample at the origin of a 5^3 grid of L: 8 cells touch it, one triangle
        // each, 6 vertices (one per axis direction) at distance t = (0.5 - 0) / (1 - 0) = 0.5...
        // here with values 0 and 1 and iso 0.5.
        let mut values = vec![0f32; 5 * 5 * 5];
        values[(2 * 5 + 2) * 5 + 2] = 1.0;
        let field = Field {
            origin: [-2, -2, -2],
            size: [5; 3],
            values: &values,
        };
        let mut mesh = Mesh::default();
        march(
            &field,
            [-1, -1, -1],
            [0, 0, 0],
            [1, 1, 1],
            0.5,
            &mut mesh,
            &mut Scratch::default(),
        );
        assert_eq!(mesh.triangles(), 8);
        assert_eq!(mesh.positions.len(), 6);
        let mut ps: Vec<[f32; 3]> = mesh.positions.clone();
        ps.sort_by(|a, b| a.partial_cmp(b).unwrap());
        assert_eq!(
            ps,
            vec![
                [-0.5, 0.0, 0.0],
                [0.0, -0.5, 0.0],
                [0.0, 0.0, -0.5],
                [0.0, 0.0, 0.5],
                [0.0, 0.5, 0.0],
                [0.5, 0.0, 0.0]
            ]
        );
        // Normals point outwards: the same direction as the position here.
        for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
            assert!(p[0] * n[0] + p[1] * n[1] + p[2] * n[2] > 0.0, "{p:?} {n:?}");
        }
        // Every triangle's winding normal points outwards too.
        for t in mesh.indices.chunks(3) {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| mesh.positions[i as usize]);
            let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let n = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let centre = [
                (a[0] + b[0] + c[0]) / 3.0,
                (a[1] + b[1] + c[1]) / 3.0,
                (a[2] + b[2] + c[2]) / 3.0,
            ];
            assert!(n[0] * centre[0] + n[1] * centre[1] + n[2] * centre[2] > 0.0);
        }
    }

    #[test]
    #[should_panic(expected = "does not cover")]
    fn the_up_front_bounds_check_refuses_a_short_field() {
        let values = vec![0f32; 27];
        let field = Field {
            origin: [0; 3],
            size: [3; 3],
            values: &values,
        };
        march(
            &field,
            [0; 3],
            [0; 3],
            [1; 3],
            0.5,
            &mut Mesh::default(),
            &mut Scratch::default(),
        );
    }
}
