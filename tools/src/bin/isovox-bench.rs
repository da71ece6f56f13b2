//! `isovox-bench`: the benchmarks behind the figures in docs/benchmarks.md (`docs/cli.md`).

use clap::Parser;
use isovox_tools::bench::{run, BenchCommand};
use std::process::ExitCode;

// As in the `isovox` binary, so the servers benchmarked in-process allocate as it does.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Benchmarks that print Markdown tables next to the papers' figures and the peers'.
#[derive(Debug, Parser)]
#[command(name = "isovox-bench", version, about)]
struct Cli {
    #[command(subcommand)]
    command: BenchCommand,
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("ISOVOX_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    // The benchmarks' HTTP clients: rustls with ring (see `isovox_server::client_tls`).
    isovox_server::client_tls::install_provider();
    match run(Cli::parse().command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
