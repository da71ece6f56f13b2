//! `isovox check` and `isovox salvage`: find damage in a file, and recover its newest intact
//! version into a new one.

use super::progress;
use anyhow::{bail, Context};
use clap::Args;
use isovox_server::store::check::{check as check_file, CheckReport, Depth};
use isovox_server::store::salvage::salvage as salvage_file;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub(crate) struct CheckArgs {
    /// A VOD 2 file.
    pub input: PathBuf,
    /// Print the report as JSON (damage with offsets, every version's state).
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub(crate) struct SalvageArgs {
    /// The damaged VOD 2 file (only read).
    pub input: PathBuf,
    /// The new file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Write this version instead of the newest intact one (it must be intact).
    #[arg(long)]
    pub version: Option<u64>,
}

pub(super) fn check(a: CheckArgs) -> anyhow::Result<()> {
    let report = check_file(&a.input, Depth::Everything, &progress("checking"))
        .with_context(|| format!("cannot check {}", a.input.display()))?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&report)?)?;
    } else {
        print_report(&a, &report)?;
    }
    if report.is_damaged() {
        bail!(
            "{} is damaged: {} damaged record(s); {}",
            a.input.display(),
            report.damage.len(),
            match report.newest_intact() {
                Some(v) => format!(
                    "the newest intact version is {} (`isovox salvage` writes it to a new file)",
                    v.version
                ),
                None => "no version is intact".into(),
            }
        );
    }
    Ok(())
}

fn print_report(a: &CheckArgs, r: &CheckReport) -> anyhow::Result<()> {
    let intact = r.versions.iter().filter(|v| v.intact()).count();
    out!(
        "{}: VOD 2 file, {} bytes ({} committed), head {}",
        a.input.display(),
        r.file_bytes,
        r.committed_bytes,
        r.head
            .map_or("unknown (no valid header slot)".to_string(), |v| format!(
                "version {v}"
            ))
    )?;
    out!("  versions    {} found, {intact} intact", r.versions.len())?;
    out!("  bricks      {} records verified", r.bricks)?;
    if r.bricks_without_checksum > 0 {
        out!(
            "              {} of them without a payload checksum (written before payload checksums; `isovox compact` adds them)",
            r.bricks_without_checksum
        )?;
    }
    if r.damage.is_empty() {
        out!("  damage      none")?;
        return Ok(());
    }
    out!("  damage      {} record(s)", r.damage.len())?;
    for d in &r.damage {
        out!(
            "    offset {:>12}  {:<16}  {}",
            d.offset,
            d.record,
            d.detail
        )?;
    }
    // Versions that are not intact, in runs of consecutive versions, each with the first
    // version's reason.
    let mut i = 0;
    while i < r.versions.len() {
        let v = &r.versions[i];
        if v.intact() {
            i += 1;
            continue;
        }
        let mut j = i;
        while j + 1 < r.versions.len()
            && !r.versions[j + 1].intact()
            && r.versions[j + 1].version == r.versions[j].version + 1
        {
            j += 1;
        }
        let why = v
            .index_damage
            .clone()
            .unwrap_or_else(|| format!("{} of its bricks are damaged", v.damaged_bricks));
        let range = if i == j {
            format!("version {}", v.version)
        } else {
            format!("versions {}..={}", v.version, r.versions[j].version)
        };
        out!("  not intact  {range}: {why}")?;
        i = j + 1;
    }
    match r.newest_intact() {
        Some(v) => out!(
            "  newest intact version: {} (commit record at offset {})",
            v.version,
            v.commit
        )?,
        None => out!("  no version is intact")?,
    }
    Ok(())
}

pub(super) fn salvage(a: SalvageArgs) -> anyhow::Result<()> {
    let report = salvage_file(&a.input, &a.output, a.version, &progress("salvaging"))
        .with_context(|| format!("cannot salvage {}", a.input.display()))?;
    let head = report
        .check
        .head
        .map_or("unknown".to_string(), |v| v.to_string());
    out!(
        "{}: version {} written to {} ({} distinct bricks, {} bytes); the file's head is version {head}, {} damaged record(s)",
        a.input.display(),
        report.version,
        a.output.display(),
        report.bricks,
        report.bytes,
        report.check.damage.len()
    )?;
    Ok(())
}
