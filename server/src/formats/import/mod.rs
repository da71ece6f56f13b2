//! Imports from the formats users have: OME-Zarr and Zarr v2/v3 arrays, Neuroglancer
//! precomputed, NIfTI-1 and TIFF stacks, into a VOD 2 file.
//!
//! Every reader is a [`PlaneSource`]; [`import()`] builds the volume from it one slab at a time
//! ([`SlabSource`]), so memory holds one row of bricks of the input, not the input. Types other
//! than u8 and u16 are converted through a window (given, or from percentiles of a first pass
//! over the input; see [`convert`]). The file is written beside the output and renamed into
//! place only when the whole input was read without error.
//!
//! Layout: [`location`] (local path or http URL), [`planes`] (the plane stream and the slab
//! source), [`convert`] (types and windows), one module per format.

pub mod codecs;
pub mod convert;
pub mod location;
pub mod nifti;
pub mod planes;
pub mod precomputed;
pub mod tiff;
pub mod zarr;

use self::convert::{number, Conversion, DType, Sampler};
use self::location::Location;
pub use self::planes::{PlaneSource, SlabSource};
use super::FormatsError;
use crate::progress::Progress;
use crate::store::build::build_streams;
use crate::store::build::sibling;
use crate::store::{BrickSource, BuildOptions};
use isovox_proto::channel::ChannelInfo;
use isovox_proto::vod2::FileHeader;
use isovox_proto::{VolumeLayout, VoxelType};
use std::path::Path;
use std::str::FromStr;
use std::time::{Duration, Instant};

/// The formats imports read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputFormat {
    /// OME-Zarr, or a Zarr v2 or v3 array.
    Zarr,
    /// Neuroglancer precomputed.
    Precomputed,
    /// NIfTI-1 (`.nii`, `.nii.gz`).
    Nifti,
    /// A multi-page TIFF file or a folder of TIFF files.
    Tiff,
}

impl InputFormat {
    /// The format's name on the command line (`--from`).
    pub fn name(self) -> &'static str {
        match self {
            InputFormat::Zarr => "zarr",
            InputFormat::Precomputed => "precomputed",
            InputFormat::Nifti => "nifti",
            InputFormat::Tiff => "tiff",
        }
    }
}

impl FromStr for InputFormat {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s {
            "zarr" => InputFormat::Zarr,
            "precomputed" => InputFormat::Precomputed,
            "nifti" => InputFormat::Nifti,
            "tiff" => InputFormat::Tiff,
            other => {
                return Err(format!(
                    "unknown input format {other:?} (zarr, precomputed, nifti or tiff)"
                ))
            }
        })
    }
}

/// Which of these formats `input` is in, by its prefix (`zarr://`, `precomputed://`), its
/// metadata files (`zarr.json`, `.zgroup`, `.zarray`, `info`) or its first bytes (NIfTI,
/// TIFF). `None`: none of them (a RAW or VOD file, for the other importers).
///
/// # Errors
/// An http URL that holds none of them, or a location that cannot be read.
pub fn detect(input: &str) -> Result<Option<InputFormat>, FormatsError> {
    let (prefixed, rest) = location::strip_prefix(input);
    if let Some(name) = prefixed {
        return InputFormat::from_str(name)
            .map(Some)
            .map_err(FormatsError::BadInput);
    }
    let location = Location::parse(rest)?;
    if let Location::Local(path) = &location {
        if path.is_file() {
            return Ok(if nifti::sniff(path) || nifti::named(path) {
                Some(InputFormat::Nifti)
            } else if tiff::sniff(path) {
                Some(InputFormat::Tiff)
            } else {
                None
            });
        }
        if !path.is_dir() {
            return Ok(None);
        }
    }
    if zarr::sniff(&location)? {
        return Ok(Some(InputFormat::Zarr));
    }
    if location.get("info", 16 << 20)?.is_some() {
        return Ok(Some(InputFormat::Precomputed));
    }
    match &location {
        Location::Local(_) => Ok(Some(InputFormat::Tiff)),
        Location::Http { base, .. } => Err(FormatsError::input(format!(
            "{base}: neither zarr.json, .zgroup, .zarray nor info answered: not a Zarr or precomputed volume"
        ))),
    }
}

/// Opens `input` (a path or URL, optionally with a format prefix) as `format`.
///
/// # Errors
/// What the format's reader fails with when opening.
pub fn open(input: &str, format: InputFormat) -> Result<Box<dyn PlaneSource>, FormatsError> {
    let (_, rest) = location::strip_prefix(input);
    let location = Location::parse(rest)?;
    let local = |what: &str| {
        location
            .path()
            .map(Path::to_path_buf)
            .ok_or_else(|| FormatsError::input(format!("{rest}: {what} is read from a local path")))
    };
    Ok(match format {
        InputFormat::Zarr => Box::new(zarr::ZarrInput::open(&location)?),
        InputFormat::Precomputed => Box::new(precomputed::PrecomputedInput::open(location)?),
        InputFormat::Nifti => Box::new(nifti::NiftiInput::open(&local("NIfTI")?)?),
        InputFormat::Tiff => Box::new(tiff::TiffInput::open(&local("a TIFF stack")?)?),
    })
}

/// How to import.
#[derive(Debug, Clone)]
pub struct ImportOptions {
    /// The brick edge of the volume, in voxels.
    pub brick: u32,
    /// How bricks are compressed, and the progress of the build (bricks written).
    pub build: BuildOptions,
    /// The volume's type; `None`: u8 for u8 and i8 inputs, u16 for the rest.
    pub target: Option<VoxelType>,
    /// The window other types are mapped through; `None`: from `percentiles`.
    pub window: Option<(f64, f64)>,
    /// Percentiles (0..100) the window is taken from when none is given.
    pub percentiles: (f64, f64),
    /// The voxel scale; `None`: the input's (1, 1, 1 when it records none).
    pub voxel_scale: Option<[f32; 3]>,
    /// Label maps imported beside the image as attribute channels (`docs/channels.md`).
    pub channels: Vec<ChannelInput>,
}

/// A label map to import as an attribute channel: `--channel NAME=INPUT`.
#[derive(Debug, Clone)]
pub struct ChannelInput {
    /// The channel's name (`label`, `material`, ...).
    pub name: String,
    /// Where it is (a path or http URL), in any format an image may be in.
    pub input: String,
    /// Its format.
    pub format: InputFormat,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            brick: 32,
            build: BuildOptions::default(),
            target: None,
            window: None,
            percentiles: (0.5, 99.5),
            voxel_scale: None,
            channels: Vec::new(),
        }
    }
}

/// How values were converted, for the user.
#[derive(Debug, Clone, PartialEq)]
pub enum ConversionNote {
    /// Stored as they were.
    None,
    /// Through the window given.
    Window {
        /// The value mapped to 0.
        lo: f64,
        /// The value mapped to the type's largest.
        hi: f64,
    },
    /// Through the window of these percentiles of a sample of `sampled` values.
    Percentiles {
        /// The value mapped to 0.
        lo: f64,
        /// The value mapped to the type's largest.
        hi: f64,
        /// The percentiles `lo` and `hi` are.
        percentiles: (f64, f64),
        /// Values in the sample.
        sampled: usize,
    },
}

/// What an import did.
#[derive(Debug, Clone)]
pub struct ImportReport {
    /// The input's format.
    pub format: InputFormat,
    /// Voxels per axis (x, y, z).
    pub dims: [u32; 3],
    /// The input's voxel type.
    pub input_type: DType,
    /// The volume's voxel type.
    pub voxel_type: VoxelType,
    /// World size of one voxel (x, y, z).
    pub voxel_scale: [f32; 3],
    /// How values were converted.
    pub conversion: ConversionNote,
    /// The attribute channels imported beside the image.
    pub channels: Vec<ChannelInfo>,
    /// Bytes of input voxels read (once; a percentile pass reads them twice).
    pub input_bytes: u64,
    /// Bytes of the VOD 2 file written.
    pub file_bytes: u64,
    /// How long the import took.
    pub elapsed: Duration,
}

impl std::fmt::Display for ImportReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [x, y, z] = self.dims;
        write!(
            f,
            "{} volume of {x} x {y} x {z} {} voxels stored as {}",
            self.format.name(),
            self.input_type,
            self.voxel_type
        )?;
        match &self.conversion {
            ConversionNote::None => {}
            ConversionNote::Window { lo, hi } => {
                write!(
                    f,
                    ", mapped from the window {}..{} (--window)",
                    number(*lo),
                    number(*hi)
                )?;
            }
            ConversionNote::Percentiles {
                lo,
                hi,
                percentiles,
                sampled,
            } => write!(
                f,
                ", mapped from the window {}..{}: the {}th and {}th percentiles of {sampled} voxels sampled evenly (--window LO,HI to choose)",
                number(*lo),
                number(*hi),
                percentiles.0,
                percentiles.1
            )?,
        }
        for c in &self.channels {
            write!(
                f,
                "; channel {} ({}{})",
                c.name,
                c.voxel_type,
                if c.sparse { ", sparse" } else { "" }
            )?;
        }
        let s = self.elapsed.as_secs_f64();
        write!(
            f,
            "; voxel scale {:?}; {} bytes in {s:.2} s ({:.1} MB/s of input)",
            self.voxel_scale,
            self.file_bytes,
            self.input_bytes as f64 / 1e6 / s.max(1e-9)
        )
    }
}

/// Chooses how `dtype` values become `target`, reading the input once more (through `reopen`)
/// for percentiles when no window is given.
fn choose_conversion(
    dtype: DType,
    target: VoxelType,
    options: &ImportOptions,
    dims: [u32; 3],
    reopen: &dyn Fn() -> Result<Box<dyn PlaneSource>, FormatsError>,
    progress: &dyn Progress,
) -> Result<(Conversion, ConversionNote), FormatsError> {
    if let Some((lo, hi)) = options.window {
        return Ok((
            Conversion::Window { lo, hi, target },
            ConversionNote::Window { lo, hi },
        ));
    }
    if dtype.is(target) {
        return Ok((Conversion::Identity(target), ConversionNote::None));
    }
    let total = dims.iter().map(|&d| u64::from(d)).product();
    let mut sampler = Sampler::new(total);
    let mut runs = planes::PlaneRuns::new(reopen()?);
    let step = runs.source().depth().max(1);
    progress.start(u64::from(dims[2]));
    let sampled = (|| {
        let mut z = 0;
        while z < dims[2] {
            let z1 = (z + step).min(dims[2]);
            sampler.take(dtype, runs.planes(z, z1)?);
            progress.advance(u64::from(z1 - z));
            z = z1;
        }
        Ok::<_, FormatsError>(())
    })();
    progress.finish();
    sampled?;
    let (lo, hi, sampled) = sampler.window(options.percentiles)?;
    Ok((
        Conversion::Window { lo, hi, target },
        ConversionNote::Percentiles {
            lo,
            hi,
            percentiles: options.percentiles,
            sampled,
        },
    ))
}

/// The label maps `inputs` as channels of a volume of `layout`: their descriptions and their
/// sources. A map must have the image's shape; its values are kept as ids, in the channel type
/// [`DType::label_type`] gives (a value past it is an error). A `material` channel counts 0
/// like any value in its coarser levels; every other name is a segmentation's, where 0
/// (unlabelled) loses (`sparse`).
///
/// # Errors
/// A map cannot be opened, has another shape, or the names are not valid channel names.
fn open_channels(
    inputs: &[ChannelInput],
    layout: &VolumeLayout,
) -> Result<(Vec<ChannelInfo>, Vec<SlabSource>), FormatsError> {
    let mut infos = Vec::new();
    let mut sources = Vec::new();
    for c in inputs {
        let source = open(&c.input, c.format)?;
        if source.dims() != layout.dims() {
            return Err(FormatsError::input(format!(
                "channel {}: {} is {:?} voxels, the image {:?}; a label map has the image's shape",
                c.name,
                c.input,
                source.dims(),
                layout.dims()
            )));
        }
        let voxel_type = DType::label_type(source.dtype());
        let channel_layout = layout.with_voxel_type(voxel_type);
        infos.push(ChannelInfo {
            sparse: c.name != "material",
            ..ChannelInfo::new(&c.name, voxel_type)
        });
        sources.push(SlabSource::new(
            channel_layout,
            source,
            Conversion::Labels(voxel_type),
        )?);
    }
    isovox_proto::channel::validate_channels(&infos)
        .map_err(|e| FormatsError::BadArgument(format!("--channel: {e}")))?;
    Ok((infos, sources))
}

/// An input opened for a build: the header of the volume it makes and the sources of its
/// streams (density, then each `--channel`), with what the report says about it.
#[derive(Debug)]
pub struct Prepared {
    /// The new volume's header (its channels listed).
    pub header: FileHeader,
    sources: Vec<SlabSource>,
    format: InputFormat,
    dims: [u32; 3],
    input_type: DType,
    voxel_type: VoxelType,
    voxel_scale: [f32; 3],
    conversion: ConversionNote,
    channels: Vec<ChannelInfo>,
}

impl Prepared {
    /// The level-0 source of each stream, in stream order (density first).
    pub fn sources(&self) -> Vec<&dyn BrickSource> {
        self.sources.iter().map(|s| s as &dyn BrickSource).collect()
    }

    /// Joins every reader.
    ///
    /// # Errors
    /// The first read that failed during the build.
    pub fn finish(self) -> Result<(), FormatsError> {
        let finished: Vec<_> = self.sources.into_iter().map(SlabSource::finish).collect();
        finished.into_iter().find(|r| r.is_err()).unwrap_or(Ok(()))
    }
}

/// Opens `input` (a path or http URL) as `format` for a build: chooses its conversion (`scan`
/// is told the progress of a percentile pass) and opens its channels. An import and each part
/// of a split import ([`crate::store::remote::parts`]) start here, so they agree on the header
/// and the voxels.
///
/// # Errors
/// The input cannot be read or is malformed or unsupported.
pub fn prepare(
    input: &str,
    format: InputFormat,
    options: &ImportOptions,
    scan: &dyn Progress,
) -> Result<Prepared, FormatsError> {
    let source = open(input, format)?;
    let dims = source.dims();
    let dtype = source.dtype();
    let target = options.target.unwrap_or(dtype.default_target());
    let voxel_scale = options
        .voxel_scale
        .or(source.voxel_scale())
        .unwrap_or([1.0; 3]);
    let layout = VolumeLayout::new(dims, options.brick, target)
        .map_err(|e| FormatsError::input(format!("{input}: {e}")))?;
    let (conversion, note) =
        choose_conversion(dtype, target, options, dims, &|| open(input, format), scan)?;
    let slabs = SlabSource::new(layout.clone(), source, conversion)?;
    let (channels, channel_slabs) = open_channels(&options.channels, &layout)?;
    let header = if channels.is_empty() {
        FileHeader::new(layout, voxel_scale)
    } else {
        FileHeader::with_channels(layout, voxel_scale, channels.clone())
            .map_err(|e| FormatsError::BadArgument(e.to_string()))?
    };
    Ok(Prepared {
        header,
        sources: std::iter::once(slabs).chain(channel_slabs).collect(),
        format,
        dims,
        input_type: dtype,
        voxel_type: target,
        voxel_scale,
        conversion: note,
        channels,
    })
}

/// Imports `input` (a path or http URL) as `format` into a new VOD 2 file at `output`.
/// `scan` is told the progress of a percentile pass (planes read), `options.build.progress`
/// that of the import (bricks written).
///
/// # Errors
/// The input cannot be read or is malformed or unsupported (nothing is left at `output`
/// then), or the file cannot be written.
pub fn import(
    input: &str,
    format: InputFormat,
    output: &Path,
    options: &ImportOptions,
    scan: &dyn Progress,
) -> Result<ImportReport, FormatsError> {
    let start = Instant::now();
    let prepared = prepare(input, format, options, scan)?;
    let tmp = sibling(output, ".isovox-tmp");
    // A volume without channels is built exactly as `build_vod2` builds it: its header is
    // `FileHeader::new`, and `build_vod2` is `build_streams` with that header.
    let built = build_streams(
        &tmp,
        prepared.header.clone(),
        &prepared.sources(),
        &options.build,
    );
    let dims = prepared.dims;
    let mut summary = ImportReport {
        format: prepared.format,
        dims,
        input_type: prepared.input_type,
        voxel_type: prepared.voxel_type,
        voxel_scale: prepared.voxel_scale,
        conversion: prepared.conversion.clone(),
        channels: prepared.channels.clone(),
        input_bytes: dims.iter().map(|&d| u64::from(d)).product::<u64>()
            * prepared.input_type.bytes() as u64,
        file_bytes: 0,
        elapsed: Duration::ZERO,
    };
    // Every source finished (its reader joined), the first error kept.
    let finished = prepared.finish();
    let outcome = match (built, finished) {
        (_, Err(e)) => Err(e),
        (Err(e), Ok(())) => Err(FormatsError::Store(e)),
        (Ok(report), Ok(())) => std::fs::rename(&tmp, output)
            .map(|()| report)
            .map_err(FormatsError::io_path("cannot rename into", output)),
    };
    let report = match outcome {
        Ok(r) => r,
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
    };
    summary.file_bytes = report.file_bytes;
    summary.elapsed = start.elapsed();
    Ok(summary)
}
