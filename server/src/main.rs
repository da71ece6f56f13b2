//! The `isovox` command-line tool (`docs/cli.md`).

mod cli;

use clap::Parser;
use cli::{run, Cli};
use std::process::ExitCode;

// The server allocates small, short-lived buffers per request (headers, paths, response
// parts) from every worker thread; mimalloc's thread-local free lists serve that pattern with
// less locking than glibc's malloc.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("ISOVOX_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        // The reader of our output has gone (`isovox inspect f.vod | head -1`): it took what
        // it wanted; nothing failed.
        Err(e) if cli::is_broken_pipe(&e) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
