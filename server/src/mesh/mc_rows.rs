//! The marching-cubes kernel a row of cells at a time, after VTK's Flying Edges: most cells of
//! a tile that holds a surface lie wholly on one side of it, so the kernel first learns, a
//! 64-bit word per row of points, which points are inside, and from those words alone which
//! edges are crossed and which cells are mixed; only crossed edges and mixed cells cost more.
//!
//! Three passes over the points of `[lo, hi]`, rows along x, 63 cells (64 points) to a word,
//! successive words of a row overlapping by one point so that every cell has its corners in one
//! word:
//! 1. inside bits: one word per 64 points of a row, from the field's values, a vector of
//!    compares at a time ([`super::inside`]);
//! 2. crossed edges: for each row, the edges from its points along x (a word xor itself shifted),
//!    y and z (xor the next row's word) that the iso value crosses; one vertex for each, row
//!    after row, its id written where the edge's slot is (only crossed edges' slots are written
//!    and read, so nothing is cleared between calls);
//! 3. triangles: a cell row's four rows of corners give its mixed cells (the corners' and/or
//!    differ), each one's case from eight bits of the words, its triangles' vertices from the
//!    slots of its edges.
//!
//! The vertices are those [`super::mc_reference`] makes, bit for bit (the same formulas on the
//! same samples: every crossed edge between points of `[lo, hi]` is an edge of a mixed cell,
//! and each mixed cell's triangles use all its crossed edges), in another order; the triangles
//! are the same, in the same order.

use super::mc::{local_point, BorderVertex, Field, Mesh, Sample};
use super::table::{table, EDGES, EDGE_AXIS};
use std::sync::OnceLock;

/// Cells per word: a word holds 64 points of a row, the corners of 63 cells.
const CELLS: usize = 63;

/// One word of one row of points: 64 points from `x = 63 w` (relative to `lo`), the last one
/// shared with the next word.
#[derive(Debug, Clone, Copy, Default)]
struct RowWord {
    /// Bit b: point `63 w + b` is inside (0 past the last point).
    inside: u64,
    /// For each axis, bit b: the edge from point `63 w + b` along that axis is crossed and lies
    /// between points of `[lo, hi]`.
    crossed: [u64; 3],
}

/// What [`march`] leaves to find its vertices again.
#[derive(Debug, Default)]
pub(super) struct RowsScratch {
    /// Row `z (n_y + 1) + y` of points, word w: `words[row * width + w]`.
    words: Vec<RowWord>,
    /// The vertex on the edge from point x of a row along an axis, where that edge is crossed
    /// (stale elsewhere): `ids[(row * 3 + axis) * (n_x + 1) + x]`.
    ids: Vec<u32>,
    /// The mixed cells of the last call: `first slot << 8 | case`.
    cells: Vec<u64>,
    /// The vertices of the current call, before they are appended to its mesh at once.
    made: Mesh,
    /// Words per row (0 when the last call had no cells).
    width: usize,
    lo: [i64; 3],
    n: [usize; 3],
}

impl RowsScratch {
    /// The id of the vertex the last [`march`] made on the grid edge from `p0` along `axis`.
    pub(super) fn vertex_on_edge(&self, p0: [i64; 3], axis: usize) -> Option<u32> {
        if self.width == 0 {
            return None;
        }
        let l = local_point(p0, self.lo, self.n)?;
        let row = l[2] * (self.n[1] + 1) + l[1];
        let w = (l[0] / CELLS).min(self.width - 1);
        let word = &self.words[row * self.width + w];
        let crossed = word.crossed[axis] >> (l[0] - w * CELLS) & 1 == 1;
        crossed.then(|| self.ids[(row * 3 + axis) * (self.n[0] + 1) + l[0]])
    }
}

/// The bits below bit `k` (k <= 63).
#[inline]
fn below(k: usize) -> u64 {
    (1u64 << k) - 1
}

/// Where each cell edge's vertex is recorded: which of the cell's four rows of corners holds
/// its lower endpoint (corners `2r` and `2r + 1`: row `r = c >> 1`), its axis, and its lower
/// endpoint's offset along x.
const EDGE_PLACES: [(usize, usize, usize); 12] = {
    let mut out = [(0, 0, 0); 12];
    let mut e = 0;
    while e < 12 {
        let c0 = EDGES[e].0 as usize;
        out[e] = (c0 >> 1, EDGE_AXIS[e] as usize, c0 & 1);
        e += 1;
    }
    out
};

/// The case table laid out flat: the edges of case c are `edges[start[c]..start[c + 1]]`.
struct FlatTable {
    edges: Vec<u8>,
    start: [usize; 257],
}

fn flat_table() -> &'static FlatTable {
    static FLAT: OnceLock<FlatTable> = OnceLock::new();
    FLAT.get_or_init(|| {
        let mut flat = FlatTable {
            edges: Vec::new(),
            start: [0; 257],
        };
        for (case, tris) in table().iter().enumerate() {
            flat.edges.extend_from_slice(tris);
            flat.start[case + 1] = flat.edges.len();
        }
        flat
    })
}

/// What making a vertex needs beside its edge.
struct Vertices<'a, 'f, S> {
    field: &'a Field<'f, S>,
    iso: f32,
    lo: [i64; 3],
    /// Cells per axis.
    n: [usize; 3],
    frame: [i64; 3],
    /// The id of the first vertex the call makes (the mesh's vertices before it).
    first_id: u32,
}

/// [`super::mc::faces_of`] for the point `lo + local` of the box `[lo, lo + n]`.
#[inline]
fn faces_of(local: [usize; 3], n: [usize; 3]) -> u8 {
    let mut f = 0;
    for a in 0..3 {
        f |= u8::from(local[a] == 0) << (2 * a) | u8::from(local[a] == n[a]) << (2 * a + 1);
    }
    f
}

impl<S: Sample> Vertices<'_, '_, S> {
    /// Appends to `out` the vertices on the crossed edges `bits` of word `w` of row `(y, z)`
    /// (relative to `lo`) along `AXIS`, whose first point has index `start` in the field,
    /// recording their ids in `ids` (the row's ids along `AXIS`) and the border ones in
    /// `border`. The axis is a constant so that each of the three copies indexes its arrays
    /// and strides statically.
    #[inline]
    fn make<const AXIS: usize>(
        &self,
        mut bits: u64,
        (w, y, z): (usize, usize, usize),
        start: usize,
        ids: &mut [u32],
        made: &mut Mesh,
        border: &mut Vec<BorderVertex>,
    ) {
        let values = self.field.values;
        let stride = [
            1,
            self.field.size[0],
            self.field.size[0] * self.field.size[1],
        ][AXIS];
        while bits != 0 {
            let b = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let x = w * CELLS + b;
            let local = [x, y, z];
            let p0 = [0, 1, 2].map(|a| self.lo[a] + local[a] as i64);
            let i0 = start + x;
            let (v0, v1) = (values[i0].to_f32(), values[i0 + stride].to_f32());
            let t = (self.iso - v0) / (v1 - v0);
            let mut pos = [0, 1, 2].map(|a| (p0[a] - self.frame[a]) as f32);
            pos[AXIS] += t;
            let id = self.first_id + made.positions.len() as u32;
            ids[x] = id;
            made.positions.push(pos);
            made.normals
                .push(self.field.crossing_normal(i0, AXIS, t, v1 >= self.iso));
            let mut upper = local;
            upper[AXIS] += 1;
            let faces = [faces_of(local, self.n), faces_of(upper, self.n)];
            if faces != [0, 0] {
                border.push(BorderVertex {
                    id,
                    p0,
                    axis: AXIS as u8,
                    t,
                    faces,
                });
            }
        }
    }
}

/// [`super::mc::march`] a row at a time (the caller has checked the field's extent).
pub(super) fn march<S: Sample>(
    field: &Field<'_, S>,
    (lo, hi): ([i64; 3], [i64; 3]),
    frame: [i64; 3],
    iso: f32,
    out: &mut Mesh,
    (scratch, border): (&mut RowsScratch, &mut Vec<BorderVertex>),
) {
    border.clear();
    let n = [0, 1, 2].map(|a| (hi[a] - lo[a]) as usize);
    scratch.lo = lo;
    scratch.n = n;
    if n.contains(&0) {
        // No cell, no vertex.
        scratch.width = 0;
        return;
    }
    let width = n[0].div_ceil(CELLS);
    scratch.width = width;
    let (row_points, plane_rows) = (n[0] + 1, n[1] + 1);
    let rows = plane_rows * (n[2] + 1);
    // Every word is written before it is read, and only crossed edges' ids are written, and
    // read: no clearing needed.
    scratch.words.resize(rows * width, RowWord::default());
    scratch.ids.resize(rows * 3 * row_points, 0);
    let words = &mut scratch.words[..];
    // Rows are visited z, then y: the field index of a row's first point is a sum, no division.
    let first = field.index(lo);
    let (field_row, field_plane) = (field.size[0], field.size[0] * field.size[1]);
    // The cells (and edges along x) of word w.
    let cells_of = |w: usize| (n[0] - w * CELLS).min(CELLS);

    // 1. Inside bits.
    let cut = S::cut(iso);
    for z in 0..=n[2] {
        for y in 0..=n[1] {
            let start = first + z * field_plane + y * field_row;
            let values = &field.values[start..start + row_points];
            let row = z * plane_rows + y;
            for (w, word) in words[row * width..][..width].iter_mut().enumerate() {
                let from = w * CELLS;
                word.inside = S::inside_bits(&values[from..(from + 64).min(row_points)], cut);
            }
        }
    }

    // 2. Crossed edges and their vertices, row after row.
    for z in 0..=n[2] {
        for y in 0..=n[1] {
            let row = z * plane_rows + y;
            for w in 0..width {
                let at = row * width + w;
                let inside = words[at].inside;
                let along_x = (inside ^ inside >> 1) & below(cells_of(w));
                let along_y = if y < n[1] {
                    inside ^ words[at + width].inside
                } else {
                    0
                };
                let along_z = if z < n[2] {
                    inside ^ words[at + plane_rows * width].inside
                } else {
                    0
                };
                words[at].crossed = [along_x, along_y, along_z];
            }
        }
    }
    // Made into the scratch's buffers (which stop growing after the first tiles) and
    // appended at once, so the mesh is allocated once, at its size: counting the crossed
    // edges first to reserve it cost more (a popcount is a loop of a dozen instructions on
    // baseline x86-64).
    let made = &mut scratch.made;
    made.positions.clear();
    made.normals.clear();
    let first_id = out.positions.len() as u32;
    let vertices = Vertices {
        field,
        iso,
        lo,
        n,
        frame,
        first_id,
    };
    for z in 0..=n[2] {
        for y in 0..=n[1] {
            let row = z * plane_rows + y;
            let start = first + z * field_plane + y * field_row;
            let ids = &mut scratch.ids[row * 3 * row_points..][..3 * row_points];
            let (ids_x, ids_yz) = ids.split_at_mut(row_points);
            let (ids_y, ids_z) = ids_yz.split_at_mut(row_points);
            for w in 0..width {
                let owned = if w + 1 < width { below(CELLS) } else { !0 };
                let crossed = words[row * width + w].crossed.map(|c| c & owned);
                if crossed == [0; 3] {
                    continue;
                }
                let at = (w, y, z);
                vertices.make::<0>(crossed[0], at, start, ids_x, made, border);
                vertices.make::<1>(crossed[1], at, start, ids_y, made, border);
                vertices.make::<2>(crossed[2], at, start, ids_z, made, border);
            }
        }
    }
    out.positions.extend_from_slice(&made.positions);
    out.normals.extend_from_slice(&made.normals);

    // 3. Triangles, cell row after cell row.
    let table = flat_table();
    let words = &scratch.words[..];
    let ids = &scratch.ids[..];
    // Where the id of each cell edge is, from `row * 3 * row_points + x` for the cell at x of
    // cell row `row`.
    let edge_slots = EDGE_PLACES.map(|(r, axis, dx)| {
        let row = [0, 1, plane_rows, plane_rows + 1][r];
        (row * 3 + axis) * row_points + dx
    });
    // First the mixed cells, each as its first slot and case, and how many indices they make
    // (reserved at once: the mesh grows once per call, not once per doubling).
    let mixed_cells = &mut scratch.cells;
    mixed_cells.clear();
    let mut indices = 0;
    for z in 0..n[2] {
        for y in 0..n[1] {
            let row = z * plane_rows + y;
            // The rows of corners 0-1, 2-3, 4-5, 6-7.
            let corner_rows = [row, row + 1, row + plane_rows, row + plane_rows + 1];
            for w in 0..width {
                let [a, b, c, d] = corner_rows.map(|r| words[r * width + w].inside);
                let (all, any) = (a & b & c & d, a | b | c | d);
                // A cell is mixed when some corner is inside and some is not.
                let mut mixed = (any | any >> 1) & !(all & all >> 1) & below(cells_of(w));
                while mixed != 0 {
                    let bit = mixed.trailing_zeros() as usize;
                    mixed &= mixed - 1;
                    let case = (a >> bit & 3)
                        | (b >> bit & 3) << 2
                        | (c >> bit & 3) << 4
                        | (d >> bit & 3) << 6;
                    let base = row * 3 * row_points + w * CELLS + bit;
                    indices += table.start[case as usize + 1] - table.start[case as usize];
                    mixed_cells.push((base as u64) << 8 | case);
                }
            }
        }
    }
    out.indices.reserve(indices);
    for &cell in mixed_cells.iter() {
        let (base, case) = ((cell >> 8) as usize, (cell & 0xff) as usize);
        // Extended a cell at a time, not pushed an index at a time: no capacity check per
        // index, which showed in profiles of the kernel on scans.
        let edges = &table.edges[table.start[case]..table.start[case + 1]];
        out.indices
            .extend(edges.iter().map(|&e| ids[base + edge_slots[e as usize]]));
    }
}
