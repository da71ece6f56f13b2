//! Shutting a server down, the same over plain HTTP (`http::run`) and over TLS
//! (`http::run_tls`), on real sockets with a raw HTTP/1.1 client:
//!
//! - open change feeds end at once, with the response's last chunk, and the server stops; the
//!   grace is an hour here, so neither can be the grace running out;
//! - a request that would never finish (its body never comes) is cut when the grace runs out,
//!   and the server stops;
//! - with any number of connection threads, connections at once are all served (plain reads
//!   and routed ones, all on the connection threads) until the shutdown, and then the
//!   port refuses connections;
//! - a server whose runtime is dropped without a shutdown stops its connection threads all
//!   the same;
//! - an edit cut by the shutdown while it waits for its volume's writer leaves the volume
//!   editable: its writer task lives on the server's runtime, not on the connection thread
//!   that took the edit.
//!
//! The TLS server gets a certificate made by `openssl` (as `.ci/run` installs it); the client
//! trusts exactly that certificate.

use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::catalog::Catalog;
use isovox_server::generate::WorldSource;
use isovox_server::http::{run, run_tls, AppState, ServerConfig};
use isovox_server::store::{build_vod2, BuildOptions};
use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_rustls::rustls::pki_types::ServerName;

use crate::raw_http;
use crate::tls;
use raw_http::{get, get_once, read_to_close, read_until};
use tls::{tls, Tls};

/// Far longer than anything here should take: reaching it means the shutdown hangs.
const HANGS: Duration = Duration::from_secs(60);

/// A byte stream to the server, plain or TLS.
trait Stream: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Stream for T {}

/// A small world `w.vod` in `dir`.
fn world(dir: &Path) {
    let layout = VolumeLayout::new([64, 32, 64], 16, VoxelType::U8).unwrap();
    let source = WorldSource::new(layout.clone(), 7);
    build_vod2(
        &dir.join("w.vod"),
        &layout,
        [1.0; 3],
        &source,
        &BuildOptions::default(),
    )
    .unwrap();
}

/// A server on an ephemeral port, plain or TLS: where it listens, the sender that starts its
/// shutdown, and the task that ends when the shutdown is done.
struct Running {
    addr: SocketAddr,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

async fn start(dir: &Path, grace: Duration, tls: Option<&Tls>) -> Running {
    let config = ServerConfig {
        shutdown_grace: grace,
        ..ServerConfig::default()
    };
    start_with(dir, config, tls).await
}

async fn start_with(dir: &Path, config: ServerConfig, tls: Option<&Tls>) -> Running {
    let state = AppState::with_config(Catalog::open_dir(dir).unwrap(), config);
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let shutdown = async {
        let _ = stopped.await;
    };
    let task = match tls {
        None => tokio::spawn(run(listener, state, shutdown)),
        Some(tls) => tokio::spawn(run_tls(listener, tls.server.clone(), state, shutdown)),
    };
    Running { addr, stop, task }
}

async fn connect(addr: SocketAddr, tls: Option<&Tls>) -> Box<dyn Stream> {
    let tcp = TcpStream::connect(addr).await.unwrap();
    match tls {
        None => Box::new(tcp),
        Some(tls) => {
            let name = ServerName::IpAddress(addr.ip().into());
            Box::new(tls.client.connect(name, tcp).await.unwrap())
        }
    }
}

/// Starts the shutdown and waits until the server has stopped.
async fn stop(server: Running, which: &str) {
    let _ = server.stop.send(());
    tokio::time::timeout(HANGS, server.task)
        .await
        .unwrap_or_else(|_| panic!("{which}: the server did not stop within {HANGS:?}"))
        .unwrap()
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_change_feeds_over_http_and_tls() {
    let dir = tempfile::tempdir().unwrap();
    world(dir.path());
    let tls = tls(&[b"http/1.1"]);
    for tls in [None, Some(&tls)] {
        let which = if tls.is_some() { "TLS" } else { "plain HTTP" };
        let server = start(dir.path(), Duration::from_secs(3600), tls).await;
        let mut feeds = Vec::new();
        for _ in 0..3 {
            let mut feed = connect(server.addr, tls).await;
            feed.write_all(b"GET /v1/volumes/w/events HTTP/1.1\r\nHost: isovox\r\n\r\n")
                .await
                .unwrap();
            let mut bytes = Vec::new();
            read_until(feed.as_mut(), &mut bytes, "event: hello").await;
            let head = String::from_utf8_lossy(&bytes).to_string();
            assert!(head.starts_with("HTTP/1.1 200"), "{which}: {head}");
            assert!(head.contains("text/event-stream"), "{which}: {head}");
            feeds.push((feed, bytes));
        }

        // The server stops although the feeds' clients have not read a byte since: it does not
        // wait for them.
        stop(server, which).await;
        for (mut feed, mut bytes) in feeds {
            let rest = tokio::time::timeout(HANGS, read_to_close(feed.as_mut()))
                .await
                .unwrap_or_else(|_| panic!("{which}: a feed was still open after {HANGS:?}"));
            bytes.extend(rest);
            // The chunked response ended with its last chunk: the feed ended, it was not cut.
            let text = String::from_utf8_lossy(&bytes);
            assert!(text.ends_with("\r\n0\r\n\r\n"), "{which}: {text:?}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_closes_a_request_still_running_when_the_grace_runs_out() {
    let dir = tempfile::tempdir().unwrap();
    world(dir.path());
    let tls = tls(&[b"http/1.1"]);
    for tls in [None, Some(&tls)] {
        let which = if tls.is_some() { "TLS" } else { "plain HTTP" };
        let server = start(dir.path(), Duration::from_millis(200), tls).await;
        // A batch request whose body never comes: it would wait for it forever.
        let mut stalled = connect(server.addr, tls).await;
        stalled
            .write_all(
                b"POST /v1/volumes/w/batch HTTP/1.1\r\nHost: isovox\r\n\
                  Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"keys\":",
            )
            .await
            .unwrap();
        stalled.flush().await.unwrap();
        // The server is serving: another connection is answered meanwhile.
        let mut other = connect(server.addr, tls).await;
        other
            .write_all(b"GET /healthz HTTP/1.1\r\nHost: isovox\r\n\r\n")
            .await
            .unwrap();
        let mut answer = Vec::new();
        read_until(other.as_mut(), &mut answer, "\r\n\r\nok").await;

        stop(server, which).await;
        let bytes = tokio::time::timeout(HANGS, read_to_close(stalled.as_mut()))
            .await
            .unwrap_or_else(|_| panic!("{which}: the stalled request's connection stayed open"));
        // Closed without an answer: the request was cut, not answered.
        assert!(
            bytes.is_empty(),
            "{which}: {:?}",
            String::from_utf8_lossy(&bytes)
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_connection_thread_serves_until_the_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    world(dir.path());
    // 0 is taken as 1.
    for threads in [0, 1, 3] {
        let config = ServerConfig {
            connection_threads: threads,
            shutdown_grace: HANGS,
            ..ServerConfig::default()
        };
        let server = start_with(dir.path(), config, None).await;
        let addr = server.addr;
        let mut clients = tokio::task::JoinSet::new();
        for client in 0..24u32 {
            clients.spawn(async move {
                let mut tcp = TcpStream::connect(addr).await.unwrap();
                // A plain brick, the same brick routed (a query), a document of the router
                // and a chunk of the Zarr view, one after the other on one connection.
                let brick = format!("/v1/volumes/w/bricks/0/{}/0/{}", client % 4, client / 8);
                for path in [
                    brick.clone(),
                    format!("{brick}?version=1"),
                    "/v1/volumes/w".to_string(),
                    format!("/v1/volumes/w/zarr/0/c/{}/0/{}", client / 8, client % 4),
                ] {
                    let answer = get(&mut tcp, &path, "").await.unwrap();
                    // A chunk of fill values may be absent (404); the rest is there.
                    let expected: &[u16] = if path.contains("/zarr/") {
                        &[200, 404]
                    } else {
                        &[200]
                    };
                    assert!(
                        expected.contains(&answer.status),
                        "{threads} threads, {path}: {}",
                        answer.head
                    );
                }
            });
        }
        while let Some(client) = clients.join_next().await {
            client.unwrap();
        }
        stop(server, &format!("{threads} connection threads")).await;
        assert!(
            TcpStream::connect(addr).await.is_err(),
            "{threads} threads: still accepting after the shutdown"
        );
    }
}

#[test]
fn dropping_the_runtime_stops_the_connection_threads() {
    let dir = tempfile::tempdir().unwrap();
    world(dir.path());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let server = runtime.block_on(async {
        let server = start(dir.path(), HANGS, None).await;
        let answer = get_once(server.addr, "/healthz").await.unwrap();
        assert_eq!(answer.status, 200, "{}", answer.head);
        server
    });
    let Running { addr, stop, task } = server;
    // The server's task goes with its runtime; its shutdown signal was never sent (`stop` is
    // still held).
    drop(task);
    drop(runtime);
    let deadline = std::time::Instant::now() + HANGS;
    while std::net::TcpStream::connect(addr).is_ok() {
        assert!(
            std::time::Instant::now() < deadline,
            "still accepting {HANGS:?} after its runtime was dropped"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    drop(stop);
}

/// A write token for the edit tests (secrets have at least 16 characters).
const SECRET: &str = "a-write-token-for-shutdown-tests";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edit_cut_by_the_shutdown_leaves_the_volume_editable() {
    use isovox_server::cancel::CancelToken;
    use isovox_server::http::auth::{Scope, Tokens};

    let dir = tempfile::tempdir().unwrap();
    world(dir.path());
    let mut tokens = Tokens::default();
    tokens.add("t", SECRET, Scope::Write).unwrap();
    let config = ServerConfig {
        tokens,
        connection_threads: 1,
        shutdown_grace: Duration::from_millis(100),
        ..ServerConfig::default()
    };
    let state = AppState::with_config(Catalog::open_dir(dir.path()).unwrap(), config);
    let volume = state.catalog.get("w").unwrap().clone();
    // The writer is held (as a compaction holds it), so the edit's writer task waits for it.
    let held = volume.lock_writer().await;
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop_tx, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(run(listener, state.clone(), async {
        let _ = stopped.await;
    }));
    let body = r#"{"op":"union","term":{"cuboid":{"origin":[4,4,4],"size":[6,6,6]}}}"#;
    let mut tcp = TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST /v1/volumes/w/edits HTTP/1.1\r\nHost: isovox\r\nAuthorization: Bearer {SECRET}\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    tcp.write_all(head.as_bytes()).await.unwrap();
    let deadline = std::time::Instant::now() + HANGS;
    while volume.queue_depth() == 0 {
        assert!(
            std::time::Instant::now() < deadline,
            "the edit never queued"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    // The shutdown cuts the edit (its grace runs out) and stops the connection thread.
    stop(
        Running {
            addr,
            stop: stop_tx,
            task,
        },
        "edit",
    )
    .await;
    drop(tcp);
    drop(held);

    // The volume takes the next edit: a writer runs for it.
    let request = serde_json::from_str(body).unwrap();
    let cancel = CancelToken::never();
    let edit = volume
        .prepare_edit(
            &request,
            &state.edit_limits(),
            &state.resolver(),
            None,
            &cancel,
        )
        .unwrap();
    let runtime = tokio::runtime::Handle::current();
    let work = isovox_server::volume::group::Work::edit(edit, false);
    let submitted = volume.submit(work, None, cancel, state.group_commit(), &runtime);
    let answer = tokio::time::timeout(HANGS, submitted)
        .await
        .unwrap_or_else(|_| panic!("the edit after the shutdown hangs"))
        .unwrap();
    assert_eq!(answer.version, answer.previous + 1);
}
