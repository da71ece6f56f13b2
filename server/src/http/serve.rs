//! Serving [`super::app`] on a listener until a shutdown signal, one loop for both transports:
//! plain HTTP ([`run`]) and HTTPS with HTTP/2 and HTTP/1.1 by ALPN ([`run_tls`]; `tls.rs` reads
//! the certificate).
//!
//! Every connection is admitted, watched and closed by the limits of `connections.rs`: at
//! most so many open, a deadline for request heads (and the TLS handshake), another for
//! connections without a request in progress.
//!
//! Shutdown, the same on both: stop accepting; end every open change feed at once (a feed never
//! ends by itself, so a graceful shutdown that waited for it would wait forever; subscribers
//! reconnect with `since=` and miss nothing); let the other requests in flight finish, for up
//! to [`ServerConfig::shutdown_grace`](super::ServerConfig::shutdown_grace); then close the
//! connections still open.

use super::connections::{Admission, Admitted, Tracked, Watched};
use super::{app, AppState};
use axum::extract::Request;
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto;
use hyper_util::service::TowerToHyperService;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tokio::task::JoinSet;
use tokio_rustls::{rustls, TlsAcceptor};

/// How long an HTTP/2 connection closed for its limits (so without a stream open) may take to
/// say goodbye (GOAWAY) before it is dropped.
const GOODBYE: Duration = Duration::from_secs(1);

/// Serves `state` over plain HTTP on `listener` until `shutdown` completes, then shuts down as
/// the module documentation says.
///
/// # Errors
/// None today: a failed accept (out of file descriptors and the like) is logged and retried.
pub async fn run(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    serve(listener, None, state, shutdown).await
}

/// Serves `state` over TLS (`tls`, from [`super::tls::config`]) on `listener` until `shutdown`
/// completes, then shuts down as [`run`] does.
///
/// # Errors
/// As [`run`].
pub async fn run_tls(
    listener: TcpListener,
    tls: Arc<rustls::ServerConfig>,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    serve(listener, Some(TlsAcceptor::from(tls)), state, shutdown).await
}

async fn serve(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    // The loop runs as a task of its own, on a runtime worker, whoever awaits `serve`: awaited
    // in `block_on` it would run on the calling thread, and every accepted connection would be
    // two wake-ups across threads (the I/O driver's worker waking that thread, its spawn waking
    // a worker), every closed one a third. Spawned from a worker, a connection's task starts
    // on that worker, next.
    match tokio::spawn(accept_until_shutdown(listener, tls, state, shutdown)).await {
        Ok(served) => served,
        Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
        Err(e) => Err(std::io::Error::other(e)),
    }
}

async fn accept_until_shutdown(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let (closing, grace) = (state.closing.clone(), state.config.shutdown_grace);
    let open = state.connections.clone();
    let service = tower::ServiceBuilder::new()
        .map_request(|r: Request<hyper::body::Incoming>| r.map(axum::body::Body::new))
        .service(app(state));
    let mut connections = JoinSet::new();
    tokio::pin!(shutdown);
    loop {
        let (tcp, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                // Out of file descriptors and the like: wait rather than spin.
                Err(e) => {
                    tracing::warn!("accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            // Forget the connections that ended.
            Some(_) = connections.join_next(), if !connections.is_empty() => continue,
            () = &mut shutdown => break,
        };
        let admitted = loop {
            match open.admit() {
                Admission::Open(admitted) => break Some(admitted),
                Admission::Refused => break None,
                Admission::Wait => open.closed().await,
            }
        };
        // At the limit with every connection busy: closed at once (dropped).
        let Some(admitted) = admitted else {
            tracing::debug!("connection from {peer} refused: {} open", open.open());
            continue;
        };
        let _ = tcp.set_nodelay(true);
        let service = TowerToHyperService::new(service.clone());
        let (tls, closing) = (tls.clone(), closing.clone());
        connections.spawn(connection(tcp, peer, tls, service, admitted, closing));
    }
    drop(listener);
    closing.close();
    let finished = async { while connections.join_next().await.is_some() {} };
    if tokio::time::timeout(grace, finished).await.is_err() {
        tracing::info!(
            "closing the {} connections still open after {grace:?}",
            connections.len()
        );
    }
    connections.shutdown().await;
    Ok(())
}

/// One connection: the TLS handshake (when there is TLS) within the header timeout, then
/// HTTP/1.1 or HTTP/2 (by what the client speaks) until it closes, its limits close it, or the
/// server shuts down.
async fn connection<S>(
    tcp: TcpStream,
    peer: std::net::SocketAddr,
    tls: Option<TlsAcceptor>,
    service: S,
    admitted: Admitted,
    closing: Closing,
) where
    S: Service,
{
    let Some(acceptor) = tls else {
        let io = Watched::new(tcp, admitted.slot().clone());
        return serve_connection(io, service, admitted, closing, peer).await;
    };
    let stream = tokio::select! {
        handshake = acceptor.accept(tcp) => match handshake {
            Ok(stream) => stream,
            Err(e) => return tracing::debug!("TLS handshake with {peer} failed: {e}"),
        },
        why = admitted.expired() => {
            return tracing::debug!("TLS handshake with {peer} ended: {why:?}");
        }
        () = closing.closed() => return,
    };
    if stream.get_ref().1.alpn_protocol() == Some(b"h2") {
        admitted.slot().set_h2();
    }
    let io = Watched::new(stream, admitted.slot().clone());
    serve_connection(io, service, admitted, closing, peer).await;
}

/// What serves one connection's requests.
trait Service:
    hyper::service::Service<
        hyper::Request<hyper::body::Incoming>,
        Response = axum::response::Response,
        Error = std::convert::Infallible,
        Future: Send + 'static,
    > + Send
    + 'static
{
}

impl<S> Service for S where
    S: hyper::service::Service<
            hyper::Request<hyper::body::Incoming>,
            Response = axum::response::Response,
            Error = std::convert::Infallible,
            Future: Send + 'static,
        > + Send
        + 'static
{
}

/// HTTP/1.1 or HTTP/2 on one connection, until it closes, its limits close it (gracefully:
/// they only close connections without a request in progress) or a shutdown has let its
/// requests finish.
async fn serve_connection<I, S>(
    io: Watched<I>,
    service: S,
    admitted: Admitted,
    closing: Closing,
    peer: std::net::SocketAddr,
) where
    I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    S: Service,
{
    let builder = auto::Builder::new(TokioExecutor::new());
    let service = Tracked::new(service, admitted.slot().clone());
    let conn = builder.serve_connection_with_upgrades(TokioIo::new(io), service);
    tokio::pin!(conn);
    let why = tokio::select! {
        biased;
        ended = conn.as_mut() => {
            if let Err(e) = ended {
                tracing::debug!("connection from {peer} ended: {e}");
            }
            return;
        }
        why = admitted.expired() => Some(why),
        () = closing.closed() => None,
    };
    let slot = admitted.slot();
    let Some(why) = why.filter(|_| slot.idle()) else {
        // Shutting down, or a request began as the connection was told to make room: the
        // requests in flight finish (within the server's grace when shutting down).
        conn.as_mut().graceful_shutdown();
        let _ = conn.await;
        return;
    };
    tracing::debug!("closing the connection from {peer}: {why:?}");
    // No request is in progress (none can begin before the drop: requests begin only while
    // this task polls `conn`). HTTP/1.1 has nothing to finish and nothing to say: drop it now
    // (a graceful close would wait for the rest of a head that may never come).
    if !slot.h2() {
        return;
    }
    // HTTP/2 tells the client which streams were not served (GOAWAY); a stream that came just
    // now still gets its answer; otherwise the connection has a moment for that.
    conn.as_mut().graceful_shutdown();
    loop {
        tokio::select! {
            _ = conn.as_mut() => return,
            () = tokio::time::sleep(GOODBYE) => if slot.idle() { return },
        }
    }
}

/// Tells the responses that would never end by themselves (the change feed) that the server is
/// shutting down. Every clone shares one signal.
#[derive(Debug, Clone)]
pub struct Closing(Arc<watch::Sender<bool>>);

impl Default for Closing {
    fn default() -> Self {
        Closing(Arc::new(watch::Sender::new(false)))
    }
}

impl Closing {
    fn close(&self) {
        self.0.send_replace(true);
    }

    /// Resolves once the server is shutting down (at once if it already is).
    pub fn closed(&self) -> impl Future<Output = ()> + Send + 'static {
        let mut rx = self.0.subscribe();
        async move {
            // An error means the sender is gone: nobody can close any more.
            if rx.wait_for(|closing| *closing).await.is_err() {
                std::future::pending::<()>().await;
            }
        }
    }
}

/// A server running on the current tokio runtime (see [`spawn`]); dropping it shuts the server
/// down gracefully.
#[derive(Debug)]
pub struct Spawned {
    /// Where it listens.
    pub addr: std::net::SocketAddr,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
}

impl Spawned {
    /// `http://ADDR`, the base of every URL.
    pub fn base(&self) -> String {
        format!("http://{}", self.addr)
    }
}

impl Drop for Spawned {
    fn drop(&mut self) {
        if let Some(s) = self.shutdown.take() {
            let _ = s.send(());
        }
    }
}

/// Serves `state` on `addr` (port 0: an ephemeral port) as a task of the current tokio runtime,
/// until the returned handle is dropped. For tests, benchmarks and embedding; `isovox serve`
/// uses [`run`].
///
/// # Errors
/// The address cannot be bound.
pub async fn spawn(addr: &str, state: AppState) -> std::io::Result<Spawned> {
    let listener = TcpListener::bind(addr).await?;
    let addr = listener.local_addr()?;
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(async move {
        let stopped = async {
            let _ = rx.await;
        };
        if let Err(e) = run(listener, state, stopped).await {
            tracing::error!("server on {addr} stopped: {e}");
        }
    });
    Ok(Spawned {
        addr,
        shutdown: Some(tx),
    })
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
    }
    tracing::info!("shutting down: finishing in-flight requests");
}
