//! Index checkpoints written after edits: a checkpoint keeps the chunks of the one before that
//! no commit since has touched, copied as they are stored, and encodes only the others. What
//! it writes must be what encoding every entry afresh writes, byte for byte, and must hold what
//! the same edits give without any checkpoint.

use crate::server_process::run_isovox;
use isovox_proto::vod2::{BrickSummary, NodeEntry};
use isovox_proto::BrickKey;
use isovox_server::store::codec::Compression;
use isovox_server::store::writer::{encode_checkpoint, CheckpointChunk};
use isovox_server::store::{BrickVoxels, CheckpointPolicy, Transaction, Vod2, Vod2Writer};
use std::path::Path;

/// Never a checkpoint.
const NO_CHECKPOINT: CheckpointPolicy = CheckpointPolicy {
    max_overlay: usize::MAX,
    max_chain: usize::MAX,
};

/// A checkpoint on every commit.
const ALWAYS_CHECKPOINT: CheckpointPolicy = CheckpointPolicy {
    max_overlay: 0,
    max_chain: 0,
};

/// Writes noise into the level-0 brick at `(x, y, z)` of the head of `path`, committed with
/// `policy`; returns whether the commit wrote a checkpoint.
pub(crate) fn edit(path: &Path, [x, y, z]: [u32; 3], seed: u8, policy: CheckpointPolicy) -> bool {
    let vod = Vod2::open(path).unwrap();
    let snap = vod.head();
    let layout = snap.layout().clone();
    let mut w = Vod2Writer::open_append(path, Compression::for_edits()).unwrap();
    let voxels: Vec<u8> = (0..layout.brick_bytes())
        .map(|i| (i as u8).wrapping_mul(29).wrapping_add(seed) % 220)
        .collect();
    let key = BrickKey { level: 0, x, y, z };
    let mut t = Transaction::on(&mut w, &snap);
    t.update_level0(
        vec![(key, BrickVoxels::Data(voxels))],
        &isovox_proto::geometry::Box3::of_volume(&layout),
    )
    .unwrap();
    t.commit(policy).unwrap().checkpoint
}

/// Every entry of the head of `path`, file-wide (every stream's, in file order), raw, with its
/// summary as the head's index gives it.
fn head_entries(path: &Path) -> (Vec<u64>, Vec<BrickSummary>) {
    let vod = Vod2::open(path).unwrap();
    let snap = vod.head();
    let (mut entries, mut summaries) = (Vec::new(), Vec::new());
    for view in snap.streams() {
        for node in 0..view.layout().node_count() {
            let entry = view.entry_at(node).unwrap();
            entries.push(entry.encode());
            summaries.push(match entry {
                NodeEntry::Stored(_) => view.summary_at(node).unwrap(),
                NodeEntry::Constant(_) => BrickSummary::default(),
            });
        }
    }
    (entries, summaries)
}

#[test]
fn a_checkpoint_copies_untouched_chunks_and_equals_one_encoded_from_every_entry() {
    let dir = tempfile::tempdir().unwrap();
    let with = dir.path().join("with.vod");
    let without = dir.path().join("without.vod");
    // 32 x 8 x 32 level-0 bricks of 8: a density and a material stream of 9,363 nodes each,
    // 37 index chunks.
    run_isovox(&[
        "generate",
        "world",
        "-o",
        with.to_str().unwrap(),
        "--dims",
        "256,64,256",
        "--brick",
        "8",
        "--materials",
    ]);
    std::fs::copy(&with, &without).unwrap();
    let edits = [[0, 0, 0], [31, 7, 31], [16, 3, 9], [2, 5, 30]];
    for (i, &at) in edits.iter().enumerate() {
        assert!(!edit(&with, at, i as u8, NO_CHECKPOINT));
        assert!(!edit(&without, at, i as u8, NO_CHECKPOINT));
    }

    // What the next checkpoint keeps: most chunks, not those the edits touched.
    let vod = Vod2::open(&with).unwrap();
    let chunks = vod
        .head()
        .next_checkpoint(&[], true, true, |_, _| unreachable!("no changes"))
        .unwrap();
    let kept = chunks
        .iter()
        .filter(|c| matches!(c, CheckpointChunk::Kept(_)))
        .count();
    assert_eq!(chunks.len(), 37);
    // Each edit touches one level-0 brick and its ancestors: a chunk of density's level 0 and
    // the chunks of its coarser levels; the material stream's 19 chunks are untouched.
    assert!((20..37).contains(&kept), "{kept} of 37 chunks kept");
    drop(vod);

    // One more edit, with a checkpoint in one file and without in the other.
    let last = [9, 1, 17];
    assert!(edit(&with, last, 99, ALWAYS_CHECKPOINT));
    assert!(!edit(&without, last, 99, NO_CHECKPOINT));

    // The same entries and summaries: brick records lie at the same offsets in both files,
    // since the checkpoint is written after the last edit's bricks.
    let (entries, summaries) = head_entries(&without);
    assert_eq!(head_entries(&with), (entries.clone(), summaries.clone()));

    // And the checkpoint is the one encoding every entry writes.
    let vod = Vod2::open(&with).unwrap();
    let (at, len) = vod.head().checkpoint_span().unwrap();
    let bytes = std::fs::read(&with).unwrap();
    let written = &bytes[at as usize..(at + len) as usize];
    let fresh = encode_checkpoint(&entries, &summaries);
    assert_eq!(written.len(), fresh.len());
    assert!(written == &fresh[..], "the checkpoints differ");
}
