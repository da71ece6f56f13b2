//! `isovox import` from the field's formats (OME-Zarr and Zarr v2/v3, Neuroglancer
//! precomputed, NIfTI-1, TIFF stacks) and `isovox export --format zarr|precomputed`: parse,
//! call `isovox_server::formats`, print.

use super::data::{ExportArgs, ImportArgs, VodFormat};
use super::progress;
use anyhow::{bail, Context};
use clap::Args;
use isovox_server::formats::export::export_view;
use isovox_server::formats::import::convert::{parse_pair, parse_percentiles};
use isovox_server::formats::import::{
    detect, import as import_input, ChannelInput, ImportOptions, InputFormat,
};
use isovox_server::formats::ViewKind;
use isovox_server::store::{BuildOptions, Snapshot};
use std::sync::Arc;

/// The options of `isovox import` that only the field's formats take.
#[derive(Debug, Clone, Args)]
pub(crate) struct FormatImportArgs {
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
    /// A label map of the image's shape (any of the formats above) imported beside it as the
    /// attribute channel NAME, ids kept as they are: `--channel label=seg.nii.gz`. Repeatable.
    #[arg(long = "channel", value_name = "NAME=INPUT")]
    pub channels: Vec<String>,
}

fn parse_format(s: &str) -> Result<InputFormat, String> {
    s.parse()
}

/// The field's format `a.input()` is in (`--from`, or detected); `None` when it is in none of
/// them (a RAW or VOD file, for the other importers).
pub(super) fn input_format(a: &ImportArgs) -> anyhow::Result<Option<InputFormat>> {
    if let Some(f) = a.formats.from {
        return Ok(Some(f));
    }
    let input = a.input().to_string_lossy();
    detect(&input).with_context(|| format!("cannot read {input}"))
}

/// The options of an import of `a` from the field's formats (also each part of a split one).
pub(super) fn import_options(a: &ImportArgs, format: InputFormat) -> anyhow::Result<ImportOptions> {
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
    Ok(ImportOptions {
        brick: a.brick,
        build: BuildOptions {
            compression: a.compression.compression(),
            progress: Arc::new(progress("importing")),
        },
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
        channels: a
            .formats
            .channels
            .iter()
            .map(|c| channel_input(c))
            .collect::<anyhow::Result<_>>()?,
    })
}

/// Imports `a.input`, in `format`, into a new VOD 2 file.
pub(super) fn import(a: &ImportArgs, format: InputFormat) -> anyhow::Result<()> {
    let input = a.input().to_string_lossy();
    let options = import_options(a, format)?;
    let report = import_input(&input, format, &a.output, &options, &progress("sampling"))
        .with_context(|| format!("cannot import {input}"))?;
    out!("{}: {report}", a.output.display())?;
    Ok(())
}

/// `NAME=INPUT` of `--channel`, its format detected.
fn channel_input(arg: &str) -> anyhow::Result<ChannelInput> {
    let (name, input) = arg
        .split_once('=')
        .filter(|(n, i)| !n.is_empty() && !i.is_empty())
        .with_context(|| format!("--channel {arg:?}: NAME=INPUT expected (label=seg.nii.gz)"))?;
    let format = detect(input)
        .with_context(|| format!("cannot read {input}"))?
        .with_context(|| {
            format!("--channel {name}: {input} is in none of the formats a label map may be in (Zarr, precomputed, NIfTI, TIFF)")
        })?;
    Ok(ChannelInput {
        name: name.to_string(),
        input: input.to_string(),
        format,
    })
}

/// Writes view `kind` of `snap` as a directory tree (every level of the whole volume).
pub(super) fn export(a: &ExportArgs, snap: &Snapshot, kind: ViewKind) -> anyhow::Result<()> {
    if a.region.is_some() || a.level != 0 {
        bail!(
            "--format {} writes every level of the whole volume; --level and --region apply to raw and rawvox",
            kind.segment()
        );
    }
    let name = a
        .input
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "volume".into());
    let report = export_view(snap, kind, &name, &a.output, &progress("exporting"))
        .with_context(|| format!("cannot export {} as {}", a.input.display(), kind.segment()))?;
    out!(
        "{}: {} view of version {}: {} chunk files ({} chunks of fill values left out), {} bytes",
        a.output.display(),
        kind.segment(),
        snap.version,
        report.chunks,
        report.absent,
        report.bytes
    )?;
    Ok(())
}
