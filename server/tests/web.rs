//! The web viewer's tests, run by the README's test command (`cargo test --workspace`):
//!
//! - `npm test` in `web/`: vitest, the unit tests of the TypeScript (among them the tile
//!   selection against the vectors `proto/tests/lod_vectors.rs` writes);
//! - `node --test tests/browser.test.mjs` in `web/`: Debian's chromium (playwright-core,
//!   SwiftShader WebGL2) against this build's `isovox serve`, started and killed by the script.
//!
//! They need Node.js 20+ and `/usr/bin/chromium` (`.ci/run` installs both); `web/node_modules`
//! is installed here if building the server did not already (`build.rs` runs `npm ci`).

use std::path::PathBuf;
use std::process::Command;
use std::sync::Mutex;

fn web() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../web")
}

/// Runs `program args` in `web/` and fails with its output unless it succeeds.
fn run(program: &str, args: &[&str], envs: &[(&str, &str)]) {
    let out = Command::new(program)
        .args(args)
        .envs(envs.iter().copied())
        .current_dir(web())
        .output()
        .unwrap_or_else(|e| panic!("cannot run {program} (Node.js 20+ is needed): {e}"));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    println!("{text}");
    assert!(
        out.status.success(),
        "{program} {} failed ({}):\n{text}",
        args.join(" "),
        out.status
    );
}

/// `npm ci` once, when `web/node_modules` is missing.
fn node_modules() {
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

#[test]
fn browser_tests() {
    node_modules();
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        std::path::Path::new(&chromium).exists(),
        "{chromium} is missing: install Debian's chromium (apt-get install chromium), as .ci/run does"
    );
    run(
        "node",
        &["--test", "--test-reporter=spec", "tests/browser.test.mjs"],
        &[("ISOVOX_BIN", env!("CARGO_BIN_EXE_isovox")), ("CHROMIUM", &chromium)],
    );
}
