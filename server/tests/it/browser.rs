//! The viewer's pages in Debian's chromium (playwright-core, SwiftShader WebGL2), each test file
//! against this build's `isovox serve`, which the script starts and kills:
//! `web/tests/browser.test.mjs` (one viewer: streaming, drawing, editing, the panels) and
//! `web/tests/people.test.mjs` (two users' pages: each other's names, cursors and undo).
//!
//! One test runs both files, one after the other (`--test-concurrency=1`): each keeps chromium
//! on SwiftShader busy, and two at once would share the cores with each other rather than with
//! the rest of the suite. It is over a minute of work on its own (67 s alone), so its module
//! sorts near the start (libtest starts tests in the order of their names) and it runs beside
//! the other tests instead of after them. It needs `/usr/bin/chromium` (`.ci/run` installs it).

use crate::web::{node_modules, run};

#[test]
fn the_viewer_and_two_users_editing_together_in_chromium() {
    node_modules();
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        std::path::Path::new(&chromium).exists(),
        "{chromium} is missing: install Debian's chromium (apt-get install chromium), as .ci/run does"
    );
    run(
        "node",
        &[
            "--test",
            "--test-concurrency=1",
            "--test-reporter=spec",
            "tests/browser.test.mjs",
            "tests/people.test.mjs",
        ],
        &[
            ("ISOVOX_BIN", env!("CARGO_BIN_EXE_isovox")),
            ("CHROMIUM", &chromium),
        ],
    );
}
