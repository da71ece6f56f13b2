//! The marching-cubes kernel a row of cells at a time, after VTK's Flying Edges: most cells of
//! a tile that holds a surface lie wholly on one side of it, so the kernel first learns, a
//! 64-bit word per row of points, which points are inside, and from those words alone which
//! edges are crossed and which cells are mixed; only crossed edges and mixed cells cost more.
//!
//! Three passes over the points of `[lo, hi]`, rows along x, 63 cells (64 points) to a word,
//! successive words of a row overlapping by one point so that every cell has its corners in one
//! word:
//! 1. inside bits: one word per 64 points of a row, from the field's values;
//! 2. crossed edges: for each row, the edges from its points along x (a word xor itself shifted),
//!    y and z (xor the next row's word) that the iso value crosses; one vertex for each, in row
//!    order, so that the vertex of the b-th crossed edge of a word is the word's first id plus
//!    b: a popcount finds it again, and no table of edges is needed;
//! 3. triangles: a cell row's four rows of corners give its mixed cells (the corners' and/or
//!    differ), each one's case from eight bits of the words, its triangles' vertices by popcount.
//!
//! The vertices are those [`super::mc_reference`] makes, bit for bit (the same formulas on the
//! same samples: every crossed edge between points of `[lo, hi]` is an edge of a mixed cell,
//! and each mixed cell's triangles use all its crossed edges), in another order; the triangles
//! are the same, in the same order.

use super::mc::{faces_of, BorderVertex, Field, Mesh};
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
    /// For each axis, the id of the vertex on the word's first crossed edge: the vertex on the
    /// edge of bit b is `first + popcount(crossed below b)` (bit 63 included: its edge is bit 0
    /// of the next word, whose first id follows this word's other 63 bits).
    first: [u32; 3],
}

/// What [`march`] leaves to find its vertices again.
#[derive(Debug, Default)]
pub(super) struct RowsScratch {
    words: Vec<RowWord>,
    /// Words per row (0 when the last call had no cells).
    width: usize,
    lo: [i64; 3],
    n: [usize; 3],
}

impl RowsScratch {
    /// The id of the vertex the last [`march`] made on the grid edge from `p0` along `axis`.
    pub(super) fn vertex_on_edge(&self, p0: [i64; 3], axis: usize) -> Option<u32> {
        let l = [0, 1, 2].map(|a| p0[a] - self.lo[a]);
        if self.width == 0 || (0..3).any(|a| l[a] < 0 || l[a] as usize > self.n[a]) {
            return None;
        }
        let l = l.map(|c| c as usize);
        let w = (l[0] / CELLS).min(self.width - 1);
        let bit = l[0] - w * CELLS;
        let word = &self.words[(l[2] * (self.n[1] + 1) + l[1]) * self.width + w];
        (word.crossed[axis] >> bit & 1 == 1).then(|| word.vertex(axis, bit))
    }
}

impl RowWord {
    /// The id of the vertex on the crossed edge of bit `bit` along `axis`.
    #[inline]
    fn vertex(&self, axis: usize, bit: usize) -> u32 {
        self.first[axis] + (self.crossed[axis] & below(bit)).count_ones()
    }
}

/// The bits below bit `k` (k <= 63).
#[inline]
fn below(k: usize) -> u64 {
    (1u64 << k) - 1
}

/// Where each cell edge's crossing is recorded: which of the cell's four rows of corners holds
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

/// Bit i: `values[i] >= iso` (at most 64 values). Eight at a time, so that the comparisons
/// become vector compares and mask moves.
#[inline]
fn inside_bits(values: &[f32], iso: f32) -> u64 {
    let mut bits = 0u64;
    let mut eights = values.chunks_exact(8);
    for (k, eight) in (&mut eights).enumerate() {
        let mut byte = 0u64;
        for (j, &v) in eight.iter().enumerate() {
            byte |= u64::from(v >= iso) << j;
        }
        bits |= byte << (8 * k);
    }
    let done = values.len() - eights.remainder().len();
    for (j, &v) in eights.remainder().iter().enumerate() {
        bits |= u64::from(v >= iso) << (done + j);
    }
    bits
}

/// [`super::mc::march`] a row at a time (the caller has checked the field's extent).
pub(super) fn march(
    field: &Field<'_>,
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
    scratch.words.clear();
    if n.contains(&0) {
        // No cell, no vertex.
        scratch.width = 0;
        return;
    }
    let width = n[0].div_ceil(CELLS);
    scratch.width = width;
    let row_words = width;
    let plane_words = (n[1] + 1) * width;
    scratch
        .words
        .resize((n[2] + 1) * plane_words, RowWord::default());
    let words = &mut scratch.words[..];
    let values = field.values;
    let row_start = |y: usize, z: usize| field.index([lo[0], lo[1] + y as i64, lo[2] + z as i64]);
    // The cells (and edges along x) of word w.
    let cells_of = |w: usize| (n[0] - w * CELLS).min(CELLS);

    // 1. Inside bits.
    for z in 0..=n[2] {
        for y in 0..=n[1] {
            let start = row_start(y, z);
            let row = &values[start..start + n[0] + 1];
            let r = z * plane_words + y * row_words;
            for (w, word) in words[r..r + width].iter_mut().enumerate() {
                let from = w * CELLS;
                word.inside = inside_bits(&row[from..(from + 64).min(n[0] + 1)], iso);
            }
        }
    }

    // 2. Crossed edges and their vertices, row after row.
    let strides = [1, field.size[0], field.size[0] * field.size[1]];
    let mut next = out.positions.len() as u32;
    for z in 0..=n[2] {
        for y in 0..=n[1] {
            let r = z * plane_words + y * row_words;
            for w in 0..width {
                let inside = words[r + w].inside;
                let along_x = (inside ^ inside >> 1) & below(cells_of(w));
                let along_y = if y < n[1] {
                    inside ^ words[r + row_words + w].inside
                } else {
                    0
                };
                let along_z = if z < n[2] {
                    inside ^ words[r + plane_words + w].inside
                } else {
                    0
                };
                words[r + w].crossed = [along_x, along_y, along_z];
            }
            let start = row_start(y, z);
            for axis in 0..3 {
                for w in 0..width {
                    let word = &mut words[r + w];
                    word.first[axis] = next;
                    // Bit 63 is the next word's bit 0 (the last word has no next).
                    let owned = if w + 1 < width { below(CELLS) } else { !0 };
                    let mut bits = word.crossed[axis] & owned;
                    while bits != 0 {
                        let b = bits.trailing_zeros() as usize;
                        bits &= bits - 1;
                        let x = w * CELLS + b;
                        let p0 = [lo[0] + x as i64, lo[1] + y as i64, lo[2] + z as i64];
                        let i0 = start + x;
                        let (v0, v1) = (values[i0], values[i0 + strides[axis]]);
                        let t = (iso - v0) / (v1 - v0);
                        let mut pos = [0, 1, 2].map(|a| (p0[a] - frame[a]) as f32);
                        pos[axis] += t;
                        out.positions.push(pos);
                        out.normals
                            .push(field.crossing_normal(i0, axis, t, v1 >= iso));
                        let mut p1 = p0;
                        p1[axis] += 1;
                        let faces = [faces_of(p0, lo, hi), faces_of(p1, lo, hi)];
                        if faces != [0, 0] {
                            border.push(BorderVertex {
                                id: next,
                                p0,
                                axis: axis as u8,
                                t,
                                faces,
                            });
                        }
                        next += 1;
                    }
                }
            }
        }
    }

    // 3. Triangles, cell row after cell row.
    let table = flat_table();
    let words = &scratch.words[..];
    for z in 0..n[2] {
        for y in 0..n[1] {
            let r = z * plane_words + y * row_words;
            // The rows of corners 0-1, 2-3, 4-5, 6-7.
            let rows = [
                r,
                r + row_words,
                r + plane_words,
                r + plane_words + row_words,
            ];
            for w in 0..width {
                let corners = rows.map(|q| &words[q + w]);
                let [a, b, c, d] = corners.map(|word| word.inside);
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
                    let case = case as usize;
                    let edges = &table.edges[table.start[case]..table.start[case + 1]];
                    out.indices.extend(edges.iter().map(|&e| {
                        let (row, axis, dx) = EDGE_PLACES[e as usize];
                        corners[row].vertex(axis, bit + dx)
                    }));
                }
            }
        }
    }
}
