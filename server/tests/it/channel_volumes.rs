//! Volumes with attribute channels for the channel tests (channels, segments, mesh materials):
//! a u8 density with a u8 `material` and a u16 `label` channel, brick 16, written from plain
//! arrays; the 64^3 ground several of them use; and a server over a directory with one write
//! token for alice.

use crate::server_process::ServerProcess;
use isovox_proto::channel::ChannelInfo;
use isovox_proto::vod2::FileHeader;
use isovox_proto::{VolumeLayout, VoxelType};
use isovox_server::store::{build_streams, BuildOptions, DenseGrid};
use std::path::Path;

/// Alice's write token in [`serve`]'s token file.
pub(crate) const TOKEN: &str = "secret-alice-0123456";

/// Writes `path`: `density` and `material` (u8, x fastest) of `dims` and a `label` channel of
/// 0s (u16, `sparse` as given), brick 16.
pub(crate) fn write_volume(
    path: &Path,
    dims: [u32; 3],
    density: &[u8],
    material: &[u8],
    label_sparse: bool,
) {
    let label = vec![0u8; 2 * density.len()];
    let sources = [
        DenseGrid::new(dims, VoxelType::U8, 16, density),
        DenseGrid::new(dims, VoxelType::U8, 16, material),
        DenseGrid::new(dims, VoxelType::U16, 16, &label),
    ];
    let sources: Vec<&dyn isovox_server::store::BrickSource> =
        sources.iter().map(|s| s as _).collect();
    let layout = VolumeLayout::new(dims, 16, VoxelType::U8).unwrap();
    let channels = vec![
        ChannelInfo::new("material", VoxelType::U8),
        ChannelInfo {
            sparse: label_sparse,
            ..ChannelInfo::new("label", VoxelType::U16)
        },
    ];
    let header = FileHeader::with_channels(layout, [1.0; 3], channels).unwrap();
    build_streams(path, header, &sources, &BuildOptions::default()).unwrap();
}

/// A 64^3 ground as `dir/world.vod`: density 255 below z = 20, material 1 everywhere, a sparse
/// label channel of 0s.
pub(crate) fn ground_64(dir: &Path) {
    let n = 64 * 64 * 64;
    let density: Vec<u8> = (0..n)
        .map(|i| if i / (64 * 64) < 20 { 255 } else { 0 })
        .collect();
    write_volume(
        &dir.join("world.vod"),
        [64; 3],
        &density,
        &vec![1u8; n],
        true,
    );
}

/// `isovox serve` over `dir`, alice holding [`TOKEN`] (write); `envs` for its environment.
pub(crate) fn serve(dir: &Path, envs: &[(&str, &str)]) -> ServerProcess {
    isovox_server::client_tls::install_provider();
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("alice {TOKEN} write\n")).unwrap();
    ServerProcess::start(
        &[
            "--data".as_ref(),
            dir.as_os_str(),
            "--token-file".as_ref(),
            tokens.as_os_str(),
        ],
        envs,
    )
}

/// POSTs `body` to `path` of `server` as alice; the answer's JSON (panics unless 2xx).
pub(crate) fn post_ok(
    server: &ServerProcess,
    path: &str,
    body: serde_json::Value,
) -> serde_json::Value {
    let r = reqwest::blocking::Client::new()
        .post(server.url(path))
        .bearer_auth(TOKEN)
        .json(&body)
        .send()
        .unwrap();
    let status = r.status();
    let text = r.text().unwrap();
    assert!(status.is_success(), "{path} {body}: {status} {text}");
    serde_json::from_str(&text).unwrap()
}
