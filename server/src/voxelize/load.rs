//! Reading triangle meshes: STL (binary and ASCII), OBJ, PLY (ASCII and binary) and glTF/GLB,
//! through the crates made for each format. Polygons are fanned into triangles; glTF node
//! transforms are applied.

use super::solid::TriMesh;
use std::path::Path;

/// Why a model could not be read.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{path}: {detail}")]
    /// The file cannot be read or parsed.
    Read {
        /// The file.
        path: String,
        /// What is wrong.
        detail: String,
    },
    /// The file's extension names no format read here.
    #[error("{0}: unknown model format (expected .stl, .obj, .ply, .gltf or .glb)")]
    UnknownFormat(String),
}

fn read_err(path: &Path, detail: impl std::fmt::Display) -> LoadError {
    LoadError::Read {
        path: path.display().to_string(),
        detail: detail.to_string(),
    }
}

/// Reads the model at `path`, choosing the reader by its extension.
///
/// # Errors
/// An unknown extension, a file that does not parse, or indices out of range.
pub fn load_model(path: &Path) -> Result<TriMesh, LoadError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    let mesh = match ext.as_str() {
        "stl" => load_stl(path)?,
        "obj" => load_obj(path)?,
        "ply" => load_ply(path)?,
        "gltf" | "glb" => load_gltf(path)?,
        _ => return Err(LoadError::UnknownFormat(path.display().to_string())),
    };
    let n = mesh.positions.len();
    if let Some(bad) = mesh.triangles.iter().flatten().find(|&&i| i as usize >= n) {
        return Err(read_err(
            path,
            format!("vertex index {bad} out of range ({n} vertices)"),
        ));
    }
    if mesh.positions.iter().flatten().any(|c| !c.is_finite()) {
        return Err(read_err(path, "a vertex coordinate is not finite"));
    }
    Ok(mesh)
}

fn load_stl(path: &Path) -> Result<TriMesh, LoadError> {
    let bytes = std::fs::read(path).map_err(|e| read_err(path, e))?;
    // A binary STL's size is 84 + 50 n: decide by that, not by the header, which many binary
    // files start with "solid" (stl_io would then read them as ASCII).
    if bytes.len() >= 84 {
        let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
        if n.checked_mul(50).and_then(|b| b.checked_add(84)) == Some(bytes.len()) {
            return Ok(binary_stl(&bytes[84..], n));
        }
    }
    let stl = stl_io::read_stl(&mut std::io::Cursor::new(&bytes)).map_err(|e| read_err(path, e))?;
    Ok(TriMesh {
        positions: stl.vertices.iter().map(|v| [v[0], v[1], v[2]]).collect(),
        triangles: stl
            .faces
            .iter()
            .map(|f| f.vertices.map(|i| i as u32))
            .collect(),
    })
}

/// The triangles of a binary STL body (`n` records of 50 bytes), three vertices each.
fn binary_stl(body: &[u8], n: usize) -> TriMesh {
    let mut mesh = TriMesh::default();
    for record in body.chunks_exact(50).take(n) {
        let f = |at: usize| {
            f32::from_le_bytes([record[at], record[at + 1], record[at + 2], record[at + 3]])
        };
        let base = mesh.positions.len() as u32;
        for v in 0..3 {
            let at = 12 + 12 * v;
            mesh.positions.push([f(at), f(at + 4), f(at + 8)]);
        }
        mesh.triangles.push([base, base + 1, base + 2]);
    }
    mesh
}

fn load_obj(path: &Path) -> Result<TriMesh, LoadError> {
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ..Default::default()
    };
    let (models, _materials) = tobj::load_obj(path, &options).map_err(|e| read_err(path, e))?;
    let mut mesh = TriMesh::default();
    for m in models {
        let base = mesh.positions.len() as u32;
        mesh.positions
            .extend(m.mesh.positions.chunks_exact(3).map(|p| [p[0], p[1], p[2]]));
        mesh.triangles.extend(
            m.mesh
                .indices
                .chunks_exact(3)
                .map(|t| [base + t[0], base + t[1], base + t[2]]),
        );
    }
    Ok(mesh)
}

fn load_ply(path: &Path) -> Result<TriMesh, LoadError> {
    use ply_rs::ply::Property;
    let mut file =
        std::io::BufReader::new(std::fs::File::open(path).map_err(|e| read_err(path, e))?);
    let parser = ply_rs::parser::Parser::<ply_rs::ply::DefaultElement>::new();
    let ply = parser.read_ply(&mut file).map_err(|e| read_err(path, e))?;
    let number = |p: Option<&Property>| -> Option<f32> {
        Some(match p? {
            Property::Float(v) => *v,
            Property::Double(v) => *v as f32,
            Property::Int(v) => *v as f32,
            Property::UInt(v) => *v as f32,
            Property::Short(v) => *v as f32,
            Property::UShort(v) => *v as f32,
            Property::Char(v) => *v as f32,
            Property::UChar(v) => *v as f32,
            _ => return None,
        })
    };
    let mut mesh = TriMesh::default();
    for v in ply.payload.get("vertex").map(Vec::as_slice).unwrap_or(&[]) {
        let p = [number(v.get("x")), number(v.get("y")), number(v.get("z"))];
        match p {
            [Some(x), Some(y), Some(z)] => mesh.positions.push([x, y, z]),
            _ => return Err(read_err(path, "a vertex without numeric x, y and z")),
        }
    }
    for f in ply.payload.get("face").map(Vec::as_slice).unwrap_or(&[]) {
        let list: Vec<u32> = match f.get("vertex_indices").or_else(|| f.get("vertex_index")) {
            Some(Property::ListInt(l)) => l.iter().map(|&i| i as u32).collect(),
            Some(Property::ListUInt(l)) => l.clone(),
            Some(Property::ListShort(l)) => l.iter().map(|&i| i as u32).collect(),
            Some(Property::ListUShort(l)) => l.iter().map(|&i| i as u32).collect(),
            Some(Property::ListUChar(l)) => l.iter().map(|&i| i as u32).collect(),
            Some(Property::ListChar(l)) => l.iter().map(|&i| i as u32).collect(),
            _ => return Err(read_err(path, "a face without a vertex index list")),
        };
        for i in 1..list.len().saturating_sub(1) {
            mesh.triangles.push([list[0], list[i], list[i + 1]]);
        }
    }
    Ok(mesh)
}

fn load_gltf(path: &Path) -> Result<TriMesh, LoadError> {
    let gltf = gltf::Gltf::open(path).map_err(|e| read_err(path, e))?;
    // Buffers: the GLB's binary chunk, or files beside a .gltf (embedded data: URIs are not
    // read; the image crates that decoding them would pull in are not worth it).
    let mut buffers: Vec<Vec<u8>> = Vec::new();
    for b in gltf.buffers() {
        let data = match b.source() {
            gltf::buffer::Source::Bin => gltf.blob.clone().ok_or_else(|| {
                read_err(
                    path,
                    "a buffer names the GLB binary chunk, which is missing",
                )
            })?,
            gltf::buffer::Source::Uri(uri) if !uri.starts_with("data:") => {
                let file = path.with_file_name(uri);
                std::fs::read(&file).map_err(|e| read_err(&file, e))?
            }
            gltf::buffer::Source::Uri(_) => {
                return Err(read_err(
                    path,
                    "embedded data: buffers are not supported; use .glb or a .bin file",
                ))
            }
        };
        if data.len() < b.length() {
            return Err(read_err(path, "a buffer is shorter than declared"));
        }
        buffers.push(data);
    }
    let doc = gltf.document;
    let mut mesh = TriMesh::default();
    let scene = doc.default_scene().or_else(|| doc.scenes().next());
    let mut stack: Vec<(gltf::Node<'_>, [[f32; 4]; 4])> = match &scene {
        Some(s) => s.nodes().map(|n| (n, IDENTITY)).collect(),
        None => Vec::new(),
    };
    while let Some((node, parent)) = stack.pop() {
        let world = mul(parent, node.transform().matrix());
        if let Some(m) = node.mesh() {
            for prim in m.primitives() {
                let mode = prim.mode();
                if !matches!(
                    mode,
                    gltf::mesh::Mode::Triangles
                        | gltf::mesh::Mode::TriangleStrip
                        | gltf::mesh::Mode::TriangleFan
                ) {
                    // Points and lines bound no volume.
                    continue;
                }
                let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d[..]));
                let Some(positions) = reader.read_positions() else {
                    continue;
                };
                let base = mesh.positions.len() as u32;
                mesh.positions
                    .extend(positions.map(|p| transform(&world, p)));
                let count = mesh.positions.len() as u32 - base;
                let indices: Vec<u32> = match reader.read_indices() {
                    Some(i) => i.into_u32().collect(),
                    None => (0..count).collect(),
                };
                let n = indices.len();
                match mode {
                    gltf::mesh::Mode::TriangleStrip => {
                        // Every other triangle of a strip is wound the other way.
                        for i in 0..n.saturating_sub(2) {
                            let (a, b) = if i % 2 == 0 { (i, i + 1) } else { (i + 1, i) };
                            mesh.triangles.push([
                                base + indices[a],
                                base + indices[b],
                                base + indices[i + 2],
                            ]);
                        }
                    }
                    gltf::mesh::Mode::TriangleFan => {
                        for i in 1..n.saturating_sub(1) {
                            mesh.triangles.push([
                                base + indices[0],
                                base + indices[i],
                                base + indices[i + 1],
                            ]);
                        }
                    }
                    _ => mesh.triangles.extend(
                        indices
                            .chunks_exact(3)
                            .map(|t| [base + t[0], base + t[1], base + t[2]]),
                    ),
                }
            }
        }
        stack.extend(node.children().map(|c| (c, world)));
    }
    Ok(mesh)
}

const IDENTITY: [[f32; 4]; 4] = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// Column-major 4x4 product `a * b` (glTF's layout).
fn mul(a: [[f32; 4]; 4], b: [[f32; 4]; 4]) -> [[f32; 4]; 4] {
    let mut out = [[0.0; 4]; 4];
    for (c, col) in out.iter_mut().enumerate() {
        for (r, v) in col.iter_mut().enumerate() {
            *v = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    out
}

fn transform(m: &[[f32; 4]; 4], p: [f32; 3]) -> [f32; 3] {
    let mut out = [0.0; 3];
    for (r, o) in out.iter_mut().enumerate() {
        *o = m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r];
    }
    out
}
