//! Typed calls for every route of the HTTP API (`docs/editing.md`, `/openapi.json`), with
//! retries.
//!
//! Every call returns `proto` types or a [`ClientError`] that carries the server's problem
//! details. Connection failures, 503 and 429 are retried with exponential backoff (honouring
//! `Retry-After`): reads always, edits only when the server cannot have applied them (the
//! connection was refused, or it answered 503/429).

use bytes::Bytes;
use isovox_proto::api::{
    ChangeEvent, ChangeList, CompactResponse, EditResponse, LevelGrid, Problem, VolumeInfo,
    VolumeList,
};
use isovox_proto::batch::{decode_batch, BatchEncoding, BatchEntry, BatchRequest};
use isovox_proto::history::{Presence, PresenceRequest};
use isovox_proto::icvg::EditRequest;
use isovox_proto::mesh::{decode_strip, decode_tile, Mesh, TileMesh, FACE_NAMES};
use isovox_proto::BrickKey;
use reqwest::header::{HeaderMap, HeaderValue};
use reqwest::{Method, RequestBuilder, StatusCode};
use std::time::Duration;

/// What a call can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server answered with an error status (and, normally, problem details).
    #[error("{status}: {}", problem.as_ref().map_or("(no problem details)", |p| p.detail.as_str()))]
    Status {
        /// The status.
        status: StatusCode,
        /// The problem details of the body, when it had them.
        problem: Option<Problem>,
    },
    /// The request did not get an answer (connection refused or reset, timeout).
    #[error("transport: {0}")]
    Transport(#[from] reqwest::Error),
    /// The answer did not decode.
    #[error("cannot decode the answer: {0}")]
    Decode(String),
}

impl ClientError {
    /// The HTTP status, when the server answered.
    pub fn status(&self) -> Option<StatusCode> {
        match self {
            ClientError::Status { status, .. } => Some(*status),
            _ => None,
        }
    }

    /// A short name for reports: the status code or the kind of transport failure.
    pub fn kind(&self) -> String {
        match self {
            ClientError::Status { status, .. } => status.as_u16().to_string(),
            ClientError::Transport(e) if e.is_timeout() => "timeout".into(),
            ClientError::Transport(e) if e.is_connect() => "connect".into(),
            ClientError::Transport(_) => "transport".into(),
            ClientError::Decode(_) => "decode".into(),
        }
    }
}

/// How calls are retried.
#[derive(Debug, Clone, Copy)]
pub struct RetryPolicy {
    /// Attempts in all (1 = no retry).
    pub attempts: u32,
    /// First backoff; doubled on every retry, with jitter, up to `max_delay`.
    pub base_delay: Duration,
    /// The longest wait between two tries.
    pub max_delay: Duration,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        RetryPolicy {
            attempts: 5,
            base_delay: Duration::from_millis(50),
            max_delay: Duration::from_secs(5),
        }
    }
}

/// One brick as the server sent it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Brick {
    /// The brick.
    pub key: BrickKey,
    /// Content hash (the ETag).
    pub hash: u64,
    /// Decoded voxels, x fastest, u16 little endian.
    pub voxels: Bytes,
}

/// One event of the change feed.
#[derive(Debug, Clone, PartialEq)]
pub enum FeedEvent {
    /// The first event: the version current when the subscription started.
    Hello {
        /// The volume's version then.
        version: u64,
    },
    /// A committed version (boxed: with its author and operation it is much larger than the
    /// other events).
    Commit(Box<ChangeEvent>),
    /// The subscriber fell behind: versions after `since` up to `version` were skipped; fetch
    /// them with [`Client::changes`].
    Resync {
        /// The last version the subscriber had.
        since: u64,
        /// The version it is told about now.
        version: u64,
    },
    /// Where another user is (or that they left: `gone`).
    Presence(Presence),
}

/// Sees every HTTP exchange a [`Client`] makes (each attempt of a retried call): load tests
/// and the streamer's statistics hang off it.
pub trait Observer: Send + Sync + std::fmt::Debug {
    /// `route` names the API route (`"brick"`, `"mesh"`, `"edit"`, ...); `outcome` is the
    /// status code, or the kind of transport failure; `bytes` the response body's length when
    /// it is known up front; `retried` says that the client tries the call again after this
    /// exchange (a 503 or 429, or a transport failure it may repeat), so it is not the call's
    /// outcome.
    fn exchange(
        &self,
        route: &'static str,
        outcome: Result<u16, &str>,
        latency: Duration,
        bytes: u64,
        retried: bool,
    );
}

/// A client of one Isovox server.
#[derive(Debug, Clone)]
pub struct Client {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
    retry: RetryPolicy,
    observer: Option<std::sync::Arc<dyn Observer>>,
}

/// `reqwest` idles connections per host; a viewer keeps a few dozen requests in flight.
const POOL_PER_HOST: usize = 64;

/// The most bytes a zstd-encoded answer may decode to (a level's voxels are at most 64 MiB, a
/// whole level's grid of a very large volume a few hundred): past it the answer is refused
/// rather than decoded without bound.
const MAX_DECODED_BYTES: u64 = 1 << 30;

impl Client {
    /// A client of the server at `base` (e.g. `http://127.0.0.1:7070`).
    ///
    /// # Errors
    /// The HTTP client cannot be built (TLS or resolver setup).
    ///
    /// # Panics
    /// This crate speaks plain HTTP and enables no TLS in reqwest. A program that also links
    /// something enabling reqwest's `rustls-no-provider` (the server library does) must install
    /// a rustls crypto provider first (`isovox_server::client_tls::install_provider`), or
    /// reqwest panics here.
    pub fn new(base: &str) -> Result<Client, ClientError> {
        let http = reqwest::Client::builder()
            .pool_max_idle_per_host(POOL_PER_HOST)
            .connect_timeout(Duration::from_secs(5))
            .build()?;
        Ok(Client {
            http,
            base: base.trim_end_matches('/').to_string(),
            token: None,
            retry: RetryPolicy::default(),
            observer: None,
        })
    }

    /// Sends `Authorization: Bearer token` (needed for edits and compaction).
    pub fn with_token(mut self, token: impl Into<String>) -> Client {
        self.token = Some(token.into());
        self
    }

    /// The same client, retrying as `retry` says.
    pub fn with_retry(mut self, retry: RetryPolicy) -> Client {
        self.retry = retry;
        self
    }

    /// Reports every exchange to `observer`.
    pub fn with_observer(mut self, observer: std::sync::Arc<dyn Observer>) -> Client {
        self.observer = Some(observer);
        self
    }

    /// The observer [`Client::with_observer`] set.
    pub(crate) fn observer(&self) -> Option<std::sync::Arc<dyn Observer>> {
        self.observer.clone()
    }

    /// The server's base URL.
    pub fn base(&self) -> &str {
        &self.base
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    fn request(&self, method: Method, path: &str) -> RequestBuilder {
        let r = self.http.request(method, self.url(path));
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    /// Sends (retrying as [`RetryPolicy`] says) and returns a successful response, or the
    /// server's problem. `idempotent` requests are retried on any transport error, others only
    /// when the connection could not be made.
    async fn send(
        &self,
        route: &'static str,
        build: impl Fn() -> RequestBuilder,
        idempotent: bool,
    ) -> Result<reqwest::Response, ClientError> {
        self.send_attempts(route, build, idempotent, self.retry.attempts)
            .await
    }

    /// [`Client::send`] with at most `attempts` attempts.
    async fn send_attempts(
        &self,
        route: &'static str,
        build: impl Fn() -> RequestBuilder,
        idempotent: bool,
        attempts: u32,
    ) -> Result<reqwest::Response, ClientError> {
        let mut attempt = 0;
        loop {
            attempt += 1;
            let last = attempt >= attempts.max(1);
            let start = std::time::Instant::now();
            let answer = build().send().await;
            // Whether this exchange ends the call, decided before the observer sees it, so
            // that load tests tell an answer the client tried again after from a failure.
            let retried = !last
                && match &answer {
                    Ok(r) => {
                        r.status() == StatusCode::SERVICE_UNAVAILABLE
                            || r.status() == StatusCode::TOO_MANY_REQUESTS
                    }
                    Err(e) => idempotent || e.is_connect(),
                };
            if let Some(o) = &self.observer {
                match &answer {
                    Ok(r) => o.exchange(
                        route,
                        Ok(r.status().as_u16()),
                        start.elapsed(),
                        r.content_length().unwrap_or(0),
                        retried,
                    ),
                    Err(e) => o.exchange(
                        route,
                        Err(if e.is_timeout() {
                            "timeout"
                        } else if e.is_connect() {
                            "connect"
                        } else {
                            "transport"
                        }),
                        start.elapsed(),
                        0,
                        retried,
                    ),
                }
            }
            let wait = match answer {
                Ok(r) if r.status().is_success() || r.status() == StatusCode::NOT_MODIFIED => {
                    return Ok(r)
                }
                Ok(r) if !retried => return Err(problem(r).await),
                Ok(r) => retry_after(r.headers()),
                Err(e) if !retried => return Err(e.into()),
                Err(_) => None,
            };
            tokio::time::sleep(wait.unwrap_or_else(|| self.backoff(attempt))).await;
        }
    }

    fn backoff(&self, attempt: u32) -> Duration {
        let exp = self
            .retry
            .base_delay
            .saturating_mul(1 << (attempt - 1).min(16))
            .min(self.retry.max_delay);
        // Jitter in [50%, 100%]: clients that failed together do not retry together.
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        exp.mul_f64(0.5 + (nanos % 1000) as f64 / 2000.0)
    }

    async fn json<T: serde::de::DeserializeOwned>(
        &self,
        route: &'static str,
        build: impl Fn() -> RequestBuilder,
        idempotent: bool,
    ) -> Result<T, ClientError> {
        let bytes = self.body(route, build, idempotent).await?;
        serde_json::from_slice(&bytes).map_err(|e| ClientError::Decode(e.to_string()))
    }

    /// The body of a successful answer, asked for with `Accept-Encoding: zstd` and decoded
    /// here. The server compresses what it builds per request (grids, voxels, meshes, change
    /// lists): a level grid's JSON shrinks tens of times, which is most of what a streamer
    /// fetches besides bricks. Brick routes are not asked this way: they send stored frames.
    async fn body(
        &self,
        route: &'static str,
        build: impl Fn() -> RequestBuilder,
        idempotent: bool,
    ) -> Result<Bytes, ClientError> {
        let answer = self
            .send(
                route,
                || build().header(reqwest::header::ACCEPT_ENCODING, "zstd"),
                idempotent,
            )
            .await?;
        let zstd = answer
            .headers()
            .get(reqwest::header::CONTENT_ENCODING)
            .is_some_and(|e| e.as_bytes().eq_ignore_ascii_case(b"zstd"));
        let bytes = answer.bytes().await?;
        if zstd {
            decode_zstd(&bytes, MAX_DECODED_BYTES).map(Bytes::from)
        } else {
            Ok(bytes)
        }
    }

    /// `GET /v1/volumes`.
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn volumes(&self) -> Result<VolumeList, ClientError> {
        self.json("volumes", || self.request(Method::GET, "/v1/volumes"), true)
            .await
    }

    /// `GET /v1/volumes/{name}`.
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn volume(&self, name: &str) -> Result<VolumeInfo, ClientError> {
        let path = format!("/v1/volumes/{name}");
        self.json("volume", || self.request(Method::GET, &path), true)
            .await
    }

    /// One brick's voxels, fetched as an lz4 block (small on the wire) and decoded.
    /// `known` is the content hash the caller holds: when the brick still has it, the server
    /// answers 304 and this returns `None`.
    ///
    /// # Errors
    /// See [`ClientError`]; `Decode` when the block does not decode to `brick_bytes`.
    pub async fn brick(
        &self,
        name: &str,
        key: BrickKey,
        version: Option<u64>,
        known: Option<u64>,
        brick_bytes: usize,
    ) -> Result<Option<Brick>, ClientError> {
        let mut path = format!(
            "/v1/volumes/{name}/bricks/{}/{}/{}/{}",
            key.level, key.x, key.y, key.z
        );
        if let Some(v) = version {
            path.push_str(&format!("?version={v}"));
        }
        let response = self
            .send(
                "brick",
                || {
                    let r = self
                        .request(Method::GET, &path)
                        .header("accept", "application/x-lz4");
                    match known {
                        Some(h) => r.header("if-none-match", format!("\"{h:016x}\"")),
                        None => r,
                    }
                },
                true,
            )
            .await?;
        if response.status() == StatusCode::NOT_MODIFIED {
            return Ok(None);
        }
        let hash = etag_hash(response.headers())
            .ok_or_else(|| ClientError::Decode("a brick without a content-hash ETag".into()))?;
        let lz4 = response
            .headers()
            .get("content-type")
            .is_some_and(|v| v.as_bytes() == b"application/x-lz4");
        let body = response.bytes().await?;
        let voxels = if lz4 {
            Bytes::from(
                lz4_flex::block::decompress(&body, brick_bytes)
                    .map_err(|e| ClientError::Decode(format!("brick {key}: {e}")))?,
            )
        } else {
            body
        };
        if voxels.len() != brick_bytes {
            return Err(ClientError::Decode(format!(
                "brick {key}: {} bytes, expected {brick_bytes}",
                voxels.len()
            )));
        }
        Ok(Some(Brick { key, hash, voxels }))
    }

    /// A brick by content hash (raw voxels).
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn blob(&self, name: &str, hash: u64) -> Result<Bytes, ClientError> {
        let path = format!("/v1/volumes/{name}/blobs/{hash:016x}");
        Ok(self
            .send("blob", || self.request(Method::GET, &path), true)
            .await?
            .bytes()
            .await?)
    }

    /// Many bricks in one request (at most `proto::batch::MAX_BATCH`), decoded voxels.
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn batch(
        &self,
        name: &str,
        keys: &[BrickKey],
        version: Option<u64>,
    ) -> Result<Vec<BatchEntry>, ClientError> {
        let path = format!("/v1/volumes/{name}/batch");
        let body = serde_json::to_vec(&BatchRequest {
            keys: keys.iter().map(|k| (k.level, k.x, k.y, k.z)).collect(),
            version,
            encoding: BatchEncoding::Raw,
        })
        .map_err(|e| ClientError::Decode(e.to_string()))?;
        let bytes = self
            .send(
                "batch",
                || {
                    self.request(Method::POST, &path)
                        .header("content-type", "application/json")
                        .body(body.clone())
                },
                true,
            )
            .await?
            .bytes()
            .await?;
        decode_batch(&bytes).map_err(|e| ClientError::Decode(e.to_string()))
    }

    /// A level's brick grid (or the box `region` of it, in bricks: min, max exclusive).
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn level_grid(
        &self,
        name: &str,
        level: u8,
        region: Option<([u32; 3], [u32; 3])>,
        version: Option<u64>,
    ) -> Result<LevelGrid, ClientError> {
        let path = level_path(name, level, "grid", region, version);
        self.json("level", || self.request(Method::GET, &path), true)
            .await
    }

    /// A level's voxels (or the box `region` of it, in voxels) as one array, x fastest.
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn level_voxels(
        &self,
        name: &str,
        level: u8,
        region: Option<([u32; 3], [u32; 3])>,
        version: Option<u64>,
    ) -> Result<Bytes, ClientError> {
        let path = level_path(name, level, "voxels", region, version);
        self.body("level", || self.request(Method::GET, &path), true)
            .await
    }

    /// One mesh tile in world coordinates, with its moves (the compact encoding, version 3;
    /// `isovox_proto::mesh::stitch` draws it with the strips of the faces that touch a coarser
    /// neighbour, [`Client::mesh_strip`]). `iso` defaults to the server's.
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn mesh_tile(
        &self,
        name: &str,
        key: BrickKey,
        iso: Option<f32>,
        version: Option<u64>,
    ) -> Result<TileMesh, ClientError> {
        let bytes = self.mesh_part(name, key, None, iso, version).await?;
        tile_answer(key, &bytes)
    }

    /// The transition strip of face `face` (0..6, in `FACE_NAMES` order) of a mesh tile, in
    /// world coordinates as drawn (a plain mesh, the compact encoding's version 1). `iso`
    /// defaults to the server's.
    ///
    /// # Errors
    /// See [`ClientError`]; a face beyond 5 is a decode error, before any request.
    pub async fn mesh_strip(
        &self,
        name: &str,
        key: BrickKey,
        face: usize,
        iso: Option<f32>,
        version: Option<u64>,
    ) -> Result<Mesh, ClientError> {
        let bytes = self.mesh_part(name, key, Some(face), iso, version).await?;
        strip_answer(key, face, &bytes)
    }

    /// The compact encoding of mesh tile `key` (`face` `None`) or of the strip of its face
    /// `face`, undecoded (the streamer counts its size; [`tile_answer`] and [`strip_answer`]
    /// decode it).
    pub(crate) async fn mesh_part(
        &self,
        name: &str,
        key: BrickKey,
        face: Option<usize>,
        iso: Option<f32>,
        version: Option<u64>,
    ) -> Result<Bytes, ClientError> {
        let tile = format!(
            "/v1/volumes/{name}/meshes/{}/{}/{}/{}",
            key.level, key.x, key.y, key.z
        );
        match face {
            None => self.mesh_bytes("mesh", tile, iso, version).await,
            Some(face) => {
                let Some(face_name) = FACE_NAMES.get(face) else {
                    return Err(ClientError::Decode(format!("tile {key}: no face {face}")));
                };
                let path = format!("{tile}/strips/{face_name}");
                self.mesh_bytes("strip", path, iso, version).await
            }
        }
    }

    /// The compact encoding of the mesh answer at `path` (a tile's or a strip's), at `iso` and
    /// `version` when given; `route` names it for the observer.
    async fn mesh_bytes(
        &self,
        route: &'static str,
        mut path: String,
        iso: Option<f32>,
        version: Option<u64>,
    ) -> Result<Bytes, ClientError> {
        path.push_str("?format=compact");
        if let Some(iso) = iso {
            path.push_str(&format!("&iso={iso}"));
        }
        if let Some(v) = version {
            path.push_str(&format!("&version={v}"));
        }
        self.body(route, || self.request(Method::GET, &path), true)
            .await
    }

    /// Applies an edit (needs a write token); with `if_match`, only at that version.
    ///
    /// # Errors
    /// See [`ClientError`]; 409 when `if_match` names another version (the problem's
    /// `version` is the current one).
    pub async fn edit(
        &self,
        name: &str,
        edit: &EditRequest,
        if_match: Option<u64>,
    ) -> Result<EditResponse, ClientError> {
        let path = format!("/v1/volumes/{name}/edits");
        let body = serde_json::to_vec(edit).map_err(|e| ClientError::Decode(e.to_string()))?;
        self.json(
            "edit",
            || {
                let r = self
                    .request(Method::POST, &path)
                    .header("content-type", "application/json")
                    .body(body.clone());
                match if_match {
                    Some(v) => r.header("if-match", v.to_string()),
                    None => r,
                }
            },
            false,
        )
        .await
    }

    /// `POST /v1/volumes/{name}/presence`: says where this client's user is; the change feed
    /// tells the others (a few a second per user at most: 429 beyond). Sent once, never
    /// retried: a position that waited for a retry is old news, and the next one follows.
    ///
    /// # Errors
    /// See [`ClientError`]; 429 when the user says where they are too often.
    pub async fn presence(
        &self,
        name: &str,
        presence: &PresenceRequest,
    ) -> Result<(), ClientError> {
        let path = format!("/v1/volumes/{name}/presence");
        let body = serde_json::to_vec(presence).map_err(|e| ClientError::Decode(e.to_string()))?;
        let build = || {
            self.request(Method::POST, &path)
                .header("content-type", "application/json")
                .body(body.clone())
        };
        self.send_attempts("presence", build, false, 1).await?;
        Ok(())
    }

    /// `POST /v1/volumes/{name}/undo`: takes back the edit of `version` (or makes an undone
    /// one again, for an undo's version).
    ///
    /// # Errors
    /// As [`Client::edit`]; 403 for another user's edit, 409 for a version that is no edit or
    /// one undone already.
    pub async fn undo(&self, name: &str, version: u64) -> Result<EditResponse, ClientError> {
        let path = format!("/v1/volumes/{name}/undo");
        let body = serde_json::to_vec(&isovox_proto::history::UndoRequest {
            version,
            message: None,
        })
        .map_err(|e| ClientError::Decode(e.to_string()))?;
        self.json(
            "undo",
            || {
                self.request(Method::POST, &path)
                    .header("content-type", "application/json")
                    .body(body.clone())
            },
            false,
        )
        .await
    }

    /// The versions after `since` (at most `limit`, the server's default when `None`).
    ///
    /// # Errors
    /// See [`ClientError`]; 410 when compaction dropped versions after `since`, 409 when
    /// `since` is after the volume's head (it was replaced: reload).
    pub async fn changes(
        &self,
        name: &str,
        since: u64,
        limit: Option<usize>,
    ) -> Result<ChangeList, ClientError> {
        let mut path = format!("/v1/volumes/{name}/changes?since={since}");
        if let Some(l) = limit {
            path.push_str(&format!("&limit={l}"));
        }
        self.json("changes", || self.request(Method::GET, &path), true)
            .await
    }

    /// Rewrites the volume's file with only its head version (needs a write token).
    ///
    /// # Errors
    /// See [`ClientError`].
    pub async fn compact(&self, name: &str) -> Result<CompactResponse, ClientError> {
        let path = format!("/v1/volumes/{name}/compact");
        self.json("compact", || self.request(Method::POST, &path), false)
            .await
    }

    /// Subscribes to the change feed; with `since`, the versions after it come first.
    ///
    /// # Errors
    /// See [`ClientError`]; 410 and 409 as for [`Client::changes`].
    pub async fn events(&self, name: &str, since: Option<u64>) -> Result<Feed, ClientError> {
        let mut path = format!("/v1/volumes/{name}/events");
        if let Some(s) = since {
            path.push_str(&format!("?since={s}"));
        }
        let response = self
            .send("events", || self.request(Method::GET, &path), true)
            .await?;
        Ok(Feed {
            response,
            buffer: Vec::new(),
            event: String::new(),
            data: String::new(),
        })
    }
}

fn level_path(
    name: &str,
    level: u8,
    format: &str,
    region: Option<([u32; 3], [u32; 3])>,
    version: Option<u64>,
) -> String {
    let mut path = format!("/v1/volumes/{name}/levels/{level}?format={format}");
    if let Some((min, max)) = region {
        path.push_str(&format!(
            "&region={},{},{},{},{},{}",
            min[0], min[1], min[2], max[0], max[1], max[2]
        ));
    }
    if let Some(v) = version {
        path.push_str(&format!("&version={v}"));
    }
    path
}

/// `bytes` decoded from zstd, refused when they would decode to more than `limit` bytes.
fn decode_zstd(bytes: &[u8], limit: u64) -> Result<Vec<u8>, ClientError> {
    use std::io::Read;
    let bad = |e: std::io::Error| ClientError::Decode(format!("zstd body: {e}"));
    // A frame that states its size (the server's do) is decoded in one call, by a context this
    // thread keeps: making a context per answer (ZSTD_createDCtx) showed in the profile of a
    // load tester of 50 streamers, with the fresh pages it allocates. Anything else (several
    // frames, a frame without its size) is decoded as a stream.
    if let Ok(Some(size)) = zstd::zstd_safe::get_frame_content_size(bytes) {
        if size > limit {
            return Err(ClientError::Decode(format!(
                "zstd body decodes to more than {limit} bytes"
            )));
        }
        thread_local! {
            static DECOMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
                const { std::cell::RefCell::new(None) };
        }
        let decoded = DECOMPRESSOR.with(|d| {
            let mut d = d.borrow_mut();
            if d.is_none() {
                *d = zstd::bulk::Decompressor::new().ok();
            }
            d.as_mut()?.decompress(bytes, size as usize).ok()
        });
        if let Some(out) = decoded.filter(|out| out.len() as u64 == size) {
            return Ok(out);
        }
    }
    let mut out = Vec::new();
    zstd::stream::read::Decoder::new(bytes)
        .map_err(bad)?
        .take(limit + 1)
        .read_to_end(&mut out)
        .map_err(bad)?;
    if out.len() as u64 > limit {
        return Err(ClientError::Decode(format!(
            "zstd body decodes to more than {limit} bytes"
        )));
    }
    Ok(out)
}

/// The content hash an ETag (`"16 hex digits"`, maybe weak) names.
fn etag_hash(headers: &HeaderMap) -> Option<u64> {
    let v = headers.get("etag")?.to_str().ok()?;
    u64::from_str_radix(v.trim_start_matches("W/").trim_matches('"'), 16).ok()
}

fn retry_after(headers: &HeaderMap) -> Option<Duration> {
    headers
        .get("retry-after")
        .and_then(|v: &HeaderValue| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map(Duration::from_secs)
}

/// The error for a non-success answer, with its problem details when it has them.
async fn problem(response: reqwest::Response) -> ClientError {
    let status = response.status();
    let problem = response
        .bytes()
        .await
        .ok()
        .and_then(|b| serde_json::from_slice::<Problem>(&b).ok());
    ClientError::Status { status, problem }
}

/// A change-feed subscription (server-sent events).
#[derive(Debug)]
pub struct Feed {
    response: reqwest::Response,
    buffer: Vec<u8>,
    event: String,
    data: String,
}

impl Feed {
    /// The next event; `None` when the server closed the stream.
    ///
    /// # Errors
    /// The connection failed, or an event did not decode.
    pub async fn next(&mut self) -> Result<Option<FeedEvent>, ClientError> {
        loop {
            while let Some(end) = self.buffer.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.buffer.drain(..=end).collect();
                let line = String::from_utf8_lossy(&line);
                let line = line.trim_end_matches(['\r', '\n']);
                if line.is_empty() {
                    // End of an event.
                    let (event, data) = (
                        std::mem::take(&mut self.event),
                        std::mem::take(&mut self.data),
                    );
                    if let Some(e) = parse_event(&event, &data)? {
                        return Ok(Some(e));
                    }
                } else if let Some(v) = line.strip_prefix("event:") {
                    self.event = v.trim().to_string();
                } else if let Some(v) = line.strip_prefix("data:") {
                    if !self.data.is_empty() {
                        self.data.push('\n');
                    }
                    self.data.push_str(v.trim_start());
                }
                // `id:` repeats the commit's version; comments (`:`) keep the line alive.
            }
            match self.response.chunk().await? {
                Some(chunk) => self.buffer.extend_from_slice(&chunk),
                None => return Ok(None),
            }
        }
    }
}

fn parse_event(event: &str, data: &str) -> Result<Option<FeedEvent>, ClientError> {
    #[derive(serde::Deserialize)]
    struct Hello {
        version: u64,
    }
    #[derive(serde::Deserialize)]
    struct Resync {
        since: u64,
        version: u64,
    }
    let bad = |e: serde_json::Error| ClientError::Decode(format!("{event} event: {e}"));
    Ok(match event {
        "hello" => Some(FeedEvent::Hello {
            version: serde_json::from_str::<Hello>(data).map_err(bad)?.version,
        }),
        "commit" => Some(FeedEvent::Commit(Box::new(
            serde_json::from_str(data).map_err(bad)?,
        ))),
        "resync" => {
            let r: Resync = serde_json::from_str(data).map_err(bad)?;
            Some(FeedEvent::Resync {
                since: r.since,
                version: r.version,
            })
        }
        "presence" => Some(FeedEvent::Presence(
            serde_json::from_str(data).map_err(bad)?,
        )),
        _ => None,
    })
}

/// Mesh tile `key` from its answer's compact encoding.
pub(crate) fn tile_answer(key: BrickKey, bytes: &[u8]) -> Result<TileMesh, ClientError> {
    decode_tile(bytes).map_err(|e| ClientError::Decode(format!("tile {key}: {e}")))
}

/// The strip of face `face` of mesh tile `key` from its answer's compact encoding.
pub(crate) fn strip_answer(key: BrickKey, face: usize, bytes: &[u8]) -> Result<Mesh, ClientError> {
    let name = FACE_NAMES.get(face).copied().unwrap_or("?");
    decode_strip(bytes).map_err(|e| ClientError::Decode(format!("strip {name} of tile {key}: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zstd_bodies_decode_within_their_limit_only() {
        let body: Vec<u8> = (0..10_000u32).flat_map(|i| (i % 7).to_le_bytes()).collect();
        let packed = zstd::bulk::compress(&body, 3).unwrap();
        assert!(packed.len() < body.len() / 10);
        assert_eq!(decode_zstd(&packed, 40_000).unwrap(), body);
        // One byte over the limit is refused, not truncated.
        assert!(matches!(
            decode_zstd(&packed, 39_999),
            Err(ClientError::Decode(_))
        ));
        // Without its size in the frame (a stream), and two frames one after the other: both
        // decoded whole.
        let streamed = zstd::stream::encode_all(&body[..], 3).unwrap();
        assert_eq!(
            zstd::zstd_safe::get_frame_content_size(&streamed).unwrap(),
            None
        );
        assert_eq!(decode_zstd(&streamed, 40_000).unwrap(), body);
        assert!(decode_zstd(&streamed, 39_999).is_err());
        let twice = [packed.clone(), packed.clone()].concat();
        assert_eq!(
            decode_zstd(&twice, 80_000).unwrap(),
            [&body[..], &body[..]].concat()
        );
        assert!(decode_zstd(&twice, 79_999).is_err());
        // Not zstd at all.
        assert!(matches!(
            decode_zstd(b"{\"level\": 0}", 1 << 20),
            Err(ClientError::Decode(_))
        ));
    }

    /// Keeps each exchange's status and whether the client said it would try again.
    #[derive(Debug, Default)]
    struct Exchanges(std::sync::Mutex<Vec<(u16, bool)>>);

    impl Observer for Exchanges {
        fn exchange(&self, _: &'static str, o: Result<u16, &str>, _: Duration, _: u64, r: bool) {
            self.0.lock().unwrap().push((o.unwrap_or(0), r));
        }
    }

    /// A server on loopback that answers its connections' requests with `statuses`, one each.
    async fn answering(statuses: Vec<u16>) -> String {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        tokio::spawn(async move {
            for status in statuses {
                let (mut socket, _) = listener.accept().await.unwrap();
                let mut head = Vec::new();
                let mut buf = [0u8; 1024];
                while !head.ends_with(b"\r\n\r\n") {
                    let n = socket.read(&mut buf).await.unwrap();
                    assert!(n > 0, "the client closed before its request ended");
                    head.extend_from_slice(&buf[..n]);
                }
                let body = if status == 200 {
                    "{\"volumes\": []}"
                } else {
                    "{}"
                };
                let answer = format!(
                    "HTTP/1.1 {status} X\r\ncontent-type: application/json\r\nretry-after: 0\r\n\
                     content-length: {}\r\nconnection: close\r\n\r\n{body}",
                    body.len()
                );
                socket.write_all(answer.as_bytes()).await.unwrap();
            }
        });
        format!("http://{addr}")
    }

    /// `GET /v1/volumes` (three attempts at most) against a server answering `statuses`: the
    /// call's success, and each exchange's status and whether the client said it would retry.
    async fn volumes_answered(statuses: Vec<u16>) -> (bool, Vec<(u16, bool)>) {
        isovox_server::client_tls::install_provider();
        let retry = RetryPolicy {
            attempts: 3,
            base_delay: Duration::from_millis(1),
            max_delay: Duration::from_millis(1),
        };
        let seen = std::sync::Arc::new(Exchanges::default());
        let client = Client::new(&answering(statuses).await)
            .unwrap()
            .with_retry(retry)
            .with_observer(seen.clone());
        let ok = client.volumes().await.is_ok();
        let exchanges = seen.0.lock().unwrap().clone();
        (ok, exchanges)
    }

    #[tokio::test]
    async fn the_observer_is_told_which_answers_the_client_tries_again_after() {
        // Shed twice, then answered: two exchanges retried, the third ends the call.
        assert_eq!(
            volumes_answered(vec![503, 429, 200]).await,
            (true, vec![(503, true), (429, true), (200, false)])
        );
        // Shed on every attempt: the last 503 is the call's failure, not retried.
        assert_eq!(
            volumes_answered(vec![503, 503, 503]).await,
            (false, vec![(503, true), (503, true), (503, false)])
        );
        // A status the client never retries ends the call at once.
        assert_eq!(
            volumes_answered(vec![500]).await,
            (false, vec![(500, false)])
        );
    }
}
