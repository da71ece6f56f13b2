//! `isovox mesh`: mesh a whole level, or the thesis's adaptive LOD around a camera (tiles of
//! neighbouring levels stitched without cracks), to a file.

use super::progress;
use anyhow::{bail, Context};
use clap::Args;
use isovox_server::mesh::files::{write_mesh, MeshFormat};
use isovox_server::mesh::level::{balanced_tiles, level_tiles, mesh_stitched, mesh_tiles, weld};
use isovox_server::mesh::tile::iso_value;
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub(crate) struct MeshArgs {
    /// A VOD 2 file.
    pub input: PathBuf,
    /// Output: .glb, .obj or .ply.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Level of detail to mesh.
    #[arg(long, default_value_t = 0)]
    pub level: u8,
    /// Iso value (default S - 0.5).
    #[arg(long)]
    pub iso: Option<f32>,
    /// Adaptive LOD: the camera position (world units) ...
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    pub camera: Option<Vec<f32>>,
    /// ... and the radius within which each level is used: level 0 within R0, level 1 within
    /// R1, ..., the coarsest level beyond the last.
    #[arg(long, value_delimiter = ',')]
    pub radii: Option<Vec<f32>>,
    /// Mesh this version instead of the newest.
    #[arg(long)]
    pub version: Option<u64>,
}

pub(super) fn mesh(a: MeshArgs) -> anyhow::Result<()> {
    let format = MeshFormat::from_path(&a.output).with_context(|| {
        format!(
            "{}: the output must end in .glb, .obj or .ply",
            a.output.display()
        )
    })?;
    let vod = super::open_vod2(&a.input)?;
    let snap = match a.version {
        Some(v) => vod.version(v)?,
        None => vod.head(),
    };
    let layout = snap.layout();
    let iso = iso_value(a.iso, layout.voxel_type()).map_err(anyhow::Error::msg)?;
    let (tiles, stitched) = match (&a.camera, &a.radii) {
        (Some(c), Some(r)) => {
            if c.len() != 3 {
                bail!("--camera takes X,Y,Z");
            }
            (balanced_tiles(&snap, [c[0], c[1], c[2]], r), true)
        }
        (None, None) => {
            if a.level >= layout.levels() {
                bail!(
                    "level {} out of range: the volume has levels 0..{}",
                    a.level,
                    layout.levels() - 1
                );
            }
            (level_tiles(&snap, a.level), false)
        }
        _ => bail!("--camera and --radii go together"),
    };
    let start = Instant::now();
    let raw = if stitched {
        mesh_stitched(&snap, &tiles, iso, &progress("meshing"))?
    } else {
        mesh_tiles(&snap, &tiles, iso, &progress("meshing"))?
    };
    let mesh = weld(&raw);
    let elapsed = start.elapsed();
    let tmp = isovox_server::store::build::sibling(&a.output, ".isovox-tmp");
    let mut out = BufWriter::new(
        std::fs::File::create(&tmp).with_context(|| format!("cannot create {}", tmp.display()))?,
    );
    write_mesh(&mesh, format, &mut out)?;
    out.flush()?;
    drop(out);
    std::fs::rename(&tmp, &a.output)?;
    eprintln!(
        "{}: {} tiles, {} triangles, {} vertices in {:.0} ms",
        a.output.display(),
        tiles.len(),
        mesh.triangles(),
        mesh.positions.len(),
        elapsed.as_secs_f64() * 1e3
    );
    Ok(())
}
