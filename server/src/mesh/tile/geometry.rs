//! The seam arithmetic: where a tile lies among its neighbours, which lattice points of the
//! coarser level its strips read on and around a face, and indices into the buffers over such
//! boxes.

use crate::mesh::transition::TileFaces;
use isovox_proto::tile::{cells, GridBox};
use isovox_proto::{BrickKey, VolumeLayout};

/// Where tile `key` lies among its neighbours, for its moves and strips.
pub(super) fn tile_faces(layout: &VolumeLayout, key: BrickKey, faces: u8) -> TileFaces {
    let (lo, hi, frame) = cells(layout, key);
    TileFaces {
        lo,
        hi,
        frame,
        coarse_frame: [key.x, key.y, key.z].map(|c| i64::from(c / 2) * layout.brick() as i64),
        faces,
    }
}

/// The number of points of a box on each axis.
pub(super) fn field_size((lo, hi): GridBox) -> [usize; 3] {
    [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize)
}

/// The coarser level's lattice points on face `face` of a tile whose strips read `(c, d)`
/// (see [`coarse_box`]): the plane c + 1 on the low side, d - 1 on the high one, over the
/// face's extent `[c + 1, d - 1]`; these decide the strip's cells.
pub(super) fn face_points(face: usize, (c, d): GridBox) -> GridBox {
    let a = face / 2;
    let (mut lo, mut hi) = (c.map(|v| v + 1), d.map(|v| v - 1));
    let at = if face & 1 == 1 { d[a] - 1 } else { c[a] + 1 };
    lo[a] = at;
    hi[a] = at;
    (lo, hi)
}

/// The coarser level's lattice points on the plane of face `face` across the whole box
/// `(c, d)`: the face's points and the ring around them that the normals read.
pub(super) fn face_plane(face: usize, (c, d): GridBox) -> GridBox {
    let a = face / 2;
    let at = if face & 1 == 1 { d[a] - 1 } else { c[a] + 1 };
    let (mut lo, mut hi) = (c, d);
    lo[a] = at;
    hi[a] = at;
    (lo, hi)
}

/// The index of point `p` in a buffer over the box from `origin` with `size` points per axis.
pub(super) fn index_in((origin, size): ([i64; 3], [usize; 3]), p: [i64; 3]) -> usize {
    let l = [0, 1, 2].map(|a| (p[a] - origin[a]) as usize);
    (l[2] * size[1] + l[1]) * size[0] + l[0]
}

/// Whether lattice point `j` of `level` lies in the volume (level-0 position `2^k j` inside
/// `[0, dims)` on every axis).
pub(super) fn lattice_inside(j: [i64; 3], dims: [u32; 3], level: u8) -> bool {
    (0..3).all(|a| (0..i64::from(dims[a])).contains(&(j[a] << level)))
}
