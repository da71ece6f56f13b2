//! Connections cannot take the server down: a real `isovox serve` process under a low
//! file-descriptor limit, real sockets.
//!
//! - 20,000 connections that send half a request and wait, and a slowloris client, while a
//!   normal client keeps asking: every one of its requests is answered;
//! - a request head sent a byte at a time is cut by the header timeout, a connection without a
//!   request by the idle timeout, over HTTP/1.1 and over TLS with HTTP/2, while a change feed
//!   stays open past the idle timeout and still delivers the next commit.
//!
//! Nothing here is timed: a limit of minutes only stops a test that hangs.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_rustls::rustls::pki_types::ServerName;

use crate::raw_http;
use crate::server_process;
use crate::tls;
use raw_http::{get, get_once, metrics, read_to_close, read_until, sample, within};
use server_process::{generate_world, ServerProcess};

/// The write token of the servers here.
const TOKEN: &str = "test-token-0123456789";

/// Far longer than anything here should take.
const HANGS: Duration = Duration::from_secs(120);

/// What the flood did.
#[derive(Debug, Default)]
struct Flood {
    connected: AtomicUsize,
    failed: AtomicUsize,
    /// Closed by the server (to make room, or by the header timeout).
    closed: AtomicUsize,
}

/// Opens `total` connections to `addr`, at most 256 connecting at once; each sends half a
/// request head and waits until the server closes it. The tasks holding the connections
/// still open.
async fn flood(addr: SocketAddr, total: usize, flood: Arc<Flood>) -> tokio::task::JoinSet<()> {
    let connecting = Arc::new(tokio::sync::Semaphore::new(256));
    let mut held = tokio::task::JoinSet::new();
    for _ in 0..total {
        let permit = connecting.clone().acquire_owned().await.unwrap();
        let flood = flood.clone();
        held.spawn(async move {
            // Long enough for the kernel's SYN retries: a connection that fails was never
            // accepted.
            let tcp = tokio::time::timeout(Duration::from_secs(30), TcpStream::connect(addr)).await;
            drop(permit);
            let Ok(Ok(mut tcp)) = tcp else {
                flood.failed.fetch_add(1, Ordering::Relaxed);
                return;
            };
            flood.connected.fetch_add(1, Ordering::Relaxed);
            let _ = tcp
                .write_all(b"GET /v1/volumes HTTP/1.1\r\nHost: isovox\r\n")
                .await;
            read_to_close(&mut tcp).await;
            flood.closed.fetch_add(1, Ordering::Relaxed);
        });
        // Forget the connections that ended.
        while held.try_join_next().is_some() {}
    }
    // Every connection attempt has ended (connected or failed).
    let _all = connecting.acquire_many(256).await.unwrap();
    held
}

/// Sends a request head one byte every `pause`, over and over, until the server closes the
/// connection; the bytes it got through.
async fn slowloris<S: AsyncRead + AsyncWrite + Unpin>(mut stream: S, pause: Duration) -> usize {
    let head = b"GET /v1/volumes HTTP/1.1\r\nHost: isovox\r\nX-Padding: ";
    let mut sent = 0;
    let mut one = [0u8; 1];
    loop {
        let byte = head.get(sent).copied().unwrap_or(b'a');
        if stream.write_all(&[byte]).await.is_err() || stream.flush().await.is_err() {
            return sent;
        }
        sent += 1;
        // The server's answer to a slowloris is to close: a read that ends or fails.
        match tokio::time::timeout(pause, stream.read(&mut one)).await {
            Ok(Ok(0) | Err(_)) => return sent,
            Ok(Ok(_)) => panic!("the server answered a request head that never ended"),
            Err(_) => {}
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twenty_thousand_idle_connections_and_a_slowloris_do_not_starve_a_client() {
    // The test opens thousands of sockets of its own.
    let _ = isovox_server::http::connections::raise_fd_limit();
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path(), "64,64,64");
    // 512 descriptors: without limits of its own, the server runs out of them long before
    // the flood ends, and then accepts nobody. Its connection limit is its default, derived
    // from the descriptor limit.
    let server = serve(dir.path(), Some(512), &[("ISOVOX_HEADER_TIMEOUT", "3")]);
    let addr = server.socket_addr();

    let counts = Arc::new(Flood::default());
    let attack = tokio::spawn(flood(addr, 20_000, counts.clone()));
    let slow = tokio::spawn(async move {
        let tcp = TcpStream::connect(addr).await.unwrap();
        slowloris(tcp, Duration::from_millis(200)).await
    });

    // The normal client: one request after another, each on a new connection, for as long as
    // the flood lasts. A connection closed before its answer (it can be the oldest idle one
    // when its request arrives) is retried once, as any HTTP client retries a GET.
    let (mut answered, mut retried) = (0, 0);
    while !attack.is_finished() || answered < 10 {
        let path = "/v1/volumes/world";
        let mut response = within(HANGS, "a request during the flood", get_once(addr, path)).await;
        if response.is_err() {
            retried += 1;
            response = within(HANGS, "a retried request", get_once(addr, path)).await;
        }
        let response = response.unwrap_or_else(|e| {
            panic!(
                "request {answered} failed: {e} (flood: {counts:?})\nserver log:\n{}",
                server.log()
            )
        });
        assert_eq!(response.status, 200, "{}", response.head);
        let info: serde_json::Value = serde_json::from_slice(&response.body).unwrap();
        assert_eq!(info["dims"], serde_json::json!([64, 64, 64]));
        answered += 1;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let _still_held = attack.await.unwrap();
    assert_eq!(
        counts.connected.load(Ordering::Relaxed),
        20_000,
        "every flood connection was accepted (the accept loop never stalled): {counts:?}"
    );
    // The slowloris was closed (by the header timeout, or to make room).
    let sent = within(HANGS, "the slowloris connection", slow)
        .await
        .unwrap();
    assert!(sent > 0);
    // The server held at most its limit, below its descriptor limit: it closed the others.
    let metrics = metrics(addr).await;
    let [max, open, evicted, timed_out, refused] = [
        "isovox_connections_max",
        "isovox_connections_open",
        "isovox_connections_evicted_total",
        "isovox_connections_timed_out_total",
        "isovox_connections_refused_total",
    ]
    .map(|name| sample(&metrics, name));
    assert!(max < 512 && open <= max, "{max} {open}");
    // It closed all the flood's connections but those it still holds (the last ones may still
    // be on their way through its accept queue).
    let closed = || counts.closed.load(Ordering::Relaxed) as u64;
    within(HANGS, "closing the flood's connections", async {
        while closed() < 20_000 - max {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    eprintln!("closed: {evicted} to make room, {timed_out} timed out, {refused} refused (so far)");
    eprintln!(
        "{answered} requests answered ({retried} on a second try) during a flood of 20,000 \
         connections ({counts:?}); the slowloris got {sent} bytes through"
    );
    assert!(get_once(addr, "/healthz").await.unwrap().status == 200);
}

/// `isovox serve` of `dir` with the write token, under `fd_limit`, configured by `env` (not
/// flags: see `server_process`).
fn serve(dir: &std::path::Path, fd_limit: Option<u32>, env: &[(&str, &str)]) -> ServerProcess {
    let data = dir.to_str().unwrap();
    let mut env = env.to_vec();
    env.extend([("ISOVOX_DATA", data), ("ISOVOX_WRITE_TOKEN", TOKEN)]);
    ServerProcess::start_limited(fd_limit, &[], &env)
}

/// A server with short timeouts: header 1 s, idle 2 s.
fn quick_server(dir: &std::path::Path, tls: Option<&tls::Tls>) -> ServerProcess {
    let mut env = vec![("ISOVOX_HEADER_TIMEOUT", "1"), ("ISOVOX_IDLE_TIMEOUT", "2")];
    if let Some(tls) = tls {
        env.push(("ISOVOX_TLS_CERT", tls.cert.to_str().unwrap()));
        env.push(("ISOVOX_TLS_KEY", tls.key.to_str().unwrap()));
    }
    serve(dir, None, &env)
}

/// A small edit.
const EDIT: &str = r#"{"op":"union","term":{"ellipsoid":{"center":[32,60,32],"radii":[3,3,3]}}}"#;

/// Applies [`EDIT`] on a connection of its own; the new version.
async fn edit(addr: SocketAddr) -> u64 {
    let body = EDIT;
    let mut tcp = TcpStream::connect(addr).await.unwrap();
    tcp.write_all(
        format!(
            "POST /v1/volumes/world/edits HTTP/1.1\r\nHost: isovox\r\nAuthorization: Bearer {TOKEN}\r\n\
             Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
        .as_bytes(),
    )
    .await
    .unwrap();
    let answer = String::from_utf8(read_to_close(&mut tcp).await).unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    let json = &answer[answer.find("\r\n\r\n").unwrap() + 4..];
    serde_json::from_str::<serde_json::Value>(json).unwrap()["version"]
        .as_u64()
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http1_slow_heads_and_idle_connections_are_closed_but_change_feeds_stay() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path(), "64,64,64");
    let server = quick_server(dir.path(), None);
    let addr = server.socket_addr();

    // A head sent a byte every 300 ms: closed by the header timeout, never answered.
    let slow = tokio::spawn(async move {
        let tcp = TcpStream::connect(addr).await.unwrap();
        slowloris(tcp, Duration::from_millis(300)).await
    });
    // A connection that sends nothing at all.
    let mut silent = TcpStream::connect(addr).await.unwrap();
    // A keep-alive connection after one answer.
    let mut idle = TcpStream::connect(addr).await.unwrap();
    assert_eq!(get(&mut idle, "/healthz", "").await.unwrap().status, 200);
    // A change feed.
    let mut feed = TcpStream::connect(addr).await.unwrap();
    feed.write_all(b"GET /v1/volumes/world/events HTTP/1.1\r\nHost: isovox\r\n\r\n")
        .await
        .unwrap();
    let mut seen = Vec::new();
    read_until(&mut feed, &mut seen, "event: hello").await;

    let sent = within(HANGS, "the slow head", slow).await.unwrap();
    assert!(sent >= 3, "closed after {sent} bytes");
    assert!(
        within(HANGS, "the silent connection", read_to_close(&mut silent))
            .await
            .is_empty()
    );
    assert!(
        within(HANGS, "the idle connection", read_to_close(&mut idle))
            .await
            .is_empty()
    );

    // Three idle timeouts later the feed is still open, and delivers the next commit.
    tokio::time::sleep(Duration::from_secs(6)).await;
    let version = edit(addr).await;
    let needle = format!("id: {version}");
    within(
        HANGS,
        "the commit on the feed",
        read_until(&mut feed, &mut seen, &needle),
    )
    .await;
}

/// Applies the edit of [`edit`] over HTTP/2.
async fn edit_h2(client: &mut h2::client::SendRequest<bytes::Bytes>, addr: SocketAddr) -> u64 {
    let body = EDIT.as_bytes();
    let request = http::Request::post(format!("https://{addr}/v1/volumes/world/edits"))
        .header("authorization", format!("Bearer {TOKEN}"))
        .header("content-type", "application/json")
        .header("content-length", body.len())
        .body(())
        .unwrap();
    let (response, mut send) = client.send_request(request, false).unwrap();
    send.send_data(bytes::Bytes::from_static(body), true)
        .unwrap();
    let response = response.await.unwrap();
    assert_eq!(response.status(), 200);
    let mut answer = Vec::new();
    let mut stream = response.into_body();
    while let Some(chunk) = stream.data().await {
        let chunk = chunk.unwrap();
        let _ = stream.flow_control().release_capacity(chunk.len());
        answer.extend_from_slice(&chunk);
    }
    serde_json::from_slice::<serde_json::Value>(&answer).unwrap()["version"]
        .as_u64()
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http2_silent_and_idle_connections_are_closed_but_change_feeds_stay() {
    let dir = tempfile::tempdir().unwrap();
    generate_world(dir.path(), "64,64,64");
    let tls = tls::tls(&[b"h2"]);
    let server = quick_server(dir.path(), Some(&tls));
    let addr = server.socket_addr();
    let connect = || async {
        let tcp = TcpStream::connect(addr).await.unwrap();
        let name = ServerName::IpAddress(addr.ip().into());
        let stream = tls.client.connect(name, tcp).await.unwrap();
        assert_eq!(stream.get_ref().1.alpn_protocol(), Some(&b"h2"[..]));
        stream
    };

    // TLS done, HTTP/2 agreed, but no preface: closed by the header timeout.
    let mut silent = connect().await;
    assert!(within(
        HANGS,
        "the silent HTTP/2 connection",
        read_to_close(&mut silent)
    )
    .await
    .is_empty());

    // One request, then nothing: the connection ends (GOAWAY, then closed).
    let (mut client, connection) = h2::client::handshake(connect().await).await.unwrap();
    let idle = tokio::spawn(connection);
    let request = http::Request::get(format!("https://{addr}/healthz"))
        .body(())
        .unwrap();
    let (response, _) = client.send_request(request, true).unwrap();
    let response = response.await.unwrap();
    assert_eq!(response.status(), 200);
    let mut body = response.into_body();
    while let Some(chunk) = body.data().await {
        chunk.unwrap();
    }
    drop(client);

    // A change feed on a connection of its own.
    let (feed_client, connection) = h2::client::handshake(connect().await).await.unwrap();
    let feed_connection = tokio::spawn(connection);
    let mut feed_client = feed_client.ready().await.unwrap();
    let request = http::Request::get(format!("https://{addr}/v1/volumes/world/events"))
        .body(())
        .unwrap();
    let (response, _) = feed_client.send_request(request, true).unwrap();
    let response = response.await.unwrap();
    assert_eq!(response.status(), 200);
    let mut events = response.into_body();
    let mut seen = String::new();
    while !seen.contains("event: hello") {
        let chunk = events.data().await.unwrap().unwrap();
        seen.push_str(&String::from_utf8_lossy(&chunk));
        let _ = events.flow_control().release_capacity(chunk.len());
    }

    let ended = within(HANGS, "the idle HTTP/2 connection", idle)
        .await
        .unwrap();
    eprintln!("the idle HTTP/2 connection ended: {ended:?}");

    tokio::time::sleep(Duration::from_secs(6)).await;
    assert!(
        !feed_connection.is_finished(),
        "the feed's connection was closed"
    );
    let version = edit_h2(&mut feed_client, addr).await;
    let needle = format!("id: {version}");
    within(HANGS, "the commit on the HTTP/2 feed", async {
        while !seen.contains(&needle) {
            let chunk = events.data().await.unwrap().unwrap();
            seen.push_str(&String::from_utf8_lossy(&chunk));
            let _ = events.flow_control().release_capacity(chunk.len());
        }
    })
    .await;
}
