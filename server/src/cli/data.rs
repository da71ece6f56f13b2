//! The data tools: import, export, generate, inspect, get.

use super::{parse_dims, parse_scale, progress, TypeArg};
use anyhow::{anyhow, bail, Context};
use clap::{Args, ValueEnum};
use isovox_proto::VolumeLayout;
use isovox_server::formats::ViewKind;
use isovox_server::generate::{
    build_scene, build_scene_with_materials, world_header, EllipsoidSource, WorldMaterials,
    WorldSource,
};
use isovox_server::geometry::Box3;
use isovox_server::progress::Silent;
use isovox_server::store::build::{build_file, build_streams_file, sibling, FileFormat};
use isovox_server::store::codec::{Compression, DEFAULT_ZSTD_LEVEL};
use isovox_server::store::inspect::inspect as inspect_vod2;
use isovox_server::store::raw::{export_raw, rawvox_header, RawInput, RAWVOX_MAGIC};
use isovox_server::store::remote::{upload_with, Bucket, CacheConfig, Head, RemoteVolume};
use isovox_server::store::vod1::{write_vod1, Vod1File, Vod1Source};
use isovox_server::store::{BrickSource, BuildOptions, DenseGrid, Vod2};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum VodFormat {
    Vod2,
    Vod1,
}

#[derive(Debug, Args)]
pub(crate) struct ImportArgs {
    /// Input: .raw (needs --dims), .rawvox (carries its shape), a VOD 1 file, or one of the
    /// field's formats, local or an http(s) URL: OME-Zarr / Zarr v2 or v3, Neuroglancer
    /// precomputed, NIfTI-1 (.nii, .nii.gz), a TIFF stack (multi-page file or folder).
    /// Not with --finish.
    #[arg(required_unless_present = "finish", conflicts_with = "finish")]
    pub input: Option<PathBuf>,
    /// Output file, or a new volume in an object store (s3://bucket/prefix/NAME).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Import only part I of N (I from 0 to N-1) of a volume in an object store: the level-0
    /// bricks of its I-th run of brick rows, stored under NAME/parts/; the volume exists once
    /// `--finish` has run. A finished part run again is skipped; a killed one resumes.
    #[arg(long, value_name = "I/N", value_parser = isovox_server::store::remote::parts::parse_part)]
    pub part: Option<(u32, u32)>,
    /// Finish a split import (all of its --part runs done): build the levels above level 0
    /// from the parts, upload the volume and create its head.
    #[arg(long, conflicts_with = "part")]
    pub finish: bool,
    /// With --finish: the N of the parts (by default, the N their markers say).
    #[arg(long, value_name = "N")]
    pub parts: Option<u32>,
    /// Voxels per axis of a RAW file: X,Y,Z.
    #[arg(long, value_parser = parse_dims)]
    pub dims: Option<[u32; 3]>,
    /// Voxel type of a RAW file (u16 is little endian).
    #[arg(long = "type", value_enum)]
    pub voxel_type: Option<TypeArg>,
    /// Brick edge in voxels, a power of two (16 as in the thesis's storage tests; 32 serves well).
    #[arg(long, default_value_t = 32)]
    pub brick: u32,
    /// World size of one voxel: SX,SY,SZ.
    #[arg(long, value_parser = parse_scale, default_value = "1,1,1")]
    pub scale: [f32; 3],
    /// Output format.
    #[arg(long, value_enum, default_value_t = VodFormat::Vod2)]
    pub format: VodFormat,
    #[command(flatten)]
    pub compression: CompressionArgs,
    #[command(flatten)]
    pub formats: super::formats::FormatImportArgs,
}

impl ImportArgs {
    /// The input path (clap requires one unless `--finish`, which reads none).
    pub(crate) fn input(&self) -> &Path {
        self.input.as_deref().unwrap_or(Path::new(""))
    }
}

/// How bricks are compressed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum CodecArg {
    /// zstd: the densest (default).
    Zstd,
    /// lz4: the fastest to decode.
    Lz4,
    /// no compression (constant bricks and deduplication still apply).
    None,
}

#[derive(Debug, Clone, Copy, Args)]
pub(crate) struct CompressionArgs {
    /// Brick compression.
    #[arg(long, value_enum, default_value_t = CodecArg::Zstd)]
    pub codec: CodecArg,
    /// zstd level (1-22): higher is smaller and slower to write; reading speed barely changes.
    #[arg(long, default_value_t = DEFAULT_ZSTD_LEVEL, value_parser = clap::value_parser!(i32).range(1..=22))]
    pub zstd_level: i32,
}

impl CompressionArgs {
    pub(crate) fn compression(&self) -> Compression {
        match self.codec {
            CodecArg::Zstd => Compression::Zstd(self.zstd_level),
            CodecArg::Lz4 => Compression::Lz4,
            CodecArg::None => Compression::None,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum ExportFormat {
    Raw,
    Rawvox,
    Vod1,
    /// OME-Zarr 0.5 (Zarr v3): a directory, every level.
    Zarr,
    /// Neuroglancer precomputed: a directory, every level.
    Precomputed,
}

#[derive(Debug, Args)]
pub(crate) struct ExportArgs {
    /// A VOD 2 file, or a volume in an object store (s3://bucket/prefix/NAME).
    pub input: PathBuf,
    /// Output file (a directory for zarr and precomputed).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Level of detail to export (0 = full resolution).
    #[arg(long, default_value_t = 0)]
    pub level: u8,
    /// Output format: raw/rawvox write one level; vod1, zarr and precomputed the whole volume.
    #[arg(long, value_enum, default_value_t = ExportFormat::Raw)]
    pub format: ExportFormat,
    /// Only this box of the level's voxels: MINX,MINY,MINZ,MAXX,MAXY,MAXZ (max exclusive).
    #[arg(long)]
    pub region: Option<String>,
    /// Export this version instead of the newest.
    #[arg(long)]
    pub version: Option<u64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum Dataset {
    /// The ICVG ellipsoid sampling function filling the volume.
    Ellipsoid,
    /// Terrain from a fractal Perlin-noise height map.
    World,
    /// The world with tunnels, a crater and a few primitives applied as ICVG edits.
    Scene,
}

#[derive(Debug, Args)]
pub(crate) struct GenerateArgs {
    /// What to generate.
    #[arg(value_enum)]
    pub dataset: Dataset,
    /// Output VOD 2 file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Voxels per axis: X,Y,Z.
    #[arg(long, value_parser = parse_dims, default_value = "256,256,256")]
    pub dims: [u32; 3],
    /// Voxel type: u8 (values 0..255) or u16 (0..65535, little endian).
    #[arg(long = "type", value_enum, default_value_t = TypeArg::U8)]
    pub voxel_type: TypeArg,
    /// Brick edge in voxels, a power of two.
    #[arg(long, default_value_t = 32)]
    pub brick: u32,
    /// Noise seed (world).
    #[arg(long, default_value_t = 1)]
    pub seed: u32,
    /// With a u8 `material` channel (world, scene): rock, soil, grass, sand and an ore vein,
    /// and marble for the scene's buildings, as the demo world has.
    #[arg(long)]
    pub materials: bool,
    #[command(flatten)]
    pub compression: CompressionArgs,
}

#[derive(Debug, Args)]
pub(crate) struct InspectArgs {
    /// A VOD 2 or VOD 1 file.
    pub input: PathBuf,
    /// Print JSON for scripts.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub(crate) struct GetArgs {
    /// A VOD 2 or VOD 1 file.
    pub input: PathBuf,
    /// Level of detail (0 = full resolution; each level above halves every axis).
    pub level: u8,
    /// The brick's x in the level's brick grid (brick units, not voxels).
    pub x: u32,
    /// The brick's y in the level's brick grid.
    pub y: u32,
    /// The brick's z in the level's brick grid.
    pub z: u32,
    /// Write here instead of stdout.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Read this version instead of the newest (VOD 2).
    #[arg(long)]
    pub version: Option<u64>,
}

/// What kind of file a path holds, by its first bytes.
pub(super) enum InputKind {
    Vod(u32),
    Rawvox,
    Raw,
}

pub(super) fn sniff(path: &Path) -> anyhow::Result<InputKind> {
    use std::io::Read;
    let mut head = [0u8; 8];
    let mut f = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let n = f
        .read(&mut head)
        .with_context(|| format!("cannot read {}", path.display()))?;
    if n >= 8 && head[..4] == isovox_proto::vod2::SIGNATURE {
        return Ok(InputKind::Vod(u32::from_le_bytes([
            head[4], head[5], head[6], head[7],
        ])));
    }
    if n >= 4 && i32::from_le_bytes([head[0], head[1], head[2], head[3]]) == RAWVOX_MAGIC {
        return Ok(InputKind::Rawvox);
    }
    Ok(InputKind::Raw)
}

/// Builds `output` from `source` (see [`build_file`]) with a progress bar.
pub(super) fn build_to(
    output: &Path,
    layout: &VolumeLayout,
    scale: [f32; 3],
    source: &dyn BrickSource,
    compression: Compression,
    format: VodFormat,
) -> anyhow::Result<()> {
    let format = match format {
        VodFormat::Vod2 => FileFormat::Vod2,
        VodFormat::Vod1 => FileFormat::Vod1,
    };
    build_file(output, layout, scale, source, &options(compression), format)
        .with_context(|| format!("cannot build {}", output.display()))?;
    Ok(())
}

/// Build options with `compression` and a progress bar.
fn options(compression: Compression) -> BuildOptions {
    BuildOptions {
        compression,
        progress: Arc::new(progress("building")),
    }
}

/// A volume in an object store named by a path argument, `s3://bucket/prefix/NAME`: the store
/// and the name.
fn in_store(path: &Path) -> anyhow::Result<Option<(Bucket, String)>> {
    let Some(url) = path.to_str().filter(|p| p.starts_with("s3://")) else {
        return Ok(None);
    };
    let (store, name) = url
        .trim_end_matches('/')
        .rsplit_once('/')
        .filter(|(store, _)| store.len() > "s3://".len())
        .ok_or_else(|| anyhow!("{url}: a volume in a store is s3://bucket/prefix/NAME"))?;
    if !isovox_server::catalog::valid_name(name) {
        bail!("{url}: a volume name is [A-Za-z0-9_.-]");
    }
    Ok(Some((Bucket::from_url(store)?, name.to_string())))
}

/// Opens volume `name` of `store` with a mirror in a temporary directory (removed on drop).
fn open_in_store(
    store: &Bucket,
    name: &str,
) -> anyhow::Result<(Arc<RemoteVolume>, Vod2, TempCache)> {
    let dir = std::env::temp_dir().join(format!("isovox-cli-{}", std::process::id()));
    let cache = CacheConfig {
        dir: dir.clone(),
        max_bytes: u64::MAX,
        ..CacheConfig::default()
    };
    let (remote, vod) = RemoteVolume::open(store, name, cache)
        .with_context(|| format!("cannot open {}/{name}", store.url()))?;
    Ok((remote, vod, TempCache(dir)))
}

/// A directory removed when dropped.
struct TempCache(PathBuf);

impl Drop for TempCache {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

pub(super) fn import(a: ImportArgs) -> anyhow::Result<()> {
    // (Not clap's `requires`: a flag that is off still counts as given there.)
    if a.parts.is_some() && !a.finish {
        bail!("--parts N goes with --finish (a part is named by --part I/N)");
    }
    let Some((store, name)) = in_store(&a.output)? else {
        if a.part.is_some() || a.finish {
            bail!(
                "--part and --finish split an import into a volume in an object store (-o s3://bucket/prefix/NAME), not a file"
            );
        }
        return import_file(a);
    };
    if a.format != VodFormat::Vod2 {
        bail!("a volume in a store is VOD 2 (drop --format vod1)");
    }
    if a.finish {
        return super::split::finish(&store, &name, a.parts);
    }
    if let Some((part, parts)) = a.part {
        return super::split::part(&a, &store, &name, part, parts);
    }
    let field_format = super::formats::input_format(&a)?.is_some();
    if !field_format && matches!(sniff(a.input())?, InputKind::Vod(2)) {
        // A VOD 2 file goes up as it is (its head version and history with it).
        let head =
            upload_with(&store.child(&name), a.input(), None, &Silent).with_context(|| {
                format!(
                    "cannot create {}/{name} (does it exist already?)",
                    store.url()
                )
            })?;
        return uploaded(&store, &name, &head);
    }
    // Built locally, then uploaded as the volume's first segment.
    let tmp = std::env::temp_dir().join(format!("isovox-import-{name}-{}.vod", std::process::id()));
    let local = ImportArgs {
        output: tmp.clone(),
        ..a
    };
    let built = import_file(local).and_then(|()| {
        upload_with(&store.child(&name), &tmp, None, &Silent).with_context(|| {
            format!(
                "cannot create {}/{name} (does it exist already?)",
                store.url()
            )
        })
    });
    let _ = std::fs::remove_file(&tmp);
    uploaded(&store, &name, &built?)
}

/// Says what an import put in the store (the head, and how many parts its segment went up in).
fn uploaded(store: &Bucket, name: &str, (head, parts): &(Head, u32)) -> anyhow::Result<()> {
    out!(
        "{}/{name}: version {}, {} bytes in one segment ({})",
        store.url(),
        head.version,
        head.committed_len,
        if *parts > 1 {
            format!("a multipart upload of {parts} parts")
        } else {
            "one PUT".to_string()
        }
    )?;
    Ok(())
}

fn import_file(a: ImportArgs) -> anyhow::Result<()> {
    if let Some(format) = super::formats::input_format(&a)? {
        return super::formats::import(&a, format);
    }
    if !a.formats.channels.is_empty() {
        bail!("--channel is for imports of the field's formats (Zarr, precomputed, NIfTI, TIFF), not RAW or VOD files");
    }
    let compress = a.compression.compression();
    match sniff(a.input())? {
        InputKind::Vod(1) => {
            let file = Vod1File::open(a.input())?;
            let vod1 = file
                .parse()
                .with_context(|| format!("{} is not a valid VOD 1 file", a.input().display()))?;
            let source = Vod1Source::new(&vod1);
            build_to(
                &a.output,
                &vod1.layout,
                vod1.voxel_scale,
                &source,
                compress,
                a.format,
            )?;
            source
                .finish()
                .with_context(|| format!("{}: a brick does not decode", a.input().display()))?;
        }
        InputKind::Vod(v) => bail!(
            "{} is already a VOD {v} file; import reads RAW, RAWVOX and VOD 1",
            a.input().display()
        ),
        kind => {
            let rawvox = matches!(kind, InputKind::Rawvox);
            let input = RawInput::open(a.input(), rawvox, a.dims, a.voxel_type.map(Into::into))?;
            let layout = VolumeLayout::new(input.dims, a.brick, input.voxel_type)?;
            let grid = DenseGrid::new(input.dims, input.voxel_type, a.brick, input.voxels());
            build_to(&a.output, &layout, a.scale, &grid, compress, a.format)?;
        }
    }
    Ok(())
}

fn parse_region(s: &str) -> anyhow::Result<Box3> {
    let v: Vec<u32> = s
        .split(',')
        .map(|p| {
            p.trim()
                .parse::<u32>()
                .map_err(|_| anyhow!("region value {p:?} is not a non-negative integer"))
        })
        .collect::<Result<_, _>>()?;
    if v.len() != 6 {
        bail!(
            "--region takes six values MINX,MINY,MINZ,MAXX,MAXY,MAXZ, got {}",
            v.len()
        );
    }
    let v: Vec<i64> = v.into_iter().map(i64::from).collect();
    Ok(Box3::new([v[0], v[1], v[2]], [v[3], v[4], v[5]]))
}

pub(super) fn export(a: ExportArgs) -> anyhow::Result<()> {
    let stored = in_store(&a.input)?;
    let (vod, _cache) = match &stored {
        Some((store, name)) => {
            let (_, vod, cache) = open_in_store(store, name)?;
            (vod, Some(cache))
        }
        None => {
            if let InputKind::Vod(v) = sniff(&a.input)? {
                if v != 2 {
                    bail!(
                        "{} is a VOD {v} file; export reads VOD 2 (import it first)",
                        a.input.display()
                    );
                }
            }
            (super::open_vod2(&a.input)?, None)
        }
    };
    let snap = match a.version {
        Some(v) => vod.version(v)?,
        None => vod.head(),
    };
    match a.format {
        ExportFormat::Zarr => super::formats::export(&a, &snap, ViewKind::Zarr),
        ExportFormat::Precomputed => super::formats::export(&a, &snap, ViewKind::Precomputed),
        ExportFormat::Vod1 => {
            if a.region.is_some() || a.level != 0 {
                bail!("--format vod1 writes the whole volume; --level and --region apply to raw and rawvox");
            }
            write_through_tmp(&a.output, |out| {
                write_vod1(&snap, true, out)?;
                Ok(())
            })?;
            out!(
                "{}: VOD 1 of version {}, levels 0..{}: {} bytes",
                a.output.display(),
                snap.version,
                snap.layout().levels() - 1,
                file_bytes(&a.output)?
            )?;
            Ok(())
        }
        ExportFormat::Raw | ExportFormat::Rawvox => {
            let layout = snap.layout();
            if a.level >= layout.levels() {
                bail!(
                    "level {} out of range: the volume has levels 0..{}",
                    a.level,
                    layout.levels() - 1
                );
            }
            let region = match &a.region {
                Some(r) => parse_region(r)?,
                None => Box3::new([0; 3], layout.level_dims(a.level).map(i64::from)),
            };
            write_through_tmp(&a.output, |out| {
                if a.format == ExportFormat::Rawvox {
                    let dims = [0, 1, 2]
                        .map(|i| u32::try_from(region.max[i] - region.min[i]).unwrap_or(0));
                    out.write_all(&rawvox_header(dims, layout.voxel_type()))?;
                }
                export_raw(&snap, a.level, region, out, &progress("exporting"))?;
                Ok(())
            })?;
            let dims = [0, 1, 2].map(|i| region.max[i].saturating_sub(region.min[i]));
            out!(
                "{}: {} of version {}, level {}, voxels {},{},{}..{},{},{} ({} x {} x {}): {} bytes",
                a.output.display(),
                if a.format == ExportFormat::Rawvox { "RAWVOX" } else { "RAW" },
                snap.version,
                a.level,
                region.min[0],
                region.min[1],
                region.min[2],
                region.max[0],
                region.max[1],
                region.max[2],
                dims[0],
                dims[1],
                dims[2],
                file_bytes(&a.output)?
            )?;
            Ok(())
        }
    }
}

/// The size of the file at `path`, for what a command reports it wrote.
fn file_bytes(path: &Path) -> anyhow::Result<u64> {
    Ok(std::fs::metadata(path)
        .with_context(|| format!("cannot read {}", path.display()))?
        .len())
}

/// Writes `output` through `write`, into a temporary file beside it renamed into place when
/// complete.
fn write_through_tmp(
    output: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let tmp = sibling(output, ".isovox-tmp");
    let mut out = BufWriter::with_capacity(
        1 << 20,
        File::create(&tmp).with_context(|| format!("cannot create {}", tmp.display()))?,
    );
    let written = write(&mut out).and_then(|()| Ok(out.flush()?));
    drop(out);
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, output)
        .with_context(|| format!("cannot move the result to {}", output.display()))
}

pub(super) fn generate(a: GenerateArgs) -> anyhow::Result<()> {
    let layout = VolumeLayout::new(a.dims, a.brick, a.voxel_type.into())?;
    let compression = a.compression.compression();
    if a.materials {
        let world = WorldSource::new(layout.clone(), a.seed);
        return match a.dataset {
            Dataset::Ellipsoid => bail!("--materials is for world and scene"),
            Dataset::World => {
                let materials = WorldMaterials::new(world.clone());
                let header = world_header(&layout)?;
                build_streams_file(
                    &a.output,
                    header,
                    &[&world, &materials],
                    &options(compression),
                )?;
                Ok(())
            }
            Dataset::Scene => Ok(build_scene_with_materials(
                &a.output,
                &world,
                &options(compression),
            )?),
        };
    }
    match a.dataset {
        Dataset::Ellipsoid => build_to(
            &a.output,
            &layout,
            [1.0; 3],
            &EllipsoidSource::new(layout.clone()),
            compression,
            VodFormat::Vod2,
        ),
        Dataset::World => build_to(
            &a.output,
            &layout,
            [1.0; 3],
            &WorldSource::new(layout.clone(), a.seed),
            compression,
            VodFormat::Vod2,
        ),
        Dataset::Scene => Ok(build_scene(
            &a.output,
            &layout,
            &WorldSource::new(layout.clone(), a.seed),
            &options(compression),
        )?),
    }
}

fn human(bytes: u64) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = bytes as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < units.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{bytes} B")
    } else {
        format!("{v:.2} {}", units[u])
    }
}

pub(super) fn inspect(a: InspectArgs) -> anyhow::Result<()> {
    match sniff(&a.input)? {
        InputKind::Vod(1) => inspect_vod1(&a),
        InputKind::Vod(2) => {
            let vod = super::open_vod2(&a.input)?;
            let i =
                inspect_vod2(&vod).with_context(|| format!("{} is damaged", a.input.display()))?;
            if a.json {
                out!("{}", serde_json::to_string_pretty(&i)?)?;
                return Ok(());
            }
            let [x, y, z] = i.dims;
            out!(
                "{}: {} file, version {} ({} commits)",
                a.input.display(),
                i.format,
                i.version,
                i.commits
            )?;
            out!(
                "  volume      {x} x {y} x {z} {} voxels, brick {}^3, voxel scale {:?}",
                i.voxel_type,
                i.brick,
                i.voxel_scale
            )?;
            out!("  levels      {}", i.levels.len())?;
            print_levels(&i.levels)?;
            out!(
                "  bricks      {} total, {} unique",
                i.bricks_total,
                i.bricks_unique
            )?;
            print_codecs(&i.codecs)?;
            for c in &i.channels {
                out!(
                    "  channel     {} ({}): {} unique bricks, {} as RAW",
                    c.name,
                    c.voxel_type,
                    c.bricks_unique,
                    human(c.raw_bytes)
                )?;
                print_levels(&c.levels)?;
                print_codecs(&c.codecs)?;
            }
            out!("  index       {}", human(i.index_bytes))?;
            out!(
                "  size        {} on disk, {} as RAW: ratio {:.2}:1",
                human(i.file_bytes),
                human(i.raw_bytes),
                i.ratio
            )?;
            out!(
                "  garbage     {} not referenced by the head version",
                human(i.garbage_bytes)
            )?;
            Ok(())
        }
        InputKind::Vod(v) => bail!("{}: VOD version {v} is not supported", a.input.display()),
        _ => bail!("{} is not a VOD file", a.input.display()),
    }
}

fn inspect_vod1(a: &InspectArgs) -> anyhow::Result<()> {
    let file = Vod1File::open(&a.input)?;
    let len = file.len();
    let v = file
        .parse()
        .with_context(|| format!("{} is not a valid VOD 1 file", a.input.display()))?;
    let raw = v.layout.raw_bytes();
    let [x, y, z] = v.layout.dims();
    if a.json {
        let j = serde_json::json!({
            "format": "VOD 1", "dims": v.layout.dims(), "voxel_type": v.layout.voxel_type(),
            "brick": v.layout.brick(), "tree_height": v.height,
            "levels": (0..v.layout.levels()).map(|l| serde_json::json!({"level": l, "grid": v.layout.grid(l)})).collect::<Vec<_>>(), "version": 1,
            "bricks_total": isovox_server::store::vod1::node_count(v.height), "bricks_unique": v.unique_bricks(),
            "file_bytes": len, "raw_bytes": raw, "ratio": raw as f64 / len as f64,
        });
        out!("{}", serde_json::to_string_pretty(&j)?)?;
    } else {
        out!("{}: VOD 1 file (thesis layout)", a.input.display())?;
        out!(
            "  volume      {x} x {y} x {z} {} voxels, brick {}^3",
            v.layout.voxel_type(),
            v.layout.brick()
        )?;
        out!(
            "  octree      height {}, {} nodes, {} unique bricks",
            v.height,
            isovox_server::store::vod1::node_count(v.height),
            v.unique_bricks()
        )?;
        out!(
            "  size        {} on disk, {} as RAW: ratio {:.2}:1",
            human(len),
            human(raw),
            raw as f64 / len as f64
        )?;
    }
    Ok(())
}

pub(super) fn get(a: GetArgs) -> anyhow::Result<()> {
    let bytes = match sniff(&a.input)? {
        InputKind::Vod(1) => {
            let file = Vod1File::open(&a.input)?;
            let v = file.parse()?;
            let key = v.layout.key(a.level, a.x, a.y, a.z)?;
            let mut out = vec![0u8; v.layout.brick_bytes()];
            v.read_into(key, &mut out)?;
            out
        }
        _ => {
            let vod = super::open_vod2(&a.input)?;
            let snap = match a.version {
                Some(v) => vod.version(v)?,
                None => vod.head(),
            };
            let key = snap.layout().key(a.level, a.x, a.y, a.z)?;
            snap.read(key)?
        }
    };
    match a.output {
        Some(path) => std::fs::write(&path, &bytes)
            .with_context(|| format!("cannot write {}", path.display()))?,
        None => {
            let mut stdout = std::io::stdout().lock();
            stdout.write_all(&bytes)?;
            stdout.flush()?;
        }
    }
    Ok(())
}

#[derive(Debug, Args)]
pub(crate) struct CompactArgs {
    /// The VOD 2 file to compact in place, or a volume in an object store
    /// (s3://bucket/prefix/NAME).
    pub input: PathBuf,
    /// For a volume in a store: objects its head no longer references are deleted once they
    /// are this old, in seconds (replicas still reading an older head need them until then).
    #[arg(long, default_value_t = isovox_server::volume::write::GC_GRACE.as_secs())]
    pub grace_secs: u64,
}

pub(super) fn compact(a: CompactArgs) -> anyhow::Result<()> {
    let report = match in_store(&a.input)? {
        Some((store, name)) => {
            let (remote, vod, _cache) = open_in_store(&store, &name)?;
            let grace = std::time::Duration::from_secs(a.grace_secs);
            isovox_server::store::compact::compact_remote(&remote, &vod, grace)
                .with_context(|| format!("cannot compact {}", a.input.display()))?
        }
        None => {
            let vod = super::open_vod2(&a.input)?;
            let head = vod.head();
            isovox_server::store::compact::compact(&vod, &head, &progress("compacting"))
                .with_context(|| format!("cannot compact {}", a.input.display()))?
        }
    };
    out!(
        "{}: version {} kept, {} distinct bricks, {} -> {} bytes ({:.1}% saved) in {:.2} s",
        a.input.display(),
        report.version,
        report.bricks,
        report.bytes_before,
        report.bytes_after,
        100.0 * (1.0 - report.bytes_after as f64 / report.bytes_before.max(1) as f64),
        report.elapsed.as_secs_f64()
    )?;
    Ok(())
}

/// The levels of one stream's pyramid, one line each.
fn print_levels(levels: &[isovox_server::store::inspect::LevelStats]) -> anyhow::Result<()> {
    for l in levels {
        let [gx, gy, gz] = l.grid;
        out!("    level {:>2}  grid {gx:>5} x {gy:>5} x {gz:>5}  {:>10} bricks  {:>10} constant  {:>10} stored", l.level, l.bricks, l.constant, l.stored)?;
    }
    Ok(())
}

/// One stream's bricks by codec.
fn print_codecs(c: &isovox_server::store::inspect::CodecStats) -> anyhow::Result<()> {
    out!(
        "  by codec    constant {} bricks (no payload); zstd {} records, {}; lz4 {} records, {}; raw {} records, {}",
        c.constant_bricks, c.zstd_records, human(c.zstd_bytes), c.lz4_records, human(c.lz4_bytes), c.raw_records, human(c.raw_bytes)
    )?;
    if c.palette_records > 0 {
        out!(
            "              palette {} records, {}",
            c.palette_records,
            human(c.palette_bytes)
        )?;
    }
    Ok(())
}
