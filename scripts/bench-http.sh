#!/usr/bin/env bash
# Brick requests per second and latency with wrk (2 threads, 64 connections, random keys over a
# 512^3 world) against isovox serve, nginx serving the same bytes as static files
# (open_file_cache on), and a bare axum handler returning static bytes of the same size.
# Installs wrk and nginx from Debian's packages (never CI). Prints a Markdown table.
set -euo pipefail
cd "$(dirname "$0")/.."
command -v wrk >/dev/null && command -v nginx >/dev/null || { apt-get update -qq && apt-get install -y -qq wrk nginx; }
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench http --dir bench-out/http "$@"
