//! The stored voxels a tile and its strips read: the bricks of a level over a box (looked up
//! once), gathered row by row into buffers as f32 or as stored, their ranges, and the lattice
//! values resampled from them.

use super::geometry::field_size;
use crate::mesh::lattice::{lattice_field, LatticeScratch};
use crate::mesh::mc::Field;
use crate::store::codec::min_max;
use crate::store::decoded::{decode, DecodedBricks};
use crate::store::{Snapshot, StoreError, StoredBrick};
use bytes::Bytes;
use isovox_proto::tile::{bricks_of, stored_box, GridBox};
use isovox_proto::{BrickKey, VolumeLayout, VoxelType};

/// The lattice values of `level` over `[lo, hi]` (inclusive), as a field over `out`: the stored
/// voxels themselves at level 0, resampled from the stored voxels around them above; L outside
/// the volume at every level.
pub(super) fn lattice<'o>(
    snap: &Snapshot,
    level: u8,
    (lo, hi): ([i64; 3], [i64; 3]),
    bricks: Option<&DecodedBricks>,
    (window, stored, scratch): (&mut BrickWindow, &mut Vec<f32>, &mut LatticeScratch),
    out: &'o mut Vec<f32>,
) -> Result<Field<'o>, StoreError> {
    let layout = snap.layout();
    let (slo, shi) = stored_box(level, (lo, hi));
    window.open(snap, level, (slo, shi), bricks)?;
    if level == 0 {
        gather(window, layout, lo, field_size((lo, hi)), out);
        let out: &'o Vec<f32> = out;
        return Ok(Field {
            origin: lo,
            size: field_size((lo, hi)),
            values: out,
        });
    }
    gather(window, layout, slo, field_size((slo, shi)), stored);
    let field = Field {
        origin: slo,
        size: field_size((slo, shi)),
        values: stored,
    };
    let t = layout.voxel_type();
    let lattice = lattice_field(&field, (lo, hi), level, t, scratch, &mut *out);
    let (origin, size) = (lattice.origin, lattice.size);
    let low = layout.voxel_type().low() as f32;
    pad_outside(out, (origin, size), layout.dims(), level, low);
    let out: &'o Vec<f32> = out;
    Ok(Field {
        origin,
        size,
        values: out,
    })
}

/// Sets the lattice points of `level` that lie outside the volume (level-0 position `2^k j`
/// outside `[0, dims)`) to `low`, as level 0's padding is. Resampled there, they would ring
/// past L next to bright voxels (Catmull-Rom's negative weights, squared across an edge of the
/// volume), drawing surfaces in the padding that the finer level, all L there, cannot meet:
/// its transition strips would find crossings where it has no vertices.
pub(super) fn pad_outside(
    values: &mut [f32],
    (origin, size): ([i64; 3], [usize; 3]),
    dims: [u32; 3],
    level: u8,
    low: f32,
) {
    let step = 1i64 << level;
    let inside = |a: usize, j: i64| (0..i64::from(dims[a])).contains(&(j * step));
    let last = [0, 1, 2].map(|a| origin[a] + size[a] as i64 - 1);
    if (0..3).all(|a| inside(a, origin[a]) && inside(a, last[a])) {
        return;
    }
    for z in 0..size[2] {
        let z_in = inside(2, origin[2] + z as i64);
        for y in 0..size[1] {
            let yz_in = z_in && inside(1, origin[1] + y as i64);
            let row = &mut values[(z * size[1] + y) * size[0]..][..size[0]];
            for (x, v) in row.iter_mut().enumerate() {
                if !(yz_in && inside(0, origin[0] + x as i64)) {
                    *v = low;
                }
            }
        }
    }
}

/// What one brick holds, looked up once.
#[derive(Debug, Clone)]
enum BrickVoxels {
    /// One value throughout: a constant brick, or L outside the volume.
    Constant(u64),
    /// The brick's voxels as stored (little-endian).
    Voxels(Bytes),
}

/// The bricks of one level holding a box of voxels, each looked up (and decoded, or taken from
/// the shared cache) once, so that the many small reads of a tile's strips do not repeat the
/// index lookups.
#[derive(Debug, Default)]
pub(super) struct BrickWindow {
    /// The first brick position on each axis, and the number of bricks.
    first: [i64; 3],
    count: [usize; 3],
    /// x fastest.
    bricks: Vec<BrickVoxels>,
}

impl BrickWindow {
    /// Looks up the bricks of `level` holding the voxels `(lo, hi)` (inclusive).
    pub(super) fn open(
        &mut self,
        snap: &Snapshot,
        level: u8,
        voxels: GridBox,
        cache: Option<&DecodedBricks>,
    ) -> Result<(), StoreError> {
        let layout = snap.layout();
        let grid = layout.grid(level).map(i64::from);
        let (first, last) = bricks_of(layout.brick(), voxels);
        self.first = first;
        self.count = [0, 1, 2].map(|a| (last[a] - first[a] + 1) as usize);
        self.bricks.clear();
        for z in first[2]..=last[2] {
            for y in first[1]..=last[1] {
                for x in first[0]..=last[0] {
                    let c = [x, y, z];
                    if !(0..3).all(|a| c[a] >= 0 && c[a] < grid[a]) {
                        self.bricks.push(BrickVoxels::Constant(0)); // outside: L
                        continue;
                    }
                    let key = BrickKey {
                        level,
                        x: x as u32,
                        y: y as u32,
                        z: z as u32,
                    };
                    self.bricks.push(match snap.stored(key)? {
                        StoredBrick::Constant(v) => BrickVoxels::Constant(v),
                        record @ StoredBrick::Record { header, .. } => {
                            BrickVoxels::Voxels(match cache {
                                Some(cache) => cache.voxels(header.hash, &record, layout)?,
                                None => decode(&record, layout)?,
                            })
                        }
                    });
                }
            }
        }
        Ok(())
    }

    /// The brick at position `c` (inside the window).
    fn brick(&self, c: [i64; 3]) -> &BrickVoxels {
        let l = [0, 1, 2].map(|a| (c[a] - self.first[a]) as usize);
        &self.bricks[(l[2] * self.count[1] + l[1]) * self.count[0] + l[0]]
    }
}

/// One row of stored voxels, as its brick holds it.
enum Row<'a> {
    /// One value across the row: a constant brick, or L outside the volume.
    Constant(u64),
    /// The row's voxels as stored (little-endian).
    Voxels(&'a [u8]),
}

/// Visits the stored voxels over the box `origin .. origin + size` (within `window`) row by
/// row, brick by brick: `visit(at, width, row)` for each row piece, `at` its first voxel's
/// index in a buffer over the box (x fastest). Together the pieces cover the box once.
fn for_each_row(
    window: &BrickWindow,
    layout: &VolumeLayout,
    origin: [i64; 3],
    size: [usize; 3],
    mut visit: impl FnMut(usize, usize, Row<'_>),
) {
    let b = layout.brick() as i64;
    let bytes_per_voxel = layout.voxel_type().bytes();
    let end = [0, 1, 2].map(|a| origin[a] + size[a] as i64); // exclusive
    for bz in origin[2].div_euclid(b)..=(end[2] - 1).div_euclid(b) {
        for by in origin[1].div_euclid(b)..=(end[1] - 1).div_euclid(b) {
            for bx in origin[0].div_euclid(b)..=(end[0] - 1).div_euclid(b) {
                let c = [bx, by, bz];
                let blo = c.map(|v| v * b);
                let from = [0, 1, 2].map(|a| blo[a].max(origin[a]));
                let to = [0, 1, 2].map(|a| (blo[a] + b).min(end[a]));
                let width = (to[0] - from[0]) as usize;
                let rows = (from[2]..to[2]).flat_map(|z| (from[1]..to[1]).map(move |y| (y, z)));
                let at = |y: i64, z: i64| {
                    ((((z - origin[2]) as usize * size[1]) + (y - origin[1]) as usize) * size[0])
                        + (from[0] - origin[0]) as usize
                };
                match window.brick(c) {
                    BrickVoxels::Constant(v) => {
                        rows.for_each(|(y, z)| visit(at(y, z), width, Row::Constant(*v)));
                    }
                    BrickVoxels::Voxels(voxels) => {
                        for (y, z) in rows {
                            let src = (((z - blo[2]) * b + (y - blo[1])) * b + (from[0] - blo[0]))
                                as usize;
                            let row = &voxels[src * bytes_per_voxel..][..width * bytes_per_voxel];
                            visit(at(y, z), width, Row::Voxels(row));
                        }
                    }
                }
            }
        }
    }
}

/// Writes into `out` the stored voxels over the box `origin .. origin + size` (within
/// `window`; L outside the volume), x fastest. Every value is written once (no clearing pass).
pub(super) fn gather(
    window: &BrickWindow,
    layout: &VolumeLayout,
    origin: [i64; 3],
    size: [usize; 3],
    out: &mut Vec<f32>,
) {
    out.resize(size[0] * size[1] * size[2], 0.0);
    let t = layout.voxel_type();
    for_each_row(window, layout, origin, size, |at, width, row| {
        let dst = &mut out[at..at + width];
        match (row, t) {
            (Row::Constant(v), _) => dst.fill(v as f32),
            (Row::Voxels(bytes), VoxelType::U8) => {
                for (d, s) in dst.iter_mut().zip(bytes) {
                    *d = f32::from(*s);
                }
            }
            (Row::Voxels(bytes), VoxelType::U16) => {
                for (d, s) in dst.iter_mut().zip(bytes.chunks_exact(2)) {
                    *d = f32::from(u16::from_le_bytes([s[0], s[1]]));
                }
            }
            (Row::Voxels(bytes), wide) => {
                for (i, d) in dst.iter_mut().enumerate() {
                    *d = isovox_proto::voxel::value_at(bytes, wide, i) as f32;
                }
            }
        }
    });
}

/// A voxel type as a tile's samples hold it.
pub(super) trait StoredVoxel: Copy + Default {
    /// The value of a constant brick (or of L outside the volume).
    fn from_constant(v: u64) -> Self;
    /// Copies a row of stored voxels (little-endian for u16) into `dst`.
    fn copy_row(dst: &mut [Self], stored: &[u8]);
}

impl StoredVoxel for u8 {
    fn from_constant(v: u64) -> Self {
        // A u8 volume's values fit a u8.
        v as u8
    }

    fn copy_row(dst: &mut [u8], stored: &[u8]) {
        dst.copy_from_slice(stored);
    }
}

impl StoredVoxel for u16 {
    fn from_constant(v: u64) -> Self {
        v as u16
    }

    fn copy_row(dst: &mut [u16], stored: &[u8]) {
        for (d, s) in dst.iter_mut().zip(stored.chunks_exact(2)) {
            *d = u16::from_le_bytes([s[0], s[1]]);
        }
    }
}

/// Writes into `out` the stored voxels over the box `origin .. origin + size` (within
/// `window`; L outside the volume), x fastest, as they are stored ([`gather`] converts them to
/// f32). Every value is written once.
pub(super) fn gather_voxels<V: StoredVoxel>(
    window: &BrickWindow,
    layout: &VolumeLayout,
    origin: [i64; 3],
    size: [usize; 3],
    out: &mut Vec<V>,
) {
    out.resize(size[0] * size[1] * size[2], V::default());
    for_each_row(window, layout, origin, size, |at, width, row| {
        let dst = &mut out[at..at + width];
        match row {
            Row::Constant(v) => dst.fill(V::from_constant(v)),
            Row::Voxels(bytes) => V::copy_row(dst, bytes),
        }
    });
}

/// The least and greatest stored voxel over the box `(lo, hi)` (within `window`; L outside
/// the volume), read from the bricks as they are.
pub(super) fn voxel_range(
    window: &BrickWindow,
    layout: &VolumeLayout,
    (lo, hi): GridBox,
) -> (u64, u64) {
    let t = layout.voxel_type();
    let mut range = (u64::MAX, u64::MIN);
    for_each_row(window, layout, lo, field_size((lo, hi)), |_, _, row| {
        let (l, h) = match row {
            Row::Constant(v) => (v, v),
            Row::Voxels(bytes) => min_max(bytes, t),
        };
        range = (range.0.min(l), range.1.max(h));
    });
    range
}
