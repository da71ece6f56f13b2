//! The marching-cubes case table, generated from first principles instead of copied.
//!
//! For each of the 256 inside/outside patterns of a cell's corners, the iso-contour is traced
//! face by face: on each face, every maximal run of inside corners (going counter-clockwise as
//! seen from outside the cell) gives one segment, from the crossed edge entering the run to the
//! crossed edge leaving it. On an ambiguous face (inside corners on one diagonal) this separates
//! the two inside corners. The rule depends only on a face's four corners, so two cells sharing a
//! face draw the same segments on it, in opposite directions: the surface has no holes between
//! cells and is consistently oriented. The segments chain into closed loops (each crossed edge
//! starts one segment and ends another), and each loop is fanned into triangles wound so that
//! their normal points from inside to outside.
//!
//! Corner `i` sits at `(i & 1, i >> 1 & 1, i >> 2 & 1)`. Edge `e` joins the corners of
//! [`EDGES`]`[e]`, lower corner first; it runs along axis [`EDGE_AXIS`]`[e]`.

use std::sync::OnceLock;

/// The 12 edges as (lower corner, upper corner).
pub const EDGES: [(u8, u8); 12] = [
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7), // along x
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7), // along y
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7), // along z
];

/// The axis each edge runs along.
pub const EDGE_AXIS: [u8; 12] = [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2];

fn corner_pos(c: u8) -> [i32; 3] {
    [(c & 1) as i32, (c >> 1 & 1) as i32, (c >> 2 & 1) as i32]
}

fn edge_between(a: u8, b: u8) -> u8 {
    let (lo, hi) = (a.min(b), a.max(b));
    EDGES
        .iter()
        .position(|&e| e == (lo, hi))
        .expect("corners of a face are joined by an edge") as u8
}

/// The six faces, each as its four corners counter-clockwise seen from outside the cell.
fn faces() -> Vec<[u8; 4]> {
    let mut out = Vec::new();
    for axis in 0..3 {
        for side in 0..2 {
            let corners: Vec<u8> = (0..8u8).filter(|&c| corner_pos(c)[axis] == side).collect();
            // Sort by angle around the face centre in a right-handed frame (u, v, normal).
            let (ua, va) = ((axis + 1) % 3, (axis + 2) % 3);
            let angle = |c: u8| {
                let p = corner_pos(c);
                let (u, v) = (p[ua] as f64 - 0.5, p[va] as f64 - 0.5);
                // (ua, va, axis) is a cyclic permutation of (x, y, z), so u x v = +axis; for the
                // face whose outward normal is -axis, counter-clockwise means clockwise in (u, v).
                let a = v.atan2(u);
                if side == 1 {
                    a
                } else {
                    -a
                }
            };
            let mut sorted = corners;
            sorted.sort_by(|&a, &b| angle(a).total_cmp(&angle(b)));
            out.push([sorted[0], sorted[1], sorted[2], sorted[3]]);
        }
    }
    out
}

/// Triangles of each case, as edge indices, three per triangle.
pub fn table() -> &'static [Vec<u8>; 256] {
    static TABLE: OnceLock<[Vec<u8>; 256]> = OnceLock::new();
    TABLE.get_or_init(|| {
        let faces = faces();
        std::array::from_fn(|case| triangles(case as u8, &faces))
    })
}

fn triangles(case: u8, faces: &[[u8; 4]]) -> Vec<u8> {
    let inside = |c: u8| case >> c & 1 == 1;
    // next[e] = the edge the contour goes to after edge e.
    let mut next = [u8::MAX; 12];
    for f in faces {
        run_segments(f, inside, edge_between, &mut next);
    }
    // The faces each edge lies on, as bits in the order of `faces`.
    let on: [u8; 12] = std::array::from_fn(|e| {
        let (a, b) = EDGES[e];
        faces
            .iter()
            .enumerate()
            .filter(|(_, f)| f.contains(&a) && f.contains(&b))
            .fold(0, |m, (i, _)| m | 1 << i)
    });
    let mut out = Vec::new();
    for lp in chain(&next) {
        // Fan, in loop order: the loop runs counter-clockwise seen from outside the surface, so
        // the triangles' normals point outwards (checked by `single_corner_faces_out`). From
        // the first vertex whose fan has no triangle lying in a face of the cell: a loop that
        // crosses an ambiguous face twice has four vertices there, and a triangle on three of
        // them would lie where the cell across that face may draw one too.
        let n = lp.len();
        let flat = |i: usize, k: usize| {
            let t = [lp[i], lp[(i + k) % n], lp[(i + k + 1) % n]];
            on[t[0] as usize] & on[t[1] as usize] & on[t[2] as usize] != 0
        };
        let apex = (0..n)
            .find(|&i| (1..n - 1).all(|k| !flat(i, k)))
            .unwrap_or(0);
        for k in 1..n - 1 {
            out.extend_from_slice(&[lp[apex], lp[(apex + k) % n], lp[(apex + k + 1) % n]]);
        }
    }
    out
}

/// The face rule, shared with the transition table: on a face given by its corners
/// counter-clockwise seen from outside the cell, each maximal run of inside corners gives one
/// segment, from the edge entering the run to the edge leaving it, written `next[enter] =
/// leave`. `edge(a, b)` names the edge joining consecutive corners a and b.
pub fn run_segments<const N: usize>(
    face: &[u8],
    inside: impl Fn(u8) -> bool,
    edge: impl Fn(u8, u8) -> u8,
    next: &mut [u8; N],
) {
    let k = face.len();
    for i in 0..k {
        // A run starts at corner face[i] when it is inside and its predecessor is not.
        let prev = face[(i + k - 1) % k];
        if !inside(face[i]) || inside(prev) {
            continue;
        }
        let mut j = i;
        while inside(face[(j + 1) % k]) {
            j = (j + 1) % k;
        }
        next[edge(prev, face[i]) as usize] = edge(face[j], face[(j + 1) % k]);
    }
}

/// The loops of a segment map (`next[e]`: the edge after `e`, `u8::MAX` where `e` is not
/// crossed), each starting at its smallest edge.
pub fn chain<const N: usize>(next: &[u8; N]) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut used = [false; N];
    for start in 0..N as u8 {
        if next[start as usize] == u8::MAX || used[start as usize] {
            continue;
        }
        let mut lp = vec![start];
        used[start as usize] = true;
        let mut e = next[start as usize];
        while e != start {
            lp.push(e);
            used[e as usize] = true;
            e = next[e as usize];
        }
        out.push(lp);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edge_mid(e: u8) -> [f64; 3] {
        let (a, b) = EDGES[e as usize];
        let (pa, pb) = (corner_pos(a), corner_pos(b));
        [0, 1, 2].map(|i| (pa[i] + pb[i]) as f64 / 2.0)
    }

    fn normal(t: &[u8]) -> [f64; 3] {
        let (a, b, c) = (edge_mid(t[0]), edge_mid(t[1]), edge_mid(t[2]));
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ]
    }

    #[test]
    fn trivial_cases_are_empty() {
        assert!(table()[0].is_empty());
        assert!(table()[255].is_empty());
    }

    #[test]
    fn single_corner_faces_out() {
        // Only corner 0 (the origin) inside: one triangle across edges 0, 4, 8, its normal
        // pointing away from the origin, towards +x+y+z.
        let t = &table()[1];
        assert_eq!(t.len(), 3);
        let mut edges = t.clone();
        edges.sort();
        assert_eq!(edges, vec![0, 4, 8]);
        let n = normal(t);
        assert!(n[0] > 0.0 && n[1] > 0.0 && n[2] > 0.0, "{n:?}");
        // Only corner 7 inside: the normal points towards -x-y-z.
        let n = normal(&table()[128]);
        assert!(n[0] < 0.0 && n[1] < 0.0 && n[2] < 0.0, "{n:?}");
    }

    #[test]
    fn every_case_uses_exactly_its_crossed_edges_and_closes_within_the_cell() {
        for case in 0..=255u8 {
            let t = &table()[case as usize];
            assert_eq!(t.len() % 3, 0);
            let crossed: Vec<u8> = (0..12u8)
                .filter(|&e| {
                    let (a, b) = EDGES[e as usize];
                    (case >> a & 1) != (case >> b & 1)
                })
                .collect();
            let mut used: Vec<u8> = t.clone();
            used.sort();
            used.dedup();
            assert_eq!(used, crossed, "case {case:#010b}");
            // Inside each cell the triangles of a loop share their fan edges in pairs; the
            // boundary of the case's surface lies on the cell faces: every segment between two
            // crossed edges on the same face appears exactly once (counting both directions).
            let mut boundary: std::collections::HashMap<(u8, u8), i32> =
                std::collections::HashMap::new();
            for tri in t.chunks(3) {
                for k in 0..3 {
                    let (a, b) = (tri[k], tri[(k + 1) % 3]);
                    *boundary.entry((a.min(b), a.max(b))).or_default() +=
                        if a < b { 1 } else { -1 };
                }
            }
            // Interior fan edges cancel (+1 and -1): the winding is consistent within the cell.
            for ((a, b), n) in boundary {
                assert!(
                    n.abs() <= 1,
                    "case {case:#010b}: edge {a}-{b} used {n} times one way"
                );
            }
        }
    }

    #[test]
    fn no_triangle_lies_in_a_face_of_the_cell() {
        // Three crossed edges of one face: each face's edges by hand (x, y, z faces).
        let face_edges: [[u8; 4]; 6] = [
            [4, 6, 8, 10],
            [5, 7, 9, 11],
            [0, 2, 8, 9],
            [1, 3, 10, 11],
            [0, 1, 4, 5],
            [2, 3, 6, 7],
        ];
        for case in 0..=255u8 {
            for t in table()[case as usize].chunks(3) {
                for f in &face_edges {
                    assert!(
                        !t.iter().all(|e| f.contains(e)),
                        "case {case:#010b}: triangle {t:?} lies in a face"
                    );
                }
            }
        }
    }

    #[test]
    fn complement_cases_mirror() {
        // Inverting inside and outside gives the same number of triangles in cases without an
        // ambiguous face (the disambiguation rule is not symmetric: case 9, corners 0 and 3 on
        // one face's diagonal, is two triangles, its complement a four-triangle tunnel).
        assert_eq!(table()[9].len(), 6);
        assert_eq!(table()[!9u8 as usize].len(), 12);
        for case in [1u8, 3, 5, 17, 24, 7, 15] {
            assert_eq!(
                table()[case as usize].len(),
                table()[!case as usize].len(),
                "case {case}"
            );
        }
    }
}
