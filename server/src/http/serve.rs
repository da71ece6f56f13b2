//! Serving [`super::app`] on a listener until a shutdown signal, one loop for both transports:
//! plain HTTP ([`run`]) and HTTPS with HTTP/2 and HTTP/1.1 by ALPN ([`run_tls`]; `tls.rs` reads
//! the certificate).
//!
//! Shutdown, the same on both: stop accepting; end every open change feed at once (a feed never
//! ends by itself, so a graceful shutdown that waited for it would wait forever; subscribers
//! reconnect with `since=` and miss nothing); let the other requests in flight finish, for up
//! to [`ServerConfig::shutdown_grace`](super::ServerConfig::shutdown_grace); then close the
//! connections still open.

use super::{app, AppState};
use axum::extract::Request;
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto;
use hyper_util::server::graceful::{GracefulShutdown, Watcher};
use hyper_util::service::TowerToHyperService;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio::task::JoinSet;
use tokio_rustls::{rustls, TlsAcceptor};

/// A TLS handshake that has not finished by then is dropped (a stalled client holds no task).
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

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
    let (closing, grace) = (state.closing.clone(), state.config.shutdown_grace);
    let service = tower::ServiceBuilder::new()
        .map_request(|r: Request<hyper::body::Incoming>| r.map(axum::body::Body::new))
        .service(app(state));
    let graceful = GracefulShutdown::new();
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
        let _ = tcp.set_nodelay(true);
        let service = TowerToHyperService::new(service.clone());
        let watcher = graceful.watcher();
        let tls = tls.clone();
        connections.spawn(async move {
            let Some(acceptor) = tls else {
                return serve_connection(TokioIo::new(tcp), service, watcher, peer).await;
            };
            match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(tcp)).await {
                Ok(Ok(stream)) => {
                    serve_connection(TokioIo::new(stream), service, watcher, peer).await
                }
                Ok(Err(e)) => tracing::debug!("TLS handshake with {peer} failed: {e}"),
                Err(_) => tracing::debug!("TLS handshake with {peer} timed out"),
            }
        });
    }
    drop(listener);
    closing.close();
    if tokio::time::timeout(grace, graceful.shutdown())
        .await
        .is_err()
    {
        tracing::info!(
            "closing the {} connections still open after {grace:?}",
            connections.len()
        );
    }
    connections.shutdown().await;
    Ok(())
}

/// HTTP/1.1 or HTTP/2 (by what the client speaks) on one connection, until it closes or a
/// graceful shutdown has let its requests finish.
async fn serve_connection<S, I>(
    io: TokioIo<I>,
    service: S,
    watcher: Watcher,
    peer: std::net::SocketAddr,
) where
    I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    S: hyper::service::Service<
            hyper::Request<hyper::body::Incoming>,
            Response = axum::response::Response,
            Error = std::convert::Infallible,
        > + Send
        + 'static,
    S::Future: Send + 'static,
{
    let builder = auto::Builder::new(TokioExecutor::new());
    let conn = builder.serve_connection_with_upgrades(io, service);
    if let Err(e) = watcher.watch(conn.into_owned()).await {
        tracing::debug!("connection from {peer} ended: {e}");
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
