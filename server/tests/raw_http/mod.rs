//! A raw HTTP/1.1 client for the tests that need to see the bytes and the connection: what
//! arrives, when the server closes, how slowly a client reads.

#![allow(dead_code)]

use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

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
    let length = head
        .lines()
        .find_map(|l| {
            let (name, value) = l.split_once(':')?;
            name.eq_ignore_ascii_case("content-length")
                .then(|| value.trim().parse().ok())?
        })
        .unwrap_or(0);
    Ok((status, head, length, bytes[end..].to_vec()))
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
