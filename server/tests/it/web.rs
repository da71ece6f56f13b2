//! The web viewer's tests, run by the README's test command (`cargo test --workspace`):
//! `npm test` in `web/` (vitest, the unit tests of the TypeScript, among them the tile selection
//! against the vectors `proto/tests/lod_vectors.rs` writes), and what the server sends the
//! viewer. The pages in chromium are [`crate::browser`]'s.
//!
//! They need Node.js 20+ (`.ci/run` installs it); `web/node_modules` is installed here if
//! building the server did not already (`build.rs` runs `npm ci`).

use crate::server_process::{run_isovox, ServerProcess};
use std::path::PathBuf;
use std::process::Command;
use std::sync::Mutex;

pub(crate) fn web() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../web")
}

/// Runs `program args` in `web/` and fails with its output unless it succeeds.
pub(crate) fn run(program: &str, args: &[&str], envs: &[(&str, &str)]) {
    let out = Command::new(program)
        .args(args)
        .envs(envs.iter().copied())
        .current_dir(web())
        .output()
        .unwrap_or_else(|e| panic!("cannot run {program} (Node.js 20+ is needed): {e}"));
    let text = crate::common::printed_output(&out);
    assert!(
        out.status.success(),
        "{program} {} failed ({}):\n{text}",
        args.join(" "),
        out.status
    );
}

/// `npm ci` once, when `web/node_modules` is missing.
pub(crate) fn node_modules() {
    static DONE: Mutex<bool> = Mutex::new(false);
    let mut done = DONE.lock().unwrap_or_else(|e| e.into_inner());
    if !*done && !web().join("node_modules/.package-lock.json").exists() {
        run("npm", &["ci", "--no-audit", "--no-fund"], &[]);
    }
    *done = true;
}

#[test]
fn typescript_unit_tests() {
    node_modules();
    run("npm", &["test", "--silent"], &[]);
}

/// A world of 128x64x128 voxels served by this build's `isovox serve` on a free port.
struct Served {
    base: String,
    // Dropped (killed) before the directory it serves is removed: fields drop in order.
    _server: ServerProcess,
    _dir: tempfile::TempDir,
}

fn serve_world() -> Served {
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let world = dir.path().join("w.vod");
    let world = world
        .to_str()
        .unwrap_or_else(|| panic!("a UTF-8 temporary path"));
    run_isovox(&[
        "generate",
        "world",
        "--dims",
        "128,64,128",
        "--brick",
        "32",
        "-o",
        world,
    ]);
    let server = ServerProcess::start(&["--data".as_ref(), dir.path().as_os_str()], &[]);
    Served {
        base: server.url(""),
        _server: server,
        _dir: dir,
    }
}

fn get(url: &str, headers: &[(&str, &str)]) -> reqwest::blocking::Response {
    isovox_server::client_tls::install_provider();
    let mut r = reqwest::blocking::Client::new().get(url);
    for (k, v) in headers {
        r = r.header(*k, *v);
    }
    r.send().unwrap_or_else(|e| panic!("{url}: {e}"))
}

fn header(r: &reqwest::blocking::Response, name: &str) -> Option<String> {
    r.headers()
        .get(name)
        .map(|v| v.to_str().unwrap_or_default().to_string())
}

#[test]
fn the_viewer_is_served_at_the_root_with_zstd_and_caching() {
    let s = serve_world();
    let page = get(&format!("{}/", s.base), &[]);
    assert_eq!(page.status().as_u16(), 200);
    assert_eq!(
        header(&page, "content-type").as_deref(),
        Some("text/html; charset=utf-8")
    );
    assert_eq!(header(&page, "cache-control").as_deref(), Some("no-cache"));
    let etag = header(&page, "etag").unwrap_or_else(|| panic!("no ETag"));
    let html = page.text().unwrap_or_default();
    // The page Vite built, with its script under /assets/.
    let at = html
        .find("/assets/")
        .unwrap_or_else(|| panic!("no script in {html}"));
    let script = &html[at..at + html[at..].find('"').unwrap_or(0)];
    assert!(script.ends_with(".js"), "{script}");
    let again = get(&format!("{}/", s.base), &[("if-none-match", &etag)]);
    assert_eq!(again.status().as_u16(), 304);

    let plain = get(&format!("{}{script}", s.base), &[]);
    assert_eq!(plain.status().as_u16(), 200);
    assert!(header(&plain, "cache-control").is_some_and(|c| c.contains("immutable")));
    assert_eq!(header(&plain, "content-encoding"), None);
    let plain = plain.bytes().unwrap_or_default();
    let packed = get(
        &format!("{}{script}", s.base),
        &[("accept-encoding", "gzip, deflate, br, zstd")],
    );
    assert_eq!(header(&packed, "content-encoding").as_deref(), Some("zstd"));
    let packed = packed.bytes().unwrap_or_default();
    assert!(
        packed.len() * 2 < plain.len(),
        "{} of {}",
        packed.len(),
        plain.len()
    );
    assert_eq!(zstd::decode_all(&packed[..]).unwrap_or_default(), plain);

    let missing = get(&format!("{}/assets/none.js", s.base), &[]);
    assert_eq!(missing.status().as_u16(), 404);
    assert_eq!(
        header(&missing, "content-type").as_deref(),
        Some("application/problem+json")
    );
}

#[test]
fn mesh_tiles_level_grids_and_batches_go_out_as_zstd_to_clients_that_accept_it() {
    let s = serve_world();
    let mut checked = 0;
    // Tiles of level 0 (grid 4x2x4) whose mesh is large enough to be compressed.
    for (x, y, z) in [
        (0, 0, 0),
        (1, 0, 1),
        (2, 0, 2),
        (1, 1, 1),
        (3, 1, 3),
        (2, 1, 0),
    ] {
        let url = format!("{}/v1/volumes/w/meshes/0/{x}/{y}/{z}", s.base);
        let plain = get(&url, &[]);
        assert_eq!(header(&plain, "content-encoding"), None);
        let plain = plain.bytes().unwrap_or_default();
        if plain.len() < 4096 {
            continue;
        }
        let packed = get(&url, &[("accept-encoding", "zstd")]);
        assert_eq!(header(&packed, "content-encoding").as_deref(), Some("zstd"));
        assert!(header(&packed, "vary")
            .is_some_and(|v| v.to_ascii_lowercase().contains("accept-encoding")));
        let packed = packed.bytes().unwrap_or_default();
        assert!(packed.len() < plain.len());
        assert_eq!(zstd::decode_all(&packed[..]).unwrap_or_default(), plain);
        checked += 1;
    }
    assert!(checked >= 2, "{checked} tiles with a surface");
    let url = format!("{}/v1/volumes/w/levels/0", s.base);
    let plain = get(&url, &[]).bytes().unwrap_or_default();
    let packed = get(&url, &[("accept-encoding", "zstd")]);
    assert_eq!(header(&packed, "content-encoding").as_deref(), Some("zstd"));
    let packed = packed.bytes().unwrap_or_default();
    assert_eq!(zstd::decode_all(&packed[..]).unwrap_or_default(), plain);

    // A batch of every level-0 brick (32 KiB each, mostly air and rock).
    let keys: Vec<String> = (0..4)
        .flat_map(|z| (0..2).flat_map(move |y| (0..4).map(move |x| format!("[0,{x},{y},{z}]"))))
        .collect();
    let body = format!("{{\"keys\":[{}]}}", keys.join(","));
    let batch = |accept: Option<&str>| {
        isovox_server::client_tls::install_provider();
        let mut r = reqwest::blocking::Client::new()
            .post(format!("{}/v1/volumes/w/batch", s.base))
            .header("content-type", "application/json")
            .body(body.clone());
        if let Some(a) = accept {
            r = r.header("accept-encoding", a);
        }
        r.send().unwrap_or_else(|e| panic!("batch: {e}"))
    };
    let plain = batch(None);
    assert_eq!(plain.status().as_u16(), 200);
    assert_eq!(header(&plain, "content-encoding"), None);
    let plain = plain.bytes().unwrap_or_default();
    let packed = batch(Some("zstd"));
    assert_eq!(header(&packed, "content-encoding").as_deref(), Some("zstd"));
    let packed = packed.bytes().unwrap_or_default();
    assert!(
        packed.len() < plain.len(),
        "{} of {}",
        packed.len(),
        plain.len()
    );
    assert_eq!(zstd::decode_all(&packed[..]).unwrap_or_default(), plain);
}
