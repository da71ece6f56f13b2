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
//! handlers never block their thread (CPU work, file writes and reads of volumes kept in an
//! object store go to threads of their own: `cpu.rs`, the volume writers,
//! [`AppState::read_volume`]). Reading a volume kept in an object store may fetch pages from
//! the store and wait for them, so the fast path leaves those volumes to the router, whose
//! handlers read them on the store-read threads.

use super::{bricks, views, AppState};
use crate::formats::ViewKind;
use crate::volume::LiveVolume;
use axum::extract::Request;
use axum::http::Method;
use axum::response::Response;
use futures_util::future::Either;
use std::convert::Infallible;
use std::future::{ready, Ready};
use std::task::{Context, Poll};

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
