//! The transition-cell case table, generated with the face rule of the regular table
//! ([`super::table`]) instead of copied.
//!
//! A transition cell joins a 2x2 block of a tile's boundary cells to the one face of a cell of
//! the next coarser level (Lengyel 2010, "Voxel-Based Terrain for Real-Time Virtual
//! Simulations"): 9 samples on its full-resolution face, 4 on its half-resolution face. Here the
//! coarse samples are the coarser level's own values at the same lattice points as the fine
//! face's corners, not copies of them (a coarse value is a mean, see `docs/lod-meshes.md`), so
//! all 13 samples are independent: 8192 cases, and the four edges joining a fine corner to its
//! coarse twin can be crossed too.
//!
//! The cell in its canonical frame (u, v, n), right-handed, n pointing from the fine face to
//! the coarse one:
//!
//! ```text
//!   fine sample F(i, j), i, j in 0..3, at (i, j, 0): sample i + 3j      (0..9)
//!   coarse sample C(i, j), i, j in 0..2, at (2i, 2j, 1): sample 9 + i + 2j   (9..13)
//! ```
//!
//! Its nine faces: four fine squares (the outer faces of the four fine boundary cells), one
//! coarse square (the face of the coarse cell), and four lateral pentagons (three fine samples,
//! two coarse ones), each shared with the next transition cell or, at a tile's edge, with the
//! neighbouring tile's strip. The contour is traced face by face with the regular table's rule
//! (one segment per maximal run of inside corners, counter-clockwise seen from outside), which
//! depends on a face's samples alone: the coarse square is cut exactly as the coarse tile cuts
//! it, each fine square exactly as the fine tile's boundary cell cuts it, and a pentagon
//! identically from both of its cells. The segments chain into closed loops, wound like the
//! regular table's.
//!
//! The table stores each case's loops. They are triangulated where the cell's shape is known
//! (`super::transition`), by [`triangulate`]: a loop can lie flat on the fine face (a cap), and
//! one combinatorial triangulation does not fit every position of its vertices. The cells at a
//! strip's ends have a collapsed side and are traced there too, with [`faces`] and
//! [`run_segments`].

use std::sync::OnceLock;

/// Samples of the cell.
pub const SAMPLES: usize = 13;

/// The canonical position of sample `s`, in fine-cell units, with the coarse face at n = 1.
pub const fn sample_position(s: u8) -> [i32; 3] {
    if s < 9 {
        [(s % 3) as i32, (s / 3) as i32, 0]
    } else {
        let c = s - 9;
        [2 * (c & 1) as i32, 2 * (c >> 1) as i32, 1]
    }
}

/// Fine sample F(i, j).
pub const fn fine(i: u8, j: u8) -> u8 {
    i + 3 * j
}

/// Coarse sample C(i, j), at the position of F(2i, 2j).
pub const fn coarse(i: u8, j: u8) -> u8 {
    9 + i + 2 * j
}

/// The 20 edges as (lower sample, upper sample): along u or v, the lower end has the smaller
/// coordinate; a connecting edge runs from the fine corner to its coarse twin.
pub const EDGES: [(u8, u8); 20] = [
    // fine, along u
    (fine(0, 0), fine(1, 0)),
    (fine(1, 0), fine(2, 0)),
    (fine(0, 1), fine(1, 1)),
    (fine(1, 1), fine(2, 1)),
    (fine(0, 2), fine(1, 2)),
    (fine(1, 2), fine(2, 2)),
    // fine, along v
    (fine(0, 0), fine(0, 1)),
    (fine(0, 1), fine(0, 2)),
    (fine(1, 0), fine(1, 1)),
    (fine(1, 1), fine(1, 2)),
    (fine(2, 0), fine(2, 1)),
    (fine(2, 1), fine(2, 2)),
    // coarse, along u then v
    (coarse(0, 0), coarse(1, 0)),
    (coarse(0, 1), coarse(1, 1)),
    (coarse(0, 0), coarse(0, 1)),
    (coarse(1, 0), coarse(1, 1)),
    // connecting
    (fine(0, 0), coarse(0, 0)),
    (fine(2, 0), coarse(1, 0)),
    (fine(0, 2), coarse(0, 1)),
    (fine(2, 2), coarse(1, 1)),
];

/// What an edge joins.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EdgeKind {
    /// Two fine samples.
    Fine,
    /// Two coarse samples.
    Coarse,
    /// A fine corner and its coarse twin.
    Connecting,
}

/// What edge `e` joins.
pub fn edge_kind(e: u8) -> EdgeKind {
    match e {
        0..12 => EdgeKind::Fine,
        12..16 => EdgeKind::Coarse,
        _ => EdgeKind::Connecting,
    }
}

/// The edge joining samples `a` and `b` (consecutive corners of a face).
pub fn edge_between(a: u8, b: u8) -> u8 {
    let (lo, hi) = (a.min(b), a.max(b));
    EDGES
        .iter()
        .position(|&(x, y)| (x.min(y), x.max(y)) == (lo, hi))
        .expect("consecutive corners of a face are joined by an edge") as u8
}

/// The lateral sides of the cell, in the order u = 0, u = 2, v = 0, v = 2.
pub const SIDES: usize = 4;

/// Whether sample `s` lies on lateral side `side`.
pub const fn on_side(s: u8, side: usize) -> bool {
    let p = sample_position(s);
    match side {
        0 => p[0] == 0,
        1 => p[0] == 2,
        2 => p[1] == 0,
        _ => p[1] == 2,
    }
}

/// The lateral sides each edge lies on (both its samples on it), as bits in [`SIDES`] order.
pub const EDGE_SIDES: [u8; EDGES.len()] = {
    let mut out = [0u8; EDGES.len()];
    let mut e = 0;
    while e < EDGES.len() {
        let mut side = 0;
        while side < SIDES {
            if on_side(EDGES[e].0, side) && on_side(EDGES[e].1, side) {
                out[e] |= 1 << side;
            }
            side += 1;
        }
        e += 1;
    }
    out
};

/// The nine faces, each as its corners counter-clockwise seen from outside the cell: the four
/// fine squares, the coarse square, then the lateral sides in [`SIDES`] order.
pub fn faces() -> &'static [Vec<u8>] {
    static FACES: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    FACES.get_or_init(make_faces)
}

fn make_faces() -> Vec<Vec<u8>> {
    let mut faces: Vec<(Vec<u8>, [f64; 3])> = Vec::new();
    for j in 0..2 {
        for i in 0..2 {
            let corners = vec![
                fine(i, j),
                fine(i + 1, j),
                fine(i + 1, j + 1),
                fine(i, j + 1),
            ];
            faces.push((corners, [0.0, 0.0, -1.0]));
        }
    }
    faces.push(((9..13).collect(), [0.0, 0.0, 1.0]));
    for side in 0..SIDES {
        let corners: Vec<u8> = (0..SAMPLES as u8).filter(|&s| on_side(s, side)).collect();
        let normal = match side {
            0 => [-1.0, 0.0, 0.0],
            1 => [1.0, 0.0, 0.0],
            2 => [0.0, -1.0, 0.0],
            _ => [0.0, 1.0, 0.0],
        };
        faces.push((corners, normal));
    }
    faces
        .into_iter()
        .map(|(mut corners, normal)| {
            // Sort by angle around the centroid in a frame (a, b) with a x b = the outward normal.
            let pos = |s: u8| sample_position(s).map(f64::from);
            let n = corners.len() as f64;
            let centre = corners.iter().fold([0.0; 3], |acc, &s| {
                let p = pos(s);
                [acc[0] + p[0] / n, acc[1] + p[1] / n, acc[2] + p[2] / n]
            });
            let a = if normal[2] != 0.0 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 0.0, 1.0]
            };
            let b = cross(normal, a);
            let angle = |s: u8| {
                let p = pos(s);
                let d = [p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]];
                dot(d, b).atan2(dot(d, a))
            };
            corners.sort_by(|&x, &y| angle(x).total_cmp(&angle(y)));
            corners
        })
        .collect()
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The contour loops of `case` (bit `s` set: sample `s` is inside), as edge indices, each loop
/// counter-clockwise seen from outside the surface.
pub fn loops(case: u16) -> Vec<Vec<u8>> {
    let mut next = [u8::MAX; EDGES.len()];
    for f in faces() {
        run_segments(f, case, &mut next);
    }
    chain(&next)
}

/// The face rule of the regular table ([`super::table::run_segments`]) on one face of the cell
/// (corners counter-clockwise from outside), for `case`.
pub fn run_segments(face: &[u8], case: u16, next: &mut [u8; EDGES.len()]) {
    super::table::run_segments(face, |s| case >> s & 1 == 1, edge_between, next);
}

pub use super::table::chain;

/// The transition width the triangulation is chosen for: the fine face sits this far (in fine
/// cells) inside the coarse face. `super::transition` moves vertices by the same amount.
pub const WIDTH: f64 = 0.5;

/// Where the vertex on edge `e` sits in the drawn cell when it is at the edge's midpoint: the
/// coarse face at n = 0, the fine face WIDTH below it.
#[cfg(test)]
fn drawn_midpoint(e: u8) -> [f64; 3] {
    let (a, b) = EDGES[e as usize];
    let at = |s: u8| {
        let p = sample_position(s).map(f64::from);
        [p[0], p[1], if s < 9 { -WIDTH } else { 0.0 }]
    };
    let (pa, pb) = (at(a), at(b));
    [0, 1, 2].map(|i| (pa[i] + pb[i]) / 2.0)
}

/// The area of the triangle with corners `a`, `b`, `c`.
pub fn area(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let n = cross(
        [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
        [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
    );
    dot(n, n).sqrt() / 2.0
}

/// The minimum-area triangulation of a polygon with corners `points` (in order; the
/// triangles, as corner indices, keep that winding), appended to `out`, refusing, as long as
/// another triangulation exists, triangles with an area below `flat` and diagonals (i, j) with
/// `refused(i, j)`; returns whether it could refuse them all. On a flat polygon the minimum is
/// a triangulation without overlap (any overlap adds area).
pub fn triangulate(
    points: &[[f64; 3]],
    flat: f64,
    refused: impl Fn(usize, usize) -> bool,
    out: &mut Vec<[usize; 3]>,
) -> bool {
    let n = points.len();
    if n < 3 {
        return true;
    }
    assert!(
        n <= EDGES.len(),
        "a loop visits each of the cell's edges at most once"
    );
    if n == 3 {
        out.push([0, 1, 2]);
        return area(points[0], points[1], points[2]) >= flat;
    }
    if n == 4 {
        // Two diagonals: the one with less area (and nothing refused), without the tables.
        let cost = |t: [[usize; 3]; 2], d: (usize, usize)| {
            let areas = t.map(|[i, k, j]| area(points[i], points[k], points[j]));
            let bad = refused(d.0, d.1) || areas.iter().any(|&a| a < flat);
            (bad, areas[0] + areas[1])
        };
        let first = [[0, 1, 2], [0, 2, 3]];
        let second = [[0, 1, 3], [1, 2, 3]];
        let (b1, a1) = cost(first, (0, 2));
        let (b2, a2) = cost(second, (1, 3));
        // Ties go to the diagonal 1-3, as the general case resolves them.
        let take_first = (b1, a1) < (b2, a2);
        let (t, bad) = if take_first {
            (first, b1)
        } else {
            (second, b2)
        };
        out.extend(t);
        return !bad;
    }
    // Loops of a transition cell are short: the tables sized for the common case on the
    // stack, the longest ones (up to every edge of the cell) in larger ones.
    if n <= 8 {
        min_area::<8>(points, flat, refused, out)
    } else {
        min_area::<{ EDGES.len() }>(points, flat, refused, out)
    }
}

/// The dynamic programme of [`triangulate`] for polygons of at most `M` corners.
fn min_area<const M: usize>(
    points: &[[f64; 3]],
    flat: f64,
    refused: impl Fn(usize, usize) -> bool,
    out: &mut Vec<[usize; 3]>,
) -> bool {
    const REFUSED: f64 = 1e9;
    let n = points.len();
    // The refused diagonals, one bit per corner (polygon edges are never refused).
    let mut refused_from = [0u32; M];
    for (i, row) in refused_from.iter_mut().enumerate().take(n) {
        for j in i + 2..n {
            if !(i == 0 && j == n - 1) && refused(i, j) {
                *row |= 1 << j;
            }
        }
    }
    let diagonal = |i: usize, j: usize| refused_from[i] >> j & 1 == 1;
    let weight = |i: usize, k: usize, j: usize| {
        let a = area(points[i], points[k], points[j]);
        let refuse = a < flat || diagonal(i, k) || diagonal(k, j) || diagonal(i, j);
        a + if refuse { REFUSED } else { 0.0 }
    };
    // cost[i][j]: best triangulation of the sub-polygon i..=j; split[i][j]: its apex.
    let mut cost = [[0f64; M]; M];
    let mut split = [[0u8; M]; M];
    for len in 2..n {
        for i in 0..n - len {
            let j = i + len;
            let (c, k) = (i + 1..j)
                .map(|k| (cost[i][k] + cost[k][j] + weight(i, k, j), k))
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap_or((f64::INFINITY, i + 1));
            cost[i][j] = c;
            split[i][j] = k as u8;
        }
    }
    let mut stack = [(0usize, 0usize); M];
    let mut top = 1;
    stack[0] = (0, n - 1);
    while top > 0 {
        top -= 1;
        let (i, j) = stack[top];
        if j < i + 2 {
            continue;
        }
        let k = split[i][j] as usize;
        out.push([i, k, j]);
        stack[top] = (i, k);
        stack[top + 1] = (k, j);
        top += 2;
    }
    cost[0][n - 1] < REFUSED
}

/// [`triangulate`] with the vertices at their edges' midpoints, the triangles as edges.
#[cfg(test)]
fn triangulate_loop(lp: &[u8]) -> Vec<u8> {
    let points: Vec<[f64; 3]> = lp.iter().map(|&e| drawn_midpoint(e)).collect();
    let mut tris = Vec::new();
    triangulate(&points, 1e-9, |_, _| false, &mut tris);
    tris.into_iter().flat_map(|t| t.map(|i| lp[i])).collect()
}

/// The case table: the loops of every case, as edge indices; the loops of case `c` are
/// `edges[offsets[c]..offsets[c + 1]]`, each loop ended by [`END`].
#[derive(Debug)]
pub struct Table {
    /// Where each case's loops start in `edges`; one more at the end.
    pub offsets: Vec<u32>,
    /// The loops' edges, each loop ended by [`END`].
    pub edges: Vec<u8>,
}

/// Ends a loop in [`Table::edges`].
pub const END: u8 = u8::MAX;

impl Table {
    /// The loops of `case`.
    pub fn loops(&self, case: u16) -> impl Iterator<Item = &[u8]> {
        let c = case as usize;
        let all = &self.edges[self.offsets[c] as usize..self.offsets[c + 1] as usize];
        all.split(|&e| e == END).filter(|lp| !lp.is_empty())
    }
}

/// The table, generated on first use.
pub fn table() -> &'static Table {
    static TABLE: OnceLock<Table> = OnceLock::new();
    TABLE.get_or_init(|| {
        let mut offsets = Vec::with_capacity((1 << SAMPLES) + 1);
        let mut edges = Vec::new();
        for case in 0..1u16 << SAMPLES {
            offsets.push(edges.len() as u32);
            for lp in loops(case) {
                edges.extend(lp);
                edges.push(END);
            }
        }
        offsets.push(edges.len() as u32);
        Table { offsets, edges }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn crossed(case: u16, e: u8) -> bool {
        let (a, b) = EDGES[e as usize];
        (case >> a & 1) != (case >> b & 1)
    }

    #[test]
    fn faces_are_closed_and_consistently_oriented() {
        // Every edge lies on exactly two faces, traversed once in each direction: the faces
        // bound a closed, outward-oriented polyhedron (V - E + F = 13 - 20 + 9 = 2).
        let faces = faces();
        assert_eq!(faces.len(), 9);
        assert!(faces[5..]
            .iter()
            .enumerate()
            .all(|(side, f)| f.iter().all(|&s| on_side(s, side))));
        let mut seen: HashMap<(u8, u8), i32> = HashMap::new();
        for f in faces {
            for i in 0..f.len() {
                let (a, b) = (f[i], f[(i + 1) % f.len()]);
                let _ = edge_between(a, b);
                *seen.entry((a, b)).or_default() += 1;
            }
        }
        for &(a, b) in &EDGES {
            assert_eq!(seen.get(&(a, b)), Some(&1), "{a}->{b}");
            assert_eq!(seen.get(&(b, a)), Some(&1), "{b}->{a}");
        }
        // The coarse square runs counter-clockwise seen from +n, as a regular cell's -n face
        // does seen from inside that cell: C(0,0), C(1,0), C(1,1), C(0,1).
        assert_eq!(
            faces[4],
            vec![coarse(0, 0), coarse(1, 0), coarse(1, 1), coarse(0, 1)]
        );
    }

    #[test]
    fn every_case_uses_exactly_its_crossed_edges_once_and_closes() {
        let t = table();
        for case in 0..1u16 << SAMPLES {
            let stored: Vec<&[u8]> = t.loops(case).collect();
            assert_eq!(
                stored,
                loops(case).iter().map(Vec::as_slice).collect::<Vec<_>>()
            );
            assert!(stored.iter().all(|lp| lp.len() >= 3), "case {case:#015b}");
            let tris: Vec<u8> = stored.iter().flat_map(|lp| triangulate_loop(lp)).collect();
            assert_eq!(tris.len() % 3, 0);
            let mut used: Vec<u8> = tris.clone();
            used.sort();
            used.dedup();
            let want: Vec<u8> = (0..EDGES.len() as u8)
                .filter(|&e| crossed(case, e))
                .collect();
            assert_eq!(used, want, "case {case:#015b}");
            // Interior edges of the triangulation are used once each way; the rest (one per
            // loop segment) once: the pieces are discs bounded by the loops.
            let mut directed: HashMap<(u8, u8), i32> = HashMap::new();
            for tri in tris.chunks(3) {
                assert!(tri[0] != tri[1] && tri[1] != tri[2] && tri[0] != tri[2]);
                for k in 0..3 {
                    *directed.entry((tri[k], tri[(k + 1) % 3])).or_default() += 1;
                }
            }
            let loops = loops(case);
            let boundary: usize = loops.iter().map(Vec::len).sum();
            let mut unmatched = 0;
            for (&(a, b), &n) in &directed {
                assert_eq!(n, 1, "case {case}: edge {a}->{b} twice");
                if !directed.contains_key(&(b, a)) {
                    unmatched += 1;
                }
            }
            assert_eq!(unmatched, boundary, "case {case}");
            // Euler: a disc per loop means triangles = vertices - 2 per loop.
            assert_eq!(tris.len() / 3, boundary - 2 * loops.len(), "case {case}");
        }
    }

    #[test]
    fn coarse_square_segments_match_the_regular_table() {
        // The coarse square is a face of a coarse cell. In that cell (corners i at
        // (i & 1, i >> 1 & 1, i >> 2 & 1)) take it as the face z = 0, which the cell sees from
        // above; the transition cell sees it from below. For every pattern of its four corners
        // both tables must draw the same segments on it, in opposite directions.
        let regular = super::super::table::table();
        let reg_edges = super::super::table::EDGES;
        // coarse C(i, j) <-> regular corner i + 2j on the face z = 0 (x = u, y = v).
        let to_regular = |e: u8| -> u8 {
            let (a, b) = EDGES[e as usize];
            let (ra, rb) = (a - 9, b - 9);
            reg_edges
                .iter()
                .position(|&(x, y)| (x, y) == (ra.min(rb), ra.max(rb)))
                .unwrap_or(99) as u8
        };
        for pattern in 0..16u16 {
            // Regular cell: the four corners of z = 0 as given, the four of z = 1 outside.
            let reg_case = pattern as usize;
            // Segments on the face z = 0: consecutive triangle-loop edges both on that face.
            let face_edges = [0u8, 1, 4, 5];
            let reg_loops = regular_loops(&regular[reg_case]);
            let mut reg_segments = Vec::new();
            for lp in &reg_loops {
                for k in 0..lp.len() {
                    let (a, b) = (lp[k], lp[(k + 1) % lp.len()]);
                    if face_edges.contains(&a) && face_edges.contains(&b) {
                        reg_segments.push((a, b));
                    }
                }
            }
            // Transition cell: the coarse corners as given, every fine sample inside, so the
            // contour on the coarse square is traced by the coarse corners alone.
            let case = (pattern << 9) | 0x1ff;
            let mut tr_segments = Vec::new();
            for lp in loops(case) {
                for k in 0..lp.len() {
                    let (a, b) = (lp[k], lp[(k + 1) % lp.len()]);
                    if edge_kind(a) == EdgeKind::Coarse && edge_kind(b) == EdgeKind::Coarse {
                        tr_segments.push((to_regular(b), to_regular(a)));
                    }
                }
            }
            reg_segments.sort();
            tr_segments.sort();
            assert_eq!(reg_segments, tr_segments, "pattern {pattern:#06b}");
        }
    }

    /// The loops of a regular-table entry, recovered from its fan triangles: the boundary
    /// edges of the triangulation, chained.
    fn regular_loops(tris: &[u8]) -> Vec<Vec<u8>> {
        let mut directed: HashMap<(u8, u8), i32> = HashMap::new();
        for t in tris.chunks(3) {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        let mut next: HashMap<u8, u8> = HashMap::new();
        for &(a, b) in directed.keys() {
            if !directed.contains_key(&(b, a)) {
                next.insert(a, b);
            }
        }
        let mut out = Vec::new();
        let mut keys: Vec<u8> = next.keys().copied().collect();
        keys.sort();
        let mut used = std::collections::HashSet::new();
        for s in keys {
            if used.contains(&s) {
                continue;
            }
            let mut lp = vec![s];
            used.insert(s);
            let mut e = next[&s];
            while e != s {
                lp.push(e);
                used.insert(e);
                e = next[&e];
            }
            out.push(lp);
        }
        out
    }

    #[test]
    fn one_inside_coarse_corner_is_a_small_cap() {
        // Only C(0,0) inside: its three edges (two coarse, one connecting) are crossed, one
        // triangle, wound with its normal pointing away from C(0,0) (towards +u +v -n).
        let case = 1u16 << coarse(0, 0);
        let lp = loops(case);
        assert_eq!(lp.len(), 1);
        let tris = triangulate_loop(&lp[0]);
        assert_eq!(tris.len(), 3);
        let [a, b, c] = [tris[0], tris[1], tris[2]].map(drawn_midpoint);
        let n = cross(
            [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
            [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
        );
        assert!(n[0] > 0.0 && n[1] > 0.0 && n[2] < 0.0, "{n:?}");
    }

    #[test]
    fn no_triangle_is_flat_at_midpoints() {
        for case in 0..1u16 << SAMPLES {
            for lp in table().loops(case) {
                for tri in triangulate_loop(lp).chunks(3) {
                    let [a, b, c] = [tri[0], tri[1], tri[2]].map(drawn_midpoint);
                    assert!(area(a, b, c) > 1e-9, "case {case:#015b}: {tri:?}");
                }
            }
        }
    }
}
