//! Triangle meshes and their wire encodings: a compact binary one for the Rust client, and glTF
//! 2.0 binary (GLB) that three.js, Blender and trimesh open as they are; and what a tile
//! carries to be stitched to coarser neighbours ([`TileMesh`]'s moves, [`stitch`]).
//!
//! Compact encoding (`application/x-isovox-mesh`), little endian; the full layout is
//! `docs/mesh-encoding.md`:
//!
//! ```text
//! 0    magic "IVMS"
//! 4    u16 format version (1: a mesh; 3: a tile, with its moves), u16 flags (bit 0: indices
//!      are u32, else u16; bit 1: a material section follows the indices)
//! 8    u32 vertex count n, u32 index count m (a multiple of 3)
//! 16   f32[3] bounds min, f32[3] bounds max (0 when empty)
//! 40   n x f32[3] positions
//!      n x i16[3] normals, each component round(c * 32767)
//!      m x u16 or u32 indices, then zero padding to 4 bytes
//! flag bit 1 only, the material section:
//!      n x u8[4] (material a, material b, weight w, 0): the vertex lies on the lattice edge
//!      from a point of material a to one of material b, at round(w / 255) of the way
//! version 3 only, the move section:
//!      u32[6] move counts, one per face (-x, +x, -y, +y, -z, +z)
//!      per face in that order, its moves: u32 vertex (< n), f32 distance along the face's axis
//! ```
//!
//! Indices are u32 when n > 65536. A transition strip is a plain mesh (version 1) whose
//! vertices are at their drawn positions. Version 2 (a tile with its six strips inside) is no
//! longer written; [`decode_compact`] still reads its regular mesh.

use crate::error::FormatError;
use crate::vod2::Fields;

/// A triangle mesh: positions, unit normals, indices (three per triangle, counter-clockwise seen
/// from outside), and optionally one material blend per vertex.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Unit normals, one per vertex.
    pub normals: Vec<[f32; 3]>,
    /// Triangles, three vertex indices each, counter-clockwise seen from outside.
    pub indices: Vec<u32>,
    /// Empty, or one entry per vertex: `[a, b, w, 0]`, the vertex lying on the lattice edge
    /// from a point of material `a` to one of material `b` at `w / 255` of the way
    /// (`docs/mesh-encoding.md`; `[0, 0, 0, 0]`: none).
    pub materials: Vec<[u8; 4]>,
}

impl Mesh {
    /// Empties the mesh, keeping its memory.
    pub fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.indices.clear();
        self.materials.clear();
    }

    /// Whether it carries materials (one per vertex).
    pub fn has_materials(&self) -> bool {
        !self.materials.is_empty()
    }

    /// The number of triangles.
    pub fn triangles(&self) -> usize {
        self.indices.len() / 3
    }

    /// Whether it has no triangle.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// Componentwise bounds of the positions (zeros when empty).
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        if self.positions.is_empty() {
            return ([0.0; 3], [0.0; 3]);
        }
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in &self.positions {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        (lo, hi)
    }

    /// Appends `other`, offsetting its indices. When either carries materials the result does,
    /// one per vertex: the vertices of the one without get `[0, 0, 0, 0]` (none).
    pub fn append(&mut self, other: &Mesh) {
        let base = self.positions.len() as u32;
        if self.has_materials() || other.has_materials() {
            self.materials.resize(self.positions.len(), [0; 4]);
            self.materials.extend_from_slice(&other.materials);
            let end = self.materials.len() + other.positions.len() - other.materials.len();
            self.materials.resize(end, [0; 4]);
        }
        self.positions.extend_from_slice(&other.positions);
        self.normals.extend_from_slice(&other.normals);
        self.indices.extend(other.indices.iter().map(|i| i + base));
    }
}

/// The six faces of a tile box, in the order of their bits in a face mask: bit 2a is the face at
/// the low end of axis a (x, y, z), bit 2a + 1 the face at the high end.
pub const FACE_NAMES: [&str; 6] = ["-x", "+x", "-y", "+y", "-z", "+z"];

/// A secondary position, as a move: vertex `vertex` moves by `distance` along the axis of face
/// `face` (`face / 2`: x, y, z) when that face touches a coarser neighbour. Moves always go
/// inwards, so `distance` is positive on a low face and negative on a high one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VertexMove {
    /// An index into the tile's vertices.
    pub vertex: u32,
    /// The face (0..6, in [`FACE_NAMES`] order) that must touch a coarser neighbour.
    pub face: u8,
    /// What is added to the vertex's coordinate on axis `face / 2`.
    pub distance: f32,
}

impl VertexMove {
    /// Whether the move applies under face mask `mask`.
    pub fn applies(&self, mask: u8) -> bool {
        self.face < 6 && mask >> self.face & 1 == 1
    }
}

/// One tile: its regular mesh and the moves that make room for the transition strips of the
/// faces that touch a coarser neighbour (`docs/lod-meshes.md`). The strips themselves are
/// objects of their own, one per face: plain meshes whose vertices are already at their drawn
/// positions (see [`stitch`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TileMesh {
    /// The mesh drawn when no face touches a coarser neighbour.
    pub mesh: Mesh,
    /// Grouped by face, in face order; a vertex has at most one move per face.
    pub moves: Vec<VertexMove>,
}

/// Adds to `positions` the moves of `moves` that apply under `mask`, in their order, each on
/// its face's axis. Indices out of range (a hand-built tile; decoded ones are checked) are
/// skipped.
pub fn apply_moves(positions: &mut [[f32; 3]], moves: &[VertexMove], mask: u8) {
    for m in moves.iter().filter(|m| m.applies(mask)) {
        if let Some(p) = positions.get_mut(m.vertex as usize) {
            p[usize::from(m.face / 2)] += m.distance;
        }
    }
}

/// Writes into `out` (cleared first) tile `tile` as drawn next to its neighbours: `mask` has bit
/// f set when face f touches a coarser neighbour (`crate::lod::face_masks` computes it). The
/// regular vertices of those faces are moved to their secondary positions, and the strips of
/// those faces (`strips[f]`, fetched for the faces in `mask`; `None`: not there yet, skipped)
/// are appended as they are. Mask 0 gives the regular mesh. A strip's vertices along the tile's
/// face are copies of the tile's moved vertices, bit for bit, so welding equal positions joins
/// them.
pub fn stitch(tile: &TileMesh, mask: u8, strips: [Option<&Mesh>; 6], out: &mut Mesh) {
    out.clear();
    out.positions.extend_from_slice(&tile.mesh.positions);
    out.normals.extend_from_slice(&tile.mesh.normals);
    out.indices.extend_from_slice(&tile.mesh.indices);
    out.materials.extend_from_slice(&tile.mesh.materials);
    apply_moves(&mut out.positions, &tile.moves, mask);
    for (face, strip) in strips.iter().enumerate() {
        if let Some(strip) = strip.filter(|_| mask >> face & 1 == 1) {
            out.append(strip);
        }
    }
}

const MAGIC: [u8; 4] = *b"IVMS";
const HEADER: usize = 40;
/// The fixed part of the move section: six per-face move counts.
const MOVES_HEADER: usize = 24;
/// One move: u32 vertex, f32 distance.
const MOVE_BYTES: usize = 8;
/// Flag bit 0: indices are u32.
const FLAG_WIDE: u16 = 1;
/// Flag bit 1: a material section follows the indices.
const FLAG_MATERIALS: u16 = 2;
/// One vertex's materials: u8 a, u8 b, u8 weight, u8 0.
const MATERIAL_BYTES: usize = 4;

fn wide(n_vertices: usize) -> bool {
    n_vertices > 65536
}

fn pad4(b: &mut Vec<u8>) {
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
}

fn put_positions(b: &mut Vec<u8>, positions: &[[f32; 3]]) {
    for p in positions {
        for c in p {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
}

fn put_normals(b: &mut Vec<u8>, normals: &[[f32; 3]]) {
    for nm in normals {
        for c in nm {
            b.extend_from_slice(&((c.clamp(-1.0, 1.0) * 32767.0).round() as i16).to_le_bytes());
        }
    }
}

fn put_indices(b: &mut Vec<u8>, indices: &[u32], wide: bool) {
    for &i in indices {
        if wide {
            b.extend_from_slice(&i.to_le_bytes());
        } else {
            b.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
}

/// The material section: one entry per vertex (missing ones as none, extra ones dropped: a
/// hand-built mesh; decoded ones have one per vertex).
fn put_materials(b: &mut Vec<u8>, mesh: &Mesh) {
    let n = mesh.positions.len();
    for i in 0..n {
        let [a, m, w, _] = mesh.materials.get(i).copied().unwrap_or([0; 4]);
        b.extend_from_slice(&[a, m, w, 0]);
    }
}

/// The compact header and regular mesh, `version` in the header, and its material section
/// when it has materials.
fn put_regular(b: &mut Vec<u8>, mesh: &Mesh, version: u16, wide: bool) {
    let mut flags = if wide { FLAG_WIDE } else { 0 };
    if mesh.has_materials() {
        flags |= FLAG_MATERIALS;
    }
    b.extend_from_slice(&MAGIC);
    b.extend_from_slice(&version.to_le_bytes());
    b.extend_from_slice(&flags.to_le_bytes());
    b.extend_from_slice(&(mesh.positions.len() as u32).to_le_bytes());
    b.extend_from_slice(&(mesh.indices.len() as u32).to_le_bytes());
    let (lo, hi) = mesh.bounds();
    for v in lo.iter().chain(&hi) {
        b.extend_from_slice(&v.to_le_bytes());
    }
    put_positions(b, &mesh.positions);
    put_normals(b, &mesh.normals);
    put_indices(b, &mesh.indices, wide);
    pad4(b);
    if mesh.has_materials() {
        put_materials(b, mesh);
    }
}

/// The move section (see the module doc): six per-face counts, then each face's moves.
fn put_moves(b: &mut Vec<u8>, moves: &[VertexMove]) {
    let mut counts = [0u32; 6];
    for m in moves {
        counts[usize::from(m.face.min(5))] += 1;
    }
    for c in counts {
        b.extend_from_slice(&c.to_le_bytes());
    }
    for face in 0..6u8 {
        for m in moves.iter().filter(|m| m.face.min(5) == face) {
            b.extend_from_slice(&m.vertex.to_le_bytes());
            b.extend_from_slice(&m.distance.to_le_bytes());
        }
    }
}

/// Encodes a mesh compactly, format version 1 (see the module doc). A transition strip is
/// served this way: a plain mesh.
pub fn encode_compact(mesh: &Mesh) -> Vec<u8> {
    let n = mesh.positions.len();
    let mut b = Vec::with_capacity(HEADER + n * 22 + mesh.indices.len() * 4 + 4);
    put_regular(&mut b, mesh, 1, wide(n));
    b
}

/// Encodes a tile with its moves, format version 3 (see the module doc). Moves are written
/// grouped by face (in their order within a face).
pub fn encode_tile(tile: &TileMesh) -> Vec<u8> {
    let mesh = &tile.mesh;
    let n = mesh.positions.len();
    let mut b = Vec::with_capacity(
        HEADER + n * 22 + mesh.indices.len() * 4 + 4 + MOVES_HEADER + tile.moves.len() * MOVE_BYTES,
    );
    put_regular(&mut b, mesh, 3, wide(n));
    put_moves(&mut b, &tile.moves);
    b
}

/// Reads `count` indices below `limit` at `at`.
fn get_indices(
    f: &Fields<'_>,
    at: &mut usize,
    count: usize,
    wide: bool,
    limit: usize,
    out: &mut Vec<u32>,
) -> Result<(), FormatError> {
    for _ in 0..count {
        let i = if wide {
            f.u32(*at)?
        } else {
            f.u16(*at)? as u32
        };
        if i as usize >= limit {
            return Err(FormatError::invalid(
                "compact mesh",
                format!("index {i} >= vertex count {limit}"),
            ));
        }
        out.push(i);
        *at += if wide { 4 } else { 2 };
    }
    Ok(())
}

fn get_vertices(
    f: &Fields<'_>,
    at: &mut usize,
    count: usize,
    positions: &mut Vec<[f32; 3]>,
    normals: &mut Vec<[f32; 3]>,
) -> Result<(), FormatError> {
    for _ in 0..count {
        positions.push([f.f32(*at)?, f.f32(*at + 4)?, f.f32(*at + 8)?]);
        *at += 12;
    }
    for _ in 0..count {
        let c = |o: usize| -> Result<f32, FormatError> { Ok(f.u16(o)? as i16 as f32 / 32767.0) };
        normals.push([c(*at)?, c(*at + 2)?, c(*at + 4)?]);
        *at += 6;
    }
    Ok(())
}

fn too_small(detail: String) -> FormatError {
    FormatError::invalid("compact mesh", detail)
}

/// Decodes the compact encoding, version 1, 2 or 3; of versions 2 and 3 the regular mesh alone.
///
/// # Errors
/// Bad magic or version, counts the bytes cannot hold, an index out of range.
pub fn decode_compact(bytes: &[u8]) -> Result<Mesh, FormatError> {
    decode_regular(bytes).map(|(mesh, ..)| mesh)
}

/// Decodes a transition strip: a plain mesh, version 1 ([`decode_compact`] of version 1 only;
/// a tile is not a strip).
///
/// # Errors
/// As [`decode_compact`], and a version other than 1.
pub fn decode_strip(bytes: &[u8]) -> Result<Mesh, FormatError> {
    match decode_regular(bytes)? {
        (mesh, 1, ..) => Ok(mesh),
        (_, version, ..) => Err(FormatError::invalid(
            "compact mesh",
            format!("a strip is version 1, not {version}"),
        )),
    }
}

/// The header's regular mesh, the version, the index width and where the rest starts.
fn decode_regular(bytes: &[u8]) -> Result<(Mesh, u16, bool, usize), FormatError> {
    let f = Fields::new("compact mesh", bytes, 0);
    f.magic(0, MAGIC)?;
    let version = f.u16(4)?;
    if !(1..=3).contains(&version) {
        return Err(FormatError::Unsupported {
            what: "compact mesh version",
            detail: version.to_string(),
        });
    }
    let flags = f.u16(6)?;
    let wide = flags & FLAG_WIDE != 0;
    let n = f.u32(8)? as usize;
    let m = f.u32(12)? as usize;
    let index_bytes = if wide { 4 } else { 2 };
    let need = (n as u64) * 18 + (m as u64) * index_bytes;
    if !m.is_multiple_of(3) || HEADER as u64 + need > bytes.len() as u64 {
        return Err(too_small(format!(
            "{n} vertices and {m} indices do not fit {} bytes",
            bytes.len()
        )));
    }
    let mut mesh = Mesh {
        positions: Vec::with_capacity(n),
        normals: Vec::with_capacity(n),
        indices: Vec::with_capacity(m),
        materials: Vec::new(),
    };
    let mut at = HEADER;
    get_vertices(&f, &mut at, n, &mut mesh.positions, &mut mesh.normals)?;
    // Version 2 indices may name transition vertices only in the strips.
    get_indices(&f, &mut at, m, wide, n, &mut mesh.indices)?;
    let mut at = at.next_multiple_of(4);
    if flags & FLAG_MATERIALS != 0 {
        let section = f.slice(at, n * MATERIAL_BYTES).map_err(|_| {
            too_small(format!(
                "a material section of {n} vertices does not fit {} bytes",
                bytes.len()
            ))
        })?;
        mesh.materials = section
            .chunks_exact(MATERIAL_BYTES)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect();
        at += n * MATERIAL_BYTES;
    }
    Ok((mesh, version, wide, at))
}

/// Decodes a tile: version 3 with its moves, or version 1 (a regular mesh, no moves). Version 2
/// (strips inside the tile) is no longer served; its regular mesh still reads with
/// [`decode_compact`].
///
/// # Errors
/// As [`decode_compact`]; version 2; in the move section, counts the bytes cannot hold, a
/// moved vertex out of range, a distance that is not finite.
pub fn decode_tile(bytes: &[u8]) -> Result<TileMesh, FormatError> {
    let (mesh, version, _, at) = decode_regular(bytes)?;
    let moves = match version {
        1 => Vec::new(),
        3 => decode_moves(&bytes[at.min(bytes.len())..], mesh.positions.len())?,
        _ => {
            return Err(FormatError::Unsupported {
                what: "compact mesh tile version",
                detail: format!("{version} (tiles with their strips inside; now 3)"),
            })
        }
    };
    Ok(TileMesh { mesh, moves })
}

/// Decodes a move section (see the module doc) for a tile of `n` vertices.
fn decode_moves(bytes: &[u8], n: usize) -> Result<Vec<VertexMove>, FormatError> {
    let f = Fields::new("mesh move section", bytes, 0);
    let mut counts = [0u64; 6];
    for (i, c) in counts.iter_mut().enumerate() {
        *c = u64::from(f.u32(4 * i)?);
    }
    let k: u64 = counts.iter().sum();
    if MOVES_HEADER as u64 + k * MOVE_BYTES as u64 > bytes.len() as u64 {
        return Err(too_small(format!(
            "{k} moves do not fit {} bytes",
            bytes.len()
        )));
    }
    let mut moves = Vec::with_capacity(k as usize);
    let mut at = MOVES_HEADER;
    for (face, &count) in counts.iter().enumerate() {
        for _ in 0..count {
            let vertex = f.u32(at)?;
            let distance = f.f32(at + 4)?;
            if vertex as usize >= n || !distance.is_finite() {
                return Err(FormatError::invalid(
                    "mesh move section",
                    format!("move of vertex {vertex} (of {n}) by {distance} on face {face}"),
                ));
            }
            moves.push(VertexMove {
                vertex,
                face: face as u8,
                distance,
            });
            at += MOVE_BYTES;
        }
    }
    Ok(moves)
}

/// Encodes a mesh as glTF 2.0 binary: one node, one mesh, one triangle primitive with POSITION
/// and NORMAL (f32 vec3) and indices (u16 or u32), accessor bounds on the positions; with
/// materials, the custom attributes `_MATERIAL` (u8 VEC2: a, b; byte stride 4) and
/// `_MATERIAL_WEIGHT` (f32 SCALAR: w / 255).
pub fn encode_glb(mesh: &Mesh) -> Vec<u8> {
    glb(mesh, None)
}

/// [`encode_glb`] of a tile's regular mesh, its moves riding along: the move section of the
/// compact encoding (see the module doc) in a buffer view of its own, named by the mesh's
/// `extras`: `{"isovox": {"moves": {"bufferView": v}}}`. Viewers that do not know it draw the
/// regular mesh; [`glb_moves`] reads it back. A strip's GLB is [`encode_glb`] of the strip.
pub fn encode_glb_tile(tile: &TileMesh) -> Vec<u8> {
    glb(&tile.mesh, Some(&tile.moves))
}

fn glb(mesh: &Mesh, moves: Option<&[VertexMove]>) -> Vec<u8> {
    let n = mesh.positions.len();
    let wide = wide(n);
    let mut bin = Vec::with_capacity(n * 24 + mesh.indices.len() * 4);
    put_positions(&mut bin, &mesh.positions);
    for nm in &mesh.normals {
        for c in nm {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let index_at = bin.len();
    put_indices(&mut bin, &mesh.indices, wide);
    let index_len = bin.len() - index_at;
    pad4(&mut bin);
    let (lo, hi) = mesh.bounds();
    let mut primitive = serde_json::json!({"attributes": {"POSITION": 0, "NORMAL": 1}, "mode": 4});
    let mut accessors = vec![
        serde_json::json!({"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3", "min": lo, "max": hi}),
        serde_json::json!({"bufferView": 1, "componentType": 5126, "count": n, "type": "VEC3"}),
    ];
    let mut views = vec![
        serde_json::json!({"buffer": 0, "byteOffset": 0, "byteLength": n * 12, "target": 34962}),
        serde_json::json!({"buffer": 0, "byteOffset": n * 12, "byteLength": n * 12, "target": 34962}),
    ];
    if !mesh.indices.is_empty() {
        primitive["indices"] = serde_json::json!(2);
        accessors.push(serde_json::json!({"bufferView": 2, "componentType": if wide { 5125 } else { 5123 }, "count": mesh.indices.len(), "type": "SCALAR"}));
        views.push(serde_json::json!({"buffer": 0, "byteOffset": index_at, "byteLength": index_len, "target": 34963}));
    }
    if mesh.has_materials() && n > 0 {
        // `_MATERIAL`: the two materials, u8 VEC2 in 4-byte elements (glTF wants vertex
        // attribute strides that are multiples of 4); `_MATERIAL_WEIGHT`: w / 255 as f32.
        let at = bin.len();
        put_materials(&mut bin, mesh);
        primitive["attributes"]["_MATERIAL"] = serde_json::json!(accessors.len());
        accessors.push(serde_json::json!({"bufferView": views.len(), "componentType": 5121, "count": n, "type": "VEC2"}));
        views.push(serde_json::json!({"buffer": 0, "byteOffset": at, "byteLength": n * MATERIAL_BYTES, "byteStride": MATERIAL_BYTES, "target": 34962}));
        let at = bin.len();
        for i in 0..n {
            let w = mesh.materials.get(i).map_or(0, |m| m[2]);
            bin.extend_from_slice(&(f32::from(w) / 255.0).to_le_bytes());
        }
        primitive["attributes"]["_MATERIAL_WEIGHT"] = serde_json::json!(accessors.len());
        accessors.push(serde_json::json!({"bufferView": views.len(), "componentType": 5126, "count": n, "type": "SCALAR"}));
        views.push(serde_json::json!({"buffer": 0, "byteOffset": at, "byteLength": n * 4, "target": 34962}));
    }
    let mut gltf_mesh = serde_json::json!({"primitives": [primitive]});
    if let Some(moves) = moves {
        let at = bin.len();
        put_moves(&mut bin, moves);
        gltf_mesh["extras"] = serde_json::json!({"isovox": {"moves": {"bufferView": views.len()}}});
        views
            .push(serde_json::json!({"buffer": 0, "byteOffset": at, "byteLength": bin.len() - at}));
    }
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "isovox"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [gltf_mesh],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": bin.len()}],
    });
    let mut json = serde_json::to_vec(&json).unwrap_or_default();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

/// The moves of a GLB tile written by [`encode_glb_tile`] (`None` when it has none).
///
/// # Errors
/// Not a GLB, its JSON or buffer views out of shape, or the section malformed (as in
/// [`decode_tile`]).
pub fn glb_moves(bytes: &[u8]) -> Result<Option<Vec<VertexMove>>, FormatError> {
    let f = Fields::new("glb", bytes, 0);
    f.magic(0, *b"glTF")?;
    let json_len = f.u32(12)? as usize;
    f.magic(16, *b"JSON")?;
    let json: serde_json::Value = serde_json::from_slice(f.slice(20, json_len)?)
        .map_err(|e| FormatError::invalid("glb", format!("JSON chunk: {e}")))?;
    let bin_at = 20 + json_len;
    let bin_len = f.u32(bin_at)? as usize;
    f.magic(bin_at + 4, *b"BIN\0")?;
    let bin = f.slice(bin_at + 8, bin_len)?;
    let Some(moves) = json.pointer("/meshes/0/extras/isovox/moves") else {
        return Ok(None);
    };
    let bad = |what: &str| FormatError::invalid("glb", format!("moves: {what}"));
    let view = moves["bufferView"]
        .as_u64()
        .ok_or_else(|| bad("no buffer view"))?;
    let view = &json["bufferViews"][view.min(u64::from(u32::MAX)) as usize];
    let (at, len) = (
        view["byteOffset"].as_u64().unwrap_or(0) as usize,
        view["byteLength"]
            .as_u64()
            .ok_or_else(|| bad("view without length"))? as usize,
    );
    let n = json["accessors"][0]["count"]
        .as_u64()
        .ok_or_else(|| bad("no positions"))? as usize;
    let section = Fields::new("glb", bin, 0).slice(at, len)?;
    decode_moves(section, n).map(Some)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn quad() -> Mesh {
        Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.5],
            ],
            normals: vec![[0.0, 0.0, 1.0]; 4],
            indices: vec![0, 1, 2, 0, 2, 3],
            materials: vec![],
        }
    }

    #[test]
    fn compact_round_trip_and_golden_header() {
        let m = quad();
        let b = encode_compact(&m);
        // 40 header + 4*12 positions + 4*6 normals + 6*2 indices = 124, padded to 124.
        assert_eq!(b.len(), 124);
        assert_eq!(
            &b[..16],
            &[b'I', b'V', b'M', b'S', 1, 0, 0, 0, 4, 0, 0, 0, 6, 0, 0, 0]
        );
        let d = decode_compact(&b).unwrap();
        assert_eq!(d.positions, m.positions);
        assert_eq!(d.indices, m.indices);
        assert_eq!(d.normals, m.normals); // 0 and 1 are exact in i16 snorm
        assert_eq!(d.bounds(), ([0.0; 3], [1.0, 1.0, 0.5]));
    }

    #[test]
    fn compact_rejects_hostile_input() {
        let b = encode_compact(&quad());
        for cut in 0..b.len() - 12 {
            assert!(decode_compact(&b[..cut]).is_err(), "cut at {cut}");
        }
        let mut huge = b.clone();
        huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode_compact(&huge).is_err());
        let mut bad_index = b.clone();
        let at = 40 + 48 + 24;
        bad_index[at..at + 2].copy_from_slice(&9u16.to_le_bytes());
        assert!(decode_compact(&bad_index).is_err());
    }

    /// A tile: the quad as its regular mesh, three moves on two faces (given out of face order:
    /// the encoding groups them by face).
    fn tile() -> TileMesh {
        TileMesh {
            mesh: quad(),
            moves: vec![
                VertexMove {
                    vertex: 1,
                    face: 1,
                    distance: -0.25,
                },
                VertexMove {
                    vertex: 3,
                    face: 3,
                    distance: -0.5,
                },
                VertexMove {
                    vertex: 2,
                    face: 1,
                    distance: -0.125,
                },
            ],
        }
    }

    /// `tile()`'s moves in the order the encoding gives them back: by face.
    fn by_face(mut moves: Vec<VertexMove>) -> Vec<VertexMove> {
        moves.sort_by_key(|m| m.face);
        moves
    }

    /// A strip for face +x of `tile()`: copies of the quad's vertices 1 and 2 moved by the +x
    /// moves, and a vertex of its own.
    fn strip() -> Mesh {
        Mesh {
            positions: vec![[0.75, 0.0, 0.0], [1.5, 0.5, 0.0], [0.875, 1.0, 0.0]],
            normals: vec![[1.0, 0.0, 0.0]; 3],
            indices: vec![0, 1, 2],
            materials: vec![],
        }
    }

    #[test]
    fn tile_round_trip_and_golden_section() {
        let t = tile();
        let b = encode_tile(&t);
        // Regular part as version 1 but version 3: 124 bytes. Moves: 24 + 3 * 8.
        assert_eq!(b.len(), 124 + 24 + 24);
        assert_eq!(&b[4..6], &[3, 0]);
        // Counts per face: +x 2, +y 1.
        assert_eq!(
            &b[124..148],
            &[0, 0, 0, 0, 2, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]
        );
        // The first +x move: vertex 1, -0.25 (0xbe800000); then vertex 2, -0.125 (0xbe000000);
        // then the +y move, vertex 3, -0.5 (0xbf000000).
        assert_eq!(
            &b[148..172],
            &[1, 0, 0, 0, 0, 0, 0x80, 0xbe, 2, 0, 0, 0, 0, 0, 0, 0xbe, 3, 0, 0, 0, 0, 0, 0, 0xbf]
        );
        let d = decode_tile(&b).unwrap();
        assert_eq!(d.mesh, t.mesh);
        assert_eq!(d.moves, by_face(t.moves.clone()));
        // The regular mesh alone, as a version-1 reader of the header would take it.
        assert_eq!(decode_compact(&b).unwrap(), t.mesh);
        // A version-1 payload is a tile without moves; a tile is no strip.
        let v1 = decode_tile(&encode_compact(&t.mesh)).unwrap();
        assert_eq!((v1.mesh, v1.moves), (t.mesh, vec![]));
        assert!(decode_strip(&b).is_err());
        assert_eq!(decode_strip(&encode_compact(&strip())).unwrap(), strip());
    }

    #[test]
    fn tile_rejects_hostile_input() {
        let b = encode_tile(&tile());
        for cut in 124..b.len() {
            assert!(decode_tile(&b[..cut]).is_err(), "cut at {cut}");
        }
        let patched = |at: usize, bytes: &[u8]| {
            let mut c = b.clone();
            c[at..at + bytes.len()].copy_from_slice(bytes);
            decode_tile(&c)
        };
        assert!(patched(124, &u32::MAX.to_le_bytes()).is_err()); // -x count
        assert!(patched(128, &u32::MAX.to_le_bytes()).is_err()); // +x count
        assert!(patched(128, &3u32.to_le_bytes()).is_err()); // one move more than the bytes
        assert!(patched(148, &4u32.to_le_bytes()).is_err()); // moved vertex out of range
        assert!(patched(148, &3u32.to_le_bytes()).is_ok());
        assert!(patched(152, &f32::NAN.to_le_bytes()).is_err()); // distance not finite
        assert!(patched(152, &f32::INFINITY.to_le_bytes()).is_err());
        assert!(patched(4, &[2, 0]).is_err()); // a version-2 tile is no longer read
        assert!(patched(4, &[4, 0]).is_err());
    }

    #[test]
    fn stitch_by_hand() {
        let t = tile();
        let s = strip();
        let mut out = Mesh::default();
        // Mask 0: the regular mesh, whatever strips are given.
        stitch(&t, 0, [None, Some(&s), None, None, None, None], &mut out);
        assert_eq!(out, t.mesh);
        // +x: vertices 1 and 2 move in x; the strip is appended as it is (vertices 4-6).
        stitch(&t, 0b10, [None, Some(&s), None, None, None, None], &mut out);
        assert_eq!(out.positions[1], [0.75, 0.0, 0.0]);
        assert_eq!(out.positions[2], [0.875, 1.0, 0.0]);
        assert_eq!(out.positions[3], [0.0, 1.0, 0.5]);
        assert_eq!(&out.positions[4..], &s.positions[..]);
        assert_eq!(out.indices[6..], [4, 5, 6]);
        // The strip's copies are the moved vertices, bit for bit.
        assert_eq!(out.positions[4], out.positions[1]);
        assert_eq!(out.positions[6], out.positions[2]);
        // +x without its strip fetched yet: moved, nothing appended.
        stitch(&t, 0b10, [None; 6], &mut out);
        assert_eq!(out.positions.len(), 4);
        assert_eq!(out.positions[1], [0.75, 0.0, 0.0]);
        // +y: vertex 3 moves in y, and the +x strip is not drawn.
        stitch(
            &t,
            0b1000,
            [None, Some(&s), None, None, None, None],
            &mut out,
        );
        assert_eq!(out.positions[3], [0.0, 0.5, 0.5]);
        assert_eq!(out.positions[1], [1.0, 0.0, 0.0]);
        assert_eq!(out.indices.len(), 6);
    }

    #[test]
    fn glb_tile_carries_the_moves() {
        let t = tile();
        let g = encode_glb_tile(&t);
        assert_eq!(g.len() % 4, 0);
        assert_eq!(glb_moves(&g).unwrap(), Some(by_face(t.moves.clone())));
        assert_eq!(glb_moves(&encode_glb(&t.mesh)).unwrap(), None);
        let json_len = u32::from_le_bytes([g[12], g[13], g[14], g[15]]) as usize;
        let json: serde_json::Value = serde_json::from_slice(&g[20..20 + json_len]).unwrap();
        assert_eq!(
            json["meshes"][0]["extras"]["isovox"]["moves"]["bufferView"],
            3
        );
        assert!(glb_moves(&g[..g.len() - 8]).is_err());
    }

    /// `quad()` with materials: rock to soil at 0.5, soil alone, soil to ore at 1/255, none.
    fn painted_quad() -> Mesh {
        Mesh {
            materials: vec![[1, 2, 128, 0], [2, 2, 0, 0], [2, 5, 1, 0], [0, 0, 0, 0]],
            ..quad()
        }
    }

    #[test]
    fn material_section_round_trip_and_golden_bytes() {
        let m = painted_quad();
        let b = encode_compact(&m);
        // Flags: bit 1 (materials), indices u16. The section follows the 124 bytes of the
        // plain mesh (indices end at 124, already a multiple of 4).
        assert_eq!(&b[6..8], &[2, 0]);
        assert_eq!(b.len(), 124 + 16);
        assert_eq!(
            &b[..124],
            &{
                let mut plain = encode_compact(&quad());
                plain[6] = 2;
                plain
            }[..]
        );
        assert_eq!(
            &b[124..],
            &[1, 2, 128, 0, 2, 2, 0, 0, 2, 5, 1, 0, 0, 0, 0, 0]
        );
        assert_eq!(decode_compact(&b).unwrap(), m);
        assert_eq!(decode_strip(&b).unwrap(), m);
        // Without materials, the bytes are exactly those of before: flag clear, no section.
        assert_eq!(&encode_compact(&quad())[6..8], &[0, 0]);
        assert!(decode_compact(&encode_compact(&quad()))
            .unwrap()
            .materials
            .is_empty());
        // Odd index count: 3 u16 indices (6 bytes) padded by 2 before the section.
        let tri = Mesh {
            indices: vec![0, 1, 2],
            ..painted_quad()
        };
        let b = encode_compact(&tri);
        let section = 40 + 48 + 24 + 6 + 2;
        assert_eq!(b.len(), section + 16);
        assert_eq!(&b[section - 2..section], &[0, 0]);
        assert_eq!(&b[section..section + 4], &[1, 2, 128, 0]);
        assert_eq!(decode_compact(&b).unwrap(), tri);
    }

    #[test]
    fn material_section_in_a_tile_comes_before_the_moves() {
        let t = TileMesh {
            mesh: painted_quad(),
            ..tile()
        };
        let b = encode_tile(&t);
        assert_eq!(&b[4..8], &[3, 0, 2, 0]);
        assert_eq!(b.len(), 124 + 16 + 24 + 24);
        assert_eq!(
            &b[124..140],
            &[1, 2, 128, 0, 2, 2, 0, 0, 2, 5, 1, 0, 0, 0, 0, 0]
        );
        // The move counts follow: +x 2, +y 1.
        assert_eq!(&b[144..148], &[2, 0, 0, 0]);
        let d = decode_tile(&b).unwrap();
        assert_eq!(d.mesh, t.mesh);
        assert_eq!(d.moves, by_face(t.moves.clone()));
        assert_eq!(decode_compact(&b).unwrap(), t.mesh);
        assert_eq!(encode_tile(&d), b);
    }

    #[test]
    fn material_section_with_u32_indices() {
        // 65537 vertices: indices are u32 (flags 3 with materials).
        let n = 65537u32;
        let mesh = Mesh {
            positions: (0..n).map(|i| [i as f32, 0.0, 0.0]).collect(),
            normals: vec![[0.0, 1.0, 0.0]; n as usize],
            indices: vec![0, 65536, 1],
            materials: (0..n)
                .map(|i| [(i % 7) as u8, (i % 5) as u8, (i % 256) as u8, 0])
                .collect(),
        };
        let b = encode_compact(&mesh);
        assert_eq!(&b[6..8], &[3, 0]);
        // 40 + 18 * 65537 + 3 * 4 = 1_179_718 bytes, padded by 2 to a multiple of 4.
        let section = 1_179_720;
        assert_eq!(b.len(), section + 4 * n as usize);
        assert_eq!(
            &b[section + 4 * 65536..],
            &[(65536 % 7) as u8, (65536 % 5) as u8, 0, 0]
        );
        assert_eq!(decode_compact(&b).unwrap(), mesh);
        let tile = TileMesh {
            mesh: mesh.clone(),
            moves: vec![VertexMove {
                vertex: 65536,
                face: 0,
                distance: 0.5,
            }],
        };
        let d = decode_tile(&encode_tile(&tile)).unwrap();
        assert_eq!(d, tile);
        // Truncated inside the section: an error, not a panic.
        assert!(decode_compact(&b[..b.len() - 1]).is_err());
    }

    #[test]
    fn material_section_rejects_hostile_input() {
        let b = encode_compact(&painted_quad());
        for cut in 0..b.len() {
            assert!(decode_compact(&b[..cut]).is_err(), "cut at {cut}");
            assert!(decode_strip(&b[..cut]).is_err(), "cut at {cut}");
        }
        let t = encode_tile(&TileMesh {
            mesh: painted_quad(),
            ..tile()
        });
        for cut in 0..t.len() {
            assert!(decode_tile(&t[..cut]).is_err(), "cut at {cut}");
        }
        // The flag set on a mesh without the section: too short.
        let mut flagged = encode_compact(&quad());
        flagged[6] |= 2;
        assert!(decode_compact(&flagged).is_err());
        // A huge vertex count with the flag: refused before allocating.
        let mut huge = b.clone();
        huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode_compact(&huge).is_err());
    }

    #[test]
    fn append_stitch_and_glb_carry_materials() {
        let mut m = quad();
        m.append(&painted_quad());
        assert_eq!(m.materials.len(), 8);
        assert_eq!(&m.materials[..4], &[[0; 4]; 4]);
        assert_eq!(&m.materials[4..], &painted_quad().materials[..]);
        let mut p = painted_quad();
        p.append(&quad());
        assert_eq!(&p.materials[..4], &painted_quad().materials[..]);
        assert_eq!(&p.materials[4..], &[[0; 4]; 4]);
        let mut plain = quad();
        plain.append(&quad());
        assert!(plain.materials.is_empty());
        let t = TileMesh {
            mesh: painted_quad(),
            ..tile()
        };
        let mut out = Mesh::default();
        stitch(
            &t,
            0b10,
            [None, Some(&strip()), None, None, None, None],
            &mut out,
        );
        assert_eq!(out.materials.len(), out.positions.len());
        assert_eq!(&out.materials[..4], &t.mesh.materials[..]);
        assert_eq!(&out.materials[4..], &[[0; 4]; 3]);
        // GLB: the two custom attributes, the moves' view after them.
        let g = encode_glb_tile(&t);
        let json_len = u32::from_le_bytes([g[12], g[13], g[14], g[15]]) as usize;
        let json: serde_json::Value = serde_json::from_slice(&g[20..20 + json_len]).unwrap();
        let attributes = &json["meshes"][0]["primitives"][0]["attributes"];
        let (a, w) = (
            attributes["_MATERIAL"].as_u64().unwrap() as usize,
            attributes["_MATERIAL_WEIGHT"].as_u64().unwrap() as usize,
        );
        assert_eq!(json["accessors"][a]["type"], "VEC2");
        assert_eq!(json["accessors"][a]["componentType"], 5121);
        assert_eq!(json["accessors"][w]["type"], "SCALAR");
        assert_eq!(json["accessors"][w]["componentType"], 5126);
        let view = json["accessors"][a]["bufferView"].as_u64().unwrap() as usize;
        assert_eq!(json["bufferViews"][view]["byteStride"], 4);
        let bin = 20 + json_len + 8;
        let at = bin + json["bufferViews"][view]["byteOffset"].as_u64().unwrap() as usize;
        assert_eq!(
            &g[at..at + 16],
            &[1, 2, 128, 0, 2, 2, 0, 0, 2, 5, 1, 0, 0, 0, 0, 0]
        );
        let wv = json["accessors"][w]["bufferView"].as_u64().unwrap() as usize;
        let at = bin + json["bufferViews"][wv]["byteOffset"].as_u64().unwrap() as usize;
        let w0 = f32::from_le_bytes([g[at], g[at + 1], g[at + 2], g[at + 3]]);
        assert_eq!(w0, 128.0 / 255.0);
        assert_eq!(glb_moves(&g).unwrap(), Some(by_face(t.moves.clone())));
        // Without materials, no custom attribute.
        let g = encode_glb_tile(&tile());
        let json_len = u32::from_le_bytes([g[12], g[13], g[14], g[15]]) as usize;
        let json: serde_json::Value = serde_json::from_slice(&g[20..20 + json_len]).unwrap();
        assert!(json["meshes"][0]["primitives"][0]["attributes"]
            .get("_MATERIAL")
            .is_none());
    }

    fn arbitrary_tile() -> impl Strategy<Value = TileMesh> {
        let point = || [-1e4f32..1e4, -1e4f32..1e4, -1e4f32..1e4];
        (1usize..40).prop_flat_map(move |n| {
            (
                proptest::collection::vec(point(), n),
                proptest::collection::vec(0u32..n as u32, 0..30),
                proptest::collection::vec((0u32..n as u32, 0u8..6, -2f32..2.0), 0..20),
                proptest::option::of(proptest::collection::vec(any::<[u8; 3]>(), n)),
            )
                .prop_map(move |(positions, regular, moves, materials)| TileMesh {
                    mesh: Mesh {
                        normals: vec![[0.0, 0.0, 1.0]; positions.len()],
                        positions,
                        indices: regular.iter().flat_map(|&i| [i, i, i]).collect(),
                        materials: materials
                            .unwrap_or_default()
                            .into_iter()
                            .map(|[a, b, w]| [a, b, w, 0])
                            .collect(),
                    },
                    moves: moves
                        .into_iter()
                        .map(|(vertex, face, distance)| VertexMove {
                            vertex,
                            face,
                            distance,
                        })
                        .collect(),
                })
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn decoding_any_bytes_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
            let _ = decode_tile(&bytes);
            let _ = decode_compact(&bytes);
            let _ = decode_strip(&bytes);
            let _ = glb_moves(&bytes);
        }

        #[test]
        fn a_changed_byte_never_panics_and_stitches(at in 0usize..172, byte in any::<u8>(), mask in 0u8..64) {
            let mut b = encode_tile(&tile());
            b[at] = byte;
            if let Ok(t) = decode_tile(&b) {
                let mut out = Mesh::default();
                let s = strip();
                stitch(&t, mask, [Some(&s); 6], &mut out);
                prop_assert!(out.indices.iter().all(|&i| (i as usize) < out.positions.len()));
            }
            let mut s = encode_compact(&strip());
            let at = at % s.len();
            s[at] = byte;
            if let Ok(m) = decode_strip(&s) {
                prop_assert!(m.indices.iter().all(|&i| (i as usize) < m.positions.len()));
            }
        }

        #[test]
        fn tiles_round_trip(t in arbitrary_tile()) {
            let b = encode_tile(&t);
            let d = decode_tile(&b).map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(&d.mesh.positions, &t.mesh.positions);
            prop_assert_eq!(&d.mesh.indices, &t.mesh.indices);
            prop_assert_eq!(&d.mesh.materials, &t.mesh.materials);
            prop_assert_eq!(&d.moves, &by_face(t.moves.clone()));
            prop_assert_eq!(encode_tile(&d), b);
            prop_assert_eq!(glb_moves(&encode_glb_tile(&t)).ok().flatten(), Some(d.moves));
        }
    }

    #[test]
    fn glb_layout() {
        let g = encode_glb(&quad());
        assert_eq!(&g[..4], b"glTF");
        assert_eq!(
            u32::from_le_bytes([g[8], g[9], g[10], g[11]]) as usize,
            g.len()
        );
        assert_eq!(&g[16..20], b"JSON");
        assert_eq!(g.len() % 4, 0);
    }
}
