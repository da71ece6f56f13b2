//! What a run measured ([`LoadReport`]), built one section at a time (routes, edits,
//! notifications, streamers) from the recorder and the workers' results.

use super::editor::EditorResult;
use super::stats::{Latency, Recorder};
use super::subscriber::SubscriberResult;
use super::viewer::ViewerResult;
use super::{LoadConfig, Tiles};
use isovox_client::streamer::StreamerConfig;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

/// One route's figures (`route` is the client's name for it: `brick`, `mesh`, `edit`, ...;
/// `all` for the sum).
#[derive(Debug, Clone, Serialize)]
pub struct RouteReport {
    pub route: String,
    /// Exchanges (every attempt of a retried call).
    pub requests: u64,
    /// 2xx answers.
    pub ok: u64,
    /// 304 answers (revalidated bricks).
    pub not_modified: u64,
    /// Exchanges that failed their call: other statuses and transport failures, except those
    /// the client tried again after (`retried`).
    pub errors: u64,
    /// Unsuccessful exchanges the client tried again after (503 or 429 while the server sheds
    /// load, a transport failure of a call it may repeat); the call's last attempt decides
    /// whether it failed.
    pub retried: u64,
    /// Response body bytes (as announced by Content-Length; 0 for streams).
    pub bytes: u64,
    pub requests_per_s: f64,
    pub mib_per_s: f64,
    /// Time to the response's headers.
    pub latency_ms: Latency,
    /// Exchanges by status code or transport failure kind.
    pub outcomes: BTreeMap<String, u64>,
}

/// Errors of one kind from one source.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ErrorCount {
    /// A route (HTTP exchanges), or `streamer`, `feed`, `notification`, `edit`.
    pub source: String,
    /// A status code or transport failure kind, or what went wrong.
    pub kind: String,
    pub count: u64,
    /// Seconds after the run's start of the first and the last one (HTTP exchanges and
    /// streamer error events).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_s: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_s: Option<f64>,
}

/// What the editors did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct EditReport {
    pub editors: usize,
    /// Edits per second per editor asked for.
    pub rate_per_editor: f64,
    pub attempted: u64,
    pub acknowledged: u64,
    pub failed: u64,
    pub carves: u64,
    pub additions: u64,
    pub acknowledged_per_s: f64,
    /// From sending an edit to its acknowledgement (the whole call, retries included).
    pub latency_ms: Latency,
    /// Undos of the editors' own edits (`--undo-fraction`) acknowledged.
    pub undos: u64,
    /// Edits the server applied again over the undone ones, in all.
    pub replayed: u64,
    /// From sending an undo to its acknowledgement.
    pub undo_latency_ms: Latency,
}

/// Edit-to-notification: from an edit's acknowledgement (as its editor received it) to the
/// arrival of its version on each dedicated change-feed subscriber.
#[derive(Debug, Clone, Default, Serialize)]
pub struct NotificationReport {
    pub subscribers: usize,
    /// Acknowledged edits times subscribers.
    pub expected: u64,
    pub seen: u64,
    pub missing: u64,
    /// Notifications that arrived before the editor had its acknowledgement (counted as 0).
    pub before_ack: u64,
    /// `resync` events (a subscriber fell behind; the gap was fetched from `changes`).
    pub resyncs: u64,
    /// Times a subscription broke and was resumed.
    pub reconnects: u64,
    /// From the acknowledgement to the arrival.
    pub latency_ms: Latency,
    /// From sending the edit to the arrival (the edit's own latency included).
    pub from_send_ms: Latency,
}

/// The streamers' side, summed over every user.
#[derive(Debug, Clone, Default, Serialize)]
pub struct StreamerReport {
    pub streamers: usize,
    /// Streamers that failed to start.
    pub failed_to_start: u64,
    /// Users the ramp-up had not reached when the run ended.
    pub never_started: u64,
    /// `Ready` events (tiles delivered), all levels.
    pub tiles_ready: u64,
    /// `Ready` tiles by level (level 0 first).
    pub ready_by_level: Vec<u64>,
    /// Bytes of the delivered tiles (decoded voxels, or mesh positions, normals and indices).
    pub ready_bytes: u64,
    pub dropped: u64,
    /// `Stale` events: tiles an edit changed.
    pub stale: u64,
    pub version_events: u64,
    pub error_events: u64,
    /// The first few error messages.
    pub error_samples: Vec<String>,
    /// The streamers' own counts ([`StreamerStats`]).
    pub requests: u64,
    pub bytes: u64,
    pub cache_hits: u64,
    pub cache_misses: u64,
    /// `cache_hits / (cache_hits + cache_misses)`.
    pub cache_hit_rate: f64,
    pub stale_refetches: u64,
    /// Grid regions the streamers asked for, of those the ones a tile needed because a commit
    /// invalidated it ([`StreamerStats::edit_grid_requests`]), and the ones dropped before
    /// their answer was used ([`StreamerStats::grid_aborted`]: a coarser answer decided the
    /// tiles that wanted them, sent or not).
    pub grid_requests: u64,
    pub edit_grid_requests: u64,
    pub grid_aborted: u64,
    /// Tiles skipped because no surface can cross them (by the descent, or from the bricks'
    /// ranges: [`StreamerConfig::skip_empty`]).
    pub skipped: u64,
    /// Per started viewer, from its start (metadata and subscription included) to its first
    /// `Ready` tile; viewers that got none are counted in `without_tile`.
    pub first_tile_ms: Latency,
    pub without_tile: u64,
    /// Per started viewer, from its start to its first tile that draws something (a mesh
    /// tile with a triangle, a brick with voxels on both sides of the surface value); viewers
    /// that got none are counted in `without_drawn`.
    pub first_drawn_ms: Latency,
    pub without_drawn: u64,
    pub resident_at_end: u64,
    pub in_flight_at_end: u64,
    /// The streamers' limits on requests in flight at the end, summed: `max_in_flight` each,
    /// less where the server answered 503 and the limit has not grown back yet.
    pub in_flight_limit_at_end: u64,
    /// The newest version any streamer had reached at the end.
    pub max_version: u64,
    /// The oldest version a streamer had reached at the end.
    pub min_version: u64,
}

/// Everything a run measured.
#[derive(Debug, Clone, Serialize)]
pub struct LoadReport {
    pub url: String,
    pub volume: String,
    pub viewers: usize,
    pub editors: usize,
    pub tiles: String,
    pub path: String,
    /// The streamers' detail radii, world units (level k within `radii[k]`).
    pub radii: Vec<f32>,
    /// Requests each streamer keeps in flight.
    pub max_in_flight: usize,
    /// Each streamer's content cache, bytes.
    pub cache_bytes: usize,
    /// The configured duration.
    pub duration_s: f64,
    /// From the first request to the end of the drain; rates are per this.
    pub elapsed_s: f64,
    pub version_start: u64,
    pub version_end: u64,
    pub total: RouteReport,
    pub routes: Vec<RouteReport>,
    pub errors: Vec<ErrorCount>,
    /// The sum of `errors`; `isovox-load` exits non-zero when it is not 0.
    pub errors_total: u64,
    pub edits: EditReport,
    pub notifications: NotificationReport,
    pub streamers: StreamerReport,
    /// Presence messages, when viewers sent them (`--presence-hz`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub presence: Option<super::presence::PresenceReport>,
}

/// Everything a run measured, section by section; the failures every section finds are listed
/// in `errors` in the order of the sections.
pub(super) fn report(
    config: &LoadConfig,
    recorder: &Recorder,
    elapsed: Duration,
    (version_start, version_end): (u64, u64),
    editors: &[EditorResult],
    subscribers: &[SubscriberResult],
    viewers: &[ViewerResult],
) -> LoadReport {
    let secs = elapsed.as_secs_f64().max(1e-9);
    let mut errors = Vec::new();
    let (routes, total) = route_section(recorder, secs, &mut errors);
    let (edits, acks) = edit_section(config, editors, secs, &mut errors);
    let notifications = notification_section(subscribers, &acks, &mut errors);
    let streamers = streamer_section(viewers, recorder.start, &mut errors);
    let errors_total = errors.iter().map(|e| e.count).sum();

    LoadReport {
        url: config.url.clone(),
        volume: config.volume.clone(),
        viewers: config.viewers,
        editors: config.editors,
        tiles: match config.tiles {
            Tiles::Bricks => "bricks".into(),
            Tiles::Meshes { .. } => "meshes".into(),
        },
        path: config.path.name().into(),
        radii: viewers
            .iter()
            .find(|v| v.started)
            .map(|v| v.radii.clone())
            .unwrap_or_default(),
        max_in_flight: config
            .max_in_flight
            .unwrap_or(StreamerConfig::default().max_in_flight),
        cache_bytes: config.cache_bytes,
        duration_s: config.duration.as_secs_f64(),
        elapsed_s: secs,
        version_start,
        version_end,
        total,
        routes,
        errors,
        errors_total,
        edits,
        notifications,
        streamers,
        presence: None,
    }
}

/// Each route's figures and all of them together, from every exchange the recorder saw (over
/// `secs`); each route's failures, by kind, into `errors`.
fn route_section(
    recorder: &Recorder,
    secs: f64,
    errors: &mut Vec<ErrorCount>,
) -> (Vec<RouteReport>, RouteReport) {
    let mut routes = Vec::new();
    let mut all_latencies = Vec::new();
    let mut all_outcomes: BTreeMap<String, u64> = BTreeMap::new();
    let (mut all_bytes, mut all_errors, mut all_retried) = (0, 0, 0);
    {
        let mut accs = recorder.lock();
        for (route, acc) in accs.iter_mut() {
            all_latencies.extend_from_slice(&acc.latencies);
            for (k, v) in &acc.outcomes {
                *all_outcomes.entry(k.clone()).or_default() += v;
            }
            for (k, v) in &acc.failures {
                let times = acc.error_times.get(k);
                errors.push(ErrorCount {
                    source: (*route).to_string(),
                    kind: k.clone(),
                    count: *v,
                    first_s: times.map(|t| t.0),
                    last_s: times.map(|t| t.1),
                });
            }
            let failed = acc.failures.values().sum();
            all_bytes += acc.bytes;
            all_errors += failed;
            all_retried += acc.retried;
            routes.push(route_report(
                route,
                acc.bytes,
                (failed, acc.retried),
                &mut acc.latencies,
                &acc.outcomes,
                secs,
            ));
        }
    }
    let total = route_report(
        "all",
        all_bytes,
        (all_errors, all_retried),
        &mut all_latencies,
        &all_outcomes,
        secs,
    );
    (routes, total)
}

/// What the editors did (rates over `secs`), and when each acknowledged version was sent and
/// acknowledged; edits that failed other than over HTTP into `errors`.
fn edit_section(
    config: &LoadConfig,
    editors: &[EditorResult],
    secs: f64,
    errors: &mut Vec<ErrorCount>,
) -> (EditReport, HashMap<u64, (Instant, Instant)>) {
    let mut edit_latencies = Vec::new();
    let mut undo_latencies = Vec::new();
    let mut acks: HashMap<u64, (Instant, Instant)> = HashMap::new();
    let mut edits = EditReport {
        editors: config.editors,
        rate_per_editor: config.edit_rate,
        ..EditReport::default()
    };
    let mut edit_failures: BTreeMap<String, u64> = BTreeMap::new();
    for e in editors {
        edits.attempted += e.attempted;
        edits.carves += e.carves;
        edits.additions += e.additions;
        edits.acknowledged += e.acks.len() as u64;
        for (version, sent, acked) in &e.acks {
            acks.insert(*version, (*sent, *acked));
            edit_latencies.push(acked.saturating_duration_since(*sent));
        }
        edits.undos += e.undos.len() as u64;
        for (sent, acked, replayed) in &e.undos {
            undo_latencies.push(acked.saturating_duration_since(*sent));
            edits.replayed += replayed;
        }
        for (k, v) in &e.failures {
            edits.failed += v;
            *edit_failures.entry(k.clone()).or_default() += v;
        }
    }
    edits.acknowledged_per_s = edits.acknowledged as f64 / secs;
    edits.latency_ms = Latency::from_durations(&edit_latencies);
    edits.undo_latency_ms = Latency::from_durations(&undo_latencies);
    // HTTP failures of edits are counted with the route; the others (an answer that did not
    // decode) only here.
    for (kind, count) in edit_failures {
        if kind == "decode" {
            errors.push(ErrorCount {
                source: "edit".into(),
                kind,
                count,
                first_s: None,
                last_s: None,
            });
        }
    }
    (edits, acks)
}

/// When the subscribers saw each acknowledged version (`acks`: when it was sent and
/// acknowledged); their feed failures, and notifications that never came, into `errors`.
fn notification_section(
    subscribers: &[SubscriberResult],
    acks: &HashMap<u64, (Instant, Instant)>,
    errors: &mut Vec<ErrorCount>,
) -> NotificationReport {
    let mut notifications = NotificationReport {
        subscribers: subscribers.len(),
        ..NotificationReport::default()
    };
    let (mut note_latencies, mut from_send) = (Vec::new(), Vec::new());
    for s in subscribers {
        notifications.resyncs += s.resyncs;
        notifications.reconnects += s.reconnects;
        for (version, (sent, acked)) in acks {
            notifications.expected += 1;
            match s.seen.get(version) {
                Some(arrived) => {
                    notifications.seen += 1;
                    if arrived < acked {
                        notifications.before_ack += 1;
                    }
                    note_latencies.push(arrived.saturating_duration_since(*acked));
                    from_send.push(arrived.saturating_duration_since(*sent));
                }
                None => notifications.missing += 1,
            }
        }
        for (kind, count) in &s.errors {
            errors.push(ErrorCount {
                source: "feed".into(),
                kind: kind.clone(),
                count: *count,
                first_s: None,
                last_s: None,
            });
        }
    }
    notifications.latency_ms = Latency::from_durations(&note_latencies);
    notifications.from_send_ms = Latency::from_durations(&from_send);
    if notifications.missing > 0 {
        errors.push(ErrorCount {
            source: "notification".into(),
            kind: "missing".into(),
            count: notifications.missing,
            first_s: None,
            last_s: None,
        });
    }
    notifications
}

/// The streamers' side, summed over every user; their error events and channels closed early
/// into `errors` (times in seconds after `start`, the run's).
fn streamer_section(
    viewers: &[ViewerResult],
    start: Instant,
    errors: &mut Vec<ErrorCount>,
) -> StreamerReport {
    let mut st = StreamerReport {
        streamers: viewers.len(),
        min_version: u64::MAX,
        ..StreamerReport::default()
    };
    let mut closed_early = 0;
    let mut error_span: Option<(Instant, Instant)> = None;
    let (mut first_tiles, mut first_drawn) = (Vec::new(), Vec::new());
    for v in viewers {
        match (v.started, v.first_ready) {
            (true, Some(d)) => first_tiles.push(d),
            (true, None) => st.without_tile += 1,
            (false, _) => {}
        }
        match (v.started, v.first_drawn) {
            (true, Some(d)) => first_drawn.push(d),
            (true, None) => st.without_drawn += 1,
            (false, _) => {}
        }
        if v.not_started {
            st.never_started += 1;
        } else if !v.started {
            st.failed_to_start += 1;
        }
        st.tiles_ready += v.ready;
        if st.ready_by_level.len() < v.ready_by_level.len() {
            st.ready_by_level.resize(v.ready_by_level.len(), 0);
        }
        for (l, n) in v.ready_by_level.iter().enumerate() {
            st.ready_by_level[l] += n;
        }
        st.ready_bytes += v.ready_bytes;
        st.dropped += v.dropped;
        st.stale += v.stale;
        st.version_events += v.versions;
        st.error_events += v.errors;
        for m in &v.error_samples {
            if st.error_samples.len() < 10 {
                st.error_samples.push(m.clone());
            }
        }
        if v.closed_early {
            closed_early += 1;
        }
        if let Some((a, b)) = v.error_span {
            let span = error_span.get_or_insert((a, b));
            *span = (span.0.min(a), span.1.max(b));
        }
        if let Some(s) = &v.stats {
            st.requests += s.requests;
            st.bytes += s.bytes;
            st.cache_hits += s.cache_hits;
            st.cache_misses += s.cache_misses;
            st.stale_refetches += s.stale_refetches;
            st.grid_requests += s.grid_requests;
            st.edit_grid_requests += s.edit_grid_requests;
            st.grid_aborted += s.grid_aborted;
            st.skipped += s.skipped;
            st.resident_at_end += s.resident as u64;
            st.in_flight_at_end += s.in_flight as u64;
            st.in_flight_limit_at_end += s.in_flight_limit as u64;
            st.max_version = st.max_version.max(s.version);
            st.min_version = st.min_version.min(s.version);
        }
    }
    st.first_tile_ms = Latency::from_durations(&first_tiles);
    st.first_drawn_ms = Latency::from_durations(&first_drawn);
    if st.min_version == u64::MAX {
        st.min_version = 0;
    }
    let lookups = st.cache_hits + st.cache_misses;
    st.cache_hit_rate = if lookups > 0 {
        st.cache_hits as f64 / lookups as f64
    } else {
        0.0
    };
    let since_start = |t: Instant| t.saturating_duration_since(start).as_secs_f64();
    for (kind, count, span) in [
        ("error event", st.error_events, error_span),
        ("closed early", closed_early, None),
    ] {
        if count > 0 {
            errors.push(ErrorCount {
                source: "streamer".into(),
                kind: kind.into(),
                count,
                first_s: span.map(|s| since_start(s.0)),
                last_s: span.map(|s| since_start(s.1)),
            });
        }
    }
    st
}

/// One route's figures, with its exchanges that failed their call and those the client tried
/// again after.
fn route_report(
    route: &str,
    bytes: u64,
    (errors, retried): (u64, u64),
    latencies: &mut [u32],
    outcomes: &BTreeMap<String, u64>,
    secs: f64,
) -> RouteReport {
    let requests = latencies.len() as u64;
    let count = |f: &dyn Fn(u16) -> bool| {
        outcomes
            .iter()
            .filter(|(k, _)| k.parse::<u16>().is_ok_and(f))
            .map(|(_, v)| v)
            .sum()
    };
    RouteReport {
        route: route.to_string(),
        requests,
        ok: count(&|s| (200..300).contains(&s)),
        not_modified: count(&|s| s == 304),
        errors,
        retried,
        bytes,
        requests_per_s: requests as f64 / secs,
        mib_per_s: bytes as f64 / secs / f64::from(1u32 << 20),
        latency_ms: Latency::from_micros(latencies),
        outcomes: outcomes.clone(),
    }
}

pub(super) fn plural(n: usize) -> &'static str {
    if n == 1 {
        ""
    } else {
        "s"
    }
}
