//! An editor: seeded random carves and additions of small ellipsoids at a steady rate, each
//! timed from sending to its acknowledgement.

use super::{LoadConfig, Rng};
use isovox_client::client::Client;
use isovox_proto::api::VolumeInfo;
use isovox_proto::icvg::{EditRequest, Term};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// One editor's counts.
#[derive(Debug, Default)]
pub(super) struct EditorResult {
    pub(super) attempted: u64,
    pub(super) carves: u64,
    pub(super) additions: u64,
    /// (version, sent at, acknowledged at).
    pub(super) acks: Vec<(u64, Instant, Instant)>,
    pub(super) failures: BTreeMap<String, u64>,
    /// Undos of this editor's own edits: (sent at, acknowledged at, edits applied again).
    pub(super) undos: Vec<(Instant, Instant, u64)>,
}

/// An ellipsoid carve or addition at a random place: x and z anywhere, y in the band the demo
/// terrain's surface lies in (15% to 85% of the height).
pub(super) fn random_edit(
    rng: &mut Rng,
    info: &VolumeInfo,
    config: &LoadConfig,
) -> (bool, EditRequest) {
    let carve = f64::from(rng.unit()) < config.carve_fraction;
    let d = info.dims.map(|v| v as f32);
    let center = [
        rng.range(0.0, d[0]),
        rng.range(0.15 * d[1], 0.85 * d[1]),
        rng.range(0.0, d[2]),
    ]
    .map(|v| v as i64);
    let (lo, hi) = (
        config.edit_radius.0.max(1),
        config.edit_radius.1.max(config.edit_radius.0.max(1)),
    );
    let radii = [0; 3].map(|_| (lo + (rng.next_u64() % u64::from(hi - lo + 1)) as u32).max(1));
    let op = if carve { "difference" } else { "union" };
    (
        carve,
        EditRequest {
            op: op.into(),
            term: Some(Term::Ellipsoid { center, radii }),
            s_l: None,
            k: None,
            region: None,
            message: None,
            channel: None,
            overwrite: None,
        },
    )
}

pub(super) async fn editor(
    client: Client,
    config: Arc<LoadConfig>,
    info: Arc<VolumeInfo>,
    seed: u64,
    delay: Duration,
    mut stop: watch::Receiver<bool>,
) -> EditorResult {
    let mut result = EditorResult::default();
    let mut rng = Rng::new(seed);
    // This editor's acknowledged edits not undone yet.
    let mut mine: Vec<u64> = Vec::new();
    let period = Duration::from_secs_f64(1.0 / config.edit_rate.max(0.001));
    // Editors start at different points of their period, so they do not edit in step.
    let first = tokio::time::Instant::now() + delay + period.mul_f32(rng.unit());
    let mut tick = tokio::time::interval_at(first, period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            changed = stop.changed() => if changed.is_err() || *stop.borrow() { break } else { continue },
            _ = tick.tick() => {}
        }
        if *stop.borrow() {
            break;
        }
        let (carve, request) = random_edit(&mut rng, &info, &config);
        result.attempted += 1;
        if carve {
            result.carves += 1;
        } else {
            result.additions += 1;
        }
        let sent = Instant::now();
        match client.edit(&config.volume, &request, None).await {
            Ok(r) => {
                result.acks.push((r.version, sent, Instant::now()));
                mine.push(r.version);
            }
            Err(e) => *result.failures.entry(e.kind()).or_default() += 1,
        }
        // Undo one of this editor's own edits still in effect, picked at random: later edits
        // of everyone over it are applied again by the server.
        if !mine.is_empty() && f64::from(rng.unit()) < config.undo_fraction {
            let version = mine.swap_remove((rng.next_u64() % mine.len() as u64) as usize);
            let sent = Instant::now();
            match client.undo(&config.volume, version).await {
                Ok(r) => result
                    .undos
                    .push((sent, Instant::now(), r.replayed.unwrap_or(0))),
                Err(e) => {
                    *result
                        .failures
                        .entry(format!("undo {}", e.kind()))
                        .or_default() += 1
                }
            }
        }
    }
    result
}
