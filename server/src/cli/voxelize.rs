//! `isovox voxelize`: a triangle mesh (STL, OBJ, PLY, glTF/GLB) into a VOD 2 volume.

use super::{data, TypeArg};
use anyhow::Context;
use clap::{Args, ValueEnum};
use isovox_proto::VolumeLayout;
use isovox_server::progress::Progress;
use isovox_server::store::codec::Compression;
use isovox_server::store::DenseGrid;
use isovox_server::voxelize::{load::load_model, voxelize, Fill, Options};
use std::path::PathBuf;

#[derive(Debug, Clone, Copy, ValueEnum)]
pub(crate) enum FillArg {
    /// Fraction of the supersampled voxel centres inside, as a density (smooth surfaces).
    Density,
    /// Binary: the voxel's centre is inside.
    Center,
    /// Binary: the whole voxel is inside (conservative under-estimate).
    Inside,
    /// Binary: any part of the voxel is inside (conservative over-estimate).
    Touched,
}

#[derive(Debug, Args)]
pub(crate) struct VoxelizeArgs {
    /// The model: .stl (binary or ASCII), .obj, .ply, .gltf or .glb; it must be watertight.
    pub model: PathBuf,
    /// Output VOD 2 file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Voxels along the model's longest bounding-box side.
    #[arg(long)]
    pub size: u32,
    /// Samples per voxel and axis for the density (2: the paper's 2x2x2 box filter).
    #[arg(long, default_value_t = 2)]
    pub supersample: u32,
    /// How a voxel's value is decided from the model.
    #[arg(long, value_enum, default_value_t = FillArg::Density)]
    pub fill: FillArg,
    /// Voxels of L around the model, so its surface is closed inside the volume.
    #[arg(long, default_value_t = 2)]
    pub padding: u32,
    /// Voxel type: u8 (values 0..255) or u16 (0..65535, little endian).
    #[arg(long = "type", value_enum, default_value_t = TypeArg::U8)]
    pub voxel_type: TypeArg,
    /// Brick edge in voxels, a power of two.
    #[arg(long, default_value_t = 32)]
    pub brick: u32,
    /// Voxelize even if some edges are used by an odd number of triangles (parity decides).
    #[arg(long)]
    pub allow_open: bool,
}

pub(super) fn voxelize_cmd(a: VoxelizeArgs) -> anyhow::Result<()> {
    let start = std::time::Instant::now();
    let mesh = load_model(&a.model)?;
    let loaded = start.elapsed();
    let options = Options {
        size: a.size,
        supersample: a.supersample,
        padding: a.padding,
        fill: match a.fill {
            FillArg::Density => Fill::Density,
            FillArg::Center => Fill::Center,
            FillArg::Inside => Fill::Inside,
            FillArg::Touched => Fill::Touched,
        },
        voxel_type: a.voxel_type.into(),
        allow_open: a.allow_open,
    };
    let bar = super::progress("voxelizing");
    bar.start(1);
    let v = voxelize(&mesh, &options);
    bar.finish();
    let v = v.with_context(|| format!("cannot voxelize {}", a.model.display()))?;
    let layout = VolumeLayout::new(v.dims, a.brick, options.voxel_type)?;
    let grid = DenseGrid::new(v.dims, options.voxel_type, a.brick, &v.bytes);
    let scale = [v.voxel_size as f32; 3];
    data::build_to(
        &a.output,
        &layout,
        scale,
        &grid,
        Compression::default(),
        data::VodFormat::Vod2,
    )?;
    let r = v.report;
    let secs = r.solid_time.as_secs_f64();
    eprintln!(
        "{}: {} triangles (read in {:.2} s) -> {}x{}x{} voxels; solid {:.2} s ({:.1} M triangles/s, {:.0} M samples/s, {} bits per sample), fill {:.2} s; {:.1}% of samples inside",
        a.model.display(),
        r.triangles,
        loaded.as_secs_f64(),
        v.dims[0],
        v.dims[1],
        v.dims[2],
        secs,
        r.triangles as f64 / secs / 1e6,
        r.samples as f64 / secs / 1e6,
        (r.bit_bytes as f64 * 8.0 / r.samples as f64).round(),
        r.fill_time.as_secs_f64(),
        100.0 * r.samples_inside as f64 / r.samples as f64
    );
    Ok(())
}
