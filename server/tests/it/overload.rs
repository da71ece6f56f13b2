//! Overload is answered, not queued: a real `isovox serve` process with its default CPU queue
//! (eight places per core, `docs/limits.md`), and a burst of 512 cold mesh tiles asked at the
//! same instant on 512 connections.
//!
//! The queue never holds more than its places (sampled from `/metrics` during the burst); the
//! requests that find it full are answered with 503 and `Retry-After` (a problem document), as
//! the server's own count agrees; every tile asked again after that pause is answered with a
//! well-formed mesh, and the queue is empty at the end.
//! (Slow readers filling the response memory get the same answer: `memory_bound.rs`.)
//!
//! Nothing here is timed: a limit of minutes only stops a test that hangs.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpStream;

use crate::raw_http;
use crate::server_process;
use raw_http::{assert_mesh, get, metrics, retry_after, sample, within};
use server_process::{generate_world, ServerProcess};

/// Far longer than anything here should take.
const HANGS: Duration = Duration::from_secs(300);

/// The server's default CPU queue, as `docs/limits.md` states it: jobs running or waiting.
fn places() -> u64 {
    8 * std::thread::available_parallelism().map_or(2, |n| n.get() as u64)
}

/// Connections in the burst, each asking one tile of its own.
const BURST: usize = 512;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_beyond_the_cpu_queue_is_answered_503_with_retry_after_not_queued() {
    let _ = isovox_server::http::connections::raise_fd_limit();
    let dir = tempfile::tempdir().unwrap();
    // 512^3 in bricks of 32: 4,096 tiles at level 0, so every tile of the burst is cold.
    generate_world(dir.path(), "512,512,512");
    let server = ServerProcess::start(&[], &[("ISOVOX_DATA", dir.path().to_str().unwrap())]);
    let addr = server.socket_addr();

    // Every connection is open before any asks, then all ask at once.
    let mut streams = Vec::with_capacity(BURST);
    for _ in 0..BURST {
        streams.push(TcpStream::connect(addr).await.unwrap());
    }
    let start = Arc::new(tokio::sync::Barrier::new(BURST + 1));
    let finished = Arc::new(AtomicUsize::new(0));
    let mut burst = tokio::task::JoinSet::new();
    for (i, mut stream) in streams.into_iter().enumerate() {
        let (start, finished) = (start.clone(), finished.clone());
        burst.spawn(async move {
            // 512 different tiles of level 0.
            let path = format!(
                "/v1/volumes/world/meshes/0/{}/{}/{}",
                i % 16,
                8 + i / 16 % 4,
                i / 64
            );
            start.wait().await;
            let response = get(&mut stream, &path, "").await.unwrap();
            finished.fetch_add(1, Ordering::Relaxed);
            (path, stream, response)
        });
    }
    start.wait().await;
    // The queue's depth while the burst is worked off.
    let mut deepest = within(HANGS, "the burst", async {
        let mut deepest = 0;
        while finished.load(Ordering::Relaxed) < BURST {
            deepest = deepest.max(sample(&metrics(addr).await, "isovox_cpu_queue_depth"));
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        deepest
    })
    .await;
    let mut answered = 0;
    let mut refused = Vec::new();
    while let Some(done) = within(HANGS, "the burst", burst.join_next()).await {
        let (path, stream, response) = done.unwrap();
        match response.status {
            200 => {
                assert_mesh(&path, &response);
                answered += 1;
            }
            503 => {
                assert!(retry_after(&response.head) >= 1, "{}", response.head);
                assert!(
                    response.head.contains("application/problem+json"),
                    "{}",
                    response.head
                );
                refused.push((path, stream, response));
            }
            other => panic!("{path}: {other} {}", response.head),
        }
    }
    let after = metrics(addr).await;
    deepest = deepest.max(sample(&after, "isovox_cpu_queue_depth"));
    eprintln!(
        "a burst of {BURST} cold tiles on a queue of {}: {answered} answered, {} told 503; \
         the queue at most {deepest} deep when sampled",
        places(),
        refused.len()
    );
    assert!(deepest <= places(), "the queue held {deepest} jobs");
    // The excess was refused, not queued: with a few places per core, the 512 jobs cannot all
    // have run one after another while the requests were still arriving.
    assert!(!refused.is_empty(), "no 503 in a burst of {BURST}");
    assert_eq!(answered + refused.len(), BURST);
    let route = r#"route="/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}""#;
    assert_eq!(
        sample(
            &after,
            &format!("isovox_requests_total{{{route},status=\"503\"}}")
        ),
        refused.len() as u64,
        "the server's count of 503s"
    );

    // Each refused client waits as told and asks again, until it gets its tile.
    let mut retries = tokio::task::JoinSet::new();
    for (path, mut stream, mut response) in refused {
        retries.spawn(async move {
            while response.status == 503 {
                tokio::time::sleep(Duration::from_secs(retry_after(&response.head))).await;
                response = get(&mut stream, &path, "").await.unwrap();
            }
            assert_mesh(&path, &response);
        });
    }
    while let Some(done) = within(HANGS, "the retries", retries.join_next()).await {
        done.unwrap();
    }
    assert_eq!(sample(&metrics(addr).await, "isovox_cpu_queue_depth"), 0);
}
