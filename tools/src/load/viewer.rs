//! A viewer: one user's streamer, its camera flown along a path, its events counted.

use super::{CameraPath, LoadConfig};
use isovox_client::client::Client;
use isovox_client::streamer::{StreamEvent, Streamer, StreamerConfig, StreamerStats, TileData};
use isovox_proto::VoxelType;
use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

/// One viewer's counts.
#[derive(Debug, Default)]
pub(super) struct ViewerResult {
    pub(super) started: bool,
    /// The run ended before the ramp-up reached this user.
    pub(super) not_started: bool,
    pub(super) radii: Vec<f32>,
    pub(super) ready: u64,
    pub(super) ready_by_level: Vec<u64>,
    pub(super) ready_bytes: u64,
    pub(super) dropped: u64,
    pub(super) stale: u64,
    pub(super) versions: u64,
    pub(super) errors: u64,
    pub(super) error_samples: Vec<String>,
    /// When the first and the last error event arrived.
    pub(super) error_span: Option<(Instant, Instant)>,
    pub(super) closed_early: bool,
    pub(super) stats: Option<StreamerStats>,
    /// When the viewer began (before its streamer's start: the metadata and the subscription
    /// count), and from then to its first `Ready` event.
    began: Option<Instant>,
    pub(super) first_ready: Option<Duration>,
    /// The volume's voxel type, once the streamer started (what a brick's surface value is).
    voxel_type: Option<VoxelType>,
    /// From the viewer's start to its first `Ready` tile that draws something: a mesh tile
    /// with a triangle, or a brick with voxels on both sides of the surface value. An empty
    /// tile is `Ready` too (air near the camera comes first), so the first tile alone says
    /// little of when a viewer sees the surface.
    pub(super) first_drawn: Option<Duration>,
}

/// Whether a delivered tile draws something: a mesh tile with a triangle, or a brick whose
/// voxels lie on both sides of the surface value S (`docs/icvg.md`).
fn draws(data: &TileData, voxel_type: VoxelType) -> bool {
    match data {
        TileData::Mesh(m) => m.mesh.triangles() > 0,
        TileData::Brick(bytes) => {
            let s = voxel_type.surface();
            let (mut below, mut above) = (false, false);
            let mut see = |v: u16| {
                below |= v < s;
                above |= v >= s;
            };
            match voxel_type {
                VoxelType::U8 => bytes.iter().for_each(|&v| see(u16::from(v))),
                VoxelType::U16 => bytes
                    .chunks_exact(2)
                    .for_each(|v| see(u16::from_le_bytes([v[0], v[1]]))),
                // Density is u8 or u16: a volume of another type draws nothing here.
                VoxelType::U32 | VoxelType::U64 => {}
            }
            below && above
        }
    }
}

impl ViewerResult {
    fn record(&mut self, event: StreamEvent) {
        match event {
            StreamEvent::Ready { key, data, .. } => {
                if self.first_ready.is_none() {
                    self.first_ready = self.began.map(|b| b.elapsed());
                }
                if self.first_drawn.is_none() && self.voxel_type.is_some_and(|t| draws(&data, t)) {
                    self.first_drawn = self.began.map(|b| b.elapsed());
                }
                self.ready += 1;
                let l = usize::from(key.level);
                if self.ready_by_level.len() <= l {
                    self.ready_by_level.resize(l + 1, 0);
                }
                self.ready_by_level[l] += 1;
                self.ready_bytes += data.bytes();
            }
            StreamEvent::Dropped { .. } => self.dropped += 1,
            StreamEvent::Stale { .. } => self.stale += 1,
            StreamEvent::Version { .. } => self.versions += 1,
            StreamEvent::Error { key, error } => {
                self.errors += 1;
                let now = Instant::now();
                let span = self.error_span.get_or_insert((now, now));
                span.1 = now;
                if self.error_samples.len() < 5 {
                    self.error_samples.push(match key {
                        Some(k) => format!("{k}: {error}"),
                        None => error,
                    });
                }
            }
        }
    }
}

/// Runs `fut` while counting `rx`'s events.
async fn draining<F: Future>(
    rx: &mut mpsc::Receiver<StreamEvent>,
    result: &mut ViewerResult,
    fut: F,
) -> F::Output {
    tokio::pin!(fut);
    loop {
        tokio::select! {
            out = &mut fut => return out,
            event = rx.recv() => match event {
                Some(e) => result.record(e),
                None => return fut.await,
            },
        }
    }
}

/// One user's streamer: starts it, flies the camera until `stop`, lets it finish what it has
/// in flight, shuts it down.
#[allow(clippy::too_many_arguments)]
pub(super) async fn viewer(
    client: Client,
    config: Arc<LoadConfig>,
    streamer_config: StreamerConfig,
    mut path: CameraPath,
    delay: Duration,
    mut stop: watch::Receiver<bool>,
    mut until: watch::Receiver<Option<u64>>,
    presence: Option<(Client, Arc<super::presence::PresenceLog>, usize)>,
) -> ViewerResult {
    let mut result = ViewerResult::default();
    tokio::select! {
        () = tokio::time::sleep(delay) => {}
        _ = stop.wait_for(|s| *s) => {
            result.not_started = true;
            return result;
        }
    }
    result.began = Some(Instant::now());
    let (streamer, mut rx) = match Streamer::start(client, &config.volume, streamer_config).await {
        Ok(s) => s,
        Err(e) => {
            result.errors += 1;
            result.error_samples.push(format!("streamer start: {e}"));
            return result;
        }
    };
    result.started = true;
    result.voxel_type = Some(streamer.info().voxel_type);
    result.radii = streamer.radii().to_vec();
    let start = Instant::now();
    streamer.set_camera(path.at(0.0));
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / config.camera_hz.max(0.1)));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut open = true;
    // Presence, when asked for: the camera's position every 1/presence_hz seconds.
    let presence_period = Duration::from_secs_f64(1.0 / config.presence_hz.max(1e-3));
    let mut say_where = tokio::time::interval(presence_period);
    say_where.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut said = 0u64;
    while !*stop.borrow() {
        tokio::select! {
            changed = stop.changed() => if changed.is_err() { break },
            _ = tick.tick() => streamer.set_camera(path.at(start.elapsed().as_secs_f32())),
            _ = say_where.tick(), if presence.is_some() => {
                if let Some((client, log, user)) = &presence {
                    said += 1;
                    let label = format!("viewer {user} #{said}");
                    let at = path.at(start.elapsed().as_secs_f32());
                    let request = isovox_proto::history::PresenceRequest {
                        position: at.map(f64::from),
                        looking: None,
                        label: Some(label.clone()),
                    };
                    log.sending(&label);
                    let answer = client.presence(&config.volume, &request).await;
                    log.answered(answer.map_err(|e| e.status().map(|s| s.as_u16())));
                }
            }
            event = rx.recv(), if open => match event {
                Some(e) => result.record(e),
                None => { open = false; result.closed_early = true; }
            },
        }
    }
    // The camera stops; once the editors are done, the streamer catches up with the last
    // acknowledged version and loads what the camera needs (or the drain time runs out).
    let catch_up = async {
        let last = match until.wait_for(Option::is_some).await {
            Ok(v) => v.unwrap_or(0),
            Err(_) => 0,
        };
        streamer.wait_version(last).await;
    };
    let _ = draining(
        &mut rx,
        &mut result,
        tokio::time::timeout(config.drain, catch_up),
    )
    .await;
    result.stats = Some(streamer.stats());
    draining(&mut rx, &mut result, streamer.shutdown()).await;
    result
}
