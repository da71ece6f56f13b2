//! Checks of assembled meshes, for tests and benchmarks: closed and 2-manifold, the volume it
//! encloses, and triangles that cross each other.

use super::mc::Mesh;
use std::collections::HashMap;

/// Checks a welded mesh is closed and 2-manifold: every edge in exactly two triangles, once in
/// each direction. Returns the number of offending edges.
pub fn open_edges(mesh: &Mesh) -> usize {
    let mut count: HashMap<(u32, u32), i32> = HashMap::new();
    for t in mesh.indices.chunks_exact(3) {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *count.entry((a, b)).or_default() += 1;
        }
    }
    count
        .iter()
        .filter(|(&(a, b), &n)| n != 1 || count.get(&(b, a)) != Some(&1))
        .count()
}

/// The volume a closed, outward-wound mesh encloses (divergence theorem).
pub fn enclosed_volume(mesh: &Mesh) -> f64 {
    mesh.indices
        .chunks_exact(3)
        .map(|t| {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| mesh.positions[i as usize].map(f64::from));
            crate::geometry::tetra_volume(a, b, c)
        })
        .sum()
}

/// Triangles of a mesh with (almost) no area: two equal corners, or an area below `min_area`.
pub fn degenerate_triangles(mesh: &Mesh, min_area: f64) -> usize {
    mesh.indices
        .chunks_exact(3)
        .filter(|t| {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| mesh.positions[i as usize].map(f64::from));
            let n = cross(sub(b, a), sub(c, a));
            t[0] == t[1] || t[1] == t[2] || t[0] == t[2] || dot(n, n).sqrt() / 2.0 < min_area
        })
        .count()
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
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

/// Whether segment `p q` passes through the interior of triangle `t` (not merely touching its
/// edges or corners, nor lying in its plane).
fn segment_pierces(p: [f64; 3], q: [f64; 3], t: [[f64; 3]; 3]) -> bool {
    const EPS: f64 = 1e-9;
    let n = cross(sub(t[1], t[0]), sub(t[2], t[0]));
    let (dp, dq) = (dot(sub(p, t[0]), n), dot(sub(q, t[0]), n));
    let scale = dot(n, n).sqrt();
    if dp.abs() <= EPS * scale || dq.abs() <= EPS * scale || (dp > 0.0) == (dq > 0.0) {
        return false;
    }
    let s = dp / (dp - dq);
    let x = [0, 1, 2].map(|i| p[i] + s * (q[i] - p[i]));
    // Strictly inside: on the inner side of every edge by a margin.
    (0..3).all(|i| {
        let e = sub(t[(i + 1) % 3], t[i]);
        dot(cross(e, sub(x, t[i])), n) > EPS * scale * dot(e, e).sqrt()
    })
}

/// Pairs of triangles of a welded mesh, at least one of them with its flag set in `chosen`
/// (one flag per triangle), that cross each other: an edge of one through the interior of the
/// other (an edge sharing a corner with the other triangle is not tested), or two triangles
/// sharing an edge folded flat onto each other.
///
/// # Panics
/// `chosen` does not have one flag per triangle.
pub fn crossing_triangles(mesh: &Mesh, chosen: &[bool]) -> usize {
    let n = mesh.triangles();
    assert_eq!(chosen.len(), n, "one flag per triangle");
    let tri = |t: usize| {
        let i = &mesh.indices[3 * t..3 * t + 3];
        let p = [0, 1, 2].map(|k| mesh.positions[i[k] as usize].map(f64::from));
        ([i[0], i[1], i[2]], p)
    };
    let boxes: Vec<([f64; 3], [f64; 3])> = (0..n)
        .map(|t| {
            let (_, p) = tri(t);
            let lo = [0, 1, 2].map(|a| p.iter().map(|v| v[a]).fold(f64::INFINITY, f64::min));
            let hi = [0, 1, 2].map(|a| p.iter().map(|v| v[a]).fold(f64::NEG_INFINITY, f64::max));
            (lo, hi)
        })
        .collect();
    // Triangles by the cells of a grid about two triangles wide that their boxes overlap.
    let size = boxes
        .iter()
        .map(|(lo, hi)| (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max))
        .sum::<f64>()
        / n.max(1) as f64
        * 2.0;
    let size = if size > 0.0 { size } else { 1.0 };
    let cell = |x: f64| (x / size).floor() as i64;
    let cells = |(lo, hi): ([f64; 3], [f64; 3])| {
        let (l, h) = (lo.map(cell), hi.map(cell));
        (l[2]..=h[2]).flat_map(move |z| {
            (l[1]..=h[1]).flat_map(move |y| (l[0]..=h[0]).map(move |x| [x, y, z]))
        })
    };
    // Only triangles overlapping the box of the chosen ones can cross one of them: the others
    // stay out of the grid (in a test's small mesh, most of the triangles).
    let (mut lo_chosen, mut hi_chosen) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for (lo, hi) in (0..n).filter(|&t| chosen[t]).map(|t| boxes[t]) {
        for a in 0..3 {
            lo_chosen[a] = lo_chosen[a].min(lo[a]);
            hi_chosen[a] = hi_chosen[a].max(hi[a]);
        }
    }
    let mut grid: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    for (t, &b) in boxes.iter().enumerate() {
        let (lo, hi) = b;
        if (0..3).any(|a| hi[a] < lo_chosen[a] || hi_chosen[a] < lo[a]) {
            continue;
        }
        for c in cells(b) {
            grid.entry(c).or_default().push(t);
        }
    }
    let mut count = 0;
    let mut near = Vec::new();
    // The last triangle `a` whose list took each triangle: each near triangle is taken once
    // however many cells it shares with `a`.
    let mut taken_for = vec![usize::MAX; n];
    for a in (0..n).filter(|&t| chosen[t]) {
        let (la, ha) = boxes[a];
        near.clear();
        for c in cells(boxes[a]) {
            for &b in grid.get(&c).into_iter().flatten() {
                if taken_for[b] != a {
                    taken_for[b] = a;
                    near.push(b);
                }
            }
        }
        for &b in &near {
            if a == b || (chosen[b] && b < a) {
                continue;
            }
            let (lb, hb) = boxes[b];
            if (0..3).any(|k| ha[k] < lb[k] || hb[k] < la[k]) {
                continue;
            }
            let ((ia, pa), (ib, pb)) = (tri(a), tri(b));
            // Which corners of each triangle the other has too (bit k: corner k).
            let in_other = |ids: [u32; 3], other: [u32; 3]| {
                (0..3).fold(0u8, |m, k| m | u8::from(other.contains(&ids[k])) << k)
            };
            let (shared_a, shared_b) = (in_other(ia, ib), in_other(ib, ia));
            let shared = shared_a.count_ones();
            let mut hit = false;
            for (pts, other, shared_corners) in [(pa, pb, shared_a), (pb, pa, shared_b)] {
                for k in 0..3 {
                    // An edge with a shared corner meets the other triangle there.
                    if shared_corners >> k & 1 == 1 || shared_corners >> ((k + 1) % 3) & 1 == 1 {
                        continue;
                    }
                    hit |= segment_pierces(pts[k], pts[(k + 1) % 3], other);
                }
            }
            if shared == 2 {
                // Folded: the third corners on the same side of the shared edge, in one plane.
                let na = cross(sub(pa[1], pa[0]), sub(pa[2], pa[0]));
                let nb = cross(sub(pb[1], pb[0]), sub(pb[2], pb[0]));
                let cos = dot(na, nb) / (dot(na, na) * dot(nb, nb)).sqrt();
                hit |= cos < -1.0 + 1e-12;
            }
            count += usize::from(hit);
        }
    }
    count
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh(positions: Vec<[f32; 3]>, indices: Vec<u32>) -> Mesh {
        Mesh {
            normals: vec![[0.0, 0.0, 1.0]; positions.len()],
            positions,
            indices,
            materials: vec![],
        }
    }

    #[test]
    fn a_tetrahedron_is_closed_and_encloses_a_sixth() {
        let m = mesh(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            vec![0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3],
        );
        assert_eq!(open_edges(&m), 0);
        assert!((enclosed_volume(&m) - 1.0 / 6.0).abs() < 1e-12);
        assert_eq!(crossing_triangles(&m, &[true; 4]), 0);
        // One face dropped: its three edges are open.
        let open = mesh(m.positions.clone(), m.indices[..9].to_vec());
        assert_eq!(open_edges(&open), 3);
    }

    #[test]
    fn crossing_and_folded_triangles_are_found() {
        // A triangle in z = 0 and one standing through its middle.
        let m = mesh(
            vec![
                [0.0, 0.0, 0.0],
                [4.0, 0.0, 0.0],
                [0.0, 4.0, 0.0],
                [1.0, 1.0, -1.0],
                [1.0, 1.0, 1.0],
                [3.0, 3.0, 1.0],
            ],
            vec![0, 1, 2, 3, 4, 5],
        );
        assert_eq!(crossing_triangles(&m, &[true, false]), 1);
        assert_eq!(crossing_triangles(&m, &[false, false]), 0);
        // Two triangles on one edge, folded onto each other in one plane.
        let folded = mesh(
            vec![
                [0.0, 0.0, 0.0],
                [2.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [1.0, 2.0, 0.0],
            ],
            vec![0, 1, 2, 1, 0, 3],
        );
        assert_eq!(crossing_triangles(&folded, &[true, true]), 1);
        // Unfolded: the second on the other side of the shared edge.
        let flat = mesh(
            vec![
                [0.0, 0.0, 0.0],
                [2.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [1.0, -1.0, 0.0],
            ],
            vec![0, 1, 2, 1, 0, 3],
        );
        assert_eq!(crossing_triangles(&flat, &[true, true]), 0);
    }
}
