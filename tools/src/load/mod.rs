//! The load tester behind `isovox-load`: simulated viewers and editors against one server.
//!
//! A run starts `viewers + editors` users. Every user is a [`Streamer`] whose camera flies a
//! [`CameraPath`] (an orbit, a seeded random walk, or a recorded path), moved at
//! `camera_hz`; its event channel is drained and counted. Editors also send edits (carves and
//! additions of small ellipsoids at seeded random places) at `edit_rate` per second each. A
//! few dedicated change-feed subscribers time every acknowledged edit's version from the
//! editor's acknowledgement to its arrival on the feed. Editors and subscribers run on a runtime
//! thread of their own, so that the streamers' work does not delay their clocks.
//!
//! Every HTTP exchange of every client goes through one [`Recorder`] (an [`Observer`]): the
//! report's per-route requests, bytes, throughput and latency (time to the response's
//! headers, per attempt, so a retried call counts each attempt) come from it, with every
//! sample kept. A status other than 2xx and 304, or a transport failure, is an error.
//!
//! Users start at once, or spread over `ramp_up`. The run stops after `duration`, once
//! `max_requests` exchanges were made, or when the caller's stop future resolves
//! ([`run_until`]); editors then stop, and subscribers and streamers get up to `drain` to reach
//! the last acknowledged version (streamers also load what their still camera needs) before
//! they shut down.
//!
//! Layout:
//! - [`config`]: what a run is asked to do ([`LoadConfig`]).
//! - [`camera`]: the cameras' paths, and the seeded generator users draw from.
//! - [`viewer`], [`editor`], [`subscriber`]: the workers: a user's streamer, an editor's edits,
//!   a change-feed subscriber timing them.
//! - [`stats`]: the [`Recorder`] every HTTP exchange goes through, and latency percentiles.
//! - [`report`]: what a run measured ([`LoadReport`]), built section by section from the
//!   workers' results; [`markdown`] writes it as tables.
//! - this file: a run, from starting the workers to the report.

mod camera;
mod config;
mod editor;
mod markdown;
mod presence;
mod report;
mod stats;
mod subscriber;
mod viewer;

pub use camera::{CameraPath, RecordedPath, Rng};
pub use config::{LoadConfig, LoadError, PathSpec, Tiles};
pub use presence::PresenceReport;
pub use report::{
    EditReport, ErrorCount, LoadReport, NotificationReport, RouteReport, StreamerReport,
};
pub use stats::{Latency, Recorder};

use editor::editor;
use isovox_client::client::{Client, ClientError};
use report::report;
use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};
use subscriber::subscriber;
use tokio::sync::{oneshot, watch};
use viewer::viewer;

/// The progress bar (hidden unless asked for and stderr is a terminal).
fn progress_bar(config: &LoadConfig) -> indicatif::ProgressBar {
    use std::io::IsTerminal;
    if !config.progress || !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(config.duration.as_secs().max(1));
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} s  {msg}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar
}

/// Runs the load test and reports what it measured.
///
/// # Errors
/// The volume cannot be read, the configuration is unusable (editors without a token), or a
/// change-feed subscriber could not subscribe. Failures during the run are counted in the
/// report, not returned.
pub async fn run(config: LoadConfig) -> Result<LoadReport, LoadError> {
    run_until(config, std::future::pending()).await
}

/// Aborts the tasks it holds when dropped: a run that fails to start leaves nothing behind.
#[derive(Debug, Default)]
struct Tasks(Vec<tokio::task::AbortHandle>);

impl Drop for Tasks {
    fn drop(&mut self) {
        for t in &self.0 {
            t.abort();
        }
    }
}

/// A runtime that may be dropped from async code (it shuts down in the background).
#[derive(Debug)]
struct SideRuntime(Option<tokio::runtime::Runtime>);

impl SideRuntime {
    fn handle(&self) -> tokio::runtime::Handle {
        match &self.0 {
            Some(r) => r.handle().clone(),
            None => tokio::runtime::Handle::current(),
        }
    }
}

impl Drop for SideRuntime {
    fn drop(&mut self) {
        if let Some(r) = self.0.take() {
            r.shutdown_background();
        }
    }
}

/// [`run`], ending early (with a report) when `stop` resolves, e.g. on Ctrl-C.
///
/// # Errors
/// As [`run`].
pub async fn run_until(
    config: LoadConfig,
    stop: impl Future<Output = ()>,
) -> Result<LoadReport, LoadError> {
    if config.editors > 0 && config.token.is_none() {
        return Err(LoadError::Config("editors need a write token".into()));
    }
    if config.viewers + config.editors == 0 {
        return Err(LoadError::Config("nobody to simulate".into()));
    }
    let started = Instant::now();
    let recorder = Arc::new(Recorder::default());
    let config = Arc::new(config);
    // Linked with the server library, reqwest's rustls needs ring installed as its provider.
    isovox_server::client_tls::install_provider();
    let make_client = || -> Result<Client, ClientError> {
        let c = Client::new(&config.url)?.with_observer(recorder.clone());
        Ok(match &config.token {
            Some(t) => c.with_token(t.clone()),
            None => c,
        })
    };
    let probe = make_client()?;
    let info = Arc::new(probe.volume(&config.volume).await?);
    let version_start = info.version;
    let streamer_config = config.streamer_config(&info);
    let (stop_tx, stop_rx) = watch::channel(false);
    // After the end: the last acknowledged version, for subscribers and streamers to reach.
    let (until_tx, until_rx) = watch::channel(None::<u64>);
    let seed_of = |role: u64, i: usize| {
        Rng::new(config.seed ^ (role << 56) ^ (i as u64).wrapping_mul(0x9e37_79b9)).next_u64()
    };

    // Editors and subscribers time edits: they run on a runtime of their own, so that a
    // hundred streamers busy on the main one do not stand between an event and its clock.
    let side_runtime = SideRuntime(Some(
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("isovox-load-edits")
            .enable_all()
            .build()
            .map_err(|e| LoadError::Config(format!("cannot start a runtime: {e}")))?,
    ));
    let side = side_runtime.handle();

    let presence_log = Arc::new(presence::PresenceLog::default());
    // Subscribers first, so that every acknowledged edit comes after their hello.
    let mut tasks = Tasks::default();
    let mut subscribers = Vec::new();
    let mut hellos = Vec::new();
    for _ in 0..config.subscriber_count() {
        let (tx, rx) = oneshot::channel();
        let task = side.spawn(subscriber(
            make_client()?,
            config.volume.clone(),
            config.drain,
            tx,
            until_rx.clone(),
            presence_log.clone(),
        ));
        tasks.0.push(task.abort_handle());
        subscribers.push(task);
        hellos.push(rx);
    }
    for h in hellos {
        match h.await {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => return Err(LoadError::Client(e)),
            Err(_) => return Err(LoadError::Config("a subscriber stopped".into())),
        }
    }

    let users = config.viewers + config.editors;
    // User i starts at i/users of the ramp-up (editors are the last users).
    let ramp = |i: usize| config.ramp_up.mul_f64(i as f64 / users as f64);
    let mut viewers = Vec::with_capacity(users);
    for i in 0..users {
        // Viewers (not editors) say where they are, as the users of the presence tokens.
        let presence = match (
            config.presence_hz > 0.0 && i < config.viewers,
            &config.token,
        ) {
            (true, Some(token)) => {
                let token = match config.presence_tokens.len() {
                    0 => token.clone(),
                    n => config.presence_tokens[i % n].clone(),
                };
                Some((make_client()?.with_token(token), presence_log.clone(), i))
            }
            _ => None,
        };
        let task = tokio::spawn(viewer(
            make_client()?,
            config.clone(),
            streamer_config.clone(),
            CameraPath::new(&config.path, &info, seed_of(1, i)),
            ramp(i),
            stop_rx.clone(),
            until_rx.clone(),
            presence,
        ));
        tasks.0.push(task.abort_handle());
        viewers.push(task);
    }
    let mut editors = Vec::with_capacity(config.editors);
    for i in 0..config.editors {
        let task = side.spawn(editor(
            make_client()?,
            config.clone(),
            info.clone(),
            seed_of(2, i),
            ramp(config.viewers + i),
            stop_rx.clone(),
        ));
        tasks.0.push(task.abort_handle());
        editors.push(task);
    }

    // Run until the time is up or enough requests were made.
    let bar = progress_bar(&config);
    let run_start = Instant::now();
    let mut window: std::collections::VecDeque<(Instant, u64)> = Default::default();
    let mut tick = tokio::time::interval(Duration::from_millis(50));
    tokio::pin!(stop);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = &mut stop => break,
        }
        let now = Instant::now();
        let requests = recorder.requests();
        if now - run_start >= config.duration || config.max_requests.is_some_and(|n| requests >= n)
        {
            break;
        }
        window.push_back((now, requests));
        while window
            .front()
            .is_some_and(|(t, _)| now - *t > Duration::from_secs(1))
        {
            window.pop_front();
        }
        if let Some((t0, r0)) = window.front() {
            let dt = (now - *t0).as_secs_f64();
            let rate = if dt > 0.0 {
                (requests - r0) as f64 / dt
            } else {
                0.0
            };
            bar.set_position((now - run_start).as_secs());
            bar.set_message(format!(
                "{rate:.0} req/s, {requests} requests, {} errors",
                recorder.errors()
            ));
        }
    }
    bar.set_message("draining");
    let _ = stop_tx.send(true);

    let mut editor_results = Vec::new();
    for e in editors {
        if let Ok(r) = e.await {
            editor_results.push(r);
        }
    }
    let last_version = editor_results
        .iter()
        .flat_map(|e| e.acks.iter().map(|a| a.0))
        .max()
        .unwrap_or(version_start);
    let _ = until_tx.send(Some(last_version));
    let mut subscriber_results = Vec::with_capacity(subscribers.len());
    for s in subscribers {
        if let Ok(r) = s.await {
            subscriber_results.push(r);
        }
    }
    let mut viewer_results = Vec::new();
    for v in viewers {
        if let Ok(r) = v.await {
            viewer_results.push(r);
        }
    }
    bar.finish_and_clear();
    let elapsed = started.elapsed();
    let version_end = probe
        .volume(&config.volume)
        .await
        .map_or(last_version, |i| i.version);

    let mut report = report(
        &config,
        &recorder,
        elapsed,
        (version_start, version_end),
        &editor_results,
        &subscriber_results,
        &viewer_results,
    );
    if config.presence_hz > 0.0 {
        report.presence = Some(presence_log.report());
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::editor::random_edit;
    use super::*;
    use isovox_proto::api::VolumeInfo;
    use isovox_proto::icvg::Term;

    #[test]
    fn recorded_paths_parse_and_interpolate() {
        let p =
            RecordedPath::parse("# t x y z\n0 0 0 0\n\n2 10 20 30  # two seconds\n4 10 20 50\n")
                .unwrap();
        assert_eq!(p.span(), 4.0);
        assert_eq!(p.at(0.0), [0.0, 0.0, 0.0]);
        assert_eq!(p.at(1.0), [5.0, 10.0, 15.0]);
        assert_eq!(p.at(3.0), [10.0, 20.0, 40.0]);
        // It loops.
        assert_eq!(p.at(5.0), [5.0, 10.0, 15.0]);
        assert!(RecordedPath::parse("0 1 2").unwrap_err().contains("line 1"));
        assert!(RecordedPath::parse("1 0 0 0\n0 0 0 0")
            .unwrap_err()
            .contains("line 2"));
        assert!(RecordedPath::parse("# nothing\n").is_err());
        assert_eq!(
            RecordedPath::parse("3 1 2 3").unwrap().at(7.0),
            [1.0, 2.0, 3.0]
        );
    }

    #[test]
    fn percentiles_by_nearest_rank() {
        let mut v: Vec<u32> = (1..=1000).rev().map(|i| i * 1000).collect();
        let l = Latency::from_micros(&mut v);
        assert_eq!(l.samples, 1000);
        assert_eq!((l.p50, l.p90, l.p99, l.max), (500.0, 900.0, 990.0, 1000.0));
        assert_eq!(l.mean, 500.5);
        assert_eq!(Latency::from_micros(&mut []), Latency::default());
    }

    fn info() -> VolumeInfo {
        let layout =
            isovox_proto::VolumeLayout::new([512, 256, 512], 32, isovox_proto::VoxelType::U8)
                .unwrap();
        VolumeInfo::new("demo", &layout, [1.0; 3], 1)
    }

    #[test]
    fn paths_stay_in_their_bounds_and_differ_by_seed() {
        let info = info();
        let orbit = PathSpec::Orbit {
            radius: None,
            height: None,
            period_s: 10.0,
        };
        let (mut a, mut b) = (
            CameraPath::new(&orbit, &info, 1),
            CameraPath::new(&orbit, &info, 2),
        );
        assert_ne!(a.at(0.0), b.at(0.0));
        for i in 0..100 {
            let p = a.at(i as f32 * 0.1);
            let r = ((p[0] - 256.0).powi(2) + (p[2] - 256.0).powi(2)).sqrt();
            assert!(
                (0.8 * 179.2 - 0.01..=1.2 * 179.2 + 0.01).contains(&r),
                "{r}"
            );
            assert_eq!(p[1], 0.95 * 256.0);
        }
        let walk = PathSpec::RandomWalk {
            speed: Some(100.0),
            low: None,
            high: None,
        };
        let (mut a, mut b) = (
            CameraPath::new(&walk, &info, 1),
            CameraPath::new(&walk, &info, 1),
        );
        let mut moved = 0.0f32;
        let mut last = a.at(0.0);
        for i in 0..600 {
            let t = i as f32 / 30.0;
            let p = a.at(t);
            assert_eq!(p, b.at(t), "the same seed walks the same way");
            assert!((0.0..=512.0).contains(&p[0]) && (0.0..=512.0).contains(&p[2]));
            assert!((0.6 * 256.0..=256.0).contains(&p[1]), "{p:?}");
            moved += (0..3).map(|k| (p[k] - last[k]).powi(2)).sum::<f32>().sqrt();
            last = p;
        }
        // 100 units/s for 20 s, less what the bounces clip, more what the climbing adds.
        assert!((1500.0..=2100.0).contains(&moved), "{moved}");
    }

    #[test]
    fn edits_land_inside_the_volume() {
        let info = info();
        let config = LoadConfig::new("http://x", "demo");
        let mut rng = Rng::new(5);
        let (mut carves, mut adds) = (0, 0);
        for _ in 0..1000 {
            let (carve, e) = random_edit(&mut rng, &info, &config);
            if carve {
                carves += 1;
                assert_eq!(e.op, "difference");
            } else {
                adds += 1;
                assert_eq!(e.op, "union");
            }
            let Some(Term::Ellipsoid { center, radii }) = e.term else {
                panic!("{e:?}")
            };
            assert!(center[0] >= 0 && center[0] < 512 && center[2] >= 0 && center[2] < 512);
            assert!(center[1] >= 38 && center[1] < 218);
            assert!(radii.iter().all(|r| (4..=12).contains(r)));
        }
        assert!(carves > 400 && adds > 400);
    }
}
