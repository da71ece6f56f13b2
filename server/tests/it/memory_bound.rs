//! The server's memory is bounded by its configuration, whatever the load: a real `isovox
//! serve` process, its resident memory as the kernel reports it (`VmHWM`, the peak).
//!
//! The bound each test states: the resident memory once started, plus the caches
//! (`--mesh-cache-mb`, `--brick-cache-mb`), plus the response budget
//! (`--response-memory-mb`: bodies built and not yet sent), plus an allowance per CPU thread
//! for the job it runs ([`PER_THREAD`]), plus one per connection ([`PER_CONNECTION`]).
//!
//! - random cold mesh tiles of a 1024^3 world from 64, then 1,000 connections (the queue
//!   answers the excess with 503): every answer a well-formed mesh, the peak under the bound,
//!   the threads few (`scripts/bench-cold-tiles.sh` runs the same load at full length, with
//!   the server's defaults, and prints p99 and the 503s);
//! - 48 clients reading a 64 MiB level (and 8 a 64 MiB raw batch) slowly: the peak under the
//!   bound while they dawdle, and then every one of them gets its whole, right answer.

use isovox_proto::batch::decode_batch;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::raw_http;
use crate::server_process;
use raw_http::{assert_mesh, get, read_head, retry_after, within};
use server_process::{generate_world, run_isovox, ServerProcess};

/// Far longer than anything here should take.
const HANGS: Duration = Duration::from_secs(600);

const MIB: u64 = 1 << 20;

/// What a CPU thread's job may hold beyond the response budget: the bricks and mesh of a tile,
/// the slabs of a level being read, compressor state, the allocator's caches.
const PER_THREAD: u64 = 48 * MIB;

/// What a connection may hold: its buffers, its task, a brick on its way.
const PER_CONNECTION: u64 = 64 << 10;

/// `isovox serve` of `dir` with caches of `cache_mb` MiB each and `response_mb` MiB of
/// response memory (set by variables, not flags: see `server_process`), and its resident memory
/// once it has answered a first request.
async fn serve(dir: &std::path::Path, cache_mb: &str, response_mb: &str) -> (ServerProcess, u64) {
    let server = ServerProcess::start(
        &[],
        &[
            ("ISOVOX_DATA", dir.to_str().unwrap()),
            ("ISOVOX_MESH_CACHE_MB", cache_mb),
            ("ISOVOX_BRICK_CACHE_MB", cache_mb),
            ("ISOVOX_RESPONSE_MEMORY_MB", response_mb),
        ],
    );
    let mut probe = TcpStream::connect(server.socket_addr()).await.unwrap();
    let info = get(&mut probe, "/v1/volumes/world", "").await.unwrap();
    assert_eq!(info.status, 200);
    let baseline = server.status().rss;
    (server, baseline)
}

fn cores() -> u64 {
    std::thread::available_parallelism().map_or(2, |n| n.get() as u64)
}

/// The bound for `server` (with these caches and budget, in MiB) and `connections` clients.
fn bound(baseline: u64, caches_mb: u64, response_mb: u64, connections: u64) -> u64 {
    baseline + (caches_mb + response_mb) * MIB + cores() * PER_THREAD + connections * PER_CONNECTION
}

/// Fetches `total` random mesh tiles of levels 0-2 of a 1024^3 world over `connections`
/// keep-alive connections; a 503 is retried after a pause. Every 200 must be a well-formed
/// mesh.
async fn mesh_load(
    addr: SocketAddr,
    connections: usize,
    total: usize,
    seed: u64,
) -> (usize, usize) {
    let done = Arc::new(AtomicUsize::new(0));
    let busy = Arc::new(AtomicUsize::new(0));
    let mut clients = tokio::task::JoinSet::new();
    for c in 0..connections {
        let (done, busy) = (done.clone(), busy.clone());
        clients.spawn(async move {
            let mut rng = seed ^ (c as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
            let mut next = move |n: u32| {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                (rng % n as u64) as u32
            };
            let mut stream = TcpStream::connect(addr).await.unwrap();
            while done.load(Ordering::Relaxed) < total {
                let level = next(3);
                let n = 32 >> level;
                let path = format!(
                    "/v1/volumes/world/meshes/{level}/{}/{}/{}",
                    next(n),
                    next(n),
                    next(n)
                );
                let response = get(&mut stream, &path, "").await.unwrap();
                match response.status {
                    200 => {
                        assert_mesh(&path, &response);
                        done.fetch_add(1, Ordering::Relaxed);
                    }
                    503 => {
                        assert!(retry_after(&response.head) >= 1);
                        busy.fetch_add(1, Ordering::Relaxed);
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    other => panic!("{path}: {other} {}", response.head),
                }
            }
        });
    }
    while let Some(client) = clients.join_next().await {
        client.unwrap();
    }
    (done.load(Ordering::Relaxed), busy.load(Ordering::Relaxed))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cold_mesh_tiles_from_64_and_1000_connections_stay_within_the_bound() {
    let _ = isovox_server::http::connections::raise_fd_limit();
    let dir = tempfile::tempdir().unwrap();
    // A 1024^3 world in bricks (and tiles) of 32: under this load an unbounded server grew to
    // gigabytes and hundreds of threads.
    generate_world(dir.path(), "1024,1024,1024");
    let (server, baseline) = serve(dir.path(), "32", "64").await;
    let addr = server.socket_addr();

    for (connections, seed) in [(64, 1), (1000, 2)] {
        let (done, busy) = within(
            HANGS,
            "the mesh load",
            mesh_load(addr, connections, 5000, seed),
        )
        .await;
        let status = server.status();
        let limit = bound(baseline, 64, 64, connections as u64);
        eprintln!(
            "{connections} connections: {done} tiles, {busy} answers 503; peak {} MiB, now {} MiB, \
             {} threads (bound {} MiB, from {} MiB at start)",
            status.hwm >> 20,
            status.rss >> 20,
            status.threads,
            limit >> 20,
            baseline >> 20
        );
        assert!(
            status.hwm <= limit,
            "peak {} MiB > bound {} MiB",
            status.hwm >> 20,
            limit >> 20
        );
        // Tokio's workers, the CPU threads, rayon's, a few blocking ones: nothing that grows
        // with the load.
        assert!(
            status.threads <= 4 * cores() + 16,
            "{} threads",
            status.threads
        );
    }
}

/// A slow reader's request and what it got.
struct Reader {
    stream: TcpStream,
    /// Body bytes read so far.
    body: Vec<u8>,
    length: usize,
}

/// Sends `request` on a new connection and reads the head: `Ok` for a 200 (with the body bytes
/// that came with the head), `Err(status)` otherwise.
async fn ask(addr: SocketAddr, request: &[u8]) -> Result<Reader, u16> {
    let mut stream = TcpStream::connect(addr).await.unwrap();
    stream.write_all(request).await.unwrap();
    let (status, head, length, body) = read_head(&mut stream).await.unwrap();
    if status != 200 {
        // Told to come back later, not kept waiting.
        assert_eq!(status, 503, "{head}");
        assert!(retry_after(&head) >= 1);
        return Err(status);
    }
    Ok(Reader {
        stream,
        body,
        length,
    })
}

impl Reader {
    /// Reads `n` more bytes (or what is left), `step` at a time with `pause` between.
    async fn read(&mut self, n: usize, step: usize, pause: Duration) {
        let end = self.body.len().saturating_add(n).min(self.length);
        let mut buf = vec![0u8; step];
        while self.body.len() < end {
            let want = step.min(end - self.body.len());
            let got = self.stream.read(&mut buf[..want]).await.unwrap();
            assert!(got > 0, "the connection closed mid-body");
            self.body.extend_from_slice(&buf[..got]);
            if !pause.is_zero() {
                tokio::time::sleep(pause).await;
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_readers_of_a_64_mib_level_and_raw_batch_stay_within_the_bound() {
    let dir = tempfile::tempdir().unwrap();
    // Level 0 is 512 x 512 x 256 one-byte voxels: 64 MiB, the most one answer may carry; 2,048
    // bricks of 32^3, so a raw batch of all of them is 64 MiB too.
    generate_world(dir.path(), "512,512,256");
    let raw = dir.path().join("level0.raw");
    let vod = dir.path().join("world.vod");
    run_isovox(&[
        "export",
        vod.to_str().unwrap(),
        "-o",
        raw.to_str().unwrap(),
        "--level",
        "0",
    ]);
    let expected = std::fs::read(&raw).unwrap();
    assert_eq!(expected.len(), 64 << 20);

    let (server, baseline) = serve(dir.path(), "16", "128").await;
    let addr = server.socket_addr();

    let level =
        b"GET /v1/volumes/world/levels/0?format=voxels HTTP/1.1\r\nHost: isovox\r\n\r\n".to_vec();
    let keys: Vec<String> = (0..8)
        .flat_map(|z| (0..16).flat_map(move |y| (0..16).map(move |x| format!("[0,{x},{y},{z}]"))))
        .collect();
    let json = format!("{{\"keys\":[{}],\"encoding\":\"raw\"}}", keys.join(","));
    let batch = format!(
        "POST /v1/volumes/world/batch HTTP/1.1\r\nHost: isovox\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\n\r\n{json}",
        json.len()
    )
    .into_bytes();
    let requests: Vec<(bool, Vec<u8>)> = (0..48)
        .map(|_| (true, level.clone()))
        .chain((0..8).map(|_| (false, batch.clone())))
        .collect();

    // Everyone asks at once; those answered read 1 MiB at 640 KB/s, all at once. Meanwhile
    // the server's memory is sampled.
    let answered = Arc::new(AtomicUsize::new(0));
    let mut readers = tokio::task::JoinSet::new();
    for (is_level, request) in requests {
        let answered = answered.clone();
        readers.spawn(async move {
            let mut first = ask(addr, &request).await;
            if let Ok(reader) = &mut first {
                answered.fetch_add(1, Ordering::Relaxed);
                reader
                    .read(1 << 20, 64 << 10, Duration::from_millis(100))
                    .await;
            }
            (is_level, request, first)
        });
    }
    let mut waiting = Vec::new();
    while let Some(reader) = readers.join_next().await {
        waiting.push(reader.unwrap());
    }
    let slow_peak = server.status().hwm;
    let limit = bound(baseline, 32, 128, 56);
    eprintln!(
        "56 slow readers: {} answered at once; peak {} MiB (bound {} MiB, from {} MiB at start)",
        answered.load(Ordering::Relaxed),
        slow_peak >> 20,
        limit >> 20,
        baseline >> 20
    );
    assert!(
        slow_peak <= limit,
        "peak {} MiB > bound {} MiB",
        slow_peak >> 20,
        limit >> 20
    );
    // The budget holds two 64 MiB answers, and every answer here is still held (its reader has
    // read a sixty-fourth of it): one or two were answered, every other one was told 503.
    let at_once = answered.load(Ordering::Relaxed);
    assert!((1..=2).contains(&at_once), "{at_once} answered at once");

    // Then every reader gets its whole answer: those answered read the rest at full speed,
    // then the others ask again until they are answered (503 says: later).
    waiting.sort_by_key(|(_, _, first)| first.is_err());
    let mut complete = 0;
    for (is_level, request, first) in waiting {
        let mut reader = match first {
            Ok(reader) => reader,
            Err(_) => loop {
                match ask(addr, &request).await {
                    Ok(reader) => break reader,
                    Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                }
            },
        };
        within(
            HANGS,
            "reading an answer",
            reader.read(usize::MAX, 1 << 20, Duration::ZERO),
        )
        .await;
        if is_level {
            assert!(
                reader.body == expected,
                "a level's voxels differ from the export"
            );
        } else {
            let entries = decode_batch(&reader.body).unwrap();
            assert_eq!(entries.len(), 2048);
            for e in &entries {
                let (x, y, z) = (e.key.x as usize, e.key.y as usize, e.key.z as usize);
                for (i, row) in e.payload.chunks(32).enumerate() {
                    let (dy, dz) = (i % 32, i / 32);
                    let at = ((z * 32 + dz) * 512 + y * 32 + dy) * 512 + x * 32;
                    assert!(row == &expected[at..at + 32], "brick {:?}", e.key);
                }
            }
        }
        complete += 1;
    }
    assert_eq!(complete, 56);
    let status = server.status();
    eprintln!(
        "after: peak {} MiB, now {} MiB",
        status.hwm >> 20,
        status.rss >> 20
    );
    assert!(
        status.hwm <= limit,
        "peak {} MiB > bound {} MiB",
        status.hwm >> 20,
        limit >> 20
    );
}
