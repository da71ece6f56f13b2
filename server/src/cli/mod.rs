//! The `isovox` command line (`docs/cli.md`). Each subcommand is a thin layer: parse, call the
//! library, print. Long jobs show a progress bar on a terminal and stay quiet otherwise.
//! (Benchmarks are `isovox-bench`, in the `tools` package.)
//!
//! Standard output is written with [`out!`], never `println!`: `println!` panics when the
//! reader has gone (`isovox inspect f.vod | head -1`), `out!` returns the error, and `main`
//! ends quietly on a broken pipe. The lint below keeps it that way.
#![deny(clippy::print_stdout)]

/// `println!` that returns the write's error instead of panicking on it.
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*)
    }};
}

mod data;
mod edit;
mod formats;
mod mesh;
mod repair;
mod serve;
mod split;
mod voxelize;

use clap::{Parser, Subcommand, ValueEnum};
use isovox_proto::VoxelType;
use isovox_server::progress::Progress;
use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicU64, Ordering};

/// Isovox: large, editable volumes as brick octrees, served over HTTP.
#[derive(Debug, Parser)]
// Not `propagate_version`: `export`, `get` and `edit` have a `--version N` of their own (a
// volume version), which an automatic `--version` flag on every subcommand would clash with.
#[command(name = "isovox", version, about)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub(crate) enum Command {
    /// Serve every VOD 2 file of a data directory over HTTP (a demo world is generated on
    /// first start).
    Serve(Box<serve::ServeArgs>),
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
    /// Verify every record of every version of a file; list what is damaged (exit status 1
    /// when anything is) and which versions are intact.
    Check(repair::CheckArgs),
    /// Write a new file from the newest intact version of a damaged one (the damaged file is
    /// not touched).
    Salvage(repair::SalvageArgs),
}

/// Runs a parsed command line.
///
/// # Errors
/// Whatever the subcommand fails with, with context for the user.
pub(crate) fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Serve(a) => serve::serve(*a),
        Command::Import(a) => data::import(a),
        Command::Export(a) => data::export(a),
        Command::Generate(a) => data::generate(a),
        Command::Inspect(a) => data::inspect(a),
        Command::Edit(a) => edit::edit(a),
        Command::Mesh(a) => mesh::mesh(a),
        Command::Get(a) => data::get(a),
        Command::Compact(a) => data::compact(a),
        Command::Voxelize(a) => voxelize::voxelize_cmd(a),
        Command::Check(a) => repair::check(a),
        Command::Salvage(a) => repair::salvage(a),
    }
}

/// Whether `e` is, at bottom, a write to a pipe whose reader has gone: not a failure of the
/// command (the reader took what it wanted), so `main` ends quietly.
pub(crate) fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
    })
}

/// Voxel type as a command-line value.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum TypeArg {
    /// 8-bit voxels.
    U8,
    /// 16-bit voxels, little endian.
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

/// Opens a VOD 2 file a command names. Its path appears once in any error: the store's I/O
/// errors carry it already ("cannot open PATH: No such file or directory"), its format errors
/// name only the record, so those get it here.
fn open_vod2(path: &std::path::Path) -> anyhow::Result<isovox_server::store::Vod2> {
    isovox_server::store::Vod2::open(path).map_err(|e| match e {
        isovox_server::store::StoreError::Io { .. } => anyhow::Error::new(e),
        e => anyhow::Error::new(e).context(format!("cannot open {}", path.display())),
    })
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

fn parse_dims(s: &str) -> Result<[u32; 3], String> {
    let d = parse_triple::<u32>(s)?;
    if d.contains(&0) {
        return Err(format!("dimensions must be positive, got {s:?}"));
    }
    Ok(d)
}

fn parse_scale(s: &str) -> Result<[f32; 3], String> {
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

/// A progress bar for `what` on stderr, drawn only when a person watches.
fn progress(what: &str) -> Bar {
    Bar {
        what: what.to_string(),
        visible: interactive(),
        total: AtomicU64::new(0),
        done: AtomicU64::new(0),
        drawn: AtomicU64::new(u64::MAX),
    }
}

/// A one-line progress bar, redrawn when its percentage changes.
#[derive(Debug)]
struct Bar {
    what: String,
    visible: bool,
    total: AtomicU64,
    done: AtomicU64,
    /// The percentage last drawn.
    drawn: AtomicU64,
}

impl Bar {
    fn draw(&self, done: u64) {
        let total = self.total.load(Ordering::Relaxed).max(1);
        let percent = (done.min(total) * 100 / total).min(100);
        if !self.visible || self.drawn.swap(percent, Ordering::Relaxed) == percent {
            return;
        }
        let filled = (percent * 40 / 100) as usize;
        let bar = format!("{}{}", "=".repeat(filled), " ".repeat(40 - filled));
        let mut err = std::io::stderr().lock();
        let _ = write!(
            err,
            "\r{:>12} [{bar}] {percent:>3}% {done}/{total}",
            self.what
        );
        let _ = err.flush();
    }
}

impl Progress for Bar {
    fn start(&self, total: u64) {
        self.total.store(total, Ordering::Relaxed);
        self.draw(self.done.load(Ordering::Relaxed));
    }

    fn advance(&self, steps: u64) {
        self.draw(self.done.fetch_add(steps, Ordering::Relaxed) + steps);
    }

    fn finish(&self) {
        if self.visible {
            // Clear the line: the command's own output follows.
            eprint!("\r\x1b[2K");
        }
    }
}
