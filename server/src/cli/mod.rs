//! The `isovox` command line (`spec/cli.md`). Each subcommand is a thin layer: parse, call the
//! library, print. Long jobs show a progress bar on a terminal and stay quiet otherwise.

mod bench;
mod bench_edits;
mod bench_http;
mod bench_icvg;
mod bench_memory;
mod bench_mesh;
mod bench_voxelize;
pub(crate) mod data;
pub mod edit;
mod formats;
mod mesh;
mod serve;
mod voxelize;

use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use isovox_proto::VoxelType;
use std::io::IsTerminal;
use std::path::PathBuf;

/// Isovox: large, editable volumes as brick octrees, served over HTTP.
#[derive(Debug, Parser)]
// Not `propagate_version`: `export`, `get` and `edit` have a `--version N` of their own (a
// volume version), which an automatic `--version` flag on every subcommand would clash with.
#[command(name = "isovox", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Serve every VOD 2 file of a data directory over HTTP (a demo world is generated on
    /// first start).
    Serve(serve::ServeArgs),
    /// Import a RAW, RAWVOX or VOD 1 file into VOD 2 (or write VOD 1 with --format vod1), or
    /// OME-Zarr, Zarr, Neuroglancer precomputed, NIfTI-1 or a TIFF stack into VOD 2.
    Import(data::ImportArgs),
    /// Export a level (or a region of it) to RAW/RAWVOX, or the whole volume to VOD 1, OME-Zarr
    /// or Neuroglancer precomputed.
    Export(data::ExportArgs),
    /// Generate a synthetic data set (the thesis's Table 2) straight into a VOD 2 file.
    Generate(data::GenerateArgs),
    /// Apply an ICVG edit (JSON request, or a shorthand primitive) as a new version.
    Edit(edit::EditArgs),
    /// Mesh a level (or the adaptive LOD around a camera) with marching cubes to GLB, OBJ or PLY.
    Mesh(mesh::MeshArgs),
    /// Show a file's header, levels, bricks by codec, compression ratio and garbage bytes.
    Inspect(data::InspectArgs),
    /// Write one brick of one level, decoded (raw voxels), to a file or stdout.
    Get(data::GetArgs),
    /// Voxelize a watertight triangle mesh (STL, OBJ, PLY, glTF/GLB) into a volume.
    Voxelize(voxelize::VoxelizeArgs),
    /// Rewrite a file with only its head version (drops older versions and unreferenced
    /// bricks); run it on a file no server is writing (a server compacts with
    /// POST /v1/volumes/{name}/compact).
    Compact(data::CompactArgs),
    /// Benchmarks that print Markdown tables next to the papers' figures.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

/// Runs a parsed command line.
///
/// # Errors
/// Whatever the subcommand fails with, with context for the user.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Serve(a) => serve::serve(a),
        Command::Import(a) => data::import(a),
        Command::Export(a) => data::export(a),
        Command::Generate(a) => data::generate(a),
        Command::Inspect(a) => data::inspect(a),
        Command::Edit(a) => edit::edit(a),
        Command::Mesh(a) => mesh::mesh(a),
        Command::Get(a) => data::get(a),
        Command::Compact(a) => data::compact(a),
        Command::Voxelize(a) => voxelize::voxelize_cmd(a),
        Command::Bench(b) => bench::run(b),
    }
}

/// Voxel type as a command-line value.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum TypeArg {
    U8,
    U16,
}

impl From<TypeArg> for VoxelType {
    fn from(t: TypeArg) -> Self {
        match t {
            TypeArg::U8 => VoxelType::U8,
            TypeArg::U16 => VoxelType::U16,
        }
    }
}

/// Parses `A,B,C` into three numbers.
fn parse_triple<T: std::str::FromStr>(s: &str) -> Result<[T; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(format!("expected three comma-separated values, got {s:?}"));
    }
    let mut out = Vec::with_capacity(3);
    for p in parts {
        out.push(
            p.parse::<T>()
                .map_err(|_| format!("{p:?} is not a valid number"))?,
        );
    }
    out.try_into()
        .map_err(|_| "expected three values".to_string())
}

pub(crate) fn parse_dims(s: &str) -> Result<[u32; 3], String> {
    let d = parse_triple::<u32>(s)?;
    if d.contains(&0) {
        return Err(format!("dimensions must be positive, got {s:?}"));
    }
    Ok(d)
}

pub(crate) fn parse_scale(s: &str) -> Result<[f32; 3], String> {
    let v = parse_triple::<f32>(s)?;
    if v.iter().any(|x| !x.is_finite() || *x <= 0.0) {
        return Err(format!(
            "voxel scale must be positive and finite, got {s:?}"
        ));
    }
    Ok(v)
}

/// Whether progress bars should be drawn: only when a person is watching.
fn interactive() -> bool {
    std::io::stderr().is_terminal() && std::io::stdout().is_terminal()
}

/// A progress bar for `what` that draws on a terminal and is hidden otherwise.
pub(crate) fn progress(what: &str) -> ProgressBar {
    if !interactive() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::stderr());
    let style =
        ProgressStyle::with_template("{msg:>12} [{bar:40}] {percent:>3}% {pos}/{len} ({eta} left)")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_message(what.to_string());
    bar
}

/// A path with a suffix appended (for temporaries beside an output).
pub(crate) fn sibling(path: &std::path::Path, suffix: &str) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}
