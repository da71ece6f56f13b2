//! `isovox serve`: serve every VOD 2 file of a data directory over HTTP.

use anyhow::Context;
use clap::Args;
use isovox_server::catalog::Catalog;
use isovox_server::generate::{build_demo, DEMO_NAME};
use isovox_server::http::auth::{random_secret, Scope, Tokens};
use isovox_server::http::{run, run_tls, shutdown_signal, AppState, ServerConfig};
use isovox_server::store::BuildOptions;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub(crate) struct ServeArgs {
    /// Directory of VOD 2 files; each is served as a volume named after the file. When it holds
    /// none, a demo world is generated there first.
    #[arg(long, env = "ISOVOX_DATA", default_value = "data")]
    pub data: PathBuf,
    /// Address to listen on.
    #[arg(long, env = "ISOVOX_ADDR", default_value = "127.0.0.1:7070")]
    pub addr: SocketAddr,
    /// Memory for cached mesh tiles, in MiB.
    #[arg(long, env = "ISOVOX_MESH_CACHE_MB", default_value_t = 256)]
    pub mesh_cache_mb: usize,
    /// Memory for decoded and transcoded brick bodies, in MiB.
    #[arg(long, env = "ISOVOX_BRICK_CACHE_MB", default_value_t = 64)]
    pub brick_cache_mb: usize,
    /// Meshing jobs running or queued at once; beyond it requests get 503 with Retry-After.
    #[arg(long, env = "ISOVOX_CPU_QUEUE", default_value_t = 64)]
    pub cpu_queue: usize,
    /// Tokens, one per line: `NAME TOKEN [write|read]`. Default: DATA/tokens, created with one
    /// random write token on first start when no token is configured.
    #[arg(long, env = "ISOVOX_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// Every /v1 route needs a token (reads too).
    #[arg(long, env = "ISOVOX_PRIVATE_READS")]
    pub private_reads: bool,
    /// Edits per second per token (also the burst); beyond it 429.
    #[arg(long, env = "ISOVOX_EDIT_RATE", default_value_t = 50.0)]
    pub edit_rate: f64,
    /// Edits waiting for one volume's writer; beyond it 503.
    #[arg(long, env = "ISOVOX_EDIT_QUEUE", default_value_t = 64)]
    pub edit_queue: usize,
    /// Edits one volume's writer makes durable together at most, with one pair of syncs
    /// (each is still its own version, answered once durable); 1 syncs every edit on its own.
    #[arg(long, env = "ISOVOX_EDIT_GROUP", default_value_t = isovox_server::volume::group::DEFAULT_MAX_GROUP as u64, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub edit_group: u64,
    /// Level-0 voxels one edit may evaluate; beyond it 422.
    #[arg(long, env = "ISOVOX_MAX_EDIT_VOXELS", default_value_t = 1 << 28)]
    pub max_edit_voxels: u64,
    /// Serve HTTPS (HTTP/2 and HTTP/1.1) with this PEM certificate chain; needs --tls-key.
    #[arg(long, env = "ISOVOX_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The PEM private key of --tls-cert.
    #[arg(long, env = "ISOVOX_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// On Ctrl-C or SIGTERM, seconds to let requests in flight finish before closing their
    /// connections (change feeds end at once).
    #[arg(long, env = "ISOVOX_SHUTDOWN_GRACE", default_value_t = 10.0)]
    pub shutdown_grace: f64,
}

/// The tokens the server accepts: the token file (DATA/tokens by default, created with one
/// random write token when nothing else is configured) and `ISOVOX_WRITE_TOKEN`.
fn load_tokens(a: &ServeArgs) -> anyhow::Result<Tokens> {
    let env_token = std::env::var("ISOVOX_WRITE_TOKEN")
        .ok()
        .filter(|t| !t.is_empty());
    let default_file = a.data.join("tokens");
    let file = match &a.token_file {
        Some(f) => Some(f.clone()),
        None if default_file.exists() => Some(default_file),
        None if env_token.is_none() => {
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

pub(super) fn serve(a: ServeArgs) -> anyhow::Result<()> {
    if !has_volumes(&a.data) {
        generate_demo(&a.data)?;
    }
    let tokens = load_tokens(&a)?;
    let catalog = Catalog::open_dir(&a.data)?;
    if catalog.is_empty() {
        anyhow::bail!(
            "no volume in {} could be opened (see the errors above)",
            a.data.display()
        );
    }
    let tls = match (&a.tls_cert, &a.tls_key) {
        (Some(cert), Some(key)) => {
            Some(isovox_server::http::tls::config(cert, key).map_err(anyhow::Error::msg)?)
        }
        _ => None,
    };
    let shutdown_grace = std::time::Duration::try_from_secs_f64(a.shutdown_grace)
        .map_err(|e| anyhow::anyhow!("--shutdown-grace {}: {e}", a.shutdown_grace))?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind(a.addr)
            .await
            .with_context(|| format!("cannot listen on {}", a.addr))?;
        let addr = listener.local_addr()?;
        let names: Vec<&str> = catalog.iter().map(|(n, _)| n).collect();
        let scheme = if tls.is_some() { "https" } else { "http" };
        eprintln!(
            "isovox serving {} on {scheme}://{addr}/v1/volumes, the viewer on {scheme}://{addr}/",
            names.join(", ")
        );
        if tokens.is_empty() {
            tracing::warn!("no write token configured: every edit will be refused");
        }
        let config = ServerConfig {
            mesh_cache_bytes: a.mesh_cache_mb << 20,
            brick_cache_bytes: a.brick_cache_mb << 20,
            cpu_queue: a.cpu_queue,
            tokens,
            private_reads: a.private_reads,
            edit_rate: a.edit_rate,
            edit_queue: a.edit_queue,
            edit_group: usize::try_from(a.edit_group).unwrap_or(usize::MAX),
            max_edit_voxels: a.max_edit_voxels,
            mesh_dir: Some(a.data.join("meshes")),
            shutdown_grace,
            ..ServerConfig::default()
        };
        let state = AppState::with_config(catalog, config);
        match tls {
            Some(tls) => run_tls(listener, tls, state, shutdown_signal()).await,
            None => run(listener, state, shutdown_signal()).await,
        }
        .context("server failed")
    })
}
