//! A raw HTTP/1.1 client for the tests that need to see the bytes and the connection: what
//! arrives, when the server closes, how slowly a client reads; and what the answers of the load
//! tests carry (a mesh tile, the server's metrics), checked.

#![allow(dead_code, clippy::unwrap_used)]

use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

use isovox_proto::mesh::{decode_compact, Mesh};

/// An HTTP/1.1 response, read whole.
#[derive(Debug)]
pub(crate) struct Response {
    pub(crate) status: u16,
    pub(crate) head: String,
    pub(crate) body: Vec<u8>,
}

/// A response's head: status, the head as text, `Content-Length`, and the bytes read past the
/// head.
pub(crate) async fn read_head<S: AsyncRead + Unpin>(
    stream: &mut S,
) -> std::io::Result<(u16, String, usize, Vec<u8>)> {
    let mut bytes = Vec::new();
    let mut buf = [0u8; 8192];
    let end = loop {
        if let Some(i) = bytes.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
        let n = stream.read(&mut buf).await?;
        if n == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        bytes.extend_from_slice(&buf[..n]);
    };
    let head = String::from_utf8_lossy(&bytes[..end]).to_string();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| std::io::Error::other(format!("not an HTTP response: {head:?}")))?;
    let length = header(&head, "content-length")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    Ok((status, head, length, bytes[end..].to_vec()))
}

/// The value of header `name` in a response's `head`, trimmed.
pub(crate) fn header<'a>(head: &'a str, name: &str) -> Option<&'a str> {
    head.lines().find_map(|l| {
        let (n, value) = l.split_once(':')?;
        n.eq_ignore_ascii_case(name).then(|| value.trim())
    })
}

/// The seconds a 503's `Retry-After` asks the client to wait; panics without one.
pub(crate) fn retry_after(head: &str) -> u64 {
    header(head, "retry-after")
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("a 503 without a Retry-After in seconds: {head}"))
}

/// Sends `GET path` on `stream` (kept alive) and reads the whole response (it must carry a
/// `Content-Length`).
pub(crate) async fn get<S: AsyncRead + AsyncWrite + Unpin>(
    stream: &mut S,
    path: &str,
    headers: &str,
) -> std::io::Result<Response> {
    stream
        .write_all(format!("GET {path} HTTP/1.1\r\nHost: isovox\r\n{headers}\r\n").as_bytes())
        .await?;
    let (status, head, length, mut body) = read_head(stream).await?;
    let have = body.len();
    body.resize(length, 0);
    stream.read_exact(&mut body[have..]).await?;
    Ok(Response { status, head, body })
}

/// `GET path` on a new connection.
pub(crate) async fn get_once(addr: SocketAddr, path: &str) -> std::io::Result<Response> {
    let mut stream = tokio::net::TcpStream::connect(addr).await?;
    get(&mut stream, path, "").await
}

/// Reads until `bytes` holds `needle`; panics if the connection closes first.
pub(crate) async fn read_until<S: AsyncRead + Unpin + ?Sized>(
    stream: &mut S,
    bytes: &mut Vec<u8>,
    needle: &str,
) {
    let mut buf = [0u8; 4096];
    while !String::from_utf8_lossy(bytes).contains(needle) {
        let n = stream.read(&mut buf).await.unwrap();
        assert!(
            n > 0,
            "the connection closed before {needle:?}: {}",
            String::from_utf8_lossy(bytes)
        );
        bytes.extend_from_slice(&buf[..n]);
    }
}

/// Reads until the peer closes the connection (or it fails: a TLS connection cut without
/// `close_notify` ends with an error); the bytes read.
pub(crate) async fn read_to_close<S: AsyncRead + Unpin + ?Sized>(stream: &mut S) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut buf = [0u8; 4096];
    while let Ok(n @ 1..) = stream.read(&mut buf).await {
        bytes.extend_from_slice(&buf[..n]);
    }
    bytes
}

/// Waits for `future`, at most `limit`; panics with `what` if it has not finished by then
/// (something hangs: no test here depends on how fast anything is).
pub(crate) async fn within<F: std::future::Future>(
    limit: Duration,
    what: &str,
    future: F,
) -> F::Output {
    tokio::time::timeout(limit, future)
        .await
        .unwrap_or_else(|_| panic!("{what}: not done after {limit:?}"))
}

/// The mesh a 200 for `path` carries, checked to be well formed: whole triangles, a normal per
/// position, every index a position.
pub(crate) fn assert_mesh(path: &str, response: &Response) -> Mesh {
    assert_eq!(response.status, 200, "{path}: {}", response.head);
    let mesh = decode_compact(&response.body).unwrap();
    assert_eq!(mesh.indices.len() % 3, 0, "{path}");
    assert_eq!(mesh.normals.len(), mesh.positions.len(), "{path}");
    assert!(
        mesh.indices
            .iter()
            .all(|&i| (i as usize) < mesh.positions.len()),
        "{path}"
    );
    mesh
}

/// The server's metrics (`GET /metrics` on a new connection), as Prometheus text.
pub(crate) async fn metrics(addr: SocketAddr) -> String {
    let response = get_once(addr, "/metrics").await.unwrap();
    assert_eq!(response.status, 200, "{}", response.head);
    String::from_utf8(response.body).unwrap()
}

/// The value of a sample in Prometheus text, `name` with its labels if it has any; panics
/// without it.
pub(crate) fn sample(metrics: &str, name: &str) -> u64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {name} in {metrics}"))
}
