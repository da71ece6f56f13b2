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
//!   [`handlers::mesh_tile`]).
//! - `POST /v1/volumes/{name}/edits` ([`edit`]), `POST .../compact` ([`compact`]),
//!   `GET .../events` and `GET .../changes` ([`feed`]), `POST /v1/meshes` ([`meshes`]).
//! - `GET /`, `GET /assets/...`: the web viewer, built into the binary (`web_app.rs`).
//!
//! Plain brick requests (no query, nothing escaped) are answered before the router by the same
//! code the routed handler calls; see `fast_path.rs` for why and for what counts as plain.
//!
//! Layout: handlers by concern (`bricks`, `handlers`, `edit`, `compact`, `feed`, `meshes`,
//! `web_app`); `error` decides every status code; `extract` gives axum's extractors that error;
//! `cpu` runs CPU work off the async runtime; `compression` makes the zstd bodies inside that
//! work; `auth` checks tokens and edit rates; `bodies` keeps constant bricks' bodies; `serve`
//! is the listener loop and the shutdown, `tls` its certificates; `metrics`, `cors` and
//! `openapi` are what their names say.

pub mod auth;
pub mod bodies;
pub mod bricks;
pub mod compact;
mod compression;
mod cors;
pub mod cpu;
pub mod edit;
mod error;
pub mod extract;
mod fast_path;
pub mod feed;
pub mod handlers;
pub mod meshes;
pub mod metrics;
mod openapi;
mod request_body;
mod serve;
pub mod tls;
mod web_app;

pub use error::ApiError;
pub use serve::{run, run_tls, shutdown_signal, spawn, Closing, Spawned};

use crate::catalog::Catalog;
use crate::mesh::cache::MeshCache;
use crate::store::decoded::DecodedBricks;
use crate::volume::resolve::CatalogVolumes;
use crate::volume::{EditLimits, GroupCommit};
use axum::handler::Handler;
use axum::http::StatusCode;
use axum::routing::{get, post, MethodRouter};
use axum::Router;
use std::sync::Arc;
use std::time::Duration;
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

/// How a server runs: caches, queues, access control and edit limits.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Memory for cached mesh tiles.
    pub mesh_cache_bytes: usize,
    /// Memory for decoded bricks and their lz4 blocks (brick bodies and meshing share it).
    pub brick_cache_bytes: usize,
    /// Meshing and batch jobs running or queued at once.
    pub cpu_queue: usize,
    /// Who may write (and, with `private_reads`, read).
    pub tokens: auth::Tokens,
    /// Every `/v1` route needs a token (of either scope).
    pub private_reads: bool,
    /// Edits per second per token (and the burst).
    pub edit_rate: f64,
    /// Edits waiting for one volume's writer; beyond it 503.
    pub edit_queue: usize,
    /// Edits one volume's writer makes durable together at most (one pair of syncs); 1 syncs
    /// every edit on its own.
    pub edit_group: usize,
    /// Level-0 voxels one edit may evaluate; beyond it 422.
    pub max_edit_voxels: u64,
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
            cpu_queue: 64,
            tokens: auth::Tokens::default(),
            private_reads: false,
            edit_rate: 50.0,
            edit_queue: 64,
            edit_group: crate::volume::GroupCommit::default().max_group,
            max_edit_voxels: 1 << 28,
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
    /// Decoded bricks and their lz4 blocks by content hash, for brick bodies and meshing.
    pub bricks: Arc<DecodedBricks>,
    /// The bound on CPU work off the async runtime (meshing, batches, levels).
    pub cpu: cpu::CpuQueue,
    /// Requests and latencies per route.
    pub metrics: Arc<metrics::Metrics>,
    /// Content hash and bodies of constant bricks.
    pub constants: bodies::ConstantBricks,
    /// How the server runs.
    pub config: Arc<ServerConfig>,
    /// Edits per second per token.
    pub edit_rate: Arc<auth::RateLimiter>,
    /// Uploaded meshes for `mesh` leaves of edit terms.
    pub mesh_store: Option<Arc<crate::voxelize::store::MeshStore>>,
    /// Set when the server starts shutting down: change feeds end.
    pub closing: Closing,
}

impl AppState {
    /// A state serving `catalog` with a mesh cache of `mesh_cache_bytes` and room for
    /// `cpu_queue` meshing jobs at once (running or queued on the blocking pool).
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
            bricks: Arc::new(DecodedBricks::new(config.brick_cache_bytes)),
            cpu: cpu::CpuQueue::new(config.cpu_queue),
            metrics: Arc::new(metrics::Metrics::new(ROUTES)),
            constants: bodies::ConstantBricks::default(),
            edit_rate: Arc::new(auth::RateLimiter::new(config.edit_rate)),
            mesh_store: config
                .mesh_dir
                .as_deref()
                .map(|d| Arc::new(crate::voxelize::store::MeshStore::new(d))),
            closing: Closing::default(),
            config: Arc::new(config),
        }))
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

/// Every route template the router serves (metrics are kept per template).
pub const ROUTES: &[&str] = &[
    "/healthz",
    "/metrics",
    "/openapi.json",
    "/v1/volumes",
    "/v1/volumes/{name}",
    "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}",
    "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}",
    "/v1/volumes/{name}/blobs/{hash}",
    "/v1/volumes/{name}/batch",
    "/v1/volumes/{name}/levels/{level}",
    "/v1/volumes/{name}/edits",
    "/v1/volumes/{name}/changes",
    "/v1/volumes/{name}/events",
    "/v1/volumes/{name}/compact",
    "/v1/meshes",
    "/",
    "/index.html",
    "/assets/{*file}",
];

/// The whole service: the router inside the layers every request passes through (request
/// spans, CORS headers, the body limit, metrics). They wrap the router once, not each route:
/// `Router::layer` wraps and boxes every route's service once more per layer, which cost the
/// brick routes about a tenth of their throughput.
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
    let (allow_origin, expose_headers) = cors::layers();
    tower::ServiceBuilder::new()
        .map_response(|r: axum::http::Response<_>| r.map(axum::body::Body::new))
        .layer(TraceLayer::new_for_http())
        .layer(allow_origin)
        .layer(expose_headers)
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
        .route("/v1/volumes/{name}/batch", write(handlers::batch))
        .route("/v1/volumes/{name}/levels/{level}", read(handlers::level))
        .route("/v1/volumes/{name}/changes", read(feed::changes))
        .route_layer(timeout);
    // Edits wait for their volume's writer (bounded by the edit queue), and the change feed is
    // meant to stay open: neither gets the timeout.
    let write_routes = Router::new()
        .route("/v1/volumes/{name}/edits", write(edit::edit))
        .route("/v1/volumes/{name}/compact", write(compact::compact))
        .route("/v1/meshes", write(meshes::upload_mesh))
        .route("/v1/volumes/{name}/events", read(feed::events));
    let mut router = Router::new()
        .route("/healthz", read(handlers::healthz))
        .route("/metrics", read(metrics::metrics))
        .route("/openapi.json", read(openapi::openapi))
        .route("/v1/volumes", read(handlers::list_volumes))
        .route("/v1/volumes/{name}", read(handlers::volume_info))
        .route(
            "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}",
            read(bricks::brick),
        )
        .route("/v1/volumes/{name}/blobs/{hash}", read(bricks::blob))
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
