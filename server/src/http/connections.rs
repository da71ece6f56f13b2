//! Open connections: how many may be open, and how long one may stay without a request in
//! progress.
//!
//! Every connection takes a file descriptor and some memory, and a client can open them
//! without sending anything, or send its request a byte at a time (slowloris). So:
//! - at most [`Limits::max_connections`] are open. A connection that arrives at the limit
//!   closes the oldest idle one (no request in progress: between requests, or still sending
//!   its first), or, when none is idle, is closed itself at once. Clients that send requests
//!   get in however many connections sit idle; the accept loop waits only when many
//!   connections told to close have not closed yet (they hold descriptors for a moment).
//! - a request's head must arrive within [`Limits::header_timeout`] of its first byte (of the
//!   connection's opening for the first request, which covers the TLS handshake and the
//!   HTTP/2 preface);
//! - a connection without a request in progress for [`Limits::idle_timeout`] is closed.
//!
//! A request is in progress from its head until the last frame of its response has been taken
//! by hyper (`TrackedBody`): a change feed, which never ends, keeps its connection busy
//! however long it lasts (never idle, never closed for room) but counts against the limit. On
//! HTTP/2 a connection is idle when no stream is open, and the header timeout applies to its
//! first request only (an idle HTTP/2 connection may still exchange pings and settings).

use hyper::body::{Body as HttpBody, Frame, SizeHint};
use std::collections::BTreeMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::Notify;
use tokio::time::Instant;

/// How many connections may be open and how long they may idle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Connections open at once (change feeds included).
    pub max_connections: usize,
    /// Time for a request's head to arrive, from its first byte (from the opening, for a
    /// connection's first request).
    pub header_timeout: Duration,
    /// Time a connection may stay open without a request in progress.
    pub idle_timeout: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_connections: default_max_connections(),
            header_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(60),
        }
    }
}

/// Most connections [`default_max_connections`] allows, whatever the descriptor limit: with
/// the memory a connection takes (about 10-30 KiB idle, plus what its response holds), ten
/// thousand stay within a few hundred MiB.
const MOST_CONNECTIONS: usize = 10_000;

/// The default connection limit: what the process's file-descriptor limit leaves after an
/// eighth (at least 64) for volume files, uploads and logs, at most [`MOST_CONNECTIONS`].
pub fn default_max_connections() -> usize {
    let descriptors = fd_limit().unwrap_or(1024);
    let reserve = (descriptors / 8).max(64);
    usize::try_from(descriptors.saturating_sub(reserve))
        .unwrap_or(usize::MAX)
        .clamp(16, MOST_CONNECTIONS)
}

/// The process's soft limit on open file descriptors, when it has one.
pub fn fd_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        rustix::process::getrlimit(rustix::process::Resource::Nofile).current
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// Raises the soft file-descriptor limit to the hard one (as Go's runtime does): the soft
/// default of many systems, 1024, is a few hundred clients. Returns the limit now in force.
///
/// # Errors
/// The system refuses.
pub fn raise_fd_limit() -> std::io::Result<Option<u64>> {
    #[cfg(unix)]
    {
        use rustix::process::{getrlimit, setrlimit, Resource};
        let limit = getrlimit(Resource::Nofile);
        if limit.current.is_some() && limit.current != limit.maximum {
            setrlimit(
                Resource::Nofile,
                rustix::process::Rlimit {
                    current: limit.maximum,
                    maximum: limit.maximum,
                },
            )?;
        }
    }
    Ok(fd_limit())
}

/// The open connections of one server, and its counters.
#[derive(Debug)]
pub struct Connections {
    limits: Limits,
    epoch: Instant,
    open: Mutex<Registry>,
    refused: AtomicU64,
    evicted: AtomicU64,
    timed_out: AtomicU64,
    /// A connection told to close has closed.
    closed: Notify,
}

/// What becomes of a connection that just arrived.
#[derive(Debug)]
pub(super) enum Admission {
    /// It has a place.
    Open(Admitted),
    /// Every connection is busy: close it.
    Refused,
    /// Too many connections told to close have not closed yet: ask again once one has
    /// ([`Connections::closed`]).
    Wait,
}

/// The open connections, oldest first.
#[derive(Debug, Default)]
struct Registry {
    slots: BTreeMap<u64, Arc<Slot>>,
    next: u64,
    /// Of `slots`, those told to close (they leave in a moment).
    closing: usize,
}

impl Connections {
    /// No connection yet, these limits.
    pub fn new(limits: Limits) -> Self {
        Connections {
            limits,
            epoch: Instant::now(),
            open: Mutex::default(),
            refused: AtomicU64::new(0),
            evicted: AtomicU64::new(0),
            timed_out: AtomicU64::new(0),
            closed: Notify::new(),
        }
    }

    /// Resolves once a connection told to close has closed (perhaps already, since the last
    /// [`Connections::admit`]).
    pub(super) async fn closed(&self) {
        self.closed.notified().await;
    }

    /// The limits.
    pub fn limits(&self) -> Limits {
        self.limits
    }

    /// Connections open now, each holding a place (those told to close, which leave in a
    /// moment, are not counted): at most [`Limits::max_connections`].
    pub fn open(&self) -> usize {
        let open = self.registry();
        open.slots.len() - open.closing
    }

    /// Connections closed at once because the limit was reached and none was idle.
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }

    /// Idle connections closed to make room for a new one.
    pub fn evicted(&self) -> u64 {
        self.evicted.load(Ordering::Relaxed)
    }

    /// Connections closed by the header or the idle timeout.
    pub fn timed_out(&self) -> u64 {
        self.timed_out.load(Ordering::Relaxed)
    }

    fn registry(&self) -> std::sync::MutexGuard<'_, Registry> {
        // The lock guards a map and two counters, never held across a panic point that
        // could leave them inconsistent; a poisoned lock's data is still right.
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A place for a connection that just arrived, made by telling the oldest idle one to
    /// close when the limit is reached (see [`Admission`]).
    pub(super) fn admit(self: &Arc<Self>) -> Admission {
        let mut open = self.registry();
        if open.slots.len() - open.closing >= self.limits.max_connections {
            // Connections told to close still hold their descriptors for a moment: when many
            // have not closed yet, wait for them rather than risk running out.
            if open.closing >= CLOSING_AT_ONCE {
                return Admission::Wait;
            }
            let victim = open
                .slots
                .values()
                .find(|s| s.active.load(Ordering::Acquire) == 0 && !s.closing())
                .cloned();
            let Some(victim) = victim else {
                self.refused.fetch_add(1, Ordering::Relaxed);
                return Admission::Refused;
            };
            victim.closing.store(true, Ordering::Release);
            victim.close.notify_one();
            open.closing += 1;
            self.evicted.fetch_add(1, Ordering::Relaxed);
        }
        let id = open.next;
        open.next += 1;
        let slot = Arc::new(Slot {
            epoch: self.epoch,
            active: AtomicU32::new(0),
            idle_since: AtomicU64::new(0),
            head_since: AtomicU64::new(millis(self.epoch)),
            h2: AtomicBool::new(false),
            closing: AtomicBool::new(false),
            close: Notify::new(),
        });
        open.slots.insert(id, slot.clone());
        Admission::Open(Admitted {
            connections: self.clone(),
            id,
            slot,
        })
    }
}

/// Connections told to close that may not have closed yet, at most: the descriptors a server
/// at its limit may use beyond it (the default limit leaves more than this for other files).
/// They close as soon as their tasks run, so the accept loop waits microseconds at a time.
const CLOSING_AT_ONCE: usize = 32;

/// No request head is being read.
const NONE: u64 = u64::MAX;

/// Milliseconds since `epoch`.
fn millis(epoch: Instant) -> u64 {
    u64::try_from(epoch.elapsed().as_millis()).unwrap_or(NONE - 1)
}

/// What one connection is doing, for the limits: shared by its task, its service (requests
/// begin and end) and its byte stream (a request head starts).
#[derive(Debug)]
pub(super) struct Slot {
    epoch: Instant,
    /// Requests in progress.
    active: AtomicU32,
    /// When the last request ended, ms since `epoch`.
    idle_since: AtomicU64,
    /// When the first byte of a request head not yet complete came, ms since `epoch`, or
    /// [`NONE`].
    head_since: AtomicU64,
    /// HTTP/2: bytes between requests are not a request head.
    h2: AtomicBool,
    closing: AtomicBool,
    /// Close now (room for a new connection).
    close: Notify,
}

/// Why a connection is to close.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Expired {
    /// Closed to make room for a new connection.
    Evicted,
    /// A request head did not arrive in time.
    HeaderTimeout,
    /// No request for too long.
    IdleTimeout,
}

impl Slot {
    fn closing(&self) -> bool {
        self.closing.load(Ordering::Acquire)
    }

    /// No request in progress.
    pub(super) fn idle(&self) -> bool {
        self.active.load(Ordering::Acquire) == 0
    }

    /// Whether the connection speaks HTTP/2 (as far as is known yet).
    pub(super) fn h2(&self) -> bool {
        self.h2.load(Ordering::Relaxed)
    }

    /// The connection speaks HTTP/2.
    pub(super) fn set_h2(&self) {
        self.h2.store(true, Ordering::Relaxed);
    }

    fn begin(&self) {
        self.head_since.store(NONE, Ordering::Relaxed);
        self.active.fetch_add(1, Ordering::AcqRel);
    }

    fn end(&self) {
        if self.active.fetch_sub(1, Ordering::AcqRel) == 1 {
            self.idle_since.store(millis(self.epoch), Ordering::Relaxed);
        }
    }

    /// Bytes came in: between requests (HTTP/1), the first starts a request head.
    fn received(&self, bytes: &[u8]) {
        if bytes.is_empty() || !self.idle() || self.h2.load(Ordering::Relaxed) {
            return;
        }
        if self.head_since.load(Ordering::Relaxed) == NONE {
            self.head_since.store(millis(self.epoch), Ordering::Relaxed);
        }
    }

    /// When the connection is to close if nothing changes, ms since `epoch`; `None` while a
    /// request is in progress.
    fn deadline(&self, limits: &Limits) -> Option<(u64, Expired)> {
        if !self.idle() {
            return None;
        }
        let head = self.head_since.load(Ordering::Relaxed);
        Some(if head != NONE {
            (
                head.saturating_add(ms(limits.header_timeout)),
                Expired::HeaderTimeout,
            )
        } else {
            (
                self.idle_since
                    .load(Ordering::Relaxed)
                    .saturating_add(ms(limits.idle_timeout)),
                Expired::IdleTimeout,
            )
        })
    }
}

fn ms(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(NONE - 1)
}

/// A connection's place among the open ones; dropping it frees the place.
#[derive(Debug)]
pub(super) struct Admitted {
    connections: Arc<Connections>,
    id: u64,
    slot: Arc<Slot>,
}

impl Admitted {
    pub(super) fn slot(&self) -> &Arc<Slot> {
        &self.slot
    }

    /// Resolves when the connection is to close: it was told to make room, or it has been
    /// without a request in progress for too long (see the module documentation). Never
    /// while a request is in progress.
    pub(super) async fn expired(&self) -> Expired {
        let (slot, limits) = (&self.slot, self.connections.limits);
        // A deadline that appears while this sleeps (a request head starts, a request ends)
        // lies at least the shorter timeout after the wake-up was set, so waking at least that
        // often never misses one. Waking on every request head instead re-armed a timer per
        // request: a measurable share of a small request's cost.
        let step = ms(limits.header_timeout.min(limits.idle_timeout));
        loop {
            if slot.closing() {
                return Expired::Evicted;
            }
            let now = millis(slot.epoch);
            let deadline = slot.deadline(&limits);
            if let Some((_, why)) = deadline.filter(|&(at, _)| at <= now) {
                self.connections.timed_out.fetch_add(1, Ordering::Relaxed);
                return why;
            }
            let at = deadline
                .map_or(NONE - 1, |(at, _)| at)
                .min(now.saturating_add(step));
            tokio::select! {
                () = tokio::time::sleep_until(slot.epoch + Duration::from_millis(at)) => {}
                () = slot.close.notified() => {}
            }
        }
    }
}

impl Drop for Admitted {
    fn drop(&mut self) {
        let mut open = self.connections.registry();
        if open.slots.remove(&self.id).is_some() && self.slot.closing() {
            open.closing -= 1;
            self.connections.closed.notify_one();
        }
    }
}

/// A byte stream that tells its connection's [`Slot`] when a request head starts.
#[derive(Debug)]
pub(super) struct Watched<I> {
    inner: I,
    slot: Arc<Slot>,
    /// Bytes of the HTTP/2 preface's start still to compare (plain connections: HTTP/2 is
    /// known by its preface, `PRI * HTTP/2.0`).
    preface: &'static [u8],
}

impl<I> Watched<I> {
    pub(super) fn new(inner: I, slot: Arc<Slot>) -> Self {
        Watched {
            inner,
            slot,
            preface: b"PRI ",
        }
    }
}

impl<I: AsyncRead + Unpin> AsyncRead for Watched<I> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let polled = Pin::new(&mut self.inner).poll_read(cx, buf);
        let got = &buf.filled()[before..];
        if !got.is_empty() {
            if !self.preface.is_empty() {
                let n = got.len().min(self.preface.len());
                if got[..n] == self.preface[..n] {
                    self.preface = &self.preface[n..];
                    if self.preface.is_empty() {
                        self.slot.set_h2();
                    }
                } else {
                    self.preface = b"";
                }
            }
            self.slot.received(got);
        }
        polled
    }
}

impl<I: AsyncWrite + Unpin> AsyncWrite for Watched<I> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// A connection's service: each request is in progress (see the module documentation) from
/// the call until its response body is dropped.
#[derive(Debug, Clone)]
pub(super) struct Tracked<S> {
    inner: S,
    slot: Arc<Slot>,
}

impl<S> Tracked<S> {
    pub(super) fn new(inner: S, slot: Arc<Slot>) -> Self {
        Tracked { inner, slot }
    }
}

impl<S, R, B> hyper::service::Service<R> for Tracked<S>
where
    S: hyper::service::Service<R, Response = axum::http::Response<B>>,
{
    type Response = axum::http::Response<TrackedBody<B>>;
    type Error = S::Error;
    type Future = TrackedFuture<S::Future>;

    fn call(&self, request: R) -> Self::Future {
        self.slot.begin();
        let busy = Busy(self.slot.clone());
        TrackedFuture {
            inner: self.inner.call(request),
            busy: Some(busy),
        }
    }
}

/// A request in progress; ends when dropped.
#[derive(Debug)]
struct Busy(Arc<Slot>);

impl Drop for Busy {
    fn drop(&mut self) {
        self.0.end();
    }
}

pin_project_lite::pin_project! {
    /// A response being made; the request stays in progress in its body.
    #[derive(Debug)]
    pub(super) struct TrackedFuture<F> {
        #[pin]
        inner: F,
        busy: Option<Busy>,
    }
}

impl<F, B, E> Future for TrackedFuture<F>
where
    F: Future<Output = Result<axum::http::Response<B>, E>>,
{
    type Output = Result<axum::http::Response<TrackedBody<B>>, E>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let this = self.project();
        let response = std::task::ready!(this.inner.poll(cx));
        let busy = this.busy.take();
        Poll::Ready(response.map(|r| r.map(|inner| TrackedBody { inner, _busy: busy })))
    }
}

pin_project_lite::pin_project! {
    /// A response body; its request is in progress until it is dropped.
    #[derive(Debug)]
    pub(super) struct TrackedBody<B> {
        #[pin]
        inner: B,
        _busy: Option<Busy>,
    }
}

impl<B: HttpBody> HttpBody for TrackedBody<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<B::Data>, B::Error>>> {
        self.project().inner.poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn limits(max_connections: usize) -> Limits {
        Limits {
            max_connections,
            header_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(60),
        }
    }

    #[test]
    fn at_the_limit_the_oldest_idle_connection_makes_room() {
        let c = Arc::new(Connections::new(limits(3)));
        let a = open(&c);
        let b = open(&c);
        let d = open(&c);
        // a is busy (a change feed, say): b, the oldest idle one, goes.
        a.slot().begin();
        let e = open(&c);
        assert!(b.slot().closing() && !a.slot().closing() && !d.slot().closing());
        assert_eq!((c.open(), c.evicted()), (3, 1));
        drop(b);
        assert_eq!(c.open(), 3);
        // All busy: the newcomer is refused.
        d.slot().begin();
        e.slot().begin();
        assert!(matches!(c.admit(), Admission::Refused));
        assert_eq!(c.refused(), 1);
        // A request ends: its connection is idle again, and can make room.
        d.slot().end();
        let _f = open(&c);
        assert!(d.slot().closing());
    }

    fn open(c: &Arc<Connections>) -> Admitted {
        match c.admit() {
            Admission::Open(a) => a,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn newcomers_wait_while_many_connections_are_still_closing() {
        let c = Arc::new(Connections::new(limits(CLOSING_AT_ONCE)));
        let mut first: Vec<_> = (0..CLOSING_AT_ONCE).map(|_| open(&c)).collect();
        let second: Vec<_> = (0..CLOSING_AT_ONCE).map(|_| open(&c)).collect();
        assert!(first.iter().all(|a| a.slot().closing()));
        assert!(matches!(c.admit(), Admission::Wait));
        // One of them closes: room for one more.
        first.pop();
        let third = open(&c);
        assert!(second[0].slot().closing() && !third.slot().closing());
        assert!(matches!(c.admit(), Admission::Wait));
    }

    #[test]
    fn deadlines_follow_what_the_connection_does() {
        let c = Arc::new(Connections::new(limits(10)));
        let a = open(&c);
        let s = a.slot();
        // Just opened: its first request head is due within the header timeout.
        let (at, why) = s.deadline(&c.limits()).unwrap();
        assert_eq!(why, Expired::HeaderTimeout);
        assert!(at <= millis(c.epoch) + 10_000);
        // A request in progress: no deadline.
        s.begin();
        assert_eq!(s.deadline(&c.limits()), None);
        s.end();
        // Idle: the idle timeout, until bytes of the next head come.
        assert_eq!(s.deadline(&c.limits()).unwrap().1, Expired::IdleTimeout);
        s.received(b"GE");
        assert_eq!(s.deadline(&c.limits()).unwrap().1, Expired::HeaderTimeout);
        s.begin();
        s.end();
        // On HTTP/2, bytes between requests (pings, settings) are no request head.
        s.set_h2();
        s.received(b"\0\0\0\x04");
        assert_eq!(s.deadline(&c.limits()).unwrap().1, Expired::IdleTimeout);
    }
}
