//! Triangle meshes and their wire encodings: a compact binary one for the Rust client, and glTF
//! 2.0 binary (GLB) that three.js, Blender and trimesh open as they are; and what a tile
//! carries to be stitched to coarser neighbours ([`Transitions`], [`stitch`]).
//!
//! Compact encoding (`application/x-isovox-mesh`), little endian; the full layout is
//! `docs/mesh-encoding.md`:
//!
//! ```text
//! 0    magic "IVMS"
//! 4    u16 format version (1, or 2 with transition data), u16 flags (bit 0: indices are
//!      u32, else u16)
//! 8    u32 vertex count n, u32 index count m (a multiple of 3)
//! 16   f32[3] bounds min, f32[3] bounds max (0 when empty)
//! 40   n x f32[3] positions
//!      n x i16[3] normals, each component round(c * 32767)
//!      m x u16 or u32 indices, then zero padding to 4 bytes
//! version 2 only, the transition section:
//!      u32 transition vertex count t, u32 move count k, u32[6] strip index counts
//!      t x f32[3] positions, t x i16[3] normals, zero padding to 4 bytes
//!      k x (u32 vertex, u8 faces, 3 zero bytes, f32[3] offset)
//!      the six strips' indices (u16 or u32 as bit 0 says), zero padding to 4 bytes
//! ```
//!
//! Version 1 indices are u32 when n > 65536; version 2 indices (regular and strips) are u32
//! when n + t > 65536. Strip indices and move vertices count the regular vertices first, then
//! the transition vertices.

use crate::error::FormatError;
use crate::vod2::Fields;

/// A triangle mesh: positions, unit normals, indices (three per triangle, counter-clockwise seen
/// from outside).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Unit normals, one per vertex.
    pub normals: Vec<[f32; 3]>,
    /// Triangles, three vertex indices each, counter-clockwise seen from outside.
    pub indices: Vec<u32>,
}

impl Mesh {
    /// Empties the mesh, keeping its memory.
    pub fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.indices.clear();
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

    /// Appends `other`, offsetting its indices.
    pub fn append(&mut self, other: &Mesh) {
        let base = self.positions.len() as u32;
        self.positions.extend_from_slice(&other.positions);
        self.normals.extend_from_slice(&other.normals);
        self.indices.extend(other.indices.iter().map(|i| i + base));
    }
}

/// The six faces of a tile box, in the order of their bits in a face mask: bit 2a is the face at
/// the low end of axis a (x, y, z), bit 2a + 1 the face at the high end.
pub const FACE_NAMES: [&str; 6] = ["-x", "+x", "-y", "+y", "-z", "+z"];

/// A secondary position, as a move: vertex `vertex` moves by `offset` when every face in
/// `faces` (a face mask, never empty) touches a coarser neighbour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VertexMove {
    /// An index into the tile's regular vertices followed by its transition vertices.
    pub vertex: u32,
    /// The faces (a face mask) that must all touch a coarser neighbour for the move to apply.
    pub faces: u8,
    /// What is added to the vertex's position.
    pub offset: [f32; 3],
}

impl VertexMove {
    /// Whether the move applies under face mask `mask`.
    pub fn applies(&self, mask: u8) -> bool {
        self.faces != 0 && self.faces & !mask == 0
    }
}

/// What a tile carries besides its regular mesh so that it can be joined to coarser neighbours
/// without cracks (see `docs/lod-meshes.md`): the vertices only its transition strips use, the
/// moves that make room for the strips, and one strip per face.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Transitions {
    /// Vertices of the strips that are not regular vertices; their indices follow the regular
    /// mesh's.
    pub positions: Vec<[f32; 3]>,
    /// Their unit normals.
    pub normals: Vec<[f32; 3]>,
    /// In order; several moves of one vertex add up.
    pub moves: Vec<VertexMove>,
    /// The strip of each face (in [`FACE_NAMES`] order): triangles, as indices into the regular
    /// vertices followed by the transition vertices.
    pub strips: [Vec<u32>; 6],
}

impl Transitions {
    /// Empties it, keeping its memory.
    pub fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.moves.clear();
        for s in &mut self.strips {
            s.clear();
        }
    }

    /// Whether it holds nothing: no vertex, no move, no strip.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty() && self.moves.is_empty() && self.strips.iter().all(Vec::is_empty)
    }

    /// Triangles in all six strips.
    pub fn triangles(&self) -> usize {
        self.strips.iter().map(|s| s.len() / 3).sum()
    }
}

/// One tile: its regular mesh and its transition data.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TileMesh {
    /// The mesh drawn when no face touches a coarser neighbour.
    pub mesh: Mesh,
    /// What joins it to coarser neighbours.
    pub transitions: Transitions,
}

/// Writes into `out` (cleared first) tile `tile` as drawn next to its neighbours: `mask` has bit
/// f set when face f touches a coarser neighbour (`crate::lod::face_masks` computes it). The
/// regular vertices are moved to their secondary positions, and the strips of those faces are
/// appended with the transition vertices they use. Mask 0 gives the regular mesh. Indices out of
/// range (a hand-built tile; decoded ones are checked) are skipped with their triangle.
pub fn stitch(tile: &TileMesh, mask: u8, out: &mut Mesh) {
    out.clear();
    let (regular, tr) = (&tile.mesh, &tile.transitions);
    let n = regular.positions.len();
    out.positions.extend_from_slice(&regular.positions);
    out.normals.extend_from_slice(&regular.normals);
    out.indices.extend_from_slice(&regular.indices);
    // Transition vertices the drawn strips use, numbered in order of first use.
    let mut remap = vec![u32::MAX; tr.positions.len()];
    for (face, strip) in tr.strips.iter().enumerate() {
        if mask >> face & 1 == 0 {
            continue;
        }
        for tri in strip.chunks_exact(3) {
            let mut ids = [0u32; 3];
            let mut ok = true;
            for (k, &i) in tri.iter().enumerate() {
                let i = i as usize;
                if i < n {
                    ids[k] = i as u32;
                } else if let (Some(p), Some(nm)) = (tr.positions.get(i - n), tr.normals.get(i - n))
                {
                    if remap[i - n] == u32::MAX {
                        remap[i - n] = out.positions.len() as u32;
                        out.positions.push(*p);
                        out.normals.push(*nm);
                    }
                    ids[k] = remap[i - n];
                } else {
                    ok = false;
                }
            }
            if ok {
                out.indices.extend_from_slice(&ids);
            }
        }
    }
    for m in tr.moves.iter().filter(|m| m.applies(mask)) {
        let v = m.vertex as usize;
        let target = if v < n {
            v
        } else {
            match remap.get(v - n) {
                Some(&r) if r != u32::MAX => r as usize,
                _ => continue,
            }
        };
        if let Some(p) = out.positions.get_mut(target) {
            for (c, d) in p.iter_mut().zip(m.offset) {
                *c += d;
            }
        }
    }
}

const MAGIC: [u8; 4] = *b"IVMS";
const HEADER: usize = 40;
/// The fixed part of the transition section: t, k, six strip counts.
const SECTION_HEADER: usize = 32;
const MOVE_BYTES: usize = 20;

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

/// The compact header and regular mesh, `version` in the header.
fn put_regular(b: &mut Vec<u8>, mesh: &Mesh, version: u16, wide: bool) {
    b.extend_from_slice(&MAGIC);
    b.extend_from_slice(&version.to_le_bytes());
    b.extend_from_slice(&u16::from(wide).to_le_bytes());
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
}

/// The transition section (see the module doc), its indices `wide` or not.
fn put_section(b: &mut Vec<u8>, tr: &Transitions, wide: bool) {
    b.extend_from_slice(&(tr.positions.len() as u32).to_le_bytes());
    b.extend_from_slice(&(tr.moves.len() as u32).to_le_bytes());
    for s in &tr.strips {
        b.extend_from_slice(&(s.len() as u32).to_le_bytes());
    }
    put_positions(b, &tr.positions);
    put_normals(b, &tr.normals);
    pad4(b);
    for m in &tr.moves {
        b.extend_from_slice(&m.vertex.to_le_bytes());
        b.extend_from_slice(&[m.faces, 0, 0, 0]);
        for c in m.offset {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    for s in &tr.strips {
        put_indices(b, s, wide);
    }
    pad4(b);
}

/// Encodes a mesh compactly, format version 1 (see the module doc).
pub fn encode_compact(mesh: &Mesh) -> Vec<u8> {
    let n = mesh.positions.len();
    let mut b = Vec::with_capacity(HEADER + n * 18 + mesh.indices.len() * 4 + 4);
    put_regular(&mut b, mesh, 1, wide(n));
    b
}

/// Encodes a tile with its transition data, format version 2 (see the module doc).
pub fn encode_tile(tile: &TileMesh) -> Vec<u8> {
    let (mesh, tr) = (&tile.mesh, &tile.transitions);
    let wide = wide(mesh.positions.len() + tr.positions.len());
    let strips: usize = tr.strips.iter().map(Vec::len).sum();
    let mut b = Vec::with_capacity(
        HEADER
            + (mesh.positions.len() + tr.positions.len()) * 18
            + (mesh.indices.len() + strips) * 4
            + SECTION_HEADER
            + tr.moves.len() * MOVE_BYTES
            + 8,
    );
    put_regular(&mut b, mesh, 2, wide);
    put_section(&mut b, tr, wide);
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

/// Decodes the compact encoding, version 1 or 2; of version 2 the regular mesh alone.
///
/// # Errors
/// Bad magic or version, counts the bytes cannot hold, an index out of range.
pub fn decode_compact(bytes: &[u8]) -> Result<Mesh, FormatError> {
    decode_regular(bytes).map(|(mesh, ..)| mesh)
}

/// The header's regular mesh, the version, the index width and where the rest starts.
fn decode_regular(bytes: &[u8]) -> Result<(Mesh, u16, bool, usize), FormatError> {
    let f = Fields::new("compact mesh", bytes, 0);
    f.magic(0, MAGIC)?;
    let version = f.u16(4)?;
    if version != 1 && version != 2 {
        return Err(FormatError::Unsupported {
            what: "compact mesh version",
            detail: version.to_string(),
        });
    }
    let wide = f.u16(6)? & 1 == 1;
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
    };
    let mut at = HEADER;
    get_vertices(&f, &mut at, n, &mut mesh.positions, &mut mesh.normals)?;
    // Version 2 indices may name transition vertices only in the strips.
    get_indices(&f, &mut at, m, wide, n, &mut mesh.indices)?;
    Ok((mesh, version, wide, at.next_multiple_of(4)))
}

/// Decodes a tile, version 2 with its transition data, or version 1 (no transition data).
///
/// # Errors
/// As [`decode_compact`]; in the transition section, counts the bytes cannot hold, a strip
/// length not a multiple of 3, an index or a moved vertex out of range, a move's face mask
/// empty or with bits above the six faces.
pub fn decode_tile(bytes: &[u8]) -> Result<TileMesh, FormatError> {
    let (mesh, version, wide, at) = decode_regular(bytes)?;
    if version == 1 {
        return Ok(TileMesh {
            mesh,
            transitions: Transitions::default(),
        });
    }
    let transitions = decode_section(&bytes[at.min(bytes.len())..], mesh.positions.len(), wide)?;
    Ok(TileMesh { mesh, transitions })
}

/// Decodes a transition section (see the module doc) for a tile of `n` regular vertices.
fn decode_section(bytes: &[u8], n: usize, wide: bool) -> Result<Transitions, FormatError> {
    let f = Fields::new("mesh transition section", bytes, 0);
    let t = f.u32(0)? as usize;
    let k = f.u32(4)? as usize;
    let mut counts = [0usize; 6];
    for (i, c) in counts.iter_mut().enumerate() {
        *c = f.u32(8 + 4 * i)? as usize;
    }
    let index_bytes: u64 = if wide { 4 } else { 2 };
    let strips: u64 = counts.iter().map(|&c| c as u64).sum();
    let need = (SECTION_HEADER as u64 + (t as u64) * 18).next_multiple_of(4)
        + (k as u64) * MOVE_BYTES as u64
        + strips * index_bytes;
    if counts.iter().any(|c| !c.is_multiple_of(3)) || need > bytes.len() as u64 {
        return Err(too_small(format!(
            "{t} transition vertices, {k} moves and {strips} strip indices do not fit {} bytes",
            bytes.len()
        )));
    }
    let mut tr = Transitions {
        positions: Vec::with_capacity(t),
        normals: Vec::with_capacity(t),
        moves: Vec::with_capacity(k),
        strips: Default::default(),
    };
    let mut at = SECTION_HEADER;
    get_vertices(&f, &mut at, t, &mut tr.positions, &mut tr.normals)?;
    at = at.next_multiple_of(4);
    let limit = n + t;
    for _ in 0..k {
        let vertex = f.u32(at)?;
        let faces = f.slice(at + 4, 1)?[0];
        if vertex as usize >= limit || faces == 0 || faces >= 1 << 6 {
            return Err(FormatError::invalid(
                "mesh transition section",
                format!("move of vertex {vertex} (of {limit}) on faces {faces:#b}"),
            ));
        }
        let offset = [f.f32(at + 8)?, f.f32(at + 12)?, f.f32(at + 16)?];
        tr.moves.push(VertexMove {
            vertex,
            faces,
            offset,
        });
        at += MOVE_BYTES;
    }
    for (strip, &count) in tr.strips.iter_mut().zip(&counts) {
        strip.reserve(count);
        get_indices(&f, &mut at, count, wide, limit, strip)?;
    }
    Ok(tr)
}

/// Encodes a mesh as glTF 2.0 binary: one node, one mesh, one triangle primitive with POSITION
/// and NORMAL (f32 vec3) and indices (u16 or u32), accessor bounds on the positions.
pub fn encode_glb(mesh: &Mesh) -> Vec<u8> {
    glb(mesh, None)
}

/// [`encode_glb`] of a tile's regular mesh, its transition data riding along: the transition
/// section of the compact encoding (see the module doc) in a buffer view of its own, named by
/// the mesh's `extras`: `{"isovox": {"transitions": {"bufferView": v, "wideIndices": w}}}`.
/// Viewers that do not know it draw the regular mesh; [`glb_transitions`] reads it back.
pub fn encode_glb_tile(tile: &TileMesh) -> Vec<u8> {
    glb(&tile.mesh, Some(&tile.transitions))
}

fn glb(mesh: &Mesh, transitions: Option<&Transitions>) -> Vec<u8> {
    let n = mesh.positions.len();
    let wide = wide(n + transitions.map_or(0, |t| t.positions.len()));
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
    let mut gltf_mesh = serde_json::json!({"primitives": [primitive]});
    if let Some(tr) = transitions {
        let at = bin.len();
        put_section(&mut bin, tr, wide);
        gltf_mesh["extras"] = serde_json::json!({"isovox": {"transitions": {
            "bufferView": views.len(), "wideIndices": wide}}});
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

/// The transition data of a GLB written by [`encode_glb_tile`] (`None` when it has none).
///
/// # Errors
/// Not a GLB, its JSON or buffer views out of shape, or the section malformed (as in
/// [`decode_tile`]).
pub fn glb_transitions(bytes: &[u8]) -> Result<Option<Transitions>, FormatError> {
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
    let Some(tr) = json.pointer("/meshes/0/extras/isovox/transitions") else {
        return Ok(None);
    };
    let bad = |what: &str| FormatError::invalid("glb", format!("transitions: {what}"));
    let view = tr["bufferView"]
        .as_u64()
        .ok_or_else(|| bad("no buffer view"))?;
    let wide = tr["wideIndices"]
        .as_bool()
        .ok_or_else(|| bad("no index width"))?;
    let view = &json["bufferViews"][view as usize];
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
    decode_section(section, n, wide).map(Some)
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

    /// A tile: the quad as its regular mesh, one transition vertex, a strip on +x joining the
    /// quad's edge (1,0)-(1,1) to it, two moves.
    fn tile() -> TileMesh {
        TileMesh {
            mesh: quad(),
            transitions: Transitions {
                positions: vec![[1.5, 0.5, 0.0]],
                normals: vec![[1.0, 0.0, 0.0]],
                moves: vec![
                    VertexMove {
                        vertex: 1,
                        faces: 0b10,
                        offset: [-0.25, 0.0, 0.0],
                    },
                    VertexMove {
                        vertex: 4,
                        faces: 0b1010,
                        offset: [0.0, -0.5, 0.0],
                    },
                ],
                strips: [vec![], vec![1, 4, 2], vec![], vec![], vec![], vec![]],
            },
        }
    }

    #[test]
    fn tile_round_trip_and_golden_section() {
        let t = tile();
        let b = encode_tile(&t);
        // Regular part as version 1 but version 2: 124 bytes. Section: 32 + 1 * 18 = 50,
        // padded to 52; 2 moves of 20; 3 u16 indices = 6, padded to 8. 124 + 52 + 40 + 8.
        assert_eq!(b.len(), 124 + 52 + 40 + 8);
        assert_eq!(&b[4..6], &[2, 0]);
        assert_eq!(
            &b[124..156],
            &[
                1, 0, 0, 0, 2, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
                0, 0, 0, 0
            ]
        );
        // The first move: vertex 1, faces 0b10, offset -0.25 (0xbe800000).
        assert_eq!(&b[176..188], &[1, 0, 0, 0, 2, 0, 0, 0, 0, 0, 0x80, 0xbe]);
        let d = decode_tile(&b).unwrap();
        assert_eq!(d.mesh, t.mesh);
        assert_eq!(d.transitions, t.transitions);
        // The regular mesh alone, as a version-1 reader of the header would take it.
        assert_eq!(decode_compact(&b).unwrap(), t.mesh);
        // A version-1 payload is a tile without transition data.
        let v1 = decode_tile(&encode_compact(&t.mesh)).unwrap();
        assert_eq!((v1.mesh, v1.transitions), (t.mesh, Transitions::default()));
    }

    #[test]
    fn tile_rejects_hostile_input() {
        let b = encode_tile(&tile());
        for cut in 124..b.len() - 2 {
            assert!(decode_tile(&b[..cut]).is_err(), "cut at {cut}");
        }
        let patched = |at: usize, bytes: &[u8]| {
            let mut c = b.clone();
            c[at..at + bytes.len()].copy_from_slice(bytes);
            decode_tile(&c)
        };
        assert!(patched(124, &u32::MAX.to_le_bytes()).is_err()); // vertex count
        assert!(patched(128, &u32::MAX.to_le_bytes()).is_err()); // move count
        assert!(patched(136, &2u32.to_le_bytes()).is_err()); // strip not of triangles
        assert!(patched(176, &5u32.to_le_bytes()).is_err()); // moved vertex out of range
        assert!(patched(180, &[0]).is_err()); // move without faces
        assert!(patched(180, &[0x40]).is_err()); // a seventh face
        assert!(patched(216, &5u16.to_le_bytes()).is_err()); // strip index out of range
        assert!(patched(216, &4u16.to_le_bytes()).is_ok());
    }

    #[test]
    fn stitch_by_hand() {
        let t = tile();
        let mut out = Mesh::default();
        // Mask 0: the regular mesh.
        stitch(&t, 0, &mut out);
        assert_eq!(out, t.mesh);
        // +x: vertex 1 moves by -0.25 in x; the strip joins vertices 1, 2 and the transition
        // vertex (appended as vertex 4); its move needs +y too, so it stays.
        stitch(&t, 0b10, &mut out);
        assert_eq!(out.positions[1], [0.75, 0.0, 0.0]);
        assert_eq!(out.positions[4], [1.5, 0.5, 0.0]);
        assert_eq!(out.indices[6..], [1, 4, 2]);
        assert_eq!(out.normals.len(), 5);
        // +x and +y: both moves.
        stitch(&t, 0b1010, &mut out);
        assert_eq!(out.positions[4], [1.5, 0.0, 0.0]);
        // -x alone: no strip there, nothing moves, no transition vertex appended.
        stitch(&t, 0b01, &mut out);
        assert_eq!(out, t.mesh);
    }

    #[test]
    fn glb_tile_carries_the_section() {
        let t = tile();
        let g = encode_glb_tile(&t);
        assert_eq!(g.len() % 4, 0);
        assert_eq!(glb_transitions(&g).unwrap(), Some(t.transitions.clone()));
        assert_eq!(glb_transitions(&encode_glb(&t.mesh)).unwrap(), None);
        let json_len = u32::from_le_bytes([g[12], g[13], g[14], g[15]]) as usize;
        let json: serde_json::Value = serde_json::from_slice(&g[20..20 + json_len]).unwrap();
        assert_eq!(
            json["meshes"][0]["extras"]["isovox"]["transitions"]["bufferView"],
            3
        );
        assert!(glb_transitions(&g[..g.len() - 8]).is_err());
    }

    fn arbitrary_tile() -> impl Strategy<Value = TileMesh> {
        let point = || [-1e4f32..1e4, -1e4f32..1e4, -1e4f32..1e4];
        (1usize..40, 0usize..20).prop_flat_map(move |(n, t)| {
            let all = (n + t) as u32;
            (
                proptest::collection::vec(point(), n),
                proptest::collection::vec(0u32..n as u32, 0..30),
                proptest::collection::vec(point(), t),
                proptest::collection::vec((0u32..all, 1u8..64, point()), 0..10),
                proptest::collection::vec(proptest::collection::vec(0u32..all, 0..4), 6),
            )
                .prop_map(move |(positions, regular, extra, moves, strips)| TileMesh {
                    mesh: Mesh {
                        normals: vec![[0.0, 0.0, 1.0]; positions.len()],
                        positions,
                        indices: regular.iter().flat_map(|&i| [i, i, i]).collect(),
                    },
                    transitions: Transitions {
                        normals: vec![[1.0, 0.0, 0.0]; extra.len()],
                        positions: extra,
                        moves: moves
                            .into_iter()
                            .map(|(vertex, faces, offset)| VertexMove {
                                vertex,
                                faces,
                                offset,
                            })
                            .collect(),
                        strips: std::array::from_fn(|f| {
                            strips[f].iter().flat_map(|&i| [i, i, i]).collect()
                        }),
                    },
                })
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn decoding_any_bytes_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
            let _ = decode_tile(&bytes);
            let _ = decode_compact(&bytes);
            let _ = glb_transitions(&bytes);
        }

        #[test]
        fn a_changed_byte_never_panics_and_stitches(at in 0usize..224, byte in any::<u8>(), mask in 0u8..64) {
            let mut b = encode_tile(&tile());
            b[at] = byte;
            if let Ok(t) = decode_tile(&b) {
                let mut out = Mesh::default();
                stitch(&t, mask, &mut out);
                prop_assert!(out.indices.iter().all(|&i| (i as usize) < out.positions.len()));
            }
        }

        #[test]
        fn tiles_round_trip(t in arbitrary_tile()) {
            let b = encode_tile(&t);
            let d = decode_tile(&b).map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(&d.mesh.positions, &t.mesh.positions);
            prop_assert_eq!(&d.mesh.indices, &t.mesh.indices);
            prop_assert_eq!(&d.transitions.positions, &t.transitions.positions);
            prop_assert_eq!(&d.transitions.moves, &t.transitions.moves);
            prop_assert_eq!(&d.transitions.strips, &t.transitions.strips);
            prop_assert_eq!(encode_tile(&d), b);
            prop_assert_eq!(glb_transitions(&encode_glb_tile(&t)).ok().flatten(), Some(d.transitions));
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
