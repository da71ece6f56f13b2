//! The HTTP service: an axum router over the [`Catalog`], thin handlers, errors as responses.
//!
//! [`app`] builds the router from a state (tests call it without a socket); [`run`] serves it on
//! a listener until `shutdown` resolves, then finishes in-flight requests.
//!
//! Routes (all under `/v1` but the probes):
//! - `GET /healthz`: liveness; `GET /metrics`: Prometheus text; `GET /openapi.json`: the API.
//! - `GET /v1/volumes`, `GET /v1/volumes/{name}`: what is served and how to address it.
//! - `GET /v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}`: one brick (see [`handlers::brick`]).
//! - `GET /v1/volumes/{name}/blobs/{hash}`: a brick by content hash, cacheable forever.
//! - `POST /v1/volumes/{name}/batch`: many bricks in one response (`proto::batch`).
//! - `GET /v1/volumes/{name}/levels/{level}`: a level's brick grid, or its voxels.
//! - `GET /v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}`: one mesh tile (see
//!   [`handlers::mesh_tile`]).

pub mod auth;
pub mod bodies;
mod cors;
pub mod edits;
mod error;
pub mod handlers;
pub mod metrics;
mod openapi;

pub use error::ApiError;

use crate::catalog::Catalog;
use crate::mesh::cache::MeshCache;
use axum::handler::Handler;
use axum::http::StatusCode;
use axum::routing::{get, post, MethodRouter};
use axum::Router;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

/// Constant bricks by (value, brick bytes, voxel bytes): their content hash and decoded body.
type ConstantBricks = std::collections::HashMap<(u16, usize, usize), (u64, bytes::Bytes)>;

/// How a server runs: caches, queues, access control and edit limits.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Memory for cached mesh tiles.
    pub mesh_cache_bytes: usize,
    /// Memory for decoded and transcoded brick bodies.
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
    /// Level-0 voxels one edit may evaluate; beyond it 422.
    pub max_edit_voxels: u64,
    pub term_limits: crate::icvg::term::TermLimits,
    /// Where uploaded meshes are kept (`POST /v1/meshes`); none: uploads are refused.
    pub mesh_dir: Option<std::path::PathBuf>,
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
            max_edit_voxels: 1 << 28,
            term_limits: crate::icvg::term::TermLimits::default(),
            mesh_dir: None,
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
    pub catalog: Arc<Catalog>,
    /// Tile meshes by the content of their inputs.
    pub meshes: Arc<MeshCache>,
    /// Permits for CPU work off the async runtime (meshing); when none is free the request gets
    /// 503 with Retry-After instead of waiting in an unbounded queue.
    pub cpu: Arc<tokio::sync::Semaphore>,
    /// The semaphore's size.
    pub cpu_permits: usize,
    pub metrics: Arc<metrics::Metrics>,
    /// Content hash and body of constant bricks, by (value, brick bytes, voxel bytes): most
    /// bricks of a sparse volume are constant, and hashing 32 KiB per request would dominate.
    constants: Arc<std::sync::RwLock<ConstantBricks>>,
    pub config: Arc<ServerConfig>,
    pub edit_rate: Arc<auth::RateLimiter>,
    /// Decoded and transcoded brick bodies by content hash.
    pub bodies: Arc<bodies::BodyCache>,
    /// Uploaded meshes for `mesh` leaves of edit terms.
    pub mesh_store: Option<Arc<crate::voxelize::store::MeshStore>>,
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
            cpu: Arc::new(tokio::sync::Semaphore::new(config.cpu_queue)),
            cpu_permits: config.cpu_queue,
            metrics: Arc::new(metrics::Metrics::new(ROUTES)),
            constants: Arc::default(),
            edit_rate: Arc::new(auth::RateLimiter::new(config.edit_rate)),
            bodies: Arc::new(bodies::BodyCache::new(config.brick_cache_bytes)),
            mesh_store: config
                .mesh_dir
                .as_deref()
                .map(|d| Arc::new(crate::voxelize::store::MeshStore::new(d))),
            config: Arc::new(config),
        }))
    }
}

impl Shared {
    /// The content hash and decoded bytes of a constant brick of `layout`'s shape.
    pub fn constant_brick(
        &self,
        value: u16,
        layout: &isovox_proto::VolumeLayout,
    ) -> (u64, bytes::Bytes) {
        let key = (value, layout.brick_bytes(), layout.voxel_type().bytes());
        if let Some(hit) = self
            .constants
            .read()
            .ok()
            .and_then(|m| m.get(&key).cloned())
        {
            return hit;
        }
        let mut body = vec![0u8; layout.brick_bytes()];
        crate::store::codec::fill_constant(&mut body, value, layout.voxel_type());
        let entry = (
            isovox_proto::vod2::content_hash(&body),
            bytes::Bytes::from(body),
        );
        if let Ok(mut m) = self.constants.write() {
            m.insert(key, entry.clone());
        }
        entry
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
];

/// The router, with its layers: request spans, CORS for browser clients, metrics, a body limit,
/// and a 30 s timeout on the routes that do CPU work (meshing, batches, levels). The cheap
/// routes (bricks, blobs, metadata) answer in microseconds and skip the timeout: registering a
/// timer per request cost a measurable share of their throughput.
pub fn app(state: AppState) -> Router {
    let timeout =
        TimeoutLayer::with_status_code(StatusCode::SERVICE_UNAVAILABLE, Duration::from_secs(30));
    let cpu_routes = Router::new()
        .route(
            "/v1/volumes/{name}/meshes/{level}/{x}/{y}/{z}",
            read(handlers::mesh_tile),
        )
        .route("/v1/volumes/{name}/batch", write(handlers::batch))
        .route("/v1/volumes/{name}/levels/{level}", read(handlers::level))
        .route("/v1/volumes/{name}/changes", read(edits::changes))
        .route_layer(timeout);
    // Edits wait for their volume's writer (bounded by the edit queue), and the change feed is
    // meant to stay open: neither gets the timeout.
    let write_routes = Router::new()
        .route("/v1/volumes/{name}/edits", write(edits::edit))
        .route("/v1/volumes/{name}/compact", write(edits::compact))
        .route("/v1/meshes", write(edits::upload_mesh))
        .route("/v1/volumes/{name}/events", read(edits::events));
    let mut router = Router::new()
        .route("/healthz", read(handlers::healthz))
        .route("/metrics", read(metrics::metrics))
        .route("/openapi.json", read(openapi::openapi))
        .route("/v1/volumes", read(handlers::list_volumes))
        .route("/v1/volumes/{name}", read(handlers::volume_info))
        .route(
            "/v1/volumes/{name}/bricks/{level}/{x}/{y}/{z}",
            read(handlers::brick),
        )
        .route("/v1/volumes/{name}/blobs/{hash}", read(handlers::blob))
        .merge(cpu_routes)
        .merge(write_routes);
    if state.config.private_reads {
        // Only then: a middleware per request costs throughput on the brick routes.
        router = router.route_layer(axum::middleware::from_fn_with_state(
            state.clone(),
            edits::require_token,
        ));
    }
    let (allow_origin, expose_headers) = cors::layers();
    router
        .fallback(handlers::not_found)
        .layer(metrics::MetricsLayer::new(state.metrics.clone()))
        .with_state(state)
        // Request bodies (edit terms, batch key lists) are small; larger ones get 413.
        .layer(axum::extract::DefaultBodyLimit::max(1 << 20))
        .layer(allow_origin)
        .layer(expose_headers)
        .layer(TraceLayer::new_for_http())
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

/// Serves `state` on `listener` until `shutdown` completes, then lets in-flight requests finish.
///
/// # Errors
/// The listener fails.
pub async fn run(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    axum::serve(listener, app(state))
        .with_graceful_shutdown(shutdown)
        .await
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
