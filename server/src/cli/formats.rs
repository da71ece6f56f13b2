//! `isovox import` from the field's formats (OME-Zarr and Zarr v2/v3, Neuroglancer
//! precomputed, NIfTI-1, TIFF stacks) and `isovox export --format zarr|precomputed`: parse,
//! call `crate::formats`, print.

use super::data::{ExportArgs, ExportFormat, ImportArgs, VodFormat};
use super::progress;
use crate::formats::export::export_view;
use crate::formats::import::convert::{parse_pair, parse_percentiles};
use crate::formats::import::{detect, import as import_input, ImportOptions, InputFormat};
use crate::formats::ViewKind;
use crate::store::Vod2;
use anyhow::{bail, Context};
use clap::Args;

/// The options of `isovox import` that only the field's formats take.
#[derive(Debug, Clone, Args)]
pub struct FormatImportArgs {
    /// Read the input as this format instead of detecting it: zarr, precomputed, nifti, tiff.
    #[arg(long = "from", value_parser = parse_format)]
    pub from: Option<InputFormat>,
    /// Map voxel types other than u8/u16 (i8, i16, u32, i32, f32, f64) linearly from LO..HI onto
    /// the volume's type (--type; default u8 for i8, u16 for the rest).
    #[arg(long, allow_hyphen_values = true, value_name = "LO,HI")]
    pub window: Option<String>,
    /// Without --window: the window is these percentiles of the input (a first pass samples it).
    #[arg(long, default_value = "0.5,99.5", value_name = "LO,HI")]
    pub percentiles: String,
}

fn parse_format(s: &str) -> Result<InputFormat, String> {
    s.parse()
}

/// Runs the import when the input is in one of the field's formats; `None` leaves it to the
/// RAW and VOD importers.
pub(crate) fn import(a: &ImportArgs) -> Option<anyhow::Result<()>> {
    let input = a.input.to_string_lossy().into_owned();
    let format = match a.formats.from {
        Some(f) => f,
        None => match detect(&input) {
            Ok(Some(f)) => f,
            Ok(None) => return None,
            Err(e) => return Some(Err(e).context(format!("cannot read {input}"))),
        },
    };
    Some(run_import(a, &input, format))
}

fn run_import(a: &ImportArgs, input: &str, format: InputFormat) -> anyhow::Result<()> {
    if a.format != VodFormat::Vod2 {
        bail!(
            "imports from {} write VOD 2 (convert to VOD 1 with a second import)",
            format.name()
        );
    }
    if a.dims.is_some() {
        bail!(
            "--dims is for RAW files; a {} input carries its shape",
            format.name()
        );
    }
    let options = ImportOptions {
        brick: a.brick,
        compression: a.compression.compression(),
        target: a.voxel_type.map(Into::into),
        window: a
            .formats
            .window
            .as_deref()
            .map(|w| parse_pair(w, "--window"))
            .transpose()?,
        percentiles: parse_percentiles(&a.formats.percentiles)?,
        // The default 1,1,1 means "as the input says".
        voxel_scale: (a.scale != [1.0; 3]).then_some(a.scale),
    };
    let scan_bar = progress("sampling");
    let bar = progress("importing");
    let report = import_input(
        input,
        format,
        &a.output,
        &options,
        &|done, total| {
            scan_bar.set_length(total);
            scan_bar.set_position(done);
        },
        &|done, total| {
            bar.set_length(total);
            bar.set_position(done);
        },
    )
    .with_context(|| format!("cannot import {input}"))?;
    scan_bar.finish_and_clear();
    bar.finish_and_clear();
    println!("{}: {report}", a.output.display());
    Ok(())
}

/// Runs the export when a view's format is asked; `None` leaves it to the other exporters.
pub(crate) fn export(a: &ExportArgs) -> Option<anyhow::Result<()>> {
    let kind = match a.format {
        ExportFormat::Zarr => ViewKind::Zarr,
        ExportFormat::Precomputed => ViewKind::Precomputed,
        _ => return None,
    };
    Some(run_export(a, kind))
}

fn run_export(a: &ExportArgs, kind: ViewKind) -> anyhow::Result<()> {
    if a.region.is_some() || a.level != 0 {
        bail!("--format {} writes every level of the whole volume; --level and --region apply to raw and rawvox", kind.segment());
    }
    let vod = Vod2::open(&a.input).with_context(|| format!("cannot open {}", a.input.display()))?;
    let snap = match a.version {
        Some(v) => vod.version(v)?,
        None => vod.head(),
    };
    let name = a
        .input
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "volume".into());
    let bar = progress("exporting");
    let report = export_view(&snap, kind, &name, &a.output, &|done, total| {
        bar.set_length(total);
        bar.set_position(done);
    })
    .with_context(|| format!("cannot export {} as {}", a.input.display(), kind.segment()))?;
    bar.finish_and_clear();
    println!(
        "{}: {} view of version {}: {} chunk files ({} chunks of fill values left out), {} bytes",
        a.output.display(),
        kind.segment(),
        snap.version,
        report.chunks,
        report.absent,
        report.bytes
    );
    Ok(())
}
