//! The brick route and the live views' chunks, answered before the router when the request is
//! plain.
//!
//! `GET /v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}` is the hottest route by far (a viewer
//! streams thousands of bricks a second), and its handler is a few index lookups. Routing it
//! through axum (five path parameters decoded into ten reference-counted strings, a boxed
//! service and a boxed future per request) cost about a tenth of its throughput. So
//! [`BrickFirst`] answers plain requests for it itself: `GET`, no query, a volume name without
//! escapes, numbers in their one canonical spelling (`crate::decimal`), reads not private. It
//! answers them with the routed handler's own [`bricks::brick_at`], and only when that
//! succeeds: every other request, and every request that would fail, goes to the router, so
//! error responses are decided in one place.
//!
//! The live OME-Zarr and precomputed views are read the same way (tensorstore reading a level
//! whole asks for every chunk, a third of them absent): a plain `GET` of a document that takes
//! no work is answered by the views' own [`views::answer_ready`] (a chunk of fill values
//! included: its 404 is the handler's own, mapped in `error.rs`); one that must be made, and
//! every failure, goes to the router.
//!
//! Where each runs: the server reads connections on threads of their own, one current-thread
//! runtime each (`serve.rs` says why), and answers their requests there, plain or routed:
//! handlers never block their thread (CPU work and file writes go to threads of their own,
//! `cpu.rs` and the volume writers). Volumes kept in an object store are the exception: reading
//! one may fetch pages from the store and wait for them (announced to tokio with
//! `block_in_place`, which only a worker of a multi-threaded runtime can do). So the fast path
//! leaves them to the router, and [`Routed`] runs their requests as tasks of the server's
//! multi-threaded runtime ([`OnRuntime`]), where such a wait holds up no other connection.

use super::{bricks, views, ApiError, AppState};
use crate::formats::ViewKind;
use crate::volume::LiveVolume;
use axum::extract::Request;
use axum::http::Method;
use axum::response::{IntoResponse, Response};
use futures_util::future::Either;
use std::convert::Infallible;
use std::future::{ready, Future, Ready};
use std::pin::Pin;
use std::task::{Context, Poll};
use tokio::runtime::Handle;

/// Answers plain brick requests, hands everything else to `inner` (the router).
#[derive(Debug, Clone)]
pub(super) struct BrickFirst<S> {
    state: AppState,
    inner: S,
}

impl<S> BrickFirst<S> {
    pub(super) fn new(state: AppState, inner: S) -> Self {
        BrickFirst { state, inner }
    }
}

impl<S> tower::Service<Request> for BrickFirst<S>
where
    S: tower::Service<Request, Response = Response, Error = Infallible>,
{
    type Response = Response;
    type Error = Infallible;
    type Future = Either<Ready<Result<Response, Infallible>>, S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request) -> Self::Future {
        match plain_brick(&self.state, &request).or_else(|| plain_view(&self.state, &request)) {
            Some(response) => Either::Left(ready(Ok(response))),
            None => Either::Right(self.inner.call(request)),
        }
    }
}

/// The router: requests naming a volume kept in an object store run on `runtime` (see the
/// module documentation), the others where they were read.
#[derive(Debug, Clone)]
pub(super) struct Routed<S> {
    state: AppState,
    here: S,
    on_runtime: OnRuntime<S>,
}

impl<S: Clone> Routed<S> {
    pub(super) fn new(state: AppState, router: S, runtime: Handle) -> Self {
        Routed {
            state,
            here: router.clone(),
            on_runtime: OnRuntime::new(router, runtime),
        }
    }
}

impl<S> tower::Service<Request> for Routed<S>
where
    S: tower::Service<Request, Response = Response, Error = Infallible>,
    S::Future: Send + 'static,
{
    type Response = Response;
    type Error = Infallible;
    type Future = Either<S::Future, <OnRuntime<S> as tower::Service<Request>>::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        match self.here.poll_ready(cx) {
            Poll::Ready(Ok(())) => self.on_runtime.poll_ready(cx),
            not_ready => not_ready,
        }
    }

    fn call(&mut self, request: Request) -> Self::Future {
        if may_wait_on_a_store(&self.state, request.uri().path()) {
            Either::Right(self.on_runtime.call(request))
        } else {
            Either::Left(self.here.call(request))
        }
    }
}

/// `path` names a volume kept in an object store, or a volume name with escapes (as the
/// router would decode them; rare enough to be sent to the runtime unread).
fn may_wait_on_a_store(state: &AppState, path: &str) -> bool {
    let Some(rest) = path.strip_prefix("/v1/volumes/") else {
        return false;
    };
    let name = rest.split('/').next().unwrap_or_default();
    name.contains('%') || state.catalog.get(name).is_ok_and(|v| v.remote().is_some())
}

/// Runs `inner`'s requests as tasks of `runtime`, each cancelled (aborted) if its response is
/// no longer awaited, as a request is when its connection closes.
#[derive(Debug, Clone)]
pub(super) struct OnRuntime<S> {
    inner: S,
    runtime: Handle,
}

impl<S> OnRuntime<S> {
    pub(super) fn new(inner: S, runtime: Handle) -> Self {
        OnRuntime { inner, runtime }
    }
}

impl<S> tower::Service<Request> for OnRuntime<S>
where
    S: tower::Service<Request, Response = Response, Error = Infallible>,
    S::Future: Send + 'static,
{
    type Response = Response;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Response, Infallible>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request) -> Self::Future {
        let task = AbortOnDrop(self.runtime.spawn(self.inner.call(request)));
        Box::pin(async move {
            match task.await {
                Ok(answered) => answered,
                // Unwinds this connection's task, as a handler's panic did when handlers ran on
                // it (the connection closes; the server goes on).
                Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
                // Cancelled: the runtime is shutting down.
                Err(_) => Ok(ApiError::Overloaded(1).into_response()),
            }
        })
    }
}

/// A task that is aborted when this handle is dropped.
struct AbortOnDrop<T>(tokio::task::JoinHandle<T>);

impl<T> Future for AbortOnDrop<T> {
    type Output = Result<T, tokio::task::JoinError>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        Pin::new(&mut self.0).poll(cx)
    }
}

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// A plain brick request's (volume, level, x, y, z), or `None` for anything else.
fn parse(request: &Request) -> Option<(&str, u8, u32, u32, u32)> {
    if request.method() != Method::GET || request.uri().query().is_some() {
        return None;
    }
    let mut segments = request
        .uri()
        .path()
        .strip_prefix("/v1/volumes/")?
        .split('/');
    let name = segments.next().filter(|n| !n.contains('%'))?;
    if segments.next()? != "bricks" {
        return None;
    }
    let level = number(segments.next()?)?;
    let (x, y, z) = (
        number(segments.next()?)?,
        number(segments.next()?)?,
        number(segments.next()?)?,
    );
    if segments.next().is_some() {
        return None;
    }
    Some((name, u8::try_from(level).ok()?, x, y, z))
}

/// A number in its one spelling (`crate::decimal`), as the router reads them.
fn number(segment: &str) -> Option<u32> {
    crate::decimal::parse(segment).ok()
}

/// The response to a plain brick request that succeeds, else `None`.
fn plain_brick(state: &AppState, request: &Request) -> Option<Response> {
    if state.config.private_reads {
        return None;
    }
    let (name, level, x, y, z) = parse(request)?;
    let volume = local_volume(state, name)?;
    bricks::brick_at(state, volume, None, (level, x, y, z), request.headers()).ok()
}

/// A plain request of a live view: `GET /v1/volumes/{name}/zarr/{*path}` (or `precomputed`),
/// no query, no escapes in the name or the path: (volume, view, path within the view).
fn parse_view(request: &Request) -> Option<(&str, ViewKind, &str)> {
    if request.method() != Method::GET || request.uri().query().is_some() {
        return None;
    }
    let rest = request.uri().path().strip_prefix("/v1/volumes/")?;
    if rest.contains('%') {
        return None;
    }
    let (name, rest) = rest.split_once('/')?;
    let (view, path) = rest.split_once('/')?;
    let kind = match view {
        "zarr" => ViewKind::Zarr,
        "precomputed" => ViewKind::Precomputed,
        _ => return None,
    };
    (!name.is_empty() && !path.is_empty()).then_some((name, kind, path))
}

/// The response to a plain view request that takes no work, else `None`.
fn plain_view(state: &AppState, request: &Request) -> Option<Response> {
    if state.config.private_reads {
        return None;
    }
    let (name, kind, path) = parse_view(request)?;
    let volume = local_volume(state, name)?;
    views::answer_ready(state, volume, kind, name, path, request.headers())
}

/// Volume `name` if it is served and kept in a local file: reading it never waits on the
/// network.
fn local_volume<'a>(state: &'a AppState, name: &str) -> Option<&'a LiveVolume> {
    let volume = state.catalog.get(name).ok()?;
    volume.remote().is_none().then_some(volume)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use tokio::sync::Notify;
    use tower::Service;

    fn get(uri: &str) -> Request {
        Request::builder()
            .uri(uri)
            .body(axum::body::Body::empty())
            .unwrap_or_default()
    }

    #[test]
    fn plain_requests_parse() {
        let r = get("/v1/volumes/world/bricks/2/10/0/4294967295");
        assert_eq!(parse(&r), Some(("world", 2, 10, 0, u32::MAX)));
    }

    #[test]
    fn everything_else_goes_to_the_router() {
        for uri in [
            "/v1/volumes/world/bricks/2/10/0/4294967296",
            "/v1/volumes/world/bricks/256/0/0/0",
            "/v1/volumes/world/bricks/0/+1/0/0",
            "/v1/volumes/world/bricks/0/01/0/0",
            "/v1/volumes/world/bricks/00/1/0/0",
            "/v1/volumes/world/bricks/0/-1/0/0",
            "/v1/volumes/world/bricks/0/1/0",
            "/v1/volumes/world/bricks/0/1/0/0/",
            "/v1/volumes/world/bricks/0/1/0/0/7",
            "/v1/volumes/world/bricks/0//0/0",
            "/v1/volumes/w%6Frld/bricks/0/0/0/0",
            "/v1/volumes/world/bricks/0/0/0/0?version=1",
            "/v1/volumes/world/blobs/0/0/0/0",
            "/v1/volumes/world/meshes/0/0/0/0",
            "/v1/volumes//bricks/0/0/0/0x",
            "/v2/volumes/world/bricks/0/0/0/0",
        ] {
            assert_eq!(parse(&get(uri)), None, "{uri}");
        }
        let mut head = get("/v1/volumes/world/bricks/0/0/0/0");
        *head.method_mut() = Method::HEAD;
        assert_eq!(parse(&head), None);
    }

    /// Sets its flag when dropped.
    struct Dropped(Arc<AtomicBool>);

    impl Drop for Dropped {
        fn drop(&mut self) {
            self.0.store(true, Ordering::SeqCst);
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 1)]
    async fn a_routed_request_is_cancelled_with_its_response() {
        let (dropped, started) = (Arc::new(AtomicBool::new(false)), Arc::new(Notify::new()));
        let handler = {
            let (dropped, started) = (dropped.clone(), started.clone());
            tower::service_fn(move |_: Request| {
                let (guard, started) = (Dropped(dropped.clone()), started.clone());
                async move {
                    let _guard = guard;
                    started.notify_one();
                    std::future::pending::<Result<Response, Infallible>>().await
                }
            })
        };
        let answer = OnRuntime::new(handler, Handle::current()).call(get("/x"));
        // It runs as a task of its own, awaited or not.
        started.notified().await;
        assert!(!dropped.load(Ordering::SeqCst));
        drop(answer);
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        while !dropped.load(Ordering::SeqCst) {
            assert!(
                std::time::Instant::now() < deadline,
                "the handler still runs"
            );
            tokio::time::sleep(std::time::Duration::from_millis(1)).await;
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 1)]
    async fn a_routed_handlers_panic_unwinds_where_its_response_is_awaited() {
        let handler = tower::service_fn(|_: Request| async {
            if true {
                panic!("on purpose");
            }
            Ok::<Response, Infallible>(Response::default())
        });
        let answer = OnRuntime::new(handler, Handle::current()).call(get("/x"));
        let awaited = tokio::spawn(answer).await.unwrap_err();
        assert!(awaited.is_panic());
        let panic = awaited.into_panic();
        assert_eq!(panic.downcast_ref::<&str>(), Some(&"on purpose"));
    }

    #[test]
    fn plain_view_requests_parse() {
        let r = get("/v1/volumes/world/zarr/0/c/1/2/3");
        assert_eq!(parse_view(&r), Some(("world", ViewKind::Zarr, "0/c/1/2/3")));
        let r = get("/v1/volumes/ell/precomputed/info");
        assert_eq!(parse_view(&r), Some(("ell", ViewKind::Precomputed, "info")));
        for uri in [
            "/v1/volumes/world/zarr/0/c/1/2/3?x=1",
            "/v1/volumes/world/zarr/",
            "/v1/volumes/world/zarr",
            "/v1/volumes//zarr/zarr.json",
            "/v1/volumes/w%6Frld/zarr/zarr.json",
            "/v1/volumes/world/zarr/0/c/%31/2/3",
            "/v1/volumes/world/versions/1/zarr/zarr.json",
            "/v1/volumes/world/bricks/0/0/0/0",
        ] {
            assert_eq!(parse_view(&get(uri)), None, "{uri}");
        }
    }
}
