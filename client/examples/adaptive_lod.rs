//! The thesis's adaptive LOD result, measured with the streamer: bytes and triangles fetched for a
//! camera at a corner of a 512^3 world and a 512^3 ellipsoid, against the full level 0.
//!
//! ```sh
//! cargo run --release -p isovox-client --example adaptive_lod [-- DIR]
//! ```
//!
//! Generates both volumes in DIR (default `bench-out/adaptive`) the first time, serves them from
//! this process on an ephemeral port, and streams mesh tiles twice per volume: with radii
//! (max/4, max/2, max) around the camera at (0, height, 0) (the same camera and radii as
//! `isovox bench mesh`), and with no radii (level 0 everywhere). Prints a Markdown table.

use isovox_client::proto::{VolumeLayout, VoxelType};
use isovox_client::streamer::{StreamEvent, Streamer, StreamerConfig, TileData, TileKind};
use isovox_client::Client;
use isovox_server::catalog::Catalog;
use isovox_server::generate::{EllipsoidSource, WorldSource};
use isovox_server::http::{run, AppState};
use isovox_server::store::{build_vod2, BrickSource, BuildOptions};
use std::path::PathBuf;

/// Tiles, triangles and payload bytes a streamer delivered once idle.
async fn stream(
    client: &Client,
    volume: &str,
    camera: [f32; 3],
    radii: Vec<f32>,
) -> Result<(usize, u64, u64), Box<dyn std::error::Error>> {
    let config = StreamerConfig {
        kind: TileKind::Meshes { iso: None },
        radii,
        max_in_flight: 8,
        cache_bytes: 1 << 30,
        follow_edits: false,
        // Every tile of the selection, surfaceless ones too: the tile counts compare the
        // selections themselves.
        descent: false,
        skip_empty: false,
    };
    let (streamer, mut events) = Streamer::start(client.clone(), volume, config).await?;
    streamer.set_camera(camera);
    let counting = tokio::spawn(async move {
        let (mut tiles, mut triangles) = (0usize, 0u64);
        while let Some(e) = events.recv().await {
            if let StreamEvent::Ready {
                data: TileData::Mesh(m),
                ..
            } = e
            {
                tiles += 1;
                triangles += m.mesh.indices.len() as u64 / 3;
            }
        }
        (tiles, triangles)
    });
    streamer.wait_idle().await;
    let bytes = streamer.stats().bytes;
    streamer.shutdown().await;
    let (tiles, triangles) = counting.await?;
    Ok((tiles, triangles, bytes))
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = std::env::args()
        .nth(1)
        .map_or_else(|| PathBuf::from("bench-out/adaptive"), PathBuf::from);
    std::fs::create_dir_all(&dir)?;
    let layout = VolumeLayout::new([512, 512, 512], 32, VoxelType::U8)?;
    for name in ["world", "ellipsoid"] {
        let path = dir.join(format!("{name}.vod"));
        if !path.exists() {
            eprintln!("generating {}", path.display());
            let source: Box<dyn BrickSource> = if name == "world" {
                Box::new(WorldSource::new(layout.clone(), 1))
            } else {
                Box::new(EllipsoidSource::new(layout.clone()))
            };
            build_vod2(&path, &layout, [1.0; 3], &*source, &BuildOptions::default())?;
        }
    }
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let base = format!("http://{}", listener.local_addr()?);
    let state = AppState::new(Catalog::open_dir(&dir)?, 1 << 30, 64);
    tokio::spawn(run(listener, state, std::future::pending()));
    // reqwest has the server's rustls without a built-in provider (isovox_server::client_tls).
    isovox_server::client_tls::install_provider();
    let client = Client::new(&base)?;
    println!("### Adaptive LOD with the streamer (mesh tiles, camera at a corner (0, 512, 0), radii 128 / 256 / 512 voxels)\n");
    println!("| data set | adaptive: tiles | triangles | bytes | level 0: tiles | triangles | bytes | fewer triangles | fewer bytes |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for name in ["world", "ellipsoid"] {
        let max = 512.0f32;
        let camera = [0.0, 512.0, 0.0];
        let (at, atri, abytes) =
            stream(&client, name, camera, vec![max / 4.0, max / 2.0, max]).await?;
        // One radius beyond everything: level 0 everywhere (empty radii would mean "derive").
        let (ft, ftri, fbytes) = stream(&client, name, camera, vec![1e9]).await?;
        println!(
            "| {name} 512^3 | {at} | {atri} | {abytes} | {ft} | {ftri} | {fbytes} | {:.0}% | {:.0}% |",
            100.0 * (1.0 - atri as f64 / ftri as f64),
            100.0 * (1.0 - abytes as f64 / fbytes as f64)
        );
    }
    Ok(())
}
