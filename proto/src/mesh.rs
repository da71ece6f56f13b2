//! Triangle meshes and their wire encodings: a compact binary one for the Rust client, and glTF
//! 2.0 binary (GLB) that three.js, Blender and trimesh open as they are.
//!
//! Compact encoding (`application/x-isovox-mesh`), little endian:
//!
//! ```text
//! 0    magic "IVMS"
//! 4    u16 format version (1), u16 flags (bit 0: indices are u32, else u16)
//! 8    u32 vertex count n, u32 index count m (a multiple of 3)
//! 16   f32[3] bounds min, f32[3] bounds max (0 when empty)
//! 40   n x f32[3] positions
//!      n x i16[3] normals, each component round(c * 32767)
//!      m x u16 or u32 indices (u16 when n <= 65536), then zero padding to 4 bytes
//! ```

use crate::error::FormatError;
use crate::vod2::Fields;

/// A triangle mesh: positions, unit normals, indices (three per triangle, counter-clockwise seen
/// from outside).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub indices: Vec<u32>,
}

impl Mesh {
    pub fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.indices.clear();
    }

    pub fn triangles(&self) -> usize {
        self.indices.len() / 3
    }

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
    pub faces: u8,
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
    pub normals: Vec<[f32; 3]>,
    /// In order; several moves of one vertex add up.
    pub moves: Vec<VertexMove>,
    /// The strip of each face (in [`FACE_NAMES`] order): triangles, as indices into the regular
    /// vertices followed by the transition vertices.
    pub strips: [Vec<u32>; 6],
}

impl Transitions {
    pub fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.moves.clear();
        for s in &mut self.strips {
            s.clear();
        }
    }

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
    pub mesh: Mesh,
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

fn wide(n_vertices: usize) -> bool {
    n_vertices > 65536
}

/// Encodes a mesh compactly (see the module doc).
pub fn encode_compact(mesh: &Mesh) -> Vec<u8> {
    let n = mesh.positions.len();
    let wide = wide(n);
    let mut b = Vec::with_capacity(HEADER + n * 18 + mesh.indices.len() * 4 + 4);
    b.extend_from_slice(&MAGIC);
    b.extend_from_slice(&1u16.to_le_bytes());
    b.extend_from_slice(&(wide as u16).to_le_bytes());
    b.extend_from_slice(&(n as u32).to_le_bytes());
    b.extend_from_slice(&(mesh.indices.len() as u32).to_le_bytes());
    let (lo, hi) = mesh.bounds();
    for v in lo.iter().chain(&hi) {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for p in &mesh.positions {
        for c in p {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    for nm in &mesh.normals {
        for c in nm {
            b.extend_from_slice(&((c.clamp(-1.0, 1.0) * 32767.0).round() as i16).to_le_bytes());
        }
    }
    for &i in &mesh.indices {
        if wide {
            b.extend_from_slice(&i.to_le_bytes());
        } else {
            b.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    b
}

/// Decodes the compact encoding.
///
/// # Errors
/// Bad magic or version, counts the bytes cannot hold, an index out of range.
pub fn decode_compact(bytes: &[u8]) -> Result<Mesh, FormatError> {
    let f = Fields::new("compact mesh", bytes, 0);
    f.magic(0, MAGIC)?;
    let version = f.u16(4)?;
    if version != 1 {
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
        return Err(FormatError::invalid(
            "compact mesh",
            format!(
                "{n} vertices and {m} indices do not fit {} bytes",
                bytes.len()
            ),
        ));
    }
    let mut mesh = Mesh {
        positions: Vec::with_capacity(n),
        normals: Vec::with_capacity(n),
        indices: Vec::with_capacity(m),
    };
    let mut at = HEADER;
    for _ in 0..n {
        mesh.positions
            .push([f.f32(at)?, f.f32(at + 4)?, f.f32(at + 8)?]);
        at += 12;
    }
    for _ in 0..n {
        let c = |o: usize| -> Result<f32, FormatError> { Ok(f.u16(o)? as i16 as f32 / 32767.0) };
        mesh.normals.push([c(at)?, c(at + 2)?, c(at + 4)?]);
        at += 6;
    }
    for _ in 0..m {
        let i = if wide { f.u32(at)? } else { f.u16(at)? as u32 };
        if i as usize >= n {
            return Err(FormatError::invalid(
                "compact mesh",
                format!("index {i} >= vertex count {n}"),
            ));
        }
        mesh.indices.push(i);
        at += index_bytes as usize;
    }
    Ok(mesh)
}

/// Encodes a mesh as glTF 2.0 binary: one node, one mesh, one triangle primitive with POSITION
/// and NORMAL (f32 vec3) and indices (u16 or u32), accessor bounds on the positions.
pub fn encode_glb(mesh: &Mesh) -> Vec<u8> {
    let n = mesh.positions.len();
    let wide = wide(n);
    let mut bin = Vec::with_capacity(n * 24 + mesh.indices.len() * 4);
    for p in &mesh.positions {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for nm in &mesh.normals {
        for c in nm {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let index_at = bin.len();
    for &i in &mesh.indices {
        if wide {
            bin.extend_from_slice(&i.to_le_bytes());
        } else {
            bin.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
    let index_len = bin.len() - index_at;
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
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
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "isovox"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [primitive]}],
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

#[cfg(test)]
mod tests {
    use super::*;

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
