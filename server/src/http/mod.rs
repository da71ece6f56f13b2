//! The HTTP service: an axum router over the [`Catalog`], thin handlers, errors as responses.
//!
//! [`app`] builds the service (router and layers) from a state; [`run`] (plain HTTP) and
//! [`run_tls`] (HTTPS with HTTP/2) serve it on a listener until `shutdown` resolves, then end the
//! change feeds and let the other requests in flight finish.
//!
//! Routes (all under `/v1` but the probes and the viewer):
//! - `GET /healthz`: liveness; `GET /metrics`: Prometheus text; `GET /openapi.json`: the API.
//! - `GET /v1/volumes`, `GET /v1/volumes/{name}`: what is served and how to address it.
//! - `GET /v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}`: one brick (see [`bricks::brick`]).
//! - `GET /v1/volumes/{name}/blobs/{hash}`: a brick by content hash, cacheable forever.
//! - `POST /v1/volumes/{name}/batch`: many bricks in one response (`proto::batch`).
//! - `GET /v1/volumes/{name}/levels/{level}`: a level's brick grid, or its voxels.
//! - `GET /v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}`: one mesh tile (see
//!   [`handlers::mesh_tile`]); `.../strips/{face}`: the transition strip of one of its faces
//!   ([`handlers::mesh_strip`]).
//! - `GET /v1/volumes/{name}/channels/{channel}/segments`: a categorical channel's ids with
//!   their voxel counts and boxes; `.../segments/{id}/mesh`: one segment's closed mesh
//!   ([`segments`]).
//! - `POST /v1/volumes/{name}/edits` ([`edit`]), `POST .../compact` ([`compact`]),
//!   `GET .../events` and `GET .../changes` ([`feed`]), `POST /v1/meshes` ([`meshes`]).
//! - `GET /v1/volumes/{name}/zarr/...`, `.../precomputed/...` and their version-pinned forms
//!   under `.../versions/{version}/`: the field's formats ([`views`]).
//! - `GET /`, `GET /assets/...`: the web viewer, built into the binary (`web_app.rs`).
//!
//! Plain brick requests (no query, nothing escaped) are answered before the router by the same
//! code the routed handler calls; see `fast_path.rs` for why and for what counts as plain.
//!
//! Layout: handlers by concern (`bricks`, `handlers`, `views`, `edit`, `compact`, `feed`,
//! `meshes`, `segments`, `web_app`); `error` decides every status code; `extract` gives axum's extractors
//! that error; `cpu` runs CPU work off the async runtime; `compression` makes the zstd bodies
//! inside that work and `held` bounds their memory until they are sent; `auth` checks tokens
//! and edit rates, `oidc` an issuer's JWTs; `bodies` keeps constant bricks' bodies; `serve` is the listener loop and the
//! shutdown, `connections` the limits on open connections, `tls` its certificates; `metrics`,
//! `cors` and `openapi` are what their names say.

pub mod auth;
pub mod bodies;
pub mod bricks;
pub mod compact;
mod compression;
pub mod connections;
mod cors;
pub mod cpu;
pub mod edit;
mod error;
pub mod extract;
mod fast_path;
pub mod feed;
pub mod handlers;
pub mod held;
pub mod history;
mod mesh_answers;
pub mod meshes;
pub mod metrics;
pub mod oidc;
mod openapi;
mod request_body;
pub mod segments;
mod serve;
pub mod tls;
pub mod views;
mod web_app;

pub use error::ApiError;
pub use serve::{run, run_tls, shutdown_signal, spawn, Closing, Spawned};

use crate::catalog::Catalog;
use crate::mesh::cache::MeshCache;
use crate::store::decoded::DecodedBricks;
use crate::volume::resolve::CatalogVolumes;
use crate::volume::{EditLimits, GroupCommit, LiveVolume};
use axum::handler::Handler;
use axum::http::StatusCode;
use axum::routing::{get, post, put, MethodRouter};
use axum::Router;
use mesh_answers::MeshAnswers;
use std::sync::Arc;
use std::time::Duration;
use tower_http::timeout::TimeoutLayer;

/// How a server runs: caches, queues, connections, access control and edit limits.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Memory for cached mesh tiles; a quarter as much again keeps their answers as sent.
    pub mesh_cache_bytes: usize,
    /// Memory for decoded bricks and what is made from them (lz4 blocks, the views' zstd
    /// chunks): brick bodies, the formats' views and meshing share it.
    pub brick_cache_bytes: usize,
    /// CPU jobs (meshing, batches, levels, change lists) running or queued at once; beyond it
    /// 503. Default: eight per core ([`cpu::default_queue`]).
    pub cpu_queue: usize,
    /// Threads running CPU jobs. Default: one per core.
    pub cpu_threads: usize,
    /// Memory for the bodies CPU jobs build, held until they are sent (`held.rs`); beyond it
    /// 503.
    pub response_memory_bytes: usize,
    /// Reads of volumes kept in an object store running or queued at once; beyond it 503
    /// (`cpu::StoreReads`). Default: [`cpu::default_store_read_queue`].
    pub store_read_queue: usize,
    /// Threads running those reads (started at the first one). Default:
    /// [`cpu::default_store_read_threads`].
    pub store_read_threads: usize,
    /// Open connections, and how long they may wait for a request head or idle.
    pub connections: connections::Limits,
    /// Threads that accept and read connections, each with a runtime of its own (`serve.rs`).
    /// Default: one per core.
    pub connection_threads: usize,
    /// Who may write (and, with `private_reads`, read).
    pub tokens: auth::Tokens,
    /// JWTs of an OpenID Connect issuer, beside the tokens (`--oidc-issuer`).
    pub oidc: Option<Arc<oidc::Oidc>>,
    /// Every `/v1` route needs a token (of either scope).
    pub private_reads: bool,
    /// Edits per second per token (and the burst).
    pub edit_rate: f64,
    /// Edits waiting for one volume's writer; beyond it 503.
    pub edit_queue: usize,
    /// Edits one volume's writer makes durable together at most (one sync); 1 syncs
    /// every edit on its own.
    pub edit_group: usize,
    /// Voxels one edit may evaluate (its bricks, and what its term samples besides: mesh
    /// leaves, morphology arguments); beyond it 422.
    pub max_edit_voxels: u64,
    /// How long compiling an edit, and then evaluating it, may each take; past it the edit is
    /// stopped, nothing is committed, and the answer is 422.
    pub edit_timeout: Duration,
    /// Limits on edit terms (depth, nodes, extent).
    pub term_limits: crate::icvg::term::TermLimits,
    /// Where uploaded meshes are kept (`POST /v1/meshes`); none: uploads are refused.
    pub mesh_dir: Option<std::path::PathBuf>,
    /// How long a shutdown lets requests in flight finish before it closes their connections
    /// (change feeds end at once).
    pub shutdown_grace: Duration,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            mesh_cache_bytes: 256 << 20,
            brick_cache_bytes: 64 << 20,
            cpu_queue: cpu::default_queue(),
            cpu_threads: cpu::cores(),
            response_memory_bytes: 256 << 20,
            store_read_queue: cpu::default_store_read_queue(),
            store_read_threads: cpu::default_store_read_threads(),
            connections: connections::Limits::default(),
            connection_threads: cpu::cores(),
            tokens: auth::Tokens::default(),
            oidc: None,
            private_reads: false,
            edit_rate: 50.0,
            edit_queue: 64,
            edit_group: crate::volume::GroupCommit::default().max_group,
            max_edit_voxels: 1 << 28,
            edit_timeout: Duration::from_secs(30),
            term_limits: crate::icvg::term::TermLimits::default(),
            mesh_dir: None,
            shutdown_grace: Duration::from_secs(10),
        }
    }
}

/// What every handler can reach: one `Arc`, so the per-request clones of the state (the
/// middleware's and the handler's) touch one shared counter, not one per field.
#[derive(Debug, Clone)]
pub struct AppState(Arc<Shared>);

impl std::ops::Deref for AppState {
    type Target = Shared;

    fn deref(&self) -> &Shared {
        &self.0
    }
}

/// The server's shared parts (see [`AppState`]).
#[derive(Debug)]
pub struct Shared {
    /// The volumes served.
    pub catalog: Arc<Catalog>,
    /// Tile meshes by the content of their inputs.
    pub meshes: Arc<MeshCache>,
    /// Mesh answers (tiles and strips) as sent, by their tag and encoding: asked again (fifty
    /// viewers start on the same tiles), they are answered where the request is read, with no
    /// CPU job to wait for or be refused by.
    pub(crate) mesh_answers: Arc<MeshAnswers>,
    /// Decoded bricks and the bodies made from them by content hash, for brick bodies, the
    /// formats' views and meshing.
    pub bricks: Arc<DecodedBricks>,
    /// The bound on CPU work off the async runtime (meshing, batches, levels) and on the
    /// memory of its answers.
    pub cpu: cpu::CpuQueue,
    /// The bound on reads of volumes kept in an object store, and their threads
    /// ([`AppState::read_volume`]).
    pub store_reads: cpu::StoreReads,
    /// The open connections.
    pub connections: Arc<connections::Connections>,
    /// Requests and latencies per route.
    pub metrics: Arc<metrics::Metrics>,
    /// Content hash and bodies of constant bricks.
    pub constants: bodies::ConstantBricks,
    /// How the server runs.
    pub config: Arc<ServerConfig>,
    /// Edits per second per token.
    pub edit_rate: Arc<auth::RateLimiter>,
    /// Presence updates per second per user.
    pub presence_rate: Arc<auth::RateLimiter>,
    /// Uploaded meshes for `mesh` leaves of edit terms.
    pub mesh_store: Option<Arc<crate::voxelize::store::MeshStore>>,
    /// Set when the server starts shutting down: change feeds end.
    pub closing: Closing,
    /// The server's main runtime, set by `serve.rs` when the server starts (for [`spawn`]:
    /// the caller's runtime). Blocking work ([`cpu::blocking`]) and the
    /// volumes' writer tasks run there, never on the connection thread that took the request.
    main_runtime: std::sync::OnceLock<tokio::runtime::Handle>,
}

impl AppState {
    /// A state serving `catalog` with a mesh cache of `mesh_cache_bytes` and room for
    /// `cpu_queue` CPU jobs at once (running or queued for the CPU threads).
    pub fn new(catalog: Catalog, mesh_cache_bytes: usize, cpu_queue: usize) -> Self {
        AppState::with_config(
            catalog,
            ServerConfig {
                mesh_cache_bytes,
                cpu_queue,
                ..ServerConfig::default()
            },
        )
    }

    /// A state serving `catalog` as `config` says.
    pub fn with_config(catalog: Catalog, config: ServerConfig) -> Self {
        AppState(Arc::new(Shared {
            catalog: Arc::new(catalog),
            meshes: Arc::new(MeshCache::new(config.mesh_cache_bytes)),
            mesh_answers: Arc::new(MeshAnswers::new(config.mesh_cache_bytes / 4)),
            bricks: Arc::new(DecodedBricks::new(config.brick_cache_bytes)),
            cpu: cpu::CpuQueue::new(
                config.cpu_queue,
                config.cpu_threads,
                config.response_memory_bytes,
            ),
            store_reads: cpu::StoreReads::new(config.store_read_queue, config.store_read_threads),
            connections: Arc::new(connections::Connections::new(config.connections)),
            metrics: Arc::new(metrics::Metrics::new(ROUTES)),
            constants: bodies::ConstantBricks::default(),
            edit_rate: Arc::new(auth::RateLimiter::new(config.edit_rate)),
            presence_rate: Arc::new(auth::RateLimiter::new(PRESENCE_RATE)),
            mesh_store: config
                .mesh_dir
                .as_deref()
                .map(|d| Arc::new(crate::voxelize::store::MeshStore::new(d))),
            closing: Closing::default(),
            main_runtime: std::sync::OnceLock::new(),
            config: Arc::new(config),
        }))
    }

    /// Where blocking work and the volumes' writer tasks run: the runtime that serves this
    /// state (set when serving starts), else the current one (a handler called without a
    /// server, as in unit tests).
    ///
    /// # Panics
    /// Outside a tokio runtime before the server has started.
    pub fn main_runtime(&self) -> tokio::runtime::Handle {
        match self.main_runtime.get() {
            Some(h) => h.clone(),
            None => tokio::runtime::Handle::current(),
        }
    }

    /// `read` of volume `name` (with this state), where reading it may wait: in place for a
    /// volume kept in a local file (mapped memory; no allocation, no hop); for one kept in an
    /// object store, in place too when every page it reads is in the replica's mirror, else
    /// again on the store-read threads, whose reads may fetch pages from the store and wait
    /// for them ([`cpu::StoreReads::run`]: 503 when they are all busy). So reads of what a
    /// replica holds are never queued behind, or refused because of, reads waiting for the
    /// store. Every synchronous read of a volume in a handler goes through here: a read of a
    /// remote volume that fetched on a connection thread would stall all of that thread's
    /// connections for a round trip (debug builds assert against it in `Bucket`).
    ///
    /// # Errors
    /// 404 when no volume is called `name`; as [`cpu::StoreReads::run`]; whatever `read`
    /// fails with.
    pub async fn read_volume<T, E>(
        &self,
        name: &str,
        read: impl Fn(&AppState, &Arc<LiveVolume>) -> Result<T, E> + Send + 'static,
    ) -> Result<T, ApiError>
    where
        T: Send + 'static,
        E: Send + 'static,
        ApiError: From<E>,
    {
        let volume = self.catalog.get(name)?;
        if volume.remote().is_none() {
            return Ok(read(self, volume)?);
        }
        if let Some(done) = crate::store::remote::mirror::without_fetching(|| read(self, volume)) {
            return Ok(done?);
        }
        let (state, volume) = (self.clone(), volume.clone());
        self.store_reads.run(move || read(&state, &volume)).await
    }

    /// Records the server's main runtime (the first one given stays).
    pub(crate) fn set_main_runtime(&self, runtime: tokio::runtime::Handle) {
        let _ = self.main_runtime.set(runtime);
    }

    /// What one edit may ask for on this server.
    pub fn edit_limits(&self) -> EditLimits {
        EditLimits {
            term: self.config.term_limits,
            max_voxels: Some(self.config.max_edit_voxels),
        }
    }

    /// How a volume's writer takes edits on this server.
    pub fn group_commit(&self) -> GroupCommit {
        GroupCommit {
            max_waiting: self.config.edit_queue,
            max_group: self.config.edit_group,
            ..GroupCommit::default()
        }
    }

    /// The volumes and meshes edit terms may name: the catalog's and the uploads.
    pub fn resolver(&self) -> CatalogVolumes {
        CatalogVolumes {
            catalog: self.catalog.clone(),
            meshes: self.mesh_store.clone(),
        }
    }
}

/// Presence updates a user may send per second (bursts as large): a viewer sends one when its
/// camera moves, a few a second at most.
pub const PRESENCE_RATE: f64 = 5.0;

/// Every route template the router serves (metrics are kept per template).
pub const ROUTES: &[&str] = &[
    "/healthz",
    "/metrics",
    "/openapi.json",
    "/v1/volumes",
    "/v1/volumes/{name}",
    "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}",
    "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}",
    "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}/strips/{face}",
    "/v1/volumes/{name}/blobs/{hash}",
    "/v1/volumes/{name}/batch",
    "/v1/volumes/{name}/levels/{level}",
    "/v1/volumes/{name}/edits",
    "/v1/volumes/{name}/changes",
    "/v1/volumes/{name}/events",
    "/v1/volumes/{name}/compact",
    "/v1/volumes/{name}/history",
    "/v1/volumes/{name}/tags",
    "/v1/volumes/{name}/tags/{tag}",
    "/v1/volumes/{name}/undo",
    "/v1/volumes/{name}/revert",
    "/v1/volumes/{name}/presence",
    "/v1/auth",
    "/v1/meshes",
    "/v1/volumes/{name}/zarr/{*path}",
    "/v1/volumes/{name}/precomputed/{*path}",
    "/v1/volumes/{name}/versions/{version}/zarr/{*path}",
    "/v1/volumes/{name}/versions/{version}/precomputed/{*path}",
    "/",
    "/index.html",
    "/assets/{*file}",
];

/// The whole service: the router inside what every request passes through (metrics, which
/// also log each request at debug level, and the CORS headers). They wrap the router once, not
/// each route: `Router::layer` wraps and boxes every route's service once more per layer, which
/// cost the brick routes about a tenth of their throughput. (tower-http's `TraceLayer` was
/// here too: it timed every request and body frame again and logged every 5xx, shed 503s
/// included, as an error; internal errors log their cause where they are mapped, `error.rs`.)
///
/// Requests are answered on the thread that read them; what would hold that thread up leaves
/// it inside the handler (CPU work, blocking work, reads of volumes kept in an object store:
/// [`AppState::read_volume`]).
pub fn app(
    state: AppState,
) -> impl tower::Service<
    axum::extract::Request,
    Response = axum::response::Response,
    Error = std::convert::Infallible,
    Future: Send,
> + Clone
       + Send
       + Sync
       + 'static {
    let metrics = state.metrics.clone();
    let fast_state = state.clone();
    let router = routes(&state)
        .fallback(handlers::not_found)
        .with_state(state);
    tower::ServiceBuilder::new()
        .map_response(|r: axum::http::Response<_>| {
            let mut r = r.map(axum::body::Body::new);
            cors::add_headers(r.headers_mut());
            r
        })
        .layer(metrics::MetricsLayer::new(metrics))
        .service(fast_path::BrickFirst::new(fast_state, router))
}

/// The routes, with the layers only some of them take: a 30 s timeout on the routes that do
/// CPU work (meshing, batches, levels; the cheap routes answer in microseconds, and a timer per
/// request cost a measurable share of their throughput), and the token check when reads are
/// private.
fn routes(state: &AppState) -> Router<AppState> {
    let timeout =
        TimeoutLayer::with_status_code(StatusCode::SERVICE_UNAVAILABLE, Duration::from_secs(30));
    let cpu_routes = Router::new()
        .route(
            "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}",
            read(handlers::mesh_tile),
        )
        .route(
            "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}/strips/{face}",
            read(handlers::mesh_strip),
        )
        .route("/v1/volumes/{name}/batch", write(handlers::batch))
        .route("/v1/volumes/{name}/levels/{level}", read(handlers::level))
        .route("/v1/volumes/{name}/changes", read(feed::changes))
        .route("/v1/volumes/{name}/history", read(history::history))
        .route("/v1/volumes/{name}/tags", read(history::tags))
        .route(
            "/v1/volumes/{name}/channels/{channel}/segments",
            read(segments::segments),
        )
        .route(
            "/v1/volumes/{name}/channels/{channel}/segments/{id}/mesh",
            read(segments::segment_mesh),
        )
        .route_layer(timeout);
    // Edits wait for their volume's writer (bounded by the edit queue), and the change feed is
    // meant to stay open: neither gets the timeout.
    let write_routes = Router::new()
        .route("/v1/volumes/{name}/edits", write(edit::edit))
        .route("/v1/volumes/{name}/compact", write(compact::compact))
        .route("/v1/volumes/{name}/undo", write(history::undo))
        .route("/v1/volumes/{name}/revert", write(history::revert))
        .route(
            "/v1/volumes/{name}/tags/{tag}",
            put(history::put_tag).options(cors::preflight),
        )
        .route(
            "/v1/volumes/{name}/presence",
            write(history::post_presence).get(history::presence),
        )
        .route("/v1/meshes", write(meshes::upload_mesh))
        .route("/v1/volumes/{name}/events", read(feed::events));
    let mut router = Router::new()
        .route("/healthz", read(handlers::healthz))
        .route("/metrics", read(metrics::metrics))
        .route("/openapi.json", read(openapi::openapi))
        .route("/v1/auth", read(auth::whoami))
        .route("/v1/volumes", read(handlers::list_volumes))
        .route("/v1/volumes/{name}", read(handlers::volume_info))
        .route(
            "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}",
            read(bricks::brick),
        )
        .route("/v1/volumes/{name}/blobs/{hash}", read(bricks::blob))
        // Chunks are bricks: like the brick routes, these answer at once, and the few that
        // take work (a brick to decode or compress) take it to the CPU queue.
        .route("/v1/volumes/{name}/zarr/{*path}", read(views::zarr))
        .route(
            "/v1/volumes/{name}/precomputed/{*path}",
            read(views::precomputed),
        )
        .route(
            "/v1/volumes/{name}/versions/{version}/zarr/{*path}",
            read(views::zarr_pinned),
        )
        .route(
            "/v1/volumes/{name}/versions/{version}/precomputed/{*path}",
            read(views::precomputed_pinned),
        )
        .merge(cpu_routes)
        .merge(write_routes)
        .merge(web_app::routes());
    if state.config.private_reads {
        // Only then: a middleware per request costs throughput on the brick routes.
        router = router.route_layer(axum::middleware::from_fn_with_state(
            state.clone(),
            auth::require_token,
        ));
    }
    router
}

/// A GET route that also answers CORS preflight requests.
fn read<H, T>(handler: H) -> MethodRouter<AppState>
where
    H: Handler<T, AppState>,
    T: 'static,
{
    get(handler).options(cors::preflight)
}

/// A POST route that also answers CORS preflight requests.
fn write<H, T>(handler: H) -> MethodRouter<AppState>
where
    H: Handler<T, AppState>,
    T: 'static,
{
    post(handler).options(cors::preflight)
}
