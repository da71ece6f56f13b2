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
//! Work is split by bands of 16 rows of columns (`y`), swept in parallel on rayon. Vertices are
//! put in grid coordinates once, then the triangles are binned by band in parallel: the mesh is
//! cut into chunks, and each chunk counts, then lists, its triangles per band (a counting sort),
//! so a band's list is its slice of every chunk's list. A triangle is listed once per band its
//! bounding box reaches, never once per row, and bands are binned and swept in runs whose lists
//! hold about twice the triangles at most, so a model of huge triangles, each in every band,
//! costs no more memory than a model of small ones. In its band a triangle visits only its own
//! rows and columns, stepping its edge functions from sample to sample (exact integer sums) and
//! leaving a row at the first sample past it.

use crate::cancel::{CancelToken, Stopped};
use rayon::prelude::*;

/// Fixed-point fraction bits of x and y.
const FRAC: u32 = 16;
pub(super) const ONE: i64 = 1 << FRAC;
pub(super) const HALF: i64 = ONE / 2;

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
    /// Words per column.
    pub(super) words: usize,
    /// Columns of `words` words, x fastest, then y.
    pub(super) bits: Vec<u64>,
}

impl BitGrid {
    /// All cells off.
    pub fn new(dims: [usize; 3]) -> BitGrid {
        let words = dims[2].div_ceil(64);
        BitGrid {
            dims,
            words,
            bits: zeroed(dims[0] * dims[1] * words),
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
        self.bits.par_iter().map(|w| w.count_ones() as u64).sum()
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

/// `n` zeros, written in parallel: the first write to each page of a large vector is where the
/// kernel maps and clears it, and for a grid of a gigabyte that costs more than the voxelizing.
pub(crate) fn zeroed<T: Copy + Default + Send + Sync>(n: usize) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    v.par_extend(rayon::iter::repeat_n(T::default(), n));
    v
}

/// A vertex in grid coordinates: x, y fixed point, z in voxels.
#[derive(Debug, Clone, Copy)]
pub(super) struct GridVertex {
    x: i64,
    y: i64,
    z: f64,
}

impl GridVertex {
    pub(super) fn new(p: [f64; 3]) -> GridVertex {
        let fx = |v: f64| (v * ONE as f64).round() as i64;
        GridVertex {
            x: fx(p[0]),
            y: fx(p[1]),
            z: p[2],
        }
    }
}

/// A triangle in grid coordinates: x, y fixed point, z in voxels.
#[derive(Debug, Clone, Copy)]
pub(super) struct Projected {
    pub(super) x: [i64; 3],
    pub(super) y: [i64; 3],
    pub(super) z: [f64; 3],
    /// Twice the signed projected area, > 0 (counter-clockwise).
    pub(super) area2: i128,
    /// The sample rows its bounding box covers in the grid, `lo..=hi`.
    rows: (usize, usize),
    /// The sample columns its bounding box covers in the grid, `lo..=hi`.
    cols: (usize, usize),
}

/// Twice the signed area of (a, b, p), exact: in i128, so triangles spanning any number of
/// voxels cannot overflow (i64 products overflow past about 46,000 voxels).
pub(super) fn edge(ax: i64, ay: i64, bx: i64, by: i64, px: i64, py: i64) -> i128 {
    (bx - ax) as i128 * (py - ay) as i128 - (by - ay) as i128 * (px - ax) as i128
}

/// Whether an edge with direction (dx, dy) owns the points on it (see the module docs).
pub(super) fn owns(dx: i64, dy: i64) -> bool {
    dy > 0 || (dy == 0 && dx < 0)
}

/// The sample rows and columns the bounding box of triangle `v` covers in a grid of `dims`,
/// or `None` when it holds no sample centre.
fn reach(v: &[GridVertex; 3], dims: [usize; 3]) -> Option<((usize, usize), (usize, usize))> {
    let span =
        |c: [i64; 3], n: usize| sample_range(c[0].min(c[1]).min(c[2]), c[0].max(c[1]).max(c[2]), n);
    Some((
        span(v.map(|v| v.y), dims[1])?,
        span(v.map(|v| v.x), dims[0])?,
    ))
}

/// Triangle `v` counter-clockwise in projection; `None` when it is seen edge-on or its
/// bounding box holds no sample centre of a grid of `dims`.
pub(super) fn project(v: [GridVertex; 3], dims: [usize; 3]) -> Option<Projected> {
    let (rows, cols) = reach(&v, dims)?;
    let mut t = Projected {
        x: v.map(|v| v.x),
        y: v.map(|v| v.y),
        z: v.map(|v| v.z),
        area2: 0,
        rows,
        cols,
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
pub(super) fn sample_range(min: i64, max: i64, n: usize) -> Option<(usize, usize)> {
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
    match voxelize_solid_until(mesh, dims, to_grid, &CancelToken::never()) {
        Ok(grid) => grid,
        // A token nobody cancels, without a deadline, never stops the work.
        Err(_) => BitGrid::new(dims),
    }
}

/// Rows of columns in a band: the unit of binning and of parallel work.
pub(super) const BAND: usize = 16;

/// Band-list entries (triangle indices, 4 bytes each) held at once, at least: bands are binned
/// in runs of about this many entries, or twice the triangles if that is more.
const MIN_BIN_BUDGET: usize = 1 << 22;

/// [`voxelize_solid`], stopped by `cancel` (checked every few thousand triangles).
///
/// # Errors
/// [`Stopped`] when `cancel` stops the work.
pub fn voxelize_solid_until(
    mesh: &TriMesh,
    dims: [usize; 3],
    to_grid: impl Fn([f32; 3]) -> [f64; 3] + Sync,
    cancel: &CancelToken,
) -> Result<BitGrid, Stopped> {
    let budget = (2 * mesh.triangles.len()).max(MIN_BIN_BUDGET);
    parity_pass(mesh, dims, to_grid, cancel, budget)
}

/// The parity pass, binning at most `budget` entries at once (see [`Binning::groups`]).
fn parity_pass(
    mesh: &TriMesh,
    dims: [usize; 3],
    to_grid: impl Fn([f32; 3]) -> [f64; 3] + Sync,
    cancel: &CancelToken,
    budget: usize,
) -> Result<BitGrid, Stopped> {
    let mut grid = BitGrid::new(dims);
    if mesh.triangles.is_empty() || grid.bits.is_empty() {
        return Ok(grid);
    }
    let vertices: Vec<GridVertex> = mesh
        .positions
        .par_iter()
        .map(|&p| GridVertex::new(to_grid(p)))
        .collect();
    let corners = |i: u32| mesh.triangles[i as usize].map(|v| vertices[v as usize]);
    cancel.check()?;
    let binning = Binning::count(mesh.triangles.len(), dims, &corners);
    cancel.check()?;
    let (nz, words) = (dims[2], grid.words);
    let row_words = dims[0] * words;
    let mut rest = &mut grid.bits[..];
    for group in binning.groups(budget) {
        cancel.check()?;
        let (mine, later) = rest.split_at_mut((group.len() * BAND * row_words).min(rest.len()));
        rest = later;
        let bins = binning.bin(group.clone(), &corners);
        mine.par_chunks_mut(BAND * row_words)
            .enumerate()
            .try_for_each(|(k, bits)| -> Result<(), Stopped> {
                let mut band = Band {
                    first: (group.start + k) * BAND,
                    bits,
                    row_words,
                    words,
                    nz,
                };
                for (n, i) in bins.band(k).enumerate() {
                    if n.is_multiple_of(4096) {
                        cancel.check()?;
                    }
                    if let Some(t) = project(corners(i), dims) {
                        toggle_below(&t, &mut band);
                    }
                }
                Ok(())
            })?;
    }
    Ok(grid)
}

/// Triangle indices sorted into bands of rows in parallel: the triangles are cut into chunks,
/// and each chunk counts, then lists, its own triangles by band (a counting sort). A band's
/// list is its slice of every chunk's list, in triangle order; a triangle is listed once per
/// band its bounding box reaches.
struct Binning {
    triangles: usize,
    dims: [usize; 3],
    /// Triangles per chunk.
    size: usize,
    /// Per chunk, the entries of each band.
    counts: Vec<Vec<u32>>,
}

/// The triangles of one run of bands.
struct Bins {
    /// Per chunk: where each band's slice starts in the list (one more for the end), and the
    /// list of triangle indices.
    chunks: Vec<(Vec<u32>, Vec<u32>)>,
}

impl Binning {
    /// Counts the entries of every band; `corners` gives triangle `i` in grid coordinates.
    fn count(
        triangles: usize,
        dims: [usize; 3],
        corners: &(impl Fn(u32) -> [GridVertex; 3] + Sync),
    ) -> Binning {
        let bands = dims[1].div_ceil(BAND);
        let size = triangles
            .div_ceil(4 * rayon::current_num_threads())
            .max(4096);
        let counts = (0..triangles.div_ceil(size))
            .into_par_iter()
            .map(|c| {
                let mut counts = vec![0u32; bands];
                for i in c * size..((c + 1) * size).min(triangles) {
                    if let Some((lo, hi)) = bands_of(&corners(i as u32), dims) {
                        for n in &mut counts[lo..=hi] {
                            *n += 1;
                        }
                    }
                }
                counts
            })
            .collect();
        Binning {
            triangles,
            dims,
            size,
            counts,
        }
    }

    /// Consecutive runs of bands whose lists hold at most `budget` entries together (or one
    /// band, if it alone holds more), so the lists of a model of huge triangles, each in every
    /// band, never outgrow a few times the model: the runs are binned and swept one by one.
    fn groups(&self, budget: usize) -> Vec<std::ops::Range<usize>> {
        let bands = self.dims[1].div_ceil(BAND);
        let mut groups = Vec::new();
        let (mut start, mut held) = (0, 0);
        for b in 0..bands {
            let n: usize = self.counts.iter().map(|c| c[b] as usize).sum();
            if b > start && held + n > budget {
                groups.push(start..b);
                (start, held) = (b, 0);
            }
            held += n;
        }
        groups.push(start..bands);
        groups
    }

    /// Lists the triangles of the bands `group`.
    fn bin(
        &self,
        group: std::ops::Range<usize>,
        corners: &(impl Fn(u32) -> [GridVertex; 3] + Sync),
    ) -> Bins {
        let chunks = self
            .counts
            .par_iter()
            .enumerate()
            .map(|(c, counts)| {
                let mut starts = vec![0u32; group.len() + 1];
                for (k, b) in group.clone().enumerate() {
                    starts[k + 1] = starts[k] + counts[b];
                }
                let mut next = starts.clone();
                let mut list = vec![0u32; starts[group.len()] as usize];
                let end = ((c + 1) * self.size).min(self.triangles);
                for i in c * self.size..end {
                    let Some((lo, hi)) = bands_of(&corners(i as u32), self.dims) else {
                        continue;
                    };
                    for b in lo.max(group.start)..=hi.min(group.end - 1) {
                        let at = &mut next[b - group.start];
                        list[*at as usize] = i as u32;
                        *at += 1;
                    }
                }
                (starts, list)
            })
            .collect();
        Bins { chunks }
    }
}

/// The bands (`lo..=hi`) the bounding box of triangle `v` reaches with a sample centre.
fn bands_of(v: &[GridVertex; 3], dims: [usize; 3]) -> Option<(usize, usize)> {
    let ((lo, hi), _) = reach(v, dims)?;
    Some((lo / BAND, hi / BAND))
}

impl Bins {
    /// The triangles that reach band `k` of the run.
    fn band(&self, k: usize) -> impl Iterator<Item = u32> + '_ {
        self.chunks.iter().flat_map(move |(starts, list)| {
            list[starts[k] as usize..starts[k + 1] as usize]
                .iter()
                .copied()
        })
    }
}

/// The integer type a triangle's edge functions are stepped in: i64 where every value they
/// take fits (all but triangles tens of thousands of voxels across), i128 otherwise.
trait EdgeInt: Copy + Ord + std::ops::AddAssign + TryFrom<i128> {
    /// The value rounded to the nearest f64 (exact, then rounded once, for either type).
    fn to_f64(self) -> f64;
}

impl EdgeInt for i64 {
    fn to_f64(self) -> f64 {
        self as f64
    }
}

impl EdgeInt for i128 {
    fn to_f64(self) -> f64 {
        self as f64
    }
}

/// A band of rows of columns of the grid, being swept.
struct Band<'a> {
    /// Its first row.
    first: usize,
    /// Its rows' bits.
    bits: &'a mut [u64],
    /// Words per row.
    row_words: usize,
    /// Words per column.
    words: usize,
    /// Voxels per column.
    nz: usize,
}

/// Toggles, in `band`, the voxels below triangle `t` in every column whose centre its
/// projection covers.
fn toggle_below(t: &Projected, band: &mut Band<'_>) {
    // At a sample within one step of the triangle's bounding box, an edge function is at most
    // 2 (W + ONE)(H + ONE) in magnitude (W, H: the box's sides, fixed point).
    let side =
        |c: [i64; 3]| i128::from(c.iter().max().unwrap_or(&0) - c.iter().min().unwrap_or(&0));
    let bound = 2 * (side(t.x) + i128::from(ONE)) * (side(t.y) + i128::from(ONE));
    if bound <= i128::from(i64::MAX) {
        step_below::<i64>(t, band);
    } else {
        step_below::<i128>(t, band);
    }
}

/// [`toggle_below`] with the edge functions in `W`, which must hold every value they take: they
/// are stepped from sample to sample (exact integer sums), and a row stops at the first sample
/// past the triangle (its samples form one run).
fn step_below<W: EdgeInt>(t: &Projected, band: &mut Band<'_>) {
    let Band {
        first,
        ref mut bits,
        row_words,
        words,
        nz,
    } = *band;
    let last = first + bits.len() / row_words - 1;
    let (y0, y1) = (t.rows.0.max(first), t.rows.1.min(last));
    let (x0, x1) = t.cols;
    let (px, py) = (x0 as i64 * ONE + HALF, y0 as i64 * ONE + HALF);
    let narrow = |v: [i128; 3]| -> Option<[W; 3]> {
        let [a, b, c] = v.map(|v| W::try_from(v).ok());
        Some([a?, b?, c?])
    };
    // Edge e runs from vertex e + 1 to e + 2; its function is weight e of the barycentric
    // coordinates (times area2), and a sample is covered when every one is at least `bias`.
    let ends = |e: usize| ((e + 1) % 3, (e + 2) % 3);
    let mut at_row = [0i128; 3];
    let mut step_x = [0i128; 3];
    let mut step_y = [0i128; 3];
    let mut bias = [0i128; 3];
    for e in 0..3 {
        let (a, b) = ends(e);
        at_row[e] = edge(t.x[a], t.y[a], t.x[b], t.y[b], px, py);
        step_x[e] = -i128::from(t.y[b] - t.y[a]) * i128::from(ONE);
        step_y[e] = i128::from(t.x[b] - t.x[a]) * i128::from(ONE);
        bias[e] = i128::from(!owns(t.x[b] - t.x[a], t.y[b] - t.y[a]));
    }
    let (Some(mut at_row), Some(step_x), Some(step_y), Some(bias), Ok(area2)) = (
        narrow(at_row),
        narrow(step_x),
        narrow(step_y),
        narrow(bias),
        W::try_from(t.area2),
    ) else {
        return;
    };
    let area2 = area2.to_f64();
    for y in y0..=y1 {
        let row = &mut bits[(y - first) * row_words..][..row_words];
        let mut w = at_row;
        let mut entered = false;
        for x in x0..=x1 {
            if w[0] >= bias[0] && w[1] >= bias[1] && w[2] >= bias[2] {
                entered = true;
                let z = (w[0].to_f64() * t.z[0] + w[1].to_f64() * t.z[1] + w[2].to_f64() * t.z[2])
                    / area2;
                // Centres k + 0.5 strictly below z: k < z - 0.5.
                let below = ((z - 0.5).ceil().max(0.0) as usize).min(nz);
                let col = &mut row[x * words..(x + 1) * words];
                for word in col.iter_mut().take(below / 64) {
                    *word = !*word;
                }
                if !below.is_multiple_of(64) {
                    col[below / 64] ^= (1u64 << (below % 64)) - 1;
                }
            } else if entered {
                break;
            }
            for e in 0..3 {
                w[e] += step_x[e];
            }
        }
        for e in 0..3 {
            at_row[e] += step_y[e];
        }
    }
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
///
/// Both steps sort in parallel: vertices by position (equal positions get one id), then the
/// edges as pairs of ids, whose runs are counted.
pub fn odd_edges(mesh: &TriMesh) -> (usize, usize) {
    // -0.0 and 0.0 are one position.
    let key = |p: &[f32; 3]| p.map(|c| if c == 0.0 { 0 } else { c.to_bits() });
    let mut by_position: Vec<([u32; 3], u32)> = mesh
        .positions
        .par_iter()
        .enumerate()
        .map(|(i, p)| (key(p), i as u32))
        .collect();
    by_position.par_sort_unstable();
    let mut weld = vec![0u32; mesh.positions.len()];
    let mut id = 0;
    for (k, (position, i)) in by_position.iter().enumerate() {
        if k > 0 && by_position[k - 1].0 != *position {
            id += 1;
        }
        weld[*i as usize] = id;
    }
    // Each edge (a, b), a < b, listed under a (a counting sort), then each short list sorted.
    let ids = by_position.last().map_or(0, |_| id as usize + 1);
    let edges = || {
        mesh.triangles.iter().flat_map(|t| {
            let v = t.map(|i| weld[i as usize]);
            let degenerate = v[0] == v[1] || v[1] == v[2] || v[0] == v[2];
            [(v[0], v[1]), (v[1], v[2]), (v[2], v[0])]
                .into_iter()
                .filter(move |_| !degenerate)
                .map(|(a, b)| (a.min(b), a.max(b)))
        })
    };
    let mut start = vec![0u32; ids + 1];
    for (a, _) in edges() {
        start[a as usize + 1] += 1;
    }
    for a in 0..ids {
        start[a + 1] += start[a];
    }
    let mut next = start.clone();
    let mut ends = vec![0u32; start[ids] as usize];
    for (a, b) in edges() {
        ends[next[a as usize] as usize] = b;
        next[a as usize] += 1;
    }
    let (mut odd, mut distinct) = (0, 0);
    for a in 0..ids {
        let list = &mut ends[start[a] as usize..start[a + 1] as usize];
        list.sort_unstable();
        for run in list.chunk_by(|x, y| x == y) {
            distinct += 1;
            odd += run.len() % 2;
        }
    }
    (odd, distinct)
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

    /// A box as 12 triangles (parity needs no particular winding).
    fn cuboid(lo: [f32; 3], hi: [f32; 3], mesh: &mut TriMesh) {
        let base = mesh.positions.len() as u32;
        for i in 0..8 {
            mesh.positions.push(std::array::from_fn(|a| {
                if i >> a & 1 == 0 {
                    lo[a]
                } else {
                    hi[a]
                }
            }));
        }
        let quads = [
            [0, 1, 3, 2],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 3, 7, 5],
        ];
        for [a, b, c, d] in quads {
            mesh.triangles.push([a, b, c].map(|v| base + v));
            mesh.triangles.push([a, c, d].map(|v| base + v));
        }
    }

    #[test]
    fn bands_binned_in_several_runs_give_the_same_voxels() {
        let mut mesh = TriMesh::default();
        cuboid([2.3, 1.1, 0.4], [40.7, 70.2, 90.6], &mut mesh);
        // Taller than the grid: in every band.
        cuboid([10.0, -500.0, 3.5], [20.0, 500.0, 7.5], &mut mesh);
        cuboid([30.5, 33.5, 60.5], [31.5, 34.5, 61.5], &mut mesh);
        let dims = [48, 80, 100];
        let grid = |p: [f32; 3]| p.map(f64::from);
        let vertices: Vec<GridVertex> = mesh
            .positions
            .iter()
            .map(|&p| GridVertex::new(grid(p)))
            .collect();
        let corners = |i: u32| mesh.triangles[i as usize].map(|v| vertices[v as usize]);
        let binning = Binning::count(mesh.triangles.len(), dims, &corners);
        // A budget of one entry: each of the 5 bands is binned and swept on its own.
        assert_eq!(
            binning.groups(1),
            (0..5).map(|b| b..b + 1).collect::<Vec<_>>()
        );
        assert_eq!(binning.groups(MIN_BIN_BUDGET), vec![0..5]);
        let want = super::super::reference::voxelize_solid_reference(&mesh, dims, grid);
        assert!(want.count() > 0);
        for budget in [1, 2, 9, 30, MIN_BIN_BUDGET] {
            let got = parity_pass(&mesh, dims, grid, &CancelToken::never(), budget);
            assert!(got.as_ref() == Ok(&want), "budget {budget}");
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
