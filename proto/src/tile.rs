//! What a mesh tile owns and reads: the seam rule's arithmetic, shared by the server that meshes
//! tiles (`server/src/mesh/tile/`) and the clients that name their content by the bricks they
//! read and refetch them when one of those changes.
//!
//! Tile (x, y, z) of level k owns the cells whose lower corner lies in `[x b, (x + 1) b)` on each
//! axis (b the brick edge), and for the first tile of an axis also the cell starting at -1, so
//! that a surface touching the volume's low faces is closed. Its cells' corners are the lattice
//! points `[lo, hi]` of its level, the normals' central differences reach one point further on
//! every side. A lattice value of level 0 is a stored voxel; of a coarser level it is
//! interpolated from the stored voxels j - 2 ..= j + 1 on each axis. The transition strip of a
//! face, an object of its own, reads the layer of the tile's cells along that face and the
//! lattice points of the next coarser level on and beside the face's plane, within `[c, d]`
//! with `c = floor(lo / 2) - 1`, `d = hi / 2 + 1`.

use crate::{BrickKey, VolumeLayout};

/// A box of grid points or voxels of one level, both ends included.
pub type GridBox = ([i64; 3], [i64; 3]);

/// The cells `[lo, hi)` of tile `key` (lattice points of its level) and its frame, the
/// position of its brick's first voxel: `(lo, hi, frame)`.
pub fn cells(layout: &VolumeLayout, key: BrickKey) -> ([i64; 3], [i64; 3], [i64; 3]) {
    let b = i64::from(layout.brick());
    let pos = [key.x, key.y, key.z].map(i64::from);
    let lo = pos.map(|c| c * b - i64::from(c == 0));
    let hi = pos.map(|c| (c + 1) * b);
    (lo, hi, pos.map(|c| c * b))
}

/// The stored voxels of `level` whose lattice values cover the lattice points `points`.
pub fn stored_box(level: u8, (lo, hi): GridBox) -> GridBox {
    if level == 0 {
        (lo, hi)
    } else {
        (lo.map(|c| c - 2), hi.map(|c| c + 1))
    }
}

/// The lattice points of a tile's level its marching reads: its cells' corners and the
/// normals' halo.
pub fn field_box(layout: &VolumeLayout, key: BrickKey) -> GridBox {
    let (lo, hi, _) = cells(layout, key);
    (lo.map(|c| c - 1), hi.map(|c| c + 1))
}

/// The lattice points of the next coarser level a tile's transition strips read, in that
/// level's units.
pub fn coarse_box(layout: &VolumeLayout, key: BrickKey) -> GridBox {
    let (lo, hi, _) = cells(layout, key);
    (lo.map(|c| c.div_euclid(2) - 1), hi.map(|c| c / 2 + 1))
}

/// Whether tile `key` carries transition strips: a coarser level exists.
pub fn has_transitions(layout: &VolumeLayout, key: BrickKey) -> bool {
    key.level + 1 < layout.levels()
}

/// The bricks (of `level`, edge `brick`) holding the voxels of `voxels`: the first and last brick
/// position on each axis, possibly outside the grid (read as L).
pub fn bricks_of(brick: u32, voxels: GridBox) -> GridBox {
    let b = i64::from(brick);
    (
        voxels.0.map(|c| c.div_euclid(b)),
        voxels.1.map(|c| c.div_euclid(b)),
    )
}

/// The bricks a mesh tile (its regular mesh and moves) reads: the level and the range of brick
/// positions.
pub fn mesh_tile_reads(layout: &VolumeLayout, key: BrickKey) -> Vec<(u8, GridBox)> {
    let b = layout.brick();
    vec![(
        key.level,
        bricks_of(b, stored_box(key.level, field_box(layout, key))),
    )]
}

/// Whether face `face` (0..6, `mesh::FACE_NAMES` order) of tile `key` can ever touch a coarser
/// tile: a coarser level exists and a tile of the same level lies across the face.
pub fn has_strip(layout: &VolumeLayout, key: BrickKey, face: usize) -> bool {
    has_transitions(layout, key)
        && face < 6
        && layout
            .neighbour(key, crate::lod::FACE_DIRECTIONS[face])
            .is_some()
}

/// The lattice points of a tile's level the strip of face `face` reads: the field of the one
/// layer of the tile's cells along that face (their corners and the normals' halo).
pub fn strip_field_box(layout: &VolumeLayout, key: BrickKey, face: usize) -> GridBox {
    let (lo, hi, _) = cells(layout, key);
    let (mut a, mut b) = (lo, hi);
    let axis = face / 2;
    if face & 1 == 1 {
        a[axis] = hi[axis] - 1;
    } else {
        b[axis] = lo[axis] + 1;
    }
    (a.map(|c| c - 1), b.map(|c| c + 1))
}

/// The lattice points of the next coarser level the strip of face `face` reads, in that level's
/// units: the face's plane across [`coarse_box`] and the planes on either side (the normals).
pub fn strip_coarse_box(layout: &VolumeLayout, key: BrickKey, face: usize) -> GridBox {
    let (c, d) = coarse_box(layout, key);
    let axis = face / 2;
    let at = if face & 1 == 1 {
        d[axis] - 1
    } else {
        c[axis] + 1
    };
    let (mut lo, mut hi) = (c, d);
    lo[axis] = at - 1;
    hi[axis] = at + 1;
    (lo, hi)
}

/// The bricks the transition strip of face `face` of tile `key` reads (empty when the face has
/// no strip, [`has_strip`]): per level (the tile's, then the next coarser one), the level and
/// the range of brick positions.
pub fn strip_reads(layout: &VolumeLayout, key: BrickKey, face: usize) -> Vec<(u8, GridBox)> {
    if !has_strip(layout, key, face) {
        return Vec::new();
    }
    let b = layout.brick();
    let fine = stored_box(key.level, strip_field_box(layout, key, face));
    let coarse = stored_box(key.level + 1, strip_coarse_box(layout, key, face));
    vec![
        (key.level, bricks_of(b, fine)),
        (key.level + 1, bricks_of(b, coarse)),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::VoxelType;

    #[test]
    fn reads_by_hand() {
        // 64^3, brick 8: grids 8, 4, 2, 1.
        let layout = VolumeLayout::new([64; 3], 8, VoxelType::U8).unwrap_or_else(|e| {
            panic!("{e}");
        });
        let key = |level, x, y, z| BrickKey { level, x, y, z };
        // Level-0 tile (2, 0, 5): cells x 16..24, y -1..8 (first), z 40..48; marching reads
        // voxels x 15..=25, y -2..=9, z 39..=49: bricks x 1..=3, y -1..=1, z 4..=6.
        assert_eq!(
            mesh_tile_reads(&layout, key(0, 2, 0, 5)),
            vec![(0, ([1, -1, 4], [3, 1, 6]))]
        );
        // Its +x strip: cells x 23..24 only, field x 22..=25: bricks x 2..=3. The coarse box is
        // level-1 lattice x 7..=13, y -2..=5, z 19..=25; the +x plane is x 12, with 11 and 13
        // beside it: stored voxels x 9..=14, y -4..=6, z 17..=26: bricks x 1, y -1..=0, z 2..=3.
        assert_eq!(
            strip_reads(&layout, key(0, 2, 0, 5), 1),
            vec![(0, ([2, -1, 4], [3, 1, 6])), (1, ([1, -1, 2], [1, 0, 3]))]
        );
        // Its -x strip: cells x 16..17, field 15..=17: bricks 1..=2; coarse plane x 8 with 7
        // and 9: stored 5..=10: bricks 0..=1.
        assert_eq!(
            strip_reads(&layout, key(0, 2, 0, 5), 0),
            vec![(0, ([1, -1, 4], [2, 1, 6])), (1, ([0, -1, 2], [1, 0, 3]))]
        );
        // -y of the first tile on y: no tile across, no strip.
        assert!(!has_strip(&layout, key(0, 2, 0, 5), 2));
        assert!(strip_reads(&layout, key(0, 2, 0, 5), 2).is_empty());
        // Level 2 (lattice read from stored voxels 2 below and 1 above): cells 8..16 on x; the
        // field 7..=17 from stored 5..=18: bricks 0..=2.
        let reads = mesh_tile_reads(&layout, key(2, 1, 1, 1));
        assert_eq!(reads, vec![(2, ([0; 3], [2; 3]))]);
        assert!(has_strip(&layout, key(2, 1, 1, 1), 0));
        // The root has no coarser level, so no strip.
        assert!((0..6).all(|f| !has_strip(&layout, key(3, 0, 0, 0), f)));
    }
}
