#!/usr/bin/env bash
# Random cold mesh tiles of a 1024^3 world from 64, then 1,000 connections, each run against a
# fresh release `isovox serve`: tiles/s, 503s, p50/p99, the server's peak resident memory
# (VmHWM) and most threads, next to the bound docs/limits.md states. Generates the world on
# first run (bench-out/). Options: isovox-bench cold-tiles --help (e.g. --size 512, --tiles N,
# --cpu-queue N, --isovox OLD_BUILD). Prints a Markdown table.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench cold-tiles --dir bench-out "$@"
