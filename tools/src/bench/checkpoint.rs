//! `isovox-bench checkpoint`: what writing an index checkpoint costs on a large volume after a
//! run of small edits. A writer's checkpoint copies the previous checkpoint's chunks that no
//! commit since touched and encodes only the others; measured against encoding every chunk
//! afresh (what a checkpoint cost before, and what one still costs where every chunk changed),
//! from the same version in one process, the two ways taking turns.

use super::median;
use anyhow::Context;
use isovox_proto::BrickKey;
use isovox_server::store::codec::Compression;
use isovox_server::store::writer::{encode_checkpoint_chunks, CheckpointChunk};
use isovox_server::store::{BrickVoxels, CheckpointPolicy, Transaction, Vod2, Vod2Writer};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct CheckpointBenchArgs {
    /// The volume (copied into --dir; never written).
    #[arg(long)]
    pub world: PathBuf,
    /// Working directory for the copy (removed at the end).
    #[arg(long, default_value = "bench-out")]
    pub dir: PathBuf,
    /// Level-0 bricks edited, one commit each and no checkpoint, before the checkpoint is timed
    /// (256 commits is the server's default chain between checkpoints).
    #[arg(long, default_value_t = 256)]
    pub edits: usize,
    /// Timed checkpoints of each way.
    #[arg(long, default_value_t = 5)]
    pub rounds: usize,
}

pub fn run_bench(args: CheckpointBenchArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.dir)?;
    let path = args.dir.join("checkpoint-bench.vod");
    std::fs::copy(&args.world, &path).with_context(|| format!("copying {:?}", args.world))?;
    let never = CheckpointPolicy {
        max_overlay: usize::MAX,
        max_chain: usize::MAX,
    };
    // Edits at positions spread over the volume (a multiplicative walk), each a brick of noise.
    let layout = Vod2::open(&path)?.head().layout().clone();
    let g = layout.grid(0);
    let mut state = 0x9e37_79b9_u64;
    let started = Instant::now();
    for i in 0..args.edits {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1);
        let at = |shift: u32, n: u32| ((state >> shift) % u64::from(n)) as u32;
        let key = BrickKey {
            level: 0,
            x: at(20, g[0]),
            y: at(36, g[1]),
            z: at(48, g[2]),
        };
        let voxels: Vec<u8> = (0..layout.brick_bytes())
            .map(|j| (j as u8).wrapping_mul(29).wrapping_add(i as u8) % 220)
            .collect();
        let vod = Vod2::open(&path)?;
        let snap = vod.head();
        let mut w = Vod2Writer::open_append(&path, Compression::for_edits())?;
        let mut t = Transaction::on(&mut w, &snap);
        t.update_level0(
            vec![(key, BrickVoxels::Data(voxels))],
            &isovox_proto::geometry::Box3::of_volume(&layout),
        )?;
        t.commit(never)?;
    }
    println!(
        "{} edits of one level-0 brick each, one commit each, in {:.1} s",
        args.edits,
        started.elapsed().as_secs_f64()
    );
    let nodes = Vod2::open(&path)?.header().node_count();
    let checkpoint = |keep: bool| -> anyhow::Result<(Vec<u8>, usize, usize, f64)> {
        // A fresh open each time: no chunk decoded beforehand by the other way.
        let vod = Vod2::open(&path)?;
        let snap = vod.head();
        let t0 = Instant::now();
        let chunks = snap.next_checkpoint(&[], true, keep, |_, _| unreachable!("no changes"))?;
        let kept = chunks
            .iter()
            .filter(|c| matches!(c, CheckpointChunk::Kept(_)))
            .count();
        let total = chunks.len();
        let wide = snap.header().wide_summaries();
        let bytes = encode_checkpoint_chunks(nodes, chunks, true, wide);
        Ok((bytes, kept, total, t0.elapsed().as_secs_f64() * 1e3))
    };
    let (mut copying, mut encoding) = (Vec::new(), Vec::new());
    let (mut kept, mut total) = (0, 0);
    for _ in 0..args.rounds {
        let (a, k, n, ms_copy) = checkpoint(true)?;
        let (b, _, _, ms_all) = checkpoint(false)?;
        anyhow::ensure!(a == b, "the two ways wrote different checkpoints");
        (kept, total) = (k, n);
        copying.push(ms_copy);
        encoding.push(ms_all);
    }
    let (copy, all) = (median(copying), median(encoding));
    println!(
        "checkpoint of {nodes} entries after those edits: {kept} of {total} chunks kept as stored; \
         median of {} each, alternating: {copy:.1} ms copying untouched chunks, {all:.1} ms \
         encoding every chunk ({:.2}x)",
        args.rounds,
        all / copy
    );
    std::fs::remove_file(&path)?;
    Ok(())
}
