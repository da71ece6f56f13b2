//! A tile's transition strips: the layer of its cells along a face meshed again against the
//! coarser level's lattice values there (see [`crate::mesh::transition`]).

use super::geometry::{face_plane, face_points, field_size, index_in, lattice_inside, tile_faces};
use super::inputs::strip_inputs;
use super::voxels::{gather, lattice, pad_outside, voxel_range, BrickWindow};
use super::world::strip_to_world;
use super::{StripInputs, TileScratch};
use crate::mesh::lattice::{lattice_plane, lattice_point, value_range, weights, LatticeScratch};
use crate::mesh::mc::{march, Field, Mesh, Scratch};
use crate::mesh::transition::{mesh_strip, TransitionInput};
use crate::store::decoded::DecodedBricks;
use crate::store::{Snapshot, StoreError};
use isovox_proto::mesh::TileMesh;
use isovox_proto::tile::{
    cells, coarse_box, stored_box, strip_coarse_box, strip_field_box, GridBox,
};
use isovox_proto::{BrickKey, VolumeLayout};

/// Meshes the transition strip of face `face` of tile `key` into `out` (cleared first), in
/// world coordinates, as drawn: its vertices moved (see [`strip_to_world`]).
///
/// # Errors
/// The face is not one of six; a brick fails to read.
pub fn mesh_strip_world(
    snap: &Snapshot,
    key: BrickKey,
    face: usize,
    iso: f32,
    out: &mut Mesh,
    scratch: &mut TileScratch,
) -> Result<(), StoreError> {
    let inputs = strip_inputs(snap, key, face, iso)?;
    let mut strip = TileMesh::default();
    mesh_strip_from(snap, key, face, iso, &inputs, &mut strip, scratch)?;
    *out = strip_to_world(strip, key, snap);
    Ok(())
}

/// Meshes the transition strip of face `face` of tile `key` into `out` (cleared first), in
/// local lattice coordinates as the tile is: its mesh, with the moves of its vertices along
/// the face (see [`crate::mesh::transition::mesh_strip`]; [`strip_to_world`] draws it).
/// `inputs` comes from [`strip_inputs`]. Only the layer of the tile's cells along the face is
/// meshed again, not the tile.
///
/// Most faces that can have a strip have none, and each step that can tell so cheaply comes
/// before the dearer ones: the ranges of the stored voxels under the face, then the layer's
/// fine samples, then the coarse plane's values.
///
/// # Errors
/// A brick fails to read.
pub fn mesh_strip_from(
    snap: &Snapshot,
    key: BrickKey,
    face: usize,
    iso: f32,
    inputs: &StripInputs,
    out: &mut TileMesh,
    scratch: &mut TileScratch,
) -> Result<(), StoreError> {
    out.mesh.clear();
    out.moves.clear();
    if !inputs.may_cross || face >= 6 || inputs.faces >> face & 1 == 0 {
        return Ok(());
    }
    let strip = StripPlace::new(snap.layout(), key, face, iso);
    let bricks = scratch.bricks.clone();
    let Some(coarse_read) = open_strip_bricks(snap, &strip, bricks.as_deref(), scratch)? else {
        return Ok(());
    };
    let fine = lattice(
        snap,
        key.level,
        strip_field_box(strip.layout, key, face),
        bricks.as_deref(),
        (
            &mut scratch.fine_bricks,
            &mut scratch.stored,
            &mut scratch.lattice,
        ),
        &mut scratch.field,
    )?;
    march_layer(&strip, &fine, &mut scratch.layer, &mut scratch.march);
    let fine_side = side_of_fine_face(&strip, &fine, &scratch.march);
    if let Some(inside) = fine_side {
        // All on one side: the stored voxels' range bounds the lattice values.
        let (low, high) = strip.coarse_bounds(&scratch.coarse_bricks);
        if (inside && low >= iso) || (!inside && high < iso) {
            return Ok(());
        }
    }
    let (stored, plane) = coarse_plane(
        &strip,
        (&scratch.coarse_bricks, coarse_read),
        &mut scratch.lattice,
        &mut scratch.coarse_voxels,
        &mut scratch.region,
    );
    if let Some(inside) = fine_side {
        // The plane's own values say.
        if all_on_side(&plane, strip.points, iso, inside) {
            return Ok(());
        }
    }
    let fine_flags = match fine_side {
        Some(inside) => Err(inside),
        None => Ok(&fine),
    };
    let coarse = coarse_field(
        &strip,
        (&stored, &plane),
        fine_flags,
        (&mut scratch.flags, &mut scratch.beside),
        &mut scratch.coarse,
    );
    let input = TransitionInput {
        tile: tile_faces(strip.layout, key, inputs.faces),
        fine: &fine,
        coarse: &coarse,
        iso,
    };
    mesh_strip(
        &input,
        face,
        &scratch.layer,
        &scratch.march,
        out,
        &mut scratch.transitions,
    );
    Ok(())
}

/// Where a strip lies, what its steps read.
struct StripPlace<'a> {
    layout: &'a VolumeLayout,
    key: BrickKey,
    face: usize,
    iso: f32,
    /// The tile's cells and frame ([`cells`]).
    lo: [i64; 3],
    hi: [i64; 3],
    frame: [i64; 3],
    /// The coarser level.
    coarse_level: u8,
    /// The coarser level's lattice points the strips read ([`coarse_box`]), and those on the
    /// face ([`face_points`]).
    coarse: GridBox,
    points: GridBox,
}

impl<'a> StripPlace<'a> {
    fn new(layout: &'a VolumeLayout, key: BrickKey, face: usize, iso: f32) -> Self {
        let (lo, hi, frame) = cells(layout, key);
        let coarse = coarse_box(layout, key);
        StripPlace {
            layout,
            key,
            face,
            iso,
            lo,
            hi,
            frame,
            coarse_level: key.level + 1,
            coarse,
            points: face_points(face, coarse),
        }
    }

    /// The axis across the face.
    fn axis(&self) -> usize {
        self.face / 2
    }

    /// Bounds of the coarser level's lattice values on the face, from the stored voxels under
    /// it (within `window`).
    fn coarse_bounds(&self, window: &BrickWindow) -> (f32, f32) {
        let read = stored_box(self.coarse_level, self.points);
        value_bounds(window, self.layout, self.coarse_level, read)
    }
}

/// Bounds of the lattice values of `level` over the stored voxels `read` (within `window`),
/// from the voxels' range.
fn value_bounds(
    window: &BrickWindow,
    layout: &VolumeLayout,
    level: u8,
    read: GridBox,
) -> (f32, f32) {
    let (min, max) = voxel_range(window, layout, read);
    value_range(level, min as f32, max as f32)
}

/// Opens the bricks the strip reads: of the tile's level under the face, of the coarser level
/// around it. Returns the box of coarse voxels the strip reads, or `None` when the ranges of the
/// stored voxels under the face show that every fine and coarse sample on it lies on one side
/// of the iso value (most faces that can have a strip have none), before any lattice value is
/// computed or cell marched.
fn open_strip_bricks(
    snap: &Snapshot,
    strip: &StripPlace<'_>,
    bricks: Option<&DecodedBricks>,
    scratch: &mut TileScratch,
) -> Result<Option<GridBox>, StoreError> {
    let (layout, key, points, iso) = (strip.layout, strip.key, strip.points, strip.iso);
    let fine_points = (points.0.map(|v| 2 * v), points.1.map(|v| 2 * v));
    let fine_read = stored_box(key.level, fine_points);
    scratch
        .fine_bricks
        .open(snap, key.level, fine_read, bricks)?;
    let (fine_low, fine_high) = value_bounds(&scratch.fine_bricks, layout, key.level, fine_read);
    let (slo, shi) = stored_box(
        strip.coarse_level,
        strip_coarse_box(layout, key, strip.face),
    );
    scratch
        .coarse_bricks
        .open(snap, strip.coarse_level, (slo, shi), bricks)?;
    let (coarse_low, coarse_high) = strip.coarse_bounds(&scratch.coarse_bricks);
    let (low, high) = (fine_low.min(coarse_low), fine_high.max(coarse_high));
    if low >= iso || high < iso {
        return Ok(None);
    }
    Ok(Some((slo, shi)))
}

/// Marches the layer of the tile's cells along the face into `layer` (cleared first): its
/// vertices on the face's plane are the tile's there, bit for bit (the same samples, the same
/// formula, the same frame).
fn march_layer(strip: &StripPlace<'_>, fine: &Field<'_>, layer: &mut Mesh, scratch: &mut Scratch) {
    let (lo, hi, axis) = (strip.lo, strip.hi, strip.axis());
    let (mut layer_lo, mut layer_hi) = (lo, hi);
    if strip.face & 1 == 1 {
        layer_lo[axis] = hi[axis] - 1;
    } else {
        layer_hi[axis] = lo[axis] + 1;
    }
    // `march` appends: without this, the layer kept every earlier strip's vertices, and each
    // strip cleared a table as long as all of them (a pass of many strips grew quadratically).
    layer.clear();
    march(
        fine,
        layer_lo,
        strip.frame,
        layer_hi,
        strip.iso,
        layer,
        scratch,
    );
}

/// The side of the iso value all the face's fine samples lie on (inside: true), or `None` when
/// they straddle it. The layer's march (`scratch`) made a vertex on every crossed edge between
/// the corners and listed those on the layer's boundary, so the face is mixed exactly when one
/// of them lies in its plane (both ends on it). The face's samples are corners, unless the tile
/// is first on an axis: its faces start one point lower there, and are read one by one.
fn side_of_fine_face(strip: &StripPlace<'_>, fine: &Field<'_>, scratch: &Scratch) -> Option<bool> {
    let (face, points, iso) = (strip.face, strip.points, strip.iso);
    if strip.lo.iter().all(|c| c.rem_euclid(2) == 0) {
        let mixed = scratch
            .border
            .iter()
            .fold(0u8, |m, b| m | (b.faces[0] & b.faces[1]));
        (mixed >> face & 1 == 0).then(|| fine.value(points.0.map(|v| 2 * v)) >= iso)
    } else {
        fine_face_side(fine, points, face, iso)
    }
}

/// The coarser level's values on the plane of the face, with the ring around the face the
/// normals read, from one read of the stored voxels under the plane and the planes beside it
/// (`window` over `read`). Returns those stored voxels (in `voxels`) and the plane's values (in
/// `region`) as fields.
fn coarse_plane<'s>(
    strip: &StripPlace<'_>,
    (window, (slo, shi)): (&BrickWindow, GridBox),
    scratch: &mut LatticeScratch,
    voxels: &'s mut Vec<f32>,
    region: &'s mut Vec<f32>,
) -> (Field<'s>, Field<'s>) {
    let layout = strip.layout;
    let stored_size = field_size((slo, shi));
    gather(window, layout, slo, stored_size, voxels);
    let voxels: &'s Vec<f32> = voxels;
    let stored = Field {
        origin: slo,
        size: stored_size,
        values: voxels,
    };
    let plane_box = face_plane(strip.face, strip.coarse);
    lattice_plane(
        &stored,
        plane_box,
        strip.axis(),
        strip.coarse_level,
        layout.voxel_type(),
        scratch,
        region,
    );
    let plane_size = field_size(plane_box);
    let outside = layout.voxel_type().low() as f32;
    pad_outside(
        region,
        (plane_box.0, plane_size),
        layout.dims(),
        strip.coarse_level,
        outside,
    );
    let region: &'s Vec<f32> = region;
    let plane = Field {
        origin: plane_box.0,
        size: plane_size,
        values: region,
    };
    (stored, plane)
}

/// The coarser level's lattice values the strip reads, as a field over the strips' box
/// ([`coarse_box`]) in `out`: the face's plane (`plane`) and one point on each side of it
/// (normals), resampled from `stored`. The points beside the plane are those the strip's
/// normals read: where a coarse or connecting edge of the face is crossed, at both ends (see
/// [`crossed_points`]; `fine` as there). Computed point by point: the few the strip reads, not
/// the two planes; the others are NaN, never read.
fn coarse_field<'c>(
    strip: &StripPlace<'_>,
    (stored, plane): (&Field<'_>, &Field<'_>),
    fine: Result<&Field<'_>, bool>,
    (flags, beside): (&mut Vec<[bool; 2]>, &mut Vec<[i64; 3]>),
    out: &'c mut Vec<f32>,
) -> Field<'c> {
    let (layout, c, axis) = (strip.layout, strip.coarse.0, strip.axis());
    let size = field_size(strip.coarse);
    out.clear();
    out.resize(size[0] * size[1] * size[2], f32::NAN);
    copy_into(out, (c, size), plane);
    beside.clear();
    crossed_points(
        plane,
        strip.points,
        strip.face,
        strip.iso,
        fine,
        flags,
        beside,
    );
    let weights = weights(strip.coarse_level);
    let outside = layout.voxel_type().low() as f32;
    for &q in beside.iter() {
        for step in [-1, 1] {
            let mut p = q;
            p[axis] += step;
            let at = index_in((c, size), p);
            if out[at].is_nan() {
                out[at] = if lattice_inside(p, layout.dims(), strip.coarse_level) {
                    lattice_point(stored, p, weights)
                } else {
                    outside
                };
            }
        }
    }
    let out: &'c Vec<f32> = out;
    Field {
        origin: c,
        size,
        values: out,
    }
}

/// Whether every value of `field` over the box `points` lies on the side `inside` of `iso`.
fn all_on_side(field: &Field<'_>, (lo, hi): GridBox, iso: f32, inside: bool) -> bool {
    let width = (hi[0] - lo[0] + 1) as usize;
    (lo[2]..=hi[2]).all(|z| {
        (lo[1]..=hi[1]).all(|y| {
            let at = field.index([lo[0], y, z]);
            field.values[at..at + width]
                .iter()
                .all(|&v| (v >= iso) == inside)
        })
    })
}

/// The points of a face (`points`, a box one point thick across `face`'s axis, held by
/// `plane`) where an edge of its transition cells' coarse face or a connecting edge is
/// crossed, at either end: where a point's side of `iso` differs from a neighbour's on the
/// face, or from its fine twin's (read from `fine` at twice the point, or `fine_side` for all
/// of them). The strip computes normals there, which read the points beside the plane.
fn crossed_points(
    plane: &Field<'_>,
    (lo, hi): GridBox,
    face: usize,
    iso: f32,
    fine: Result<&Field<'_>, bool>,
    flags: &mut Vec<[bool; 2]>,
    out: &mut Vec<[i64; 3]>,
) {
    // The face's two lateral axes, and the strides along them in each field.
    let (ua, va) = [(1, 2), (0, 2), (0, 1)][face / 2];
    let (nu, nv) = (
        (hi[ua] - lo[ua] + 1) as usize,
        (hi[va] - lo[va] + 1) as usize,
    );
    let stride = |f: &Field<'_>, a: usize| [1, f.size[0], f.size[0] * f.size[1]][a];
    flags.clear();
    let first = plane.index(lo);
    let (su, sv) = (stride(plane, ua), stride(plane, va));
    for v in 0..nv {
        let row = first + v * sv;
        flags.extend((0..nu).map(|u| [plane.values[row + u * su] >= iso, false]));
    }
    match fine {
        Ok(f) => {
            // The fine twins, every other fine point.
            let first = f.index(lo.map(|c| 2 * c));
            let (su, sv) = (2 * stride(f, ua), 2 * stride(f, va));
            for v in 0..nv {
                let row = first + v * sv;
                for (u, flag) in flags[v * nu..][..nu].iter_mut().enumerate() {
                    flag[1] = f.values[row + u * su] >= iso;
                }
            }
        }
        Err(side) => flags.iter_mut().for_each(|flag| flag[1] = side),
    }
    for v in 0..nv {
        for u in 0..nu {
            let at = v * nu + u;
            let here = flags[at][0];
            let differs = |other: usize| flags[other][0] != here;
            let crossed = here != flags[at][1]
                || (u > 0 && differs(at - 1))
                || (u + 1 < nu && differs(at + 1))
                || (v > 0 && differs(at - nu))
                || (v + 1 < nv && differs(at + nu));
            if crossed {
                let mut p = lo;
                p[ua] += u as i64;
                p[va] += v as i64;
                out.push(p);
            }
        }
    }
}

/// Copies the values of `part` into `buffer`, a field over the box from `origin` with `size`
/// points per axis that holds `part`'s box.
fn copy_into(buffer: &mut [f32], (origin, size): ([i64; 3], [usize; 3]), part: &Field<'_>) {
    let width = part.size[0];
    let mut rows = part.values.chunks_exact(width);
    for z in 0..part.size[2] as i64 {
        for y in 0..part.size[1] as i64 {
            let p = [part.origin[0], part.origin[1] + y, part.origin[2] + z];
            let at = (((p[2] - origin[2]) as usize * size[1]) + (p[1] - origin[1]) as usize)
                * size[0]
                + (p[0] - origin[0]) as usize;
            if let Some(src) = rows.next() {
                buffer[at..at + width].copy_from_slice(src);
            }
        }
    }
}

/// The side of the iso value all the fine samples of face `face` lie on (inside: true), or
/// `None` when they straddle it: the fine lattice points twice the coarse face `points`, read
/// from `fine`.
fn fine_face_side(fine: &Field<'_>, points: GridBox, face: usize, iso: f32) -> Option<bool> {
    let (lo, hi) = (points.0.map(|v| 2 * v), points.1.map(|v| 2 * v));
    let base = fine.index(lo);
    let first = fine.values[base] >= iso;
    // Along the face's two lateral axes; its normal axis has one point.
    let (ua, va) = match face / 2 {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let n = fine.size;
    let stride = |a: usize| [1, n[0], n[0] * n[1]][a];
    let (su, sv) = (stride(ua), stride(va));
    let (nu, nv) = ((hi[ua] - lo[ua]) as usize, (hi[va] - lo[va]) as usize);
    let mixed = (0..=nv).any(|v| {
        let row = base + v * sv;
        (0..=nu).any(|u| (fine.values[row + u * su] >= iso) != first)
    });
    (!mixed).then_some(first)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests fail loudly on purpose

    use super::*;
    use crate::generate::WorldSource;
    use crate::mesh::tile::default_iso;
    use crate::store::{build_vod2, BuildOptions, Vod2};
    use isovox_proto::VoxelType;

    /// One scratch reused over every strip of a pass holds what the strip in hand needs, as a
    /// fresh one does: nothing of the strips before it.
    #[test]
    fn a_reused_scratch_holds_only_the_current_strips_layer() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.vod");
        let layout = VolumeLayout::new([64, 48, 64], 8, VoxelType::U8).unwrap();
        let source = WorldSource::new(layout.clone(), 3);
        build_vod2(&path, &layout, [1.0; 3], &source, &BuildOptions::default()).unwrap();
        let vod = Vod2::open(&path).unwrap();
        let snap = vod.head();
        let iso = default_iso(VoxelType::U8);
        let mut reused = TileScratch::default();
        let mut with_a_layer = 0;
        for (x, y, z) in
            (0..8).flat_map(|x| (0..6).flat_map(move |y| (0..8).map(move |z| (x, y, z))))
        {
            let key = BrickKey { level: 0, x, y, z };
            for face in 0..6 {
                let (mut a, mut b) = (Mesh::default(), Mesh::default());
                mesh_strip_world(&snap, key, face, iso, &mut a, &mut reused).unwrap();
                let mut fresh = TileScratch::default();
                mesh_strip_world(&snap, key, face, iso, &mut b, &mut fresh).unwrap();
                assert_eq!(a, b, "strip {face} of {key:?}");
                if fresh.layer.positions.is_empty() {
                    continue;
                }
                with_a_layer += 1;
                assert_eq!(
                    reused.layer.positions.len(),
                    fresh.layer.positions.len(),
                    "the layer of strip {face} of {key:?}"
                );
            }
        }
        assert!(
            with_a_layer > 10,
            "only {with_a_layer} strips marched a layer"
        );
    }
}
