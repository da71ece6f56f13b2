//! Solid voxelization by parity (Eisemann and Decoret 2008, on the CPU).
//!
//! Every column of voxels along z is a bit vector (u64 words). For each triangle and each column
//! centre `(x + 0.5, y + 0.5)` its projection covers, the bits of the voxels whose centres lie
//! below the triangle are toggled (XOR). What remains set is the inside: a centre is inside when
//! a ray from it towards +z crosses the surface an odd number of times (the Jordan theorem, and
//! the paper's definition of watertight).
//!
//! Sampling is exact, so no column is missed or counted twice where triangles meet:
//! - x and y are fixed point (16 fractional bits) and the coverage test uses integer edge
//!   functions. A centre on an edge shared by two triangles counts for exactly one of them:
//!   triangles are first turned counter-clockwise in projection, and an edge includes its points
//!   only if its direction `d` has `d.y > 0`, or `d.y == 0` and `d.x < 0`. Two triangles on
//!   either side of a shared edge see it in opposite directions, so one includes it; two on the
//!   same side (a silhouette fold, where the ray touches but does not cross) see it in the same
//!   direction, so both or neither do - parity unchanged either way.
//! - In z a triangle toggles the voxels whose centre is strictly below it: a centre exactly on
//!   a face counts as inside a solid whose face is above it, and outside one whose face is below
//!   (the half-open rule `[bottom, top)`).
//! - Triangles seen edge-on (zero projected area) toggle nothing: the ray runs along them and
//!   their neighbours decide.
//!
//! Work is split by rows of columns (one `y` each, in parallel on rayon); each triangle is
//! binned into the rows its projection covers.

use rayon::prelude::*;

/// Fixed-point fraction bits of x and y.
const FRAC: u32 = 16;
const ONE: i64 = 1 << FRAC;
const HALF: i64 = ONE / 2;

/// A triangle mesh: vertex positions and triangles as vertex indices.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Triangles, three vertex indices each.
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    /// The axis-aligned bounds of the vertices that triangles use, or `None` without triangles.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for t in &self.triangles {
            for &v in t {
                let p = self.positions[v as usize];
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
            }
        }
        (!self.triangles.is_empty()).then_some((lo, hi))
    }
}

/// A grid of bits, one column of `words` u64 per (x, y), z along the bits.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BitGrid {
    /// Size in cells.
    pub dims: [usize; 3],
    words: usize,
    bits: Vec<u64>,
}

impl BitGrid {
    /// All cells off.
    pub fn new(dims: [usize; 3]) -> BitGrid {
        let words = dims[2].div_ceil(64);
        BitGrid {
            dims,
            words,
            bits: vec![0; dims[0] * dims[1] * words],
        }
    }

    /// Bytes the bits take (the voxelizer's memory: one bit per voxel, columns padded to 64).
    pub fn bytes(&self) -> usize {
        self.bits.len() * 8
    }

    /// The words of column (x, y): bit `z % 64` of word `z / 64` is voxel z.
    pub fn column_words(&self, x: usize, y: usize) -> &[u64] {
        self.column(x, y)
    }

    fn column(&self, x: usize, y: usize) -> &[u64] {
        let at = (y * self.dims[0] + x) * self.words;
        &self.bits[at..at + self.words]
    }

    /// Whether cell (x, y, z) is on.
    pub fn get(&self, x: usize, y: usize, z: usize) -> bool {
        self.column(x, y)[z / 64] >> (z % 64) & 1 == 1
    }

    /// Sets cell (x, y, z).
    pub fn set(&mut self, x: usize, y: usize, z: usize, on: bool) {
        let at = (y * self.dims[0] + x) * self.words + z / 64;
        let bit = 1u64 << (z % 64);
        if on {
            self.bits[at] |= bit;
        } else {
            self.bits[at] &= !bit;
        }
    }

    /// Number of set bits.
    pub fn count(&self) -> u64 {
        self.bits.iter().map(|w| w.count_ones() as u64).sum()
    }

    /// `len` (at most 64) bits of column (x, y) starting at z, as the low bits of a word.
    pub fn bits_at(&self, x: usize, y: usize, z: usize, len: usize) -> u64 {
        let col = self.column(x, y);
        let (w, off) = (z / 64, z % 64);
        let mut v = col[w] >> off;
        if off + len > 64 && w + 1 < col.len() {
            v |= col[w + 1] << (64 - off);
        }
        if len < 64 {
            v &= (1u64 << len) - 1;
        }
        v
    }

    /// Sets every bit that is set in `other` (same dims).
    pub fn or_with(&mut self, other: &BitGrid) {
        for (a, b) in self.bits.iter_mut().zip(&other.bits) {
            *a |= b;
        }
    }

    /// Clears every bit that is set in `other` (same dims).
    pub fn and_not(&mut self, other: &BitGrid) {
        for (a, b) in self.bits.iter_mut().zip(&other.bits) {
            *a &= !b;
        }
    }

    /// Rows of columns (one y each), for parallel writes.
    fn rows_mut(&mut self) -> impl IndexedParallelIterator<Item = (usize, &mut [u64])> {
        let row = self.dims[0] * self.words;
        self.bits.par_chunks_mut(row.max(1)).enumerate()
    }
}

/// A triangle in grid coordinates: x, y fixed point, z in voxels.
#[derive(Debug, Clone, Copy)]
struct Projected {
    x: [i64; 3],
    y: [i64; 3],
    z: [f64; 3],
    /// Twice the signed projected area, > 0 (counter-clockwise).
    area2: i128,
}

/// Twice the signed area of (a, b, p), exact: in i128, so triangles spanning any number of
/// voxels cannot overflow (i64 products overflow past about 46,000 voxels).
fn edge(ax: i64, ay: i64, bx: i64, by: i64, px: i64, py: i64) -> i128 {
    (bx - ax) as i128 * (py - ay) as i128 - (by - ay) as i128 * (px - ax) as i128
}

/// Whether an edge with direction (dx, dy) owns the points on it (see the module docs).
fn owns(dx: i64, dy: i64) -> bool {
    dy > 0 || (dy == 0 && dx < 0)
}

fn project(p: [[f64; 3]; 3]) -> Option<Projected> {
    let fx = |v: f64| (v * ONE as f64).round() as i64;
    let mut t = Projected {
        x: [fx(p[0][0]), fx(p[1][0]), fx(p[2][0])],
        y: [fx(p[0][1]), fx(p[1][1]), fx(p[2][1])],
        z: [p[0][2], p[1][2], p[2][2]],
        area2: 0,
    };
    let area2 = edge(t.x[0], t.y[0], t.x[1], t.y[1], t.x[2], t.y[2]);
    if area2 == 0 {
        return None;
    }
    if area2 < 0 {
        t.x.swap(1, 2);
        t.y.swap(1, 2);
        t.z.swap(1, 2);
    }
    t.area2 = area2.abs();
    Some(t)
}

/// Index range `lo..=hi` of sample centres `i * ONE + HALF` within `[min, max]`, clamped to
/// `0..n`; `None` when empty.
fn sample_range(min: i64, max: i64, n: usize) -> Option<(usize, usize)> {
    let lo = (min - HALF).div_euclid(ONE) + i64::from((min - HALF).rem_euclid(ONE) != 0);
    let hi = (max - HALF).div_euclid(ONE);
    let lo = lo.max(0);
    let hi = hi.min(n as i64 - 1);
    (lo <= hi).then_some((lo as usize, hi as usize))
}

/// Voxelizes the solid a closed mesh bounds into a grid of `dims` voxels. `to_grid` maps a
/// vertex to grid coordinates (voxel `i` spans `[i, i + 1)` on each axis, centre `i + 0.5`).
pub fn voxelize_solid(
    mesh: &TriMesh,
    dims: [usize; 3],
    to_grid: impl Fn([f32; 3]) -> [f64; 3] + Sync,
) -> BitGrid {
    let mut grid = BitGrid::new(dims);
    let projected: Vec<Projected> = mesh
        .triangles
        .par_iter()
        .filter_map(|t| project(t.map(|v| to_grid(mesh.positions[v as usize]))))
        .collect();
    // Bin triangles into the rows of columns they cover.
    let mut rows: Vec<Vec<u32>> = vec![Vec::new(); dims[1]];
    for (i, t) in projected.iter().enumerate() {
        let (ymin, ymax) = (t.y.iter().min(), t.y.iter().max());
        if let (Some(&ymin), Some(&ymax)) = (ymin, ymax) {
            if let Some((lo, hi)) = sample_range(ymin, ymax, dims[1]) {
                for row in &mut rows[lo..=hi] {
                    row.push(i as u32);
                }
            }
        }
    }
    let (nx, nz, words) = (dims[0], dims[2], grid.words);
    grid.rows_mut().for_each(|(y, row)| {
        let py = y as i64 * ONE + HALF;
        for &i in &rows[y] {
            let t = &projected[i as usize];
            let xmin = t.x.iter().copied().min().unwrap_or(0);
            let xmax = t.x.iter().copied().max().unwrap_or(0);
            let Some((x0, x1)) = sample_range(xmin, xmax, nx) else {
                continue;
            };
            for x in x0..=x1 {
                let px = x as i64 * ONE + HALF;
                let mut w = [0i128; 3];
                let mut inside = true;
                for (e, we) in w.iter_mut().enumerate() {
                    let (a, b) = ((e + 1) % 3, (e + 2) % 3);
                    *we = edge(t.x[a], t.y[a], t.x[b], t.y[b], px, py);
                    if *we < 0 || (*we == 0 && !owns(t.x[b] - t.x[a], t.y[b] - t.y[a])) {
                        inside = false;
                        break;
                    }
                }
                if !inside {
                    continue;
                }
                let z = (w[0] as f64 * t.z[0] + w[1] as f64 * t.z[1] + w[2] as f64 * t.z[2])
                    / t.area2 as f64;
                // Centres k + 0.5 strictly below z: k < z - 0.5.
                let below = ((z - 0.5).ceil().max(0.0) as usize).min(nz);
                let col = &mut row[x * words..(x + 1) * words];
                for word in col.iter_mut().take(below / 64) {
                    *word = !*word;
                }
                if below % 64 != 0 {
                    col[below / 64] ^= (1u64 << (below % 64)) - 1;
                }
            }
        }
    });
    grid
}

/// The voxels whose closed box a triangle touches (the surface's conservative boundary).
pub fn voxelize_surface(
    mesh: &TriMesh,
    dims: [usize; 3],
    to_grid: impl Fn([f32; 3]) -> [f64; 3] + Sync,
) -> BitGrid {
    let mut grid = BitGrid::new(dims);
    let tris: Vec<[[f64; 3]; 3]> = mesh
        .triangles
        .iter()
        .map(|t| t.map(|v| to_grid(mesh.positions[v as usize])))
        .collect();
    let mut rows: Vec<Vec<u32>> = vec![Vec::new(); dims[1]];
    for (i, t) in tris.iter().enumerate() {
        let lo = t.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min);
        let hi = t.iter().map(|p| p[1]).fold(f64::NEG_INFINITY, f64::max);
        let (a, b) = (
            (lo.floor() as i64 - 1).max(0),
            (hi.floor() as i64 + 1).min(dims[1] as i64 - 1),
        );
        for y in a..=b {
            rows[y as usize].push(i as u32);
        }
    }
    let (nx, nz, words) = (dims[0], dims[2], grid.words);
    grid.rows_mut().for_each(|(y, row)| {
        for &i in &rows[y] {
            let t = &tris[i as usize];
            let range = |a: usize, n: usize| {
                let lo = t.iter().map(|p| p[a]).fold(f64::INFINITY, f64::min);
                let hi = t.iter().map(|p| p[a]).fold(f64::NEG_INFINITY, f64::max);
                (
                    (lo.floor() as i64 - 1).max(0),
                    (hi.floor() as i64 + 1).min(n as i64 - 1),
                )
            };
            let (x0, x1) = range(0, nx);
            let (z0, z1) = range(2, nz);
            for x in x0..=x1 {
                for z in z0..=z1 {
                    let min = [x as f64, y as f64, z as f64];
                    if triangle_meets_box(t, min) {
                        let (x, z) = (x as usize, z as usize);
                        row[x * words + z / 64] |= 1u64 << (z % 64);
                    }
                }
            }
        }
    });
    grid
}

/// Whether a triangle meets the closed unit box at `min` (separating axis test: the box's
/// three axes, the triangle's normal, and the nine edge x axis products).
fn triangle_meets_box(t: &[[f64; 3]; 3], min: [f64; 3]) -> bool {
    let c = [min[0] + 0.5, min[1] + 0.5, min[2] + 0.5];
    let v: [[f64; 3]; 3] = t.map(|p| [p[0] - c[0], p[1] - c[1], p[2] - c[2]]);
    let h = 0.5;
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let separated = |axis: [f64; 3]| {
        let r = h * (axis[0].abs() + axis[1].abs() + axis[2].abs());
        let p = v.map(|p| dot(p, axis));
        let (lo, hi) = (p[0].min(p[1]).min(p[2]), p[0].max(p[1]).max(p[2]));
        lo > r || hi < -r
    };
    for a in 0..3 {
        let mut axis = [0.0; 3];
        axis[a] = 1.0;
        if separated(axis) {
            return false;
        }
    }
    let e = [sub(v[1], v[0]), sub(v[2], v[1]), sub(v[0], v[2])];
    if separated(cross(e[0], e[1])) {
        return false;
    }
    for edge in e {
        for a in 0..3 {
            let mut unit = [0.0; 3];
            unit[a] = 1.0;
            let axis = cross(edge, unit);
            if axis != [0.0; 3] && separated(axis) {
                return false;
            }
        }
    }
    true
}

/// Edges used by an odd number of triangles (vertices welded by position): the mesh does not
/// bound a solid in the parity sense there (a hole, or an inner wall meeting the hull).
/// Returns their number and the total number of distinct edges.
pub fn odd_edges(mesh: &TriMesh) -> (usize, usize) {
    use std::collections::HashMap;
    let mut ids: HashMap<[u32; 3], u32> = HashMap::new();
    let weld: Vec<u32> = mesh
        .positions
        .iter()
        .map(|p| {
            let key = p.map(|c| if c == 0.0 { 0 } else { c.to_bits() });
            let next = ids.len() as u32;
            *ids.entry(key).or_insert(next)
        })
        .collect();
    let mut count: HashMap<(u32, u32), u32> = HashMap::new();
    for t in &mesh.triangles {
        let v = t.map(|i| weld[i as usize]);
        if v[0] == v[1] || v[1] == v[2] || v[0] == v[2] {
            continue;
        }
        for (a, b) in [(v[0], v[1]), (v[1], v[2]), (v[2], v[0])] {
            *count.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    (count.values().filter(|&&n| n % 2 == 1).count(), count.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_ranges_include_centres_on_the_bounds() {
        // Centres at 0.5, 1.5, 2.5, ...
        assert_eq!(sample_range(HALF, HALF, 10), Some((0, 0)));
        assert_eq!(sample_range(0, ONE, 10), Some((0, 0)));
        assert_eq!(sample_range(HALF + 1, ONE + HALF - 1, 10), None);
        assert_eq!(sample_range(-5 * ONE, 50 * ONE, 10), Some((0, 9)));
    }

    #[test]
    fn exactly_one_of_two_opposite_edges_owns_its_points() {
        for (dx, dy) in [(1, 0), (0, 1), (3, -2), (-1, 5), (0, -1), (-4, 0)] {
            assert!(owns(dx, dy) != owns(-dx, -dy), "({dx}, {dy})");
        }
    }

    #[test]
    fn box_overlap_agrees_with_simple_cases() {
        let t = [[0.5, 0.5, 0.5], [0.6, 0.5, 0.5], [0.5, 0.6, 0.5]];
        assert!(triangle_meets_box(&t, [0.0, 0.0, 0.0]));
        assert!(!triangle_meets_box(&t, [2.0, 0.0, 0.0]));
        // A big triangle in the plane z = 0.5 cuts every box of that layer it spans.
        let big = [[-10.0, -10.0, 0.5], [30.0, -10.0, 0.5], [-10.0, 30.0, 0.5]];
        assert!(triangle_meets_box(&big, [3.0, 4.0, 0.0]));
        assert!(!triangle_meets_box(&big, [3.0, 4.0, 1.0 + 1e-9]));
        // Touching counts (closed boxes).
        assert!(triangle_meets_box(&big, [3.0, 4.0, 0.5]));
    }
}
