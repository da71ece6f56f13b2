//! Mesh files for `isovox mesh`: GLB, OBJ, PLY (binary little endian), chosen by extension.

use super::mc::Mesh;
use std::io::{self, Write};
use std::path::Path;

/// The formats `isovox mesh` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    /// glTF binary.
    Glb,
    /// Wavefront OBJ.
    Obj,
    /// Binary little-endian PLY.
    Ply,
}

impl MeshFormat {
    /// The format named by a path's extension.
    pub fn from_path(path: &Path) -> Option<MeshFormat> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "glb" => Some(MeshFormat::Glb),
            "obj" => Some(MeshFormat::Obj),
            "ply" => Some(MeshFormat::Ply),
            _ => None,
        }
    }
}

/// Writes `mesh` in `format`.
///
/// # Errors
/// Writing fails.
pub fn write_mesh(mesh: &Mesh, format: MeshFormat, out: &mut dyn Write) -> io::Result<()> {
    match format {
        MeshFormat::Glb => out.write_all(&isovox_proto::mesh::encode_glb(mesh)),
        MeshFormat::Obj => {
            writeln!(
                out,
                "# isovox marching-cubes mesh: {} vertices, {} triangles",
                mesh.positions.len(),
                mesh.triangles()
            )?;
            for p in &mesh.positions {
                writeln!(out, "v {} {} {}", p[0], p[1], p[2])?;
            }
            for n in &mesh.normals {
                writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
            }
            for t in mesh.indices.chunks_exact(3) {
                let [a, b, c] = [t[0] + 1, t[1] + 1, t[2] + 1];
                writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}")?;
            }
            Ok(())
        }
        MeshFormat::Ply => {
            write!(
                out,
                "ply\nformat binary_little_endian 1.0\ncomment isovox marching-cubes mesh\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n",
                mesh.positions.len(),
                mesh.triangles()
            )?;
            let mut buf = Vec::with_capacity(mesh.positions.len() * 24 + mesh.triangles() * 13);
            for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
                for c in p.iter().chain(n) {
                    buf.extend_from_slice(&c.to_le_bytes());
                }
            }
            for t in mesh.indices.chunks_exact(3) {
                buf.push(3);
                for i in t {
                    buf.extend_from_slice(&i.to_le_bytes());
                }
            }
            out.write_all(&buf)
        }
    }
}
