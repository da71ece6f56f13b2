//! What a run is asked to do: its users, what they stream and how their cameras move, the
//! editors' edits, and when it ends.

use super::RecordedPath;
use isovox_client::client::ClientError;
use isovox_client::streamer::{StreamerConfig, TileKind};
use isovox_proto::api::VolumeInfo;
use std::sync::Arc;
use std::time::Duration;

/// What to stream.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tiles {
    /// Bricks (voxels).
    Bricks,
    /// Marching-cubes mesh tiles at `iso` (the server's default when `None`).
    Meshes { iso: Option<f32> },
}

/// How the cameras move (world units: voxels times the volume's voxel scale; y is up).
#[derive(Debug, Clone)]
pub enum PathSpec {
    /// A circle around the volume's vertical centre line. `radius` defaults to 35% of the
    /// smaller horizontal extent, `height` to 95% of the volume's height (above the demo
    /// terrain's hills); one turn takes `period_s`. Each viewer starts at its own angle, turns
    /// its own way, and varies the radius by up to 20%.
    Orbit {
        radius: Option<f32>,
        height: Option<f32>,
        period_s: f32,
    },
    /// A seeded random walk at `speed` units per second (default 5% of the larger horizontal
    /// extent), turning gradually, between `low` and `high` (default 60% and 100% of the
    /// height), bouncing off the volume's sides.
    RandomWalk {
        speed: Option<f32>,
        low: Option<f32>,
        high: Option<f32>,
    },
    /// A recorded path, played in a loop, each viewer from its own (seeded) point in it.
    Recorded(Arc<RecordedPath>),
}

impl PathSpec {
    pub(super) fn name(&self) -> &'static str {
        match self {
            PathSpec::Orbit { .. } => "orbit",
            PathSpec::RandomWalk { .. } => "random-walk",
            PathSpec::Recorded(_) => "recorded",
        }
    }
}

/// A load run.
#[derive(Debug, Clone)]
pub struct LoadConfig {
    /// The server, e.g. `http://127.0.0.1:7070`.
    pub url: String,
    pub volume: String,
    /// Users who only view.
    pub viewers: usize,
    /// Users who view and edit.
    pub editors: usize,
    /// How long the run lasts (unless `max_requests` stops it first).
    pub duration: Duration,
    /// Stop once this many HTTP exchanges were made (checked every 50 ms).
    pub max_requests: Option<u64>,
    /// The write token editors send.
    pub token: Option<String>,
    pub tiles: Tiles,
    pub path: PathSpec,
    /// Camera updates per second.
    pub camera_hz: f64,
    /// Users start evenly spread over this time (all at once when zero); it counts in
    /// `duration`.
    pub ramp_up: Duration,
    /// Streamer detail radii (world units); when `None`, derived from `max_error_px`.
    pub radii: Option<Vec<f32>>,
    /// The screen-space error the radii are derived for (60 degree field of view, 1080-pixel
    /// viewport: [`StreamerConfig::radii_for_screen_error`]). 16 by default: the streamer's own
    /// default (1 pixel) asks for level 0 within about 1,900 units, all of the demo world, so
    /// that after the first load a moving camera would need nothing new.
    pub max_error_px: f32,
    /// Requests each streamer keeps in flight; the streamer's default when `None`.
    pub max_in_flight: Option<usize>,
    /// Each streamer's cache. 16 MiB by default (a streamer's own default is 256 MiB, and a run
    /// holds a hundred of them in one process).
    pub cache_bytes: usize,
    /// The streamers' octree descent ([`StreamerConfig::descent`]); on by default.
    pub descent: bool,
    /// Whether mesh streamers skip the tiles their bricks' ranges rule out
    /// ([`StreamerConfig::skip_empty`]); true by default, false to ask for every tile.
    pub skip_empty: bool,
    /// Edits per second per editor.
    pub edit_rate: f64,
    /// Radii of the edited ellipsoids, voxels (each axis drawn in `min..=max`).
    pub edit_radius: (u32, u32),
    /// The share of edits that carve (difference); the others add (union).
    pub carve_fraction: f64,
    /// The share of edits after which an editor undoes one of its own edits.
    pub undo_fraction: f64,
    /// Presence messages per second per viewer (0: none): the viewer's camera position,
    /// timed to its arrival at the change-feed subscribers.
    pub presence_hz: f64,
    /// Tokens viewers say where they are with, one user each, taken in turn (the server allows
    /// a few presence messages a second per user); the write token when empty.
    pub presence_tokens: Vec<String>,
    /// Change-feed subscribers timing edit notifications; `min(viewers, 8)` (at least 1) when
    /// `None` and there are editors.
    pub subscribers: Option<usize>,
    pub seed: u64,
    /// How long, after the end, subscribers wait for the last notifications and streamers
    /// for their requests in flight.
    pub drain: Duration,
    /// Draw a progress bar on stderr (only when it is a terminal).
    pub progress: bool,
}

impl LoadConfig {
    /// A run with the defaults of `isovox-load`: 10 viewers, no editor, 30 s, bricks, orbits.
    pub fn new(url: &str, volume: &str) -> LoadConfig {
        LoadConfig {
            url: url.to_string(),
            volume: volume.to_string(),
            viewers: 10,
            editors: 0,
            duration: Duration::from_secs(30),
            max_requests: None,
            token: None,
            tiles: Tiles::Bricks,
            path: PathSpec::Orbit {
                radius: None,
                height: None,
                period_s: 60.0,
            },
            camera_hz: 30.0,
            ramp_up: Duration::ZERO,
            radii: None,
            max_error_px: 16.0,
            max_in_flight: None,
            cache_bytes: 16 << 20,
            descent: true,
            skip_empty: true,
            edit_rate: 1.0,
            edit_radius: (4, 12),
            carve_fraction: 0.5,
            undo_fraction: 0.0,
            presence_hz: 0.0,
            presence_tokens: Vec::new(),
            subscribers: None,
            seed: 1,
            drain: Duration::from_secs(10),
            progress: false,
        }
    }

    /// The streamers' configuration for `info`'s volume.
    pub fn streamer_config(&self, info: &VolumeInfo) -> StreamerConfig {
        let d = StreamerConfig::default();
        StreamerConfig {
            kind: match self.tiles {
                Tiles::Bricks => TileKind::Bricks,
                Tiles::Meshes { iso } => TileKind::Meshes { iso },
            },
            radii: self.radii.clone().unwrap_or_else(|| {
                StreamerConfig::radii_for_screen_error(
                    info,
                    60f32.to_radians(),
                    1080.0,
                    self.max_error_px,
                )
            }),
            max_in_flight: self.max_in_flight.unwrap_or(d.max_in_flight),
            cache_bytes: self.cache_bytes,
            follow_edits: true,
            descent: self.descent,
            skip_empty: self.skip_empty,
        }
    }

    pub(super) fn subscriber_count(&self) -> usize {
        if self.editors == 0 {
            return 0;
        }
        self.subscribers.unwrap_or(self.viewers.clamp(1, 8))
    }
}

/// Why a run could not start.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{0}")]
    Config(String),
    #[error("cannot read the volume: {0}")]
    Client(#[from] ClientError),
}
