//! `isovox serve`: serve every VOD 2 file of a data directory over HTTP.

use anyhow::Context;
use clap::Args;
use isovox_server::catalog::Catalog;
use isovox_server::generate::{build_demo, DEMO_NAME};
use isovox_server::http::auth::{random_secret, Scope, Tokens};
use isovox_server::http::connections::{default_max_connections, raise_fd_limit, Limits};
use isovox_server::http::cpu;
use isovox_server::http::oidc::{KeySource, Oidc, OidcConfig, DEFAULT_ROLES_CLAIM};
use isovox_server::http::{run, run_tls, shutdown_signal, AppState, ServerConfig};
use isovox_server::store::remote::head::{DEFAULT_INLINE_MAX, INLINE_LIMIT};
use isovox_server::store::remote::{
    Bucket, CacheConfig, DEFAULT_PREFETCH_INDEX, DEFAULT_READ_AHEAD,
};
use isovox_server::store::BuildOptions;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub(crate) struct ServeArgs {
    /// Directory of VOD 2 files; each is served as a volume named after the file. When it holds
    /// none, a demo world is generated there first.
    #[arg(long, env = "ISOVOX_DATA", default_value = "data")]
    pub data: PathBuf,
    /// Address to listen on, HOST:PORT; a host name (`localhost:7070`) listens on the first of
    /// its addresses that can be bound.
    #[arg(long, env = "ISOVOX_ADDR", default_value = "127.0.0.1:7070")]
    pub addr: String,
    /// Memory for cached mesh tiles, in MiB.
    #[arg(long, env = "ISOVOX_MESH_CACHE_MB", default_value_t = 256)]
    pub mesh_cache_mb: usize,
    /// Memory for decoded bricks and the bodies made from them (brick bodies, the formats'
    /// view chunks, meshing), in MiB.
    #[arg(long, env = "ISOVOX_BRICK_CACHE_MB", default_value_t = 64)]
    pub brick_cache_mb: usize,
    /// CPU jobs (mesh tiles, batches, levels, change lists) running or queued at once; beyond
    /// it requests get 503 with Retry-After. Default: eight per core.
    #[arg(long, env = "ISOVOX_CPU_QUEUE", default_value_t = cpu::default_queue())]
    pub cpu_queue: usize,
    /// Memory for the bodies of those jobs' answers until they are sent, in MiB; beyond it
    /// 503 (413 for one answer larger than all of it).
    #[arg(long, env = "ISOVOX_RESPONSE_MEMORY_MB", default_value_t = 256)]
    pub response_memory_mb: usize,
    /// Threads that accept connections and answer their requests, each with an event loop of
    /// its own, as nginx's workers. Default: one per core.
    #[arg(long, env = "ISOVOX_CONNECTION_THREADS", default_value_t = cpu::cores())]
    pub connection_threads: usize,
    /// Connections open at once (change feeds included); at the limit a new one closes the
    /// oldest idle one. Default: the file-descriptor limit less an eighth, at most 10,000.
    #[arg(long, env = "ISOVOX_MAX_CONNECTIONS")]
    pub max_connections: Option<usize>,
    /// Seconds a client has to send a request's head (from its first byte, or from the
    /// connection's opening for the first request); then the connection is closed.
    #[arg(long, env = "ISOVOX_HEADER_TIMEOUT", default_value_t = 10.0)]
    pub header_timeout: f64,
    /// Seconds a connection may stay open without a request in progress (change feeds are
    /// requests in progress).
    #[arg(long, env = "ISOVOX_IDLE_TIMEOUT", default_value_t = 60.0)]
    pub idle_timeout: f64,
    /// Tokens, one per line: `NAME TOKEN [write|read]`. Default: DATA/tokens, created with one
    /// random write token on first start when no token is configured.
    #[arg(long, env = "ISOVOX_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// Also accept JWTs of this OpenID Connect issuer (RS256, ES256), exactly as its tokens'
    /// `iss` spell it; its keys are found through ISSUER/.well-known/openid-configuration.
    /// Needs --oidc-audience.
    #[arg(long, env = "ISOVOX_OIDC_ISSUER", requires = "oidc_audience")]
    pub oidc_issuer: Option<String>,
    /// The audience the JWTs must name in `aud`: this server's client id at the issuer.
    #[arg(long, env = "ISOVOX_OIDC_AUDIENCE", requires = "oidc_issuer")]
    pub oidc_audience: Option<String>,
    /// The client id the web viewer signs in with at the issuer (a public client, authorization
    /// code with PKCE; `GET /v1/auth` tells the page). Default: the audience.
    #[arg(long, env = "ISOVOX_OIDC_CLIENT_ID", requires = "oidc_issuer")]
    pub oidc_client_id: Option<String>,
    /// The claim holding a user's roles (`write:VOLUME`, `read:VOLUME`, `*` for every volume,
    /// `admin`): a top-level claim by name, else a dotted path such as `realm_access.roles`.
    #[arg(long, env = "ISOVOX_OIDC_ROLES_CLAIM", default_value = DEFAULT_ROLES_CLAIM)]
    pub oidc_roles_claim: String,
    /// The issuer's keys (a JWKS) from this file, read once at start (no network), or from this
    /// http(s) URL without discovery.
    #[arg(long, env = "ISOVOX_OIDC_JWKS", requires = "oidc_issuer")]
    pub oidc_jwks: Option<String>,
    /// Least seconds between two fetches of the issuer's keys for tokens naming a key the server
    /// does not have (so made-up key ids cannot make it hammer the issuer).
    #[arg(long, env = "ISOVOX_OIDC_REFRESH_INTERVAL", default_value_t = 60.0)]
    pub oidc_refresh_interval: f64,
    /// Every /v1 route needs a token (reads too).
    #[arg(long, env = "ISOVOX_PRIVATE_READS")]
    pub private_reads: bool,
    /// Edits per second per token (also the burst); beyond it 429.
    #[arg(long, env = "ISOVOX_EDIT_RATE", default_value_t = 50.0)]
    pub edit_rate: f64,
    /// Edits waiting for one volume's writer; beyond it 503.
    #[arg(long, env = "ISOVOX_EDIT_QUEUE", default_value_t = 64)]
    pub edit_queue: usize,
    /// Edits one volume's writer makes durable together at most, with one sync
    /// (each is still its own version, answered once durable); 1 syncs every edit on its own.
    #[arg(long, env = "ISOVOX_EDIT_GROUP", default_value_t = isovox_server::volume::group::DEFAULT_MAX_GROUP as u64, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub edit_group: u64,
    /// Voxels one edit may evaluate (its bricks, and what mesh leaves and dilate/erode sample);
    /// beyond it 422.
    #[arg(long, env = "ISOVOX_MAX_EDIT_VOXELS", default_value_t = 1 << 28)]
    pub max_edit_voxels: u64,
    /// Seconds that compiling an edit, and then evaluating it, may each take; past it the edit
    /// is stopped (nothing committed, the volume's writer freed) and answered with 422 (503 with
    /// Retry-After when the time ran out waiting on an object store).
    #[arg(long, env = "ISOVOX_EDIT_TIMEOUT", default_value_t = 30.0)]
    pub edit_timeout: f64,
    /// Serve HTTPS (HTTP/2 and HTTP/1.1) with this PEM certificate chain; needs --tls-key.
    #[arg(long, env = "ISOVOX_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The PEM private key of --tls-cert.
    #[arg(long, env = "ISOVOX_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Serve the volumes of an object store instead of DATA's files: `s3://bucket/prefix`, each
    /// volume under `prefix/NAME/` (endpoint and credentials from the AWS_* environment:
    /// AWS_ENDPOINT, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION, AWS_ALLOW_HTTP).
    /// DATA still holds the tokens and uploaded meshes.
    #[arg(long, env = "ISOVOX_STORE")]
    pub store: Option<String>,
    /// How often a replica polls each head in the store (a conditional GET), in milliseconds.
    #[arg(long, env = "ISOVOX_FOLLOW_MS", default_value_t = 100)]
    pub follow_ms: u64,
    /// Where a replica keeps the pages it fetched from the store (default: DATA/cache).
    #[arg(long, env = "ISOVOX_CACHE_DIR")]
    pub cache_dir: Option<PathBuf>,
    /// Disk for fetched pages per volume, in MiB; past it a volume starts a fresh cache.
    #[arg(long, env = "ISOVOX_CACHE_MB", default_value_t = 1024)]
    pub cache_mb: u64,
    /// The smallest read from the store, in KiB: a cold read fetches the aligned blocks of this
    /// size it lies in (4 fetches single pages).
    #[arg(long, env = "ISOVOX_READ_AHEAD_KB", default_value_t = DEFAULT_READ_AHEAD >> 10,
          value_parser = clap::value_parser!(u64).range(4..=65536))]
    pub read_ahead_kb: u64,
    /// When a replica opens a volume, it fetches the volume's index (what level grids read) in
    /// the background if the index is at most this many MiB; 0 turns that off.
    #[arg(long, env = "ISOVOX_PREFETCH_INDEX_MB", default_value_t = DEFAULT_PREFETCH_INDEX >> 20)]
    pub prefetch_index_mb: u64,
    /// KiB of small commits' segments one head object may carry (a commit is then one PUT and
    /// a replica catching up reads it with the head); 0: every segment an object of its own.
    #[arg(long, env = "ISOVOX_INLINE_KB", default_value_t = DEFAULT_INLINE_MAX >> 10,
          value_parser = clap::value_parser!(u64).range(0..=INLINE_LIMIT >> 10))]
    pub inline_kb: u64,
    /// On Ctrl-C or SIGTERM, seconds to let requests in flight finish before closing their
    /// connections (change feeds end at once).
    #[arg(long, env = "ISOVOX_SHUTDOWN_GRACE", default_value_t = 10.0)]
    pub shutdown_grace: f64,
}

/// The tokens the server accepts: the token file (DATA/tokens by default, created with one
/// random write token when nothing else is configured: no `ISOVOX_WRITE_TOKEN`, no OIDC issuer)
/// and `ISOVOX_WRITE_TOKEN`.
fn load_tokens(a: &ServeArgs) -> anyhow::Result<Tokens> {
    let env_token = std::env::var("ISOVOX_WRITE_TOKEN")
        .ok()
        .filter(|t| !t.is_empty());
    let default_file = a.data.join("tokens");
    let file = match &a.token_file {
        Some(f) => Some(f.clone()),
        None if default_file.exists() => Some(default_file),
        None if env_token.is_none() && a.oidc_issuer.is_none() => {
            let secret = random_secret().context("cannot draw a random token")?;
            write_private(
                &default_file,
                &format!(
                    "# isovox tokens: NAME TOKEN [write|read]. Send Authorization: Bearer TOKEN.\ndemo {secret} write\n"
                ),
            )?;
            eprintln!(
                "created {} with a write token for edits (Authorization: Bearer ...)",
                default_file.display()
            );
            Some(default_file)
        }
        None => None,
    };
    let mut tokens = match file {
        Some(f) => Tokens::load(&f).map_err(anyhow::Error::msg)?,
        None => Tokens::default(),
    };
    if let Some(secret) = env_token {
        tokens
            .add("env", &secret, Scope::Write)
            .map_err(|e| anyhow::anyhow!("ISOVOX_WRITE_TOKEN: {e}"))?;
    }
    Ok(tokens)
}

/// The OIDC issuer whose JWTs are accepted, if configured: a key file is read now (an error
/// stops the start); keys from the network are fetched now, and a failure only warns (the
/// first token fetches them again), so a server restarting while its issuer is down still
/// serves its token-file users and public reads.
fn load_oidc(a: &ServeArgs) -> anyhow::Result<Option<std::sync::Arc<Oidc>>> {
    let (Some(issuer), Some(audience)) = (&a.oidc_issuer, &a.oidc_audience) else {
        return Ok(None);
    };
    let refresh_interval = seconds("oidc-refresh-interval", a.oidc_refresh_interval)?;
    let keys = match a.oidc_jwks.as_deref() {
        None => KeySource::Discover,
        Some(url) if url.starts_with("http://") || url.starts_with("https://") => {
            KeySource::Url(url.to_string())
        }
        Some(file) => KeySource::File(PathBuf::from(file)),
    };
    let from_file = matches!(keys, KeySource::File(_));
    let oidc = Oidc::new(OidcConfig {
        roles_claim: a.oidc_roles_claim.clone(),
        keys,
        refresh_interval,
        client_id: a.oidc_client_id.clone().unwrap_or_else(|| audience.clone()),
        ..OidcConfig::new(issuer, audience)
    })
    .map_err(|e| anyhow::anyhow!("--oidc-jwks: {e}"))?;
    if !from_file {
        if let Err(e) = oidc.load_blocking() {
            tracing::warn!("cannot fetch the keys of the OIDC issuer yet (the first token will try again): {e}");
        }
    }
    eprintln!(
        "accepting JWTs of {issuer} for the audience {audience} ({} keys, roles in the claim {})",
        oidc.key_count(),
        a.oidc_roles_claim
    );
    Ok(Some(std::sync::Arc::new(oidc)))
}

/// Creates `path` readable by its owner only.
fn write_private(path: &Path, text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o600);
    }
    let mut f = options
        .open(path)
        .with_context(|| format!("cannot create {}", path.display()))?;
    f.write_all(text.as_bytes())
        .and_then(|()| f.sync_all())
        .with_context(|| format!("cannot write {}", path.display()))
}

fn has_volumes(dir: &Path) -> bool {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(Result::ok)
                .any(|e| e.path().extension().is_some_and(|x| x == "vod"))
        })
        .unwrap_or(false)
}

/// Generates the demo world into `dir` (see [`build_demo`]).
fn generate_demo(dir: &Path) -> anyhow::Result<()> {
    eprintln!(
        "{} holds no volume: generating a demo world in {}",
        dir.display(),
        dir.join(format!("{DEMO_NAME}.vod")).display()
    );
    build_demo(dir, &BuildOptions::default())?;
    Ok(())
}

/// `--NAME SECS` as a duration.
fn seconds(name: &str, secs: f64) -> anyhow::Result<std::time::Duration> {
    std::time::Duration::try_from_secs_f64(secs)
        .map_err(|e| anyhow::anyhow!("--{name} {secs}: {e}"))
}

/// The volumes to serve: those of `--store`, or DATA's files (a demo world generated first
/// when there are none).
fn open_catalog(a: &ServeArgs) -> anyhow::Result<Catalog> {
    let Some(url) = &a.store else {
        if !has_volumes(&a.data) {
            generate_demo(&a.data)?;
        }
        let catalog = Catalog::open_dir(&a.data)?;
        if catalog.is_empty() {
            anyhow::bail!(
                "no volume in {} could be opened (see the errors above)",
                a.data.display()
            );
        }
        return Ok(catalog);
    };
    let bucket = Bucket::from_url(url)?;
    let cache = CacheConfig {
        dir: a.cache_dir.clone().unwrap_or_else(|| a.data.join("cache")),
        max_bytes: a.cache_mb << 20,
        read_ahead: a.read_ahead_kb << 10,
        prefetch_index: a.prefetch_index_mb << 20,
        inline_max: a.inline_kb << 10,
    };
    let catalog = Catalog::open_store(&bucket, &cache)?;
    if catalog.is_empty() {
        anyhow::bail!(
            "no volume in {url} could be opened (import one: isovox import ... -o {url}/NAME)"
        );
    }
    Ok(catalog)
}

/// Creates the data directory when it does not exist, saying so: a mistyped `--data` would
/// otherwise go unnoticed, serving a fresh demo world beside the real one.
fn create_data_dir(dir: &Path) -> anyhow::Result<()> {
    if dir.is_dir() {
        return Ok(());
    }
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let full = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf());
    tracing::warn!(
        data = %full.display(),
        "created a new, empty data directory (check --data if you meant an existing one)"
    );
    Ok(())
}

pub(super) fn serve(a: ServeArgs) -> anyhow::Result<()> {
    // Everything that can be checked without touching the disk is, and the port is bound, before
    // anything is created: a server that cannot start leaves nothing behind (no data directory,
    // demo world or token file).
    let tls = match (&a.tls_cert, &a.tls_key) {
        (Some(cert), Some(key)) => {
            Some(isovox_server::http::tls::config(cert, key).map_err(anyhow::Error::msg)?)
        }
        _ => None,
    };
    let edit_timeout = std::time::Duration::try_from_secs_f64(a.edit_timeout)
        .ok()
        .filter(|t| !t.is_zero())
        .ok_or_else(|| {
            anyhow::anyhow!(
                "--edit-timeout {}: a positive number of seconds expected",
                a.edit_timeout
            )
        })?;
    let shutdown_grace = seconds("shutdown-grace", a.shutdown_grace)?;
    if let Err(e) = raise_fd_limit() {
        tracing::warn!("cannot raise the file-descriptor limit: {e}");
    }
    let connections = Limits {
        max_connections: a
            .max_connections
            .unwrap_or_else(default_max_connections)
            .max(1),
        header_timeout: seconds("header-timeout", a.header_timeout)?,
        idle_timeout: seconds("idle-timeout", a.idle_timeout)?,
    };
    // The main runtime runs no request: the connection threads do (`http/serve.rs`). Its
    // tasks are short async loops (this function's, the followers', the volumes' writer tasks,
    // the signal handler) that hand their waits to its blocking pool: the main thread drives
    // them all, and no `block_in_place` is left that would need a multi-threaded runtime.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind(a.addr.as_str()))
        .with_context(|| format!("cannot listen on {}", a.addr))?;
    create_data_dir(&a.data)?;
    let catalog = open_catalog(&a)?;
    let tokens = load_tokens(&a)?;
    let oidc = load_oidc(&a)?;
    let followed: Vec<_> = catalog.iter().map(|(_, v)| v.clone()).collect();
    let served = runtime.block_on(async {
        let addr = listener.local_addr()?;
        let names: Vec<&str> = catalog.iter().map(|(n, _)| n).collect();
        let scheme = if tls.is_some() { "https" } else { "http" };
        eprintln!(
            "isovox serving {} on {scheme}://{addr}/v1/volumes, the viewer on {scheme}://{addr}/",
            names.join(", ")
        );
        eprintln!(
            "limits: {} connections on {} threads, {} CPU jobs queued on {} threads, {} MiB of answers in flight",
            connections.max_connections,
            a.connection_threads.max(1),
            a.cpu_queue,
            cpu::cores(),
            a.response_memory_mb
        );
        if tokens.is_empty() && oidc.is_none() {
            tracing::warn!("no write token configured: every edit will be refused");
        }
        let config = ServerConfig {
            mesh_cache_bytes: a.mesh_cache_mb << 20,
            brick_cache_bytes: a.brick_cache_mb << 20,
            cpu_queue: a.cpu_queue,
            response_memory_bytes: a.response_memory_mb << 20,
            connections,
            connection_threads: a.connection_threads.max(1),
            tokens,
            oidc,
            private_reads: a.private_reads,
            edit_rate: a.edit_rate,
            edit_queue: a.edit_queue,
            edit_group: usize::try_from(a.edit_group).unwrap_or(usize::MAX),
            max_edit_voxels: a.max_edit_voxels,
            edit_timeout,
            mesh_dir: Some(a.data.join("meshes")),
            shutdown_grace,
            ..ServerConfig::default()
        };
        let state = AppState::with_config(catalog, config);
        let every = std::time::Duration::from_millis(a.follow_ms.max(1));
        tokio::spawn(isovox_server::volume::follow::follow(followed, every, edit_timeout));
        match tls {
            Some(tls) => run_tls(listener, tls, state, shutdown_signal()).await,
            None => run(listener, state, shutdown_signal()).await,
        }
        .context("server failed")
    });
    // The listener loop has ended and closed every connection, which stopped their edits; work
    // still on the blocking pool gets a few seconds to notice, never an unbounded wait.
    runtime.shutdown_timeout(std::time::Duration::from_secs(5));
    served
}
