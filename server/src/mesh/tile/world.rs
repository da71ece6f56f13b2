//! Local lattice coordinates (relative to a tile's frame) to world coordinates: one formula for
//! every tile, so that shared vertices stay bit-identical, across levels too.

use crate::mesh::mc::Mesh;
use crate::store::Snapshot;
use isovox_proto::mesh::{apply_moves, TileMesh};
use isovox_proto::BrickKey;

/// Moves a tile's local mesh (lattice coordinates relative to the tile's frame) to world
/// coordinates: lattice point j of level k at `2^k j` times the voxel scale.
pub fn to_world(mesh: &mut Mesh, key: BrickKey, snap: &Snapshot) {
    let (positions, normals) = (&mut mesh.positions, &mut mesh.normals);
    positions_to_world(positions, key, snap);
    normals_to_world(normals, snap);
}

/// [`to_world`] for a tile with its moves (their distances too).
pub fn tile_to_world(tile: &mut TileMesh, key: BrickKey, snap: &Snapshot) {
    to_world(&mut tile.mesh, key, snap);
    let step = (1u64 << key.level) as f32;
    let scale = snap.header().voxel_scale;
    for m in &mut tile.moves {
        m.distance = m.distance * step * scale[usize::from(m.face / 2)];
    }
}

/// A local strip ([`super::mesh_strip_from`]) in world coordinates, as drawn: [`tile_to_world`], then
/// its moves applied exactly as a viewer applies the tile's (`isovox_proto::mesh::stitch`), so
/// that its copies of the tile's vertices are the tile's moved vertices bit for bit.
pub fn strip_to_world(mut strip: TileMesh, key: BrickKey, snap: &Snapshot) -> Mesh {
    tile_to_world(&mut strip, key, snap);
    apply_moves(&mut strip.mesh.positions, &strip.moves, 0x3f);
    strip.mesh
}

fn positions_to_world(positions: &mut [[f32; 3]], key: BrickKey, snap: &Snapshot) {
    let b = snap.layout().brick() as f32;
    let origin = [key.x, key.y, key.z].map(|c| c as f32 * b);
    let step = (1u64 << key.level) as f32;
    let scale = snap.header().voxel_scale;
    for p in positions {
        for a in 0..3 {
            p[a] = (p[a] + origin[a]) * step * scale[a];
        }
    }
}

fn normals_to_world(normals: &mut [[f32; 3]], snap: &Snapshot) {
    let scale = snap.header().voxel_scale;
    if scale[0] != scale[1] || scale[1] != scale[2] {
        for n in normals {
            let m = [n[0] / scale[0], n[1] / scale[1], n[2] / scale[2]];
            let len = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
            if len > 0.0 {
                *n = m.map(|c| c / len);
            }
        }
    }
}
