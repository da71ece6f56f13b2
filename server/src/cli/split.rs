//! `isovox import SRC -o s3://.../NAME --part I/N` and `isovox import --finish -o ...`: an
//! import split across machines ([`isovox_server::store::remote::parts`]). Progress goes to
//! stderr a line at a time, not as a bar: these run as batch jobs whose logs are read later.

use super::data::{sniff, ImportArgs, InputKind};
use anyhow::{bail, Context};
use isovox_proto::vod2::FileHeader;
use isovox_proto::VolumeLayout;
use isovox_server::progress::Progress;
use isovox_server::store::raw::RawInput;
use isovox_server::store::remote::parts::{self, FinishProgress, Identity, PartOutcome};
use isovox_server::store::remote::Bucket;
use isovox_server::store::vod1::{Vod1File, Vod1Source};
use isovox_server::store::{BrickSource, DenseGrid};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// Calls `use_sources` with the header of the volume `a` imports and the level-0 source of each
/// of its streams, opened as the single-process import opens them (so a split import makes
/// the same volume), then checks that every source read without error.
fn with_sources<R>(
    a: &ImportArgs,
    use_sources: impl FnOnce(FileHeader, &[&dyn BrickSource]) -> anyhow::Result<R>,
) -> anyhow::Result<R> {
    let input = a.input();
    if let Some(format) = super::formats::input_format(a)? {
        let options = super::formats::import_options(a, format)?;
        let name = input.to_string_lossy();
        let prepared = isovox_server::formats::import::prepare(
            &name,
            format,
            &options,
            &super::progress("sampling"),
        )
        .with_context(|| format!("cannot import {name}"))?;
        let used = use_sources(prepared.header.clone(), &prepared.sources());
        let read = prepared.finish();
        return match (used, read) {
            (_, Err(e)) => Err(e).with_context(|| format!("cannot import {name}")),
            (used, Ok(())) => used,
        };
    }
    if !a.formats.channels.is_empty() {
        bail!("--channel is for imports of the field's formats (Zarr, precomputed, NIfTI, TIFF), not RAW or VOD files");
    }
    match sniff(input)? {
        InputKind::Vod(1) => {
            let file = Vod1File::open(input)?;
            let vod1 = file
                .parse()
                .with_context(|| format!("{} is not a valid VOD 1 file", input.display()))?;
            let source = Vod1Source::new(&vod1);
            let header = FileHeader::new(vod1.layout.clone(), vod1.voxel_scale);
            let used = use_sources(header, &[&source]);
            source
                .finish()
                .with_context(|| format!("{}: a brick does not decode", input.display()))?;
            used
        }
        InputKind::Vod(v) => bail!(
            "{} is a VOD {v} file: it goes up whole (import it without --part)",
            input.display()
        ),
        kind => {
            let rawvox = matches!(kind, InputKind::Rawvox);
            let raw = RawInput::open(input, rawvox, a.dims, a.voxel_type.map(Into::into))?;
            let layout = VolumeLayout::new(raw.dims, a.brick, raw.voxel_type)?;
            let grid = DenseGrid::new(raw.dims, raw.voxel_type, a.brick, raw.voxels());
            use_sources(FileHeader::new(layout, a.scale), &[&grid])
        }
    }
}

/// `--part I/N`.
pub(super) fn part(
    a: &ImportArgs,
    store: &Bucket,
    name: &str,
    part: u32,
    parts_n: u32,
) -> anyhow::Result<()> {
    let volume = store.child(name);
    let start = Instant::now();
    let compression = a.compression.compression();
    let outcome = with_sources(a, |header, sources| {
        let identity = Identity::new(header, compression);
        let mut say = |line: &str| eprintln!("{line}");
        Ok(parts::write_part(
            &volume, &identity, sources, part, parts_n, &mut say,
        )?)
    })
    .with_context(|| format!("part {part}/{parts_n} of {}", volume.url()))?;
    match outcome {
        PartOutcome::AlreadyDone(m) => {
            eprintln!(
                "part {part}/{parts_n} of {} had finished already (its marker is there): skipped",
                volume.url()
            );
            out!(
                "{}: part {part}/{parts_n} (brick rows {}..{}) already done",
                volume.url(),
                m.rows[0],
                m.rows[1]
            )?;
        }
        PartOutcome::Written { marker, resumed } => {
            out!(
                "{}: part {part}/{parts_n} done: brick rows {}..{}, {} row objects ({resumed} from an earlier run), {} bytes stored in {:.2} s",
                volume.url(),
                marker.rows[0],
                marker.rows[1],
                marker.row_objects,
                marker.stored_bytes,
                start.elapsed().as_secs_f64()
            )?;
        }
    }
    Ok(())
}

/// `--finish`.
pub(super) fn finish(store: &Bucket, name: &str, parts_n: Option<u32>) -> anyhow::Result<()> {
    let volume = store.child(name);
    let start = Instant::now();
    let tmp = std::env::temp_dir().join(format!("isovox-finish-{name}-{}.vod", std::process::id()));
    let mut say = |line: &str| eprintln!("{line}");
    let upload = Lines::new("uploading", "bytes");
    let done = parts::finish(
        &volume,
        parts_n,
        &tmp,
        FinishProgress {
            build: Arc::new(Lines::new("building", "bricks")),
            upload: &upload,
            say: &mut say,
        },
    )
    .with_context(|| format!("cannot finish the split import of {}", volume.url()))?;
    out!(
        "{}: version {}, {} bytes in one segment ({}), from {} parts in {:.2} s; {} part objects deleted",
        volume.url(),
        done.head.version,
        done.head.committed_len,
        if done.upload_parts > 1 {
            format!("a multipart upload of {} parts", done.upload_parts)
        } else {
            "one PUT".to_string()
        },
        done.parts,
        start.elapsed().as_secs_f64(),
        done.deleted
    )?;
    Ok(())
}

/// Progress as a line on stderr at every tenth of the work (a log, not a bar).
struct Lines {
    what: &'static str,
    unit: &'static str,
    total: AtomicU64,
    done: AtomicU64,
}

impl Lines {
    fn new(what: &'static str, unit: &'static str) -> Lines {
        Lines {
            what,
            unit,
            total: AtomicU64::new(0),
            done: AtomicU64::new(0),
        }
    }
}

impl Progress for Lines {
    fn start(&self, total: u64) {
        self.total.store(total, Ordering::Relaxed);
        self.done.store(0, Ordering::Relaxed);
    }

    fn advance(&self, steps: u64) {
        let total = self.total.load(Ordering::Relaxed).max(1);
        let before = self.done.fetch_add(steps, Ordering::Relaxed);
        let after = before + steps;
        if before * 10 / total != after * 10 / total {
            eprintln!(
                "{}: {}% ({after} of {total} {})",
                self.what,
                (after.min(total) * 100 / total),
                self.unit
            );
        }
    }
}
