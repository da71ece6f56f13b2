//! The API document against the server that serves it: Schemathesis (pinned by
//! `scripts/fuzz-api.sh`, installed by `.ci/run`) drives this build's `isovox serve` from
//! `/openapi.json` with every check (`FUZZ_CHECKS=all`): every operation, the coverage phase
//! (each bound, enum, pattern and required field just inside and just outside), a few random
//! examples per operation and the stateful phase. It fails on any 5xx, any answer outside the
//! documented statuses, types, headers and schemas, any schema-valid request refused and any
//! schema-invalid one accepted, and on a panic in the server's log. The script's longer run
//! (500 examples per operation and phase by default) is the same with more cases.
//!
//! The run is split in two tests that run side by side (the script's `FUZZ_PART`): the coverage
//! phase of the edit operation, whose recursive term grammar makes most of the cases, and
//! everything else. Together they are the whole run.

use std::path::PathBuf;
use std::process::Command;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Runs `scripts/fuzz-api.sh` with every check and 5 examples per operation on the part `part`
/// of the run, asserts it passed, and returns its summary's "Selected:" and "Tested:" fields
/// and its output.
fn schemathesis(part: &str) -> (String, String, String) {
    let venv = repo().join("bench-out/fuzz-venv/bin/schemathesis");
    assert!(
        venv.exists(),
        "{} is missing: run `bash scripts/fuzz-api.sh --install` (as .ci/run does)",
        venv.display()
    );
    let reports = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let out = Command::new("bash")
        .arg(repo().join("scripts/fuzz-api.sh"))
        .env("ISOVOX_BIN", env!("CARGO_BIN_EXE_isovox"))
        .env("FUZZ_CHECKS", "all")
        .env("FUZZ_EXAMPLES", "5")
        .env("FUZZ_PART", part)
        .env("FUZZ_OUT", reports.path())
        .env_remove("ISOVOX_LOG")
        .output()
        .unwrap_or_else(|e| panic!("cannot run scripts/fuzz-api.sh: {e}"));
    let text = crate::common::printed_output(&out);
    assert!(
        out.status.success(),
        "Schemathesis found the document and the server at odds ({}):\n{text}",
        out.status
    );
    // The run ran cases and all passed: the summary says so, not just the exit status.
    let cases = text
        .lines()
        .skip_while(|l| l.trim() != "Test cases:")
        .nth(1)
        .unwrap_or_default();
    println!("cases: {}", cases.trim());
    assert!(
        cases.contains(" passed") && !cases.contains("fail"),
        "test cases: {cases:?}\n{text}"
    );
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.trim().strip_prefix(name))
            .map(|v| v.trim().to_string())
            .unwrap_or_else(|| panic!("no {name:?} in the summary:\n{text}"))
    };
    (field("Selected:"), field("Tested:"), text)
}

#[test]
fn schemathesis_finds_the_document_and_the_server_in_agreement() {
    let (selected, tested, text) = schemathesis("rest");
    // Every operation the document lists was reached.
    let (chosen, listed) = selected.split_once('/').unwrap_or_default();
    assert!(
        chosen == listed && listed == tested && tested != "0",
        "selected {selected}, tested {tested}:\n{text}"
    );
}

#[test]
fn schemathesis_finds_the_edit_grammar_and_the_server_in_agreement() {
    let (selected, tested, text) = schemathesis("edit-coverage");
    // The one operation, out of all the document lists, and only its coverage phase.
    assert!(
        selected.starts_with("1/") && tested == "1",
        "selected {selected}, tested {tested}:\n{text}"
    );
    let phases: Vec<&str> = text
        .lines()
        .skip_while(|l| l.trim() != "Test Phases:")
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .map(str::trim)
        .collect();
    assert!(
        phases
            .iter()
            .any(|p| p.ends_with("Coverage") && p.starts_with('✅')),
        "the coverage phase did not run and pass: {phases:?}\n{text}"
    );
}
