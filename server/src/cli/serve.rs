//! `isovox serve`: serve every VOD 2 file of a data directory over HTTP.

use crate::catalog::Catalog;
use crate::generate::WorldSource;
use crate::http::{run, shutdown_signal, AppState};
use crate::store::codec::Compression;
use anyhow::Context;
use clap::Args;
use isovox_proto::{VolumeLayout, VoxelType};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct ServeArgs {
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
    /// Meshing jobs running or queued at once; beyond it requests get 503 with Retry-After.
    #[arg(long, env = "ISOVOX_CPU_QUEUE", default_value_t = 64)]
    pub cpu_queue: usize,
}

/// Name of the volume generated on first start.
pub const DEMO_NAME: &str = "demo";

fn has_volumes(dir: &Path) -> bool {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(Result::ok)
                .any(|e| e.path().extension().is_some_and(|x| x == "vod"))
        })
        .unwrap_or(false)
}

/// Generates the demo world into `dir`: a 512 x 256 x 512 terrain with tunnels, a crater and a
/// few primitives carved and added by ICVG edits (brick 32; about a second, under 2 MB).
fn generate_demo(dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create the data directory {}", dir.display()))?;
    let path = dir.join(format!("{DEMO_NAME}.vod"));
    eprintln!(
        "{} holds no volume: generating a demo world in {}",
        dir.display(),
        path.display()
    );
    let layout = VolumeLayout::new([512, 256, 512], 32, VoxelType::U8)?;
    super::data::generate_scene(
        &path,
        &layout,
        &WorldSource::new(layout.clone(), 1),
        Compression::default(),
    )
}

pub fn serve(a: ServeArgs) -> anyhow::Result<()> {
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
        eprintln!(
            "isovox serving {} on http://{addr}/v1/volumes",
            names.join(", ")
        );
        let state = AppState::new(catalog, a.mesh_cache_mb << 20, a.cpu_queue);
        run(listener, state, shutdown_signal())
            .await
            .context("server failed")
    })
}
