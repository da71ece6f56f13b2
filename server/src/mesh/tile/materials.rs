//! Per-vertex materials of tiles and strips, from a u8 attribute channel
//! (`docs/channels.md`, "Meshes with materials"; the bytes are `docs/mesh-encoding.md`).
//!
//! A vertex lies on a lattice edge, from point p0 to p1, at t of the way (a tile's vertices on
//! the edges `march` cut; a strip's on fine, coarse or connecting edges). Its materials are
//! `[a, b, round(t * 255), 0]` with a and b the channel's values at p0 and p1, except that an end
//! of value 0 (none) takes the other end's value. The value at lattice point j of level k is the
//! channel's stored voxel j of level k (its levels are mode-downsampled, so that voxel is what
//! level k shows), 0 outside the volume. The density's lattice values are resampled; the
//! channel's values are not.
//!
//! Materials are meshed with the geometry (the same `march`, whose edges they read) and cached
//! under a key of their own: the geometry's key and the channel bricks they read
//! ([`tile_material_key`], [`strip_material_key`]), so that painting a channel changes exactly
//! the keys of the tiles and strips whose materials it reaches.

use super::geometry::lattice_inside;
use super::inputs::describe_bricks;
use super::regular::mesh_tile_from;
use super::strip::mesh_strip_from;
use super::voxels::{gather_voxels, BrickWindow};
use super::{StripInputs, TileInputs, TileScratch};
use crate::mesh::mc::{Mesh, Scratch};
use crate::mesh::transition::StripEdge;
use crate::store::decoded::DecodedBricks;
use crate::store::{Snapshot, StoreError};
use isovox_proto::mesh::TileMesh;
use isovox_proto::tile::{cells, strip_coarse_box, strip_field_box, GridBox};
use isovox_proto::{BrickKey, VoxelType};

/// The materials of a vertex on the edge from a point of value `a` to one of value `b`, at `t`
/// of the way: `[a, b, round(t * 255), 0]`, an end of value 0 (none) taking the other's value.
pub fn blend(a: u8, b: u8, t: f32) -> [u8; 4] {
    let w = (t.clamp(0.0, 1.0) * 255.0).round() as u8;
    match (a, b) {
        (0, b) => [b, b, w, 0],
        (a, 0) => [a, a, w, 0],
        (a, b) => [a, b, w, 0],
    }
}

/// Whether `channel` can give per-vertex materials: a u8 channel.
///
/// # Errors
/// Its values are not u8: the message says so.
pub fn check_material_channel(channel: &Snapshot) -> Result<(), String> {
    match channel.layout().voxel_type() {
        VoxelType::U8 => Ok(()),
        other => Err(format!(
            "per-vertex materials need a u8 channel; this one holds {}",
            other.name()
        )),
    }
}

/// The start of a material key: the geometry's key, then what the channel is.
fn describe_materials(geometry: u128, channel: &Snapshot) -> Vec<u8> {
    let mut desc = Vec::with_capacity(64 + 27 * 9);
    desc.extend_from_slice(b"materials");
    desc.extend_from_slice(&geometry.to_le_bytes());
    desc.push(channel.layout().voxel_type().bytes() as u8);
    desc
}

/// The content key of tile `key`'s mesh with the materials of `channel`: its geometry's key
/// (`inputs`) and the channel's bricks of the tile's level holding the corners of its cells.
///
/// # Errors
/// A brick summary (or, before revision 5, header) fails to read.
pub fn tile_material_key(
    channel: &Snapshot,
    key: BrickKey,
    inputs: &TileInputs,
) -> Result<u128, StoreError> {
    let mut desc = describe_materials(inputs.key, channel);
    let (lo, hi, _) = cells(channel.layout(), key);
    describe_bricks(channel, key.level, (lo, hi), (lo, hi), &mut desc)?;
    Ok(xxhash_rust::xxh3::xxh3_128(&desc))
}

/// The content key of the strip of face `face` of tile `key` with the materials of `channel`:
/// its geometry's key and the channel's bricks holding the lattice points the strip's edges
/// can end on (the tile's level along the face, the coarser level on and beside its plane).
///
/// # Errors
/// A brick summary (or, before revision 5, header) fails to read.
pub fn strip_material_key(
    channel: &Snapshot,
    key: BrickKey,
    face: usize,
    inputs: &StripInputs,
) -> Result<u128, StoreError> {
    let mut desc = describe_materials(inputs.key, channel);
    if inputs.may_cross && face < 6 && inputs.faces >> face & 1 == 1 {
        let layout = channel.layout();
        let fine = strip_field_box(layout, key, face);
        describe_bricks(channel, key.level, fine, fine, &mut desc)?;
        let coarse = strip_coarse_box(layout, key, face);
        describe_bricks(channel, key.level + 1, coarse, coarse, &mut desc)?;
    }
    Ok(xxhash_rust::xxh3::xxh3_128(&desc))
}

/// Meshes tile `key` into `out` as [`mesh_tile_from`] does (the same geometry, bit for bit), and
/// its materials from `channel` (a u8 view of the same version).
///
/// # Errors
/// A brick fails to read; `channel` is not u8.
pub fn mesh_tile_materials(
    snap: &Snapshot,
    channel: &Snapshot,
    key: BrickKey,
    iso: f32,
    inputs: &TileInputs,
    out: &mut TileMesh,
    scratch: &mut TileScratch,
) -> Result<(), StoreError> {
    mesh_tile_from(snap, key, iso, inputs, out, scratch)?;
    let (_, _, frame) = cells(snap.layout(), key);
    let mut edges = Vec::with_capacity(out.mesh.positions.len());
    regular_edges(&out.mesh, frame, &scratch.march, &mut edges);
    out.mesh.materials = materials_of(channel, key.level, &edges, scratch)?;
    Ok(())
}

/// Meshes the strip of face `face` of tile `key` into `out` as [`mesh_strip_from`] does, and
/// its materials from `channel`.
///
/// # Errors
/// A brick fails to read; `channel` is not u8.
#[allow(clippy::too_many_arguments)]
pub fn mesh_strip_materials(
    snap: &Snapshot,
    channel: &Snapshot,
    key: BrickKey,
    face: usize,
    iso: f32,
    inputs: &StripInputs,
    out: &mut TileMesh,
    scratch: &mut TileScratch,
) -> Result<(), StoreError> {
    mesh_strip_from(snap, key, face, iso, inputs, out, scratch)?;
    let n = out.mesh.positions.len();
    if n == 0 {
        return Ok(());
    }
    let mut edges = Vec::with_capacity(n);
    scratch
        .transitions
        .strip_edges(&scratch.march, n, &mut edges);
    let (_, _, frame) = cells(snap.layout(), key);
    let edges: Vec<Option<Edge>> = edges
        .into_iter()
        .zip(&out.mesh.positions)
        .map(|(e, p)| match e {
            Some(StripEdge::Edge { ends, t }) => Some(Edge {
                ends,
                t: strip_t(ends, *p, frame).unwrap_or(t),
            }),
            _ => None,
        })
        .collect();
    out.mesh.materials = materials_of(channel, key.level, &edges, scratch)?;
    Ok(())
}

/// Where a strip vertex at local position `p` (before its moves) lies on its edge, read off
/// the position as for a tile's vertices, so that a strip's copy of a tile vertex gets the
/// tile's weight bit for bit: on a fine edge (both ends of the tile's level) and on a coarse
/// one (both of the coarser level: lattice point q at 2q - frame). `None` for a connecting
/// edge, whose ends are one point apart in position: its t is the kernel's.
fn strip_t(ends: [(u8, [i64; 3]); 2], p: [f32; 3], frame: [i64; 3]) -> Option<f32> {
    let [(d0, j0), (d1, j1)] = ends;
    if d0 != d1 {
        return None;
    }
    let axis = (0..3).find(|&a| j0[a] != j1[a])?;
    let step = if d0 == 0 { 1.0 } else { 2.0 };
    let start = (j0[axis] * (1 << d0) - frame[axis]) as f32;
    Some(((p[axis] - start) / step).clamp(0.0, 1.0))
}

/// A vertex's lattice edge: its ends (`(d, j)`: point j of the tile's level plus d) and t.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Edge {
    ends: [(u8, [i64; 3]); 2],
    t: f32,
}

/// The edge of each vertex of a tile's local mesh (`frame` its frame), as `march` (whose
/// scratch made it) cut it: found from the vertex's position and confirmed by the march's
/// own record of the vertex on that edge. t is read off the position: the vertex is at
/// `p0 - frame + t` on the edge's axis.
fn regular_edges(mesh: &Mesh, frame: [i64; 3], march: &Scratch, out: &mut Vec<Option<Edge>>) {
    out.clear();
    for (id, p) in mesh.positions.iter().enumerate() {
        let base = [0, 1, 2].map(|a| p[a].floor() as i64 + frame[a]);
        // The axis whose coordinate is not an integer; when t rounded to an end (all three
        // integers), any axis, from this point or the one below.
        let found = (0..3)
            .filter(|&a| p[a].fract() != 0.0)
            .map(|a| (a, base))
            .chain((0..3).flat_map(|a| {
                let mut below = base;
                below[a] -= 1;
                [(a, base), (a, below)]
            }))
            .find(|&(a, p0)| march.vertex_on_edge(p0, a) == Some(id as u32));
        out.push(found.map(|(a, p0)| {
            let mut p1 = p0;
            p1[a] += 1;
            Edge {
                ends: [(0, p0), (0, p1)],
                t: p[a] - (p0[a] - frame[a]) as f32,
            }
        }));
    }
}

/// The materials of vertices on `edges` (of a tile of `level`; `None`: none), reading the
/// channel's voxels of that level and the next at the edges' ends.
fn materials_of(
    channel: &Snapshot,
    level: u8,
    edges: &[Option<Edge>],
    scratch: &mut TileScratch,
) -> Result<Vec<[u8; 4]>, StoreError> {
    if channel.layout().voxel_type() != VoxelType::U8 {
        return Err(StoreError::OutOfRange(
            "per-vertex materials need a u8 channel".into(),
        ));
    }
    let mut values: [Option<ChannelValues>; 2] = [None, None];
    for (d, slot) in values.iter_mut().enumerate() {
        let ends = edges
            .iter()
            .flatten()
            .flat_map(|e| e.ends)
            .filter(|&(at, _)| usize::from(at) == d)
            .map(|(_, j)| j);
        if let Some(points) = bounding_box(ends) {
            *slot = Some(ChannelValues::read(
                channel,
                level + d as u8,
                points,
                scratch.bricks.clone().as_deref(),
                &mut scratch.material_bricks,
            )?);
        }
    }
    let value = |(d, j): (u8, [i64; 3])| {
        values[usize::from(d)]
            .as_ref()
            .map_or(0, |v| v.at(channel, j))
    };
    Ok(edges
        .iter()
        .map(|e| match e {
            Some(e) => blend(value(e.ends[0]), value(e.ends[1]), e.t),
            None => [0; 4],
        })
        .collect())
}

/// The least box holding `points` (`None` when there are none).
fn bounding_box(points: impl Iterator<Item = [i64; 3]>) -> Option<GridBox> {
    points.fold(None, |b, p| {
        Some(match b {
            None => (p, p),
            Some((lo, hi)) => (
                [0, 1, 2].map(|a| lo[a].min(p[a])),
                [0, 1, 2].map(|a| hi[a].max(p[a])),
            ),
        })
    })
}

/// A channel's stored voxels of one level over a box.
struct ChannelValues {
    level: u8,
    origin: [i64; 3],
    size: [usize; 3],
    voxels: Vec<u8>,
}

impl ChannelValues {
    fn read(
        channel: &Snapshot,
        level: u8,
        (lo, hi): GridBox,
        cache: Option<&DecodedBricks>,
        window: &mut BrickWindow,
    ) -> Result<Self, StoreError> {
        let layout = channel.layout();
        window.open(channel, level, (lo, hi), cache)?;
        let size = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
        let mut voxels = Vec::new();
        gather_voxels::<u8>(window, layout, lo, size, &mut voxels);
        Ok(ChannelValues {
            level,
            origin: lo,
            size,
            voxels,
        })
    }

    /// The value at lattice point `j` (inside the box read): 0 outside the volume.
    fn at(&self, channel: &Snapshot, j: [i64; 3]) -> u8 {
        if !lattice_inside(j, channel.layout().dims(), self.level) {
            return 0;
        }
        let l = [0, 1, 2].map(|a| (j[a] - self.origin[a]) as usize);
        self.voxels[(l[2] * self.size[1] + l[1]) * self.size[0] + l[0]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blend_follows_the_rule() {
        assert_eq!(blend(2, 5, 0.5), [2, 5, 128, 0]);
        assert_eq!(blend(0, 5, 0.25), [5, 5, 64, 0]);
        assert_eq!(blend(3, 0, 1.0), [3, 3, 255, 0]);
        assert_eq!(blend(0, 0, 0.0), [0, 0, 0, 0]);
        assert_eq!(blend(4, 4, 0.1), [4, 4, 26, 0]);
    }
}
