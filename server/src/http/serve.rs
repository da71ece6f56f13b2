//! Serving [`super::app`] on a listener until a shutdown signal, one loop for both transports:
//! plain HTTP ([`run`]) and HTTPS with HTTP/2 and HTTP/1.1 by ALPN ([`run_tls`]; `tls.rs` reads
//! the certificate).
//!
//! Every connection is admitted, watched and closed by the limits of `connections.rs`: at
//! most so many open, a deadline for request heads (and the TLS handshake), another for
//! connections without a request in progress.
//!
//! Connection threads, nginx's shape: [`ServerConfig::connection_threads`](super::ServerConfig::connection_threads)
//! threads (one per core by default) each run an event loop of their own (a current-thread
//! tokio runtime) and accept from the one listening socket; a connection is served by the
//! thread with the fewest open (handed over by the one that accepted it, [`Spread`]) and stays
//! there, and its requests are answered there (what would hold the thread up leaves it from
//! inside the handler: CPU work, blocking work, reads of volumes kept in an object store;
//! `docs/architecture.md`). Why: tokio's
//! multi-threaded runtime has one I/O driver, so every connection went through one event loop,
//! woken in batches, with requests and answers handed between threads. Clients with small
//! connection pools (tensorstore's curl threads keep four each) then saw answers in bursts,
//! overflowed their pools and closed and reopened connections many times a read, each costing
//! CPU on both sides; one loop per core, as nginx's workers, answers steadily
//! (docs/benchmarks.md, formats). Every loop wakes for each new connection and one accepts it
//! (tokio registers no `EPOLLEXCLUSIVE`): a wake-up per core per connection, cheap beside the
//! connection itself at the core counts this runs on.
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
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, TcpStream};
use tokio::runtime::Handle;
use tokio::sync::{mpsc, watch};
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
    // Blocking work and the volumes' writer tasks run on this runtime, whichever connection
    // thread took their request: they outlive that thread's connections, and its runtime
    // never has a blocking pool to wait for when it stops.
    state.set_main_runtime(Handle::current());
    let accepting = Accepting {
        service: tower::ServiceBuilder::new()
            .map_request(|r: Request<hyper::body::Incoming>| r.map(axum::body::Body::new))
            .service(app(state.clone())),
        tls,
        open: state.connections.clone(),
        closing: state.closing.clone(),
        grace: state.config.shutdown_grace,
    };
    let listener = listener.into_std()?;
    // Stops the connection threads when this future ends, or is dropped with its runtime.
    let stop = StopOnDrop(Closing::default());
    let (spread, inboxes) = Spread::new(state.config.connection_threads.max(1));
    let mut threads = Vec::new();
    for (i, inbox) in inboxes.into_iter().enumerate() {
        let thread = listener.try_clone().and_then(|listener| {
            let (accepting, stopped) = (accepting.clone(), stop.0.closed());
            let here = Here {
                index: i,
                spread: spread.clone(),
                inbox,
            };
            std::thread::Builder::new()
                .name(format!("isovox-conn-{i}"))
                .spawn(move || connection_thread(listener, here, accepting, stopped))
        });
        match thread {
            Ok(thread) => threads.push(thread),
            Err(e) => {
                stop.0.close();
                join(threads).await?;
                return Err(e);
            }
        }
    }
    drop(listener);
    shutdown.await;
    stop.0.close();
    join(threads).await
}

/// What the connection threads share: the service, the connection limits, the shutdown.
#[derive(Clone)]
struct Accepting<A> {
    service: A,
    tls: Option<TlsAcceptor>,
    open: Arc<super::connections::Connections>,
    closing: Closing,
    grace: Duration,
}

/// The service every connection gets a clone of: [`app`], reading hyper's request bodies.
trait AppService:
    tower::Service<
        hyper::Request<hyper::body::Incoming>,
        Response = axum::response::Response,
        Error = std::convert::Infallible,
        Future: Send + 'static,
    > + Clone
    + Send
    + 'static
{
}

impl<A> AppService for A where
    A: tower::Service<
            hyper::Request<hyper::body::Incoming>,
            Response = axum::response::Response,
            Error = std::convert::Infallible,
            Future: Send + 'static,
        > + Clone
        + Send
        + 'static
{
}

/// A connection accepted and admitted, on its way to the thread that will serve it.
type Handoff = (std::net::TcpStream, std::net::SocketAddr, Admitted);

/// How connections are spread over the connection threads: each thread's open connections, and
/// where to send it one. Whichever thread accepts a connection, the one with the fewest open
/// serves it (the acceptor on a tie). Without this, one thread could take a whole burst of
/// connections (a thread accepts until none is waiting), and a load tester's connections,
/// opened at once and kept, could split anywhere from even to 1:2, so throughput varied widely
/// from one run to the next.
struct Spread {
    open: Vec<AtomicUsize>,
    inboxes: Vec<mpsc::UnboundedSender<Handoff>>,
}

impl Spread {
    fn new(threads: usize) -> (Arc<Spread>, Vec<mpsc::UnboundedReceiver<Handoff>>) {
        let (inboxes, receivers) = (0..threads).map(|_| mpsc::unbounded_channel()).unzip();
        let open = (0..threads).map(|_| AtomicUsize::new(0)).collect();
        (Arc::new(Spread { open, inboxes }), receivers)
    }

    /// The thread that is to serve the next connection, counted as serving it from now.
    fn take(&self, acceptor: usize) -> usize {
        let load = |i: usize| self.open[i].load(Ordering::Relaxed);
        let least = (0..self.open.len())
            .min_by_key(|&i| load(i))
            .unwrap_or(acceptor);
        let to = if load(acceptor) <= load(least) {
            acceptor
        } else {
            least
        };
        self.open[to].fetch_add(1, Ordering::Relaxed);
        to
    }

    fn ended(&self, thread: usize) {
        self.open[thread].fetch_sub(1, Ordering::Relaxed);
    }
}

/// A connection thread's place in the [`Spread`].
struct Here {
    index: usize,
    spread: Arc<Spread>,
    inbox: mpsc::UnboundedReceiver<Handoff>,
}

/// Closes its signal when dropped.
struct StopOnDrop(Closing);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.close();
    }
}

/// One connection thread: a current-thread runtime accepting from `listener` (a handle on the
/// listening socket every connection thread shares) until `stopped`, then shutting down its
/// connections as the module documentation says.
fn connection_thread<A: AppService>(
    listener: std::net::TcpListener,
    here: Here,
    accepting: Accepting<A>,
    stopped: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async move {
        let listener = TcpListener::from_std(listener)?;
        accept_until_shutdown(listener, here, accepting, stopped).await
    })
}

/// Waits for the connection threads to end; a panic in one goes on here.
async fn join(threads: Vec<std::thread::JoinHandle<std::io::Result<()>>>) -> std::io::Result<()> {
    let ended = tokio::task::spawn_blocking(move || {
        threads
            .into_iter()
            .map(std::thread::JoinHandle::join)
            .collect::<Vec<_>>()
    })
    .await
    .map_err(std::io::Error::other)?;
    let mut result = Ok(());
    for thread in ended {
        match thread {
            Ok(Ok(())) => {}
            Ok(Err(e)) => result = result.and(Err(e)),
            Err(panic) => std::panic::resume_unwind(panic),
        }
    }
    result
}

async fn accept_until_shutdown<A: AppService>(
    listener: TcpListener,
    mut here: Here,
    accepting: Accepting<A>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let Accepting {
        service,
        tls,
        open,
        closing,
        grace,
    } = accepting;
    let mut connections = JoinSet::new();
    let serve = |connections: &mut JoinSet<()>, tcp, peer, admitted| {
        let service = TowerToHyperService::new(service.clone());
        let (tls, closing) = (tls.clone(), closing.clone());
        connections.spawn(connection(tcp, peer, tls, service, admitted, closing));
    };
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
            Some((tcp, peer, admitted)) = here.inbox.recv() => {
                match TcpStream::from_std(tcp) {
                    Ok(tcp) => serve(&mut connections, tcp, peer, admitted),
                    Err(e) => {
                        tracing::warn!("connection from {peer} lost on its way: {e}");
                        here.spread.ended(here.index);
                    }
                }
                continue;
            }
            // Forget the connections that ended.
            Some(_) = connections.join_next(), if !connections.is_empty() => {
                here.spread.ended(here.index);
                continue;
            }
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
        let to = here.spread.take(here.index);
        if to == here.index {
            serve(&mut connections, tcp, peer, admitted);
            continue;
        }
        // Another thread serves it: registered with that thread's event loop instead.
        let handed = tcp.into_std().map_err(|e| e.to_string()).and_then(|tcp| {
            here.spread.inboxes[to]
                .send((tcp, peer, admitted))
                .map_err(|_| "that thread has stopped".to_string())
        });
        if let Err(e) = handed {
            // Only when shutting down: the connection is closed, as it would be in a moment.
            tracing::debug!("connection from {peer} dropped on its way: {e}");
            here.spread.ended(to);
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_connection_goes_to_the_thread_with_the_fewest_open_the_acceptor_on_a_tie() {
        let (spread, _inboxes) = Spread::new(3);
        let loads = |s: &Spread| -> Vec<usize> {
            s.open.iter().map(|o| o.load(Ordering::Relaxed)).collect()
        };
        // Every thread at 0: the acceptor keeps it.
        assert_eq!(spread.take(1), 1);
        // Thread 1 has one more than the others: the first of the least loaded gets it.
        assert_eq!(spread.take(1), 0);
        assert_eq!(spread.take(1), 2);
        assert_eq!(loads(&spread), [1, 1, 1]);
        // A tie again: the acceptor.
        assert_eq!(spread.take(0), 0);
        // Two of thread 0's end: it is now the least loaded.
        spread.ended(0);
        spread.ended(0);
        assert_eq!(loads(&spread), [0, 1, 1]);
        assert_eq!(spread.take(2), 0);
        assert_eq!(spread.take(2), 2);
        assert_eq!(loads(&spread), [1, 1, 2]);
    }
}
