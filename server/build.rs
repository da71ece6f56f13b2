//! Builds the web viewer (`web/`, TypeScript and Vite) and embeds it in the server, so that the
//! one run command (`cargo run --release -p isovox-server --bin isovox -- serve`) serves it at
//! `/` on a fresh clone, and the `isovox` binary is self-contained (no files to deploy beside
//! it, nothing built on first start).
//!
//! - `ISOVOX_WEB_DIST=DIR`: embed an already built viewer (e.g. a container build's web stage).
//! - Otherwise, when `web/package.json` exists: `npm ci` if `web/node_modules` is missing or
//!   older than the lock file, then `npm run build` into this build's `OUT_DIR` (the source tree
//!   gets only `node_modules`). Cargo runs this again only when a file under `web/` changed.
//! - Without npm on the machine the server still builds, with a page at `/` that says how to get
//!   the viewer, and a build warning.
//!
//! The embedded files become `OUT_DIR/web_assets.rs`: a table of (URL path, media type, bytes),
//! included by `src/http/web_app.rs`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

const SOURCES: &[&str] = &[
    "src",
    "index.html",
    "package.json",
    "package-lock.json",
    "vite.config.ts",
    "tsconfig.json",
];

const NOT_BUILT: &str = "<!doctype html><meta charset=utf-8><title>Isovox</title>\
<p>This <code>isovox</code> was compiled without its web viewer: <code>npm</code> (Node.js 20 or \
later) was not found. Install Node.js and build again (<code>cargo build -p isovox-server</code>), \
or set <code>ISOVOX_WEB_DIST</code> to a built <code>web/dist</code>. The API is at \
<a href=\"/v1/volumes\">/v1/volumes</a>.</p>\n";

fn main() {
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let out = PathBuf::from(std::env::var_os("OUT_DIR").unwrap_or_default());
    let web = manifest.join("../web");
    println!("cargo:rerun-if-env-changed=ISOVOX_WEB_DIST");
    let dist = if let Some(dir) = std::env::var_os("ISOVOX_WEB_DIST") {
        PathBuf::from(dir)
    } else if web.join("package.json").exists() {
        for s in SOURCES {
            println!("cargo:rerun-if-changed={}", web.join(s).display());
        }
        let dist = out.join("web");
        match build_viewer(&web, &dist) {
            Ok(()) => dist,
            Err(Missing::Npm) => {
                println!("cargo:warning=npm not found: the web viewer is not built into isovox");
                not_built(&out)
            }
        }
    } else {
        not_built(&out)
    };
    let table = asset_table(&dist);
    if let Err(e) = std::fs::write(out.join("web_assets.rs"), table) {
        panic!("cannot write web_assets.rs: {e}");
    }
}

enum Missing {
    Npm,
}

fn build_viewer(web: &Path, dist: &Path) -> Result<(), Missing> {
    if Command::new("npm").arg("--version").output().is_err() {
        return Err(Missing::Npm);
    }
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    let installed = modified(&web.join("node_modules/.package-lock.json"));
    let locked = modified(&web.join("package-lock.json"));
    if installed.is_none() || installed < locked {
        run(web, &["ci", "--no-audit", "--no-fund"]);
    }
    let dist = dist.to_string_lossy();
    run(
        web,
        &["run", "build", "--", "--outDir", &dist, "--emptyOutDir"],
    );
    Ok(())
}

fn run(dir: &Path, args: &[&str]) {
    let status = Command::new("npm")
        .args(args)
        .current_dir(dir)
        .status()
        .unwrap_or_else(|e| panic!("npm {}: {e}", args.join(" ")));
    assert!(
        status.success(),
        "npm {} failed in {} ({status})",
        args.join(" "),
        dir.display()
    );
}

fn not_built(out: &Path) -> PathBuf {
    let dir = out.join("web-not-built");
    let written = std::fs::create_dir_all(&dir)
        .and_then(|()| std::fs::write(dir.join("index.html"), NOT_BUILT));
    if let Err(e) = written {
        panic!("cannot write {}: {e}", dir.display());
    }
    dir
}

fn media_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()) {
        Some("html") => "text/html; charset=utf-8",
        Some("js") => "text/javascript; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("json") => "application/json",
        Some("svg") => "image/svg+xml",
        Some("png") => "image/png",
        Some("wasm") => "application/wasm",
        _ => "application/octet-stream",
    }
}

/// The Rust source of the asset table: every file under `dist`, by URL path.
fn asset_table(dist: &Path) -> String {
    let mut files = Vec::new();
    collect(dist, &mut files);
    files.sort();
    let mut s =
        String::from("/// (URL path, media type, bytes) of every file of the built viewer.\n");
    s.push_str("pub(super) static ASSETS: &[(&str, &str, &[u8])] = &[\n");
    for f in files {
        let rel = f.strip_prefix(dist).unwrap_or(&f);
        let url: Vec<String> = rel
            .components()
            .map(|c| c.as_os_str().to_string_lossy().into_owned())
            .collect();
        let _ = writeln!(
            s,
            "    ({:?}, {:?}, include_bytes!({:?})),",
            format!("/{}", url.join("/")),
            media_type(&f),
            f.display().to_string()
        );
    }
    s.push_str("];\n");
    s
}

fn collect(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        panic!("cannot read the built viewer in {}", dir.display());
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            collect(&p, out);
        } else {
            out.push(p);
        }
    }
}
