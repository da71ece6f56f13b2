//! The marching-cubes kernel as it was before [`super::mc_rows`]: cell by cell, each cell's
//! case from its eight corners, each vertex found again through a table of every grid edge.
//! Kept as the oracle of the current kernel (the tests compare their meshes on random fields)
//! and as the baseline `isovox-bench mesh` times next to it; [`super::mc::Kernel::Reference`]
//! selects it.

use super::mc::{faces_of, local_point, BorderVertex, Field, Mesh, Sample};
use super::table::{table, EDGES, EDGE_AXIS};

/// The vertex id of each grid edge already visited, stamped with the call that wrote it so the
/// table never needs clearing between calls.
#[derive(Debug, Default)]
pub(super) struct ReferenceScratch {
    edge_vertex: Vec<(u32, u32)>,
    stamp: u32,
    /// The last call's `lo` and cell counts, to find its edges again.
    lo: [i64; 3],
    n: [usize; 3],
}

impl ReferenceScratch {
    /// The id of the vertex the last [`march`] made on the grid edge from `p0` along `axis`.
    pub(super) fn vertex_on_edge(&self, p0: [i64; 3], axis: usize) -> Option<u32> {
        let l = local_point(p0, self.lo, self.n)?;
        let slot = (((l[2] * (self.n[1] + 1) + l[1]) * (self.n[0] + 1) + l[0]) * 3) + axis;
        match self.edge_vertex.get(slot) {
            Some(&(stamp, id)) if stamp == self.stamp && self.stamp != 0 => Some(id),
            _ => None,
        }
    }
}

/// [`super::mc::march`] cell by cell (the caller has checked the field's extent).
pub(super) fn march<S: Sample>(
    field: &Field<'_, S>,
    (lo, hi): ([i64; 3], [i64; 3]),
    frame: [i64; 3],
    iso: f32,
    out: &mut Mesh,
    (scratch, border): (&mut ReferenceScratch, &mut Vec<BorderVertex>),
) {
    let n = [0, 1, 2].map(|a| (hi[a] - lo[a]) as usize);
    // Edge slots: one per grid point of [lo, hi] and axis.
    let points = (n[0] + 1) * (n[1] + 1) * (n[2] + 1);
    scratch.stamp = scratch.stamp.wrapping_add(1);
    if scratch.stamp == 0 || scratch.edge_vertex.len() < points * 3 {
        // First use, a larger grid, or the stamp wrapped: start from a clean table.
        scratch.edge_vertex.clear();
        scratch.edge_vertex.resize(points * 3, (0, 0));
        scratch.stamp = 1;
    }
    let stamp = scratch.stamp;
    scratch.lo = lo;
    scratch.n = n;
    border.clear();
    let table = table();
    let row = |y: i64, z: i64| {
        let start = (((z - field.origin[2]) as usize * field.size[1])
            + (y - field.origin[1]) as usize)
            * field.size[0];
        let x0 = (lo[0] - field.origin[0]) as usize;
        &field.values[start + x0..start + x0 + n[0] + 1]
    };
    for z in lo[2]..hi[2] {
        for y in lo[1]..hi[1] {
            // The four rows of samples the cells of this row read (x fastest): corner c of cell x
            // is rows[c >> 1][x + (c & 1)].
            let rows = [row(y, z), row(y + 1, z), row(y, z + 1), row(y + 1, z + 1)];
            // Inside flags of the cells' x-side corners, as the bits of corners 0, 2, 4, 6.
            let side = |i: usize| -> usize {
                (rows[0][i].to_f32() >= iso) as usize
                    | ((rows[1][i].to_f32() >= iso) as usize) << 2
                    | ((rows[2][i].to_f32() >= iso) as usize) << 4
                    | ((rows[3][i].to_f32() >= iso) as usize) << 6
            };
            let mut low_side = side(0);
            for (i, x) in (lo[0]..hi[0]).enumerate() {
                let high_side = side(i + 1);
                let case = low_side | high_side << 1;
                low_side = high_side;
                if case == 0 || case == 255 {
                    continue;
                }
                let corners: [f32; 8] = std::array::from_fn(|c| rows[c >> 1][i + (c & 1)].to_f32());
                let tris = &table[case];
                if tris.is_empty() {
                    continue;
                }
                for &e in tris.iter() {
                    let (c0, c1) = EDGES[e as usize];
                    let axis = EDGE_AXIS[e as usize] as usize;
                    let p0 = [
                        x + (c0 & 1) as i64,
                        y + (c0 >> 1 & 1) as i64,
                        z + (c0 >> 2 & 1) as i64,
                    ];
                    let l = [0, 1, 2].map(|a| (p0[a] - lo[a]) as usize);
                    let slot = (((l[2] * (n[1] + 1) + l[1]) * (n[0] + 1) + l[0]) * 3) + axis;
                    let (seen, mut id) = scratch.edge_vertex[slot];
                    if seen != stamp {
                        let (v0, v1) = (corners[c0 as usize], corners[c1 as usize]);
                        let t = (iso - v0) / (v1 - v0);
                        let mut pos = [0, 1, 2].map(|a| (p0[a] - frame[a]) as f32);
                        pos[axis] += t;
                        let normal = field.crossing_normal(field.index(p0), axis, t, v1 >= iso);
                        id = out.positions.len() as u32;
                        out.positions.push(pos);
                        out.normals.push(normal);
                        scratch.edge_vertex[slot] = (stamp, id);
                        let mut p1 = p0;
                        p1[axis] += 1;
                        let faces = [faces_of(p0, lo, hi), faces_of(p1, lo, hi)];
                        if faces != [0, 0] {
                            border.push(BorderVertex {
                                id,
                                p0,
                                axis: axis as u8,
                                t,
                                faces,
                            });
                        }
                    }
                    out.indices.push(id);
                }
            }
        }
    }
}
