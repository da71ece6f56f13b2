//! The field's formats against the field's own clients: a real `isovox serve` on loopback (port
//! 0), driven by the scripts of `tests/python/` with the Python packages pinned in
//! `tests/python/requirements.txt` (tensorstore, zarr, ome-zarr, cloud-volume, nibabel,
//! tifffile, neuroglancer) and, for Neuroglancer, Debian's Chromium through playwright-core.
//!
//! Each test asserts its script's exit status; the scripts print what they compared. The
//! Python environment is `tests/python/.venv` (or `ISOVOX_PYTHON`); `.ci/run` creates it. A
//! missing environment fails these tests with the command that creates it: it is not a skip.

use crate::server_process;

use server_process::ServerProcess;
use std::path::{Path, PathBuf};
use std::process::Command;

const TOKEN: &str = "formats-test-token";

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the server crate sits in the workspace")
        .to_path_buf()
}

fn scripts() -> PathBuf {
    repo().join("tests/python")
}

/// The Python that has the pinned clients.
fn python() -> PathBuf {
    let path = std::env::var_os("ISOVOX_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| scripts().join(".venv/bin/python"));
    assert!(
        path.exists(),
        "{} does not exist: these tests need the Python clients. Create them with\n  \
         python3 -m venv tests/python/.venv && tests/python/.venv/bin/pip install -r tests/python/requirements.txt\n\
         (.ci/run does), or point ISOVOX_PYTHON at a Python that has them.",
        path.display()
    );
    path
}

fn isovox() -> Command {
    Command::new(env!("CARGO_BIN_EXE_isovox"))
}

fn ok(cmd: &mut Command) {
    let out = cmd.output().expect("the command runs");
    assert!(
        out.status.success(),
        "{cmd:?} failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `isovox serve` of `data` on an ephemeral loopback port, with a write token.
fn serve(data: &Path) -> ServerProcess {
    let tokens = data.join("tokens");
    std::fs::write(&tokens, format!("tester {TOKEN} write\n")).expect("write the token file");
    ServerProcess::start(
        &[
            "--data".as_ref(),
            data.as_os_str(),
            "--token-file".as_ref(),
            tokens.as_os_str(),
        ],
        &[],
    )
}

/// Runs a script of `tests/python` against `server` and asserts it succeeded.
fn script(name: &str, server: &ServerProcess, args: &[&str]) {
    let status = Command::new(python())
        .arg(scripts().join(name))
        .args(args)
        .current_dir(scripts())
        .status()
        .expect("the Python script runs");
    assert!(
        status.success(),
        "{name} {args:?} failed ({status}); its output is above; the server's log ends:\n{}",
        server.log_tail(40)
    );
}

/// A u8 world and a u16 ellipsoid whose dimensions are not multiples of their bricks, and
/// [`wide_labels`].
fn odd_volumes(data: &Path) {
    std::fs::create_dir_all(data).expect("create the data directory");
    ok(isovox()
        .args([
            "generate",
            "world",
            "--materials",
            "--dims",
            "197,77,141",
            "--brick",
            "32",
            "-o",
        ])
        .arg(data.join("world8.vod")));
    ok(isovox()
        .args([
            "generate",
            "ellipsoid",
            "--type",
            "u16",
            "--dims",
            "131,95,67",
            "--brick",
            "16",
            "-o",
        ])
        .arg(data.join("ellipsoid16.vod")));
    wide_labels(&data.join("labels64.vod"));
}

/// A 45 x 38 x 29 volume (brick 16) with a u32 channel `label32` and a sparse u64 channel
/// `label`: boxes of ids past u16 and past u32, past 2^53 (where a float64 would round them),
/// past 2^63 (more than a constant index entry holds: whole bricks of them are records) and
/// 2^64 - 1, so that every level of both reads back through the field's clients.
fn wide_labels(path: &Path) {
    use isovox_proto::channel::ChannelInfo;
    use isovox_proto::vod2::FileHeader;
    use isovox_proto::{VolumeLayout, VoxelType};
    use isovox_server::store::{build_streams, BrickSource, BuildOptions, DenseGrid};
    let dims = [45u32, 38, 29];
    let n = (dims[0] * dims[1] * dims[2]) as usize;
    let at = |i: usize| (i % 45, i / 45 % 38, i / (45 * 38));
    let density: Vec<u8> = (0..n).map(|i| if at(i).1 < 19 { 255 } else { 0 }).collect();
    let id32 = |i: usize| -> u32 {
        let (x, y, z) = at(i);
        match (x / 9, y / 10, z / 8) {
            (0, _, _) => 0,
            (1, 0, _) => 70_000,
            (a, b, c) => 4_000_000_000 - (a + 7 * b + 31 * c) as u32,
        }
    };
    let id64 = |i: usize| -> u64 {
        let (x, y, z) = at(i);
        if x < 16 && y < 16 && z < 16 {
            return (1 << 63) + 5; // brick (0, 0, 0) whole: a record, not a constant
        }
        match (x / 11, y / 9, z / 7) {
            (1, _, _) => 0,
            (0, _, _) => u64::MAX,
            (2, b, _) => (1 << 53) + 1 + b as u64,
            (a, b, c) => ((a + 3 * b + 17 * c) as u64) << 40,
        }
    };
    let label32: Vec<u8> = (0..n).flat_map(|i| id32(i).to_le_bytes()).collect();
    let label64: Vec<u8> = (0..n).flat_map(|i| id64(i).to_le_bytes()).collect();
    let grids = [
        DenseGrid::new(dims, VoxelType::U8, 16, &density),
        DenseGrid::new(dims, VoxelType::U32, 16, &label32),
        DenseGrid::new(dims, VoxelType::U64, 16, &label64),
    ];
    let sources: Vec<&dyn BrickSource> = grids.iter().map(|g| g as _).collect();
    let layout = VolumeLayout::new(dims, 16, VoxelType::U8).expect("a layout");
    let channels = vec![
        ChannelInfo::new("label32", VoxelType::U32),
        ChannelInfo {
            sparse: true,
            ..ChannelInfo::new("label", VoxelType::U64)
        },
    ];
    let header = FileHeader::with_channels(layout, [1.0; 3], channels).expect("a header");
    build_streams(path, header, &sources, &BuildOptions::default()).expect("the volume builds");
}

#[test]
fn python_clients_read_every_level_live_and_pinned() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let data = dir.path().join("data");
    odd_volumes(&data);
    let server = serve(&data);
    let url = server.url("");
    script(
        "views_read_back.py",
        &server,
        &[
            "--url",
            &url,
            "--token",
            TOKEN,
            "world8",
            "ellipsoid16",
            "labels64",
        ],
    );
}

#[test]
fn neuroglancer_draws_the_demo_from_both_views() {
    let node_modules = scripts().join("node_modules/playwright-core");
    assert!(
        node_modules.exists(),
        "{} does not exist: run `npm ci` in tests/python (.ci/run does)",
        node_modules.display()
    );
    assert!(
        Path::new("/usr/bin/chromium").exists(),
        "/usr/bin/chromium does not exist: apt-get install chromium (.ci/run does)"
    );
    let dir = tempfile::tempdir().expect("a temporary directory");
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).expect("create the data directory");
    // An empty data directory: the server generates its demo world, as a user sees it.
    let server = serve(&data);
    let url = server.url("");
    let out = dir.path().join("screenshots");
    std::fs::create_dir_all(&out).expect("create the screenshot directory");
    script(
        "neuroglancer_draws.py",
        &server,
        &[
            "--url",
            &url,
            "--volume",
            "demo",
            "--out",
            out.to_str().expect("a UTF-8 path"),
        ],
    );
}

#[test]
fn imports_round_trip_and_exports_read_back() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let data = dir.path().join("data");
    odd_volumes(&data);
    let server = serve(&data);
    let url = server.url("");
    let work = dir.path().join("work");
    script(
        "imports_round_trip.py",
        &server,
        &[
            "--isovox",
            env!("CARGO_BIN_EXE_isovox"),
            "--work",
            work.to_str().expect("a UTF-8 path"),
            "--url",
            &url,
            "--data",
            data.to_str().expect("a UTF-8 path"),
            "ellipsoid16",
        ],
    );
}
