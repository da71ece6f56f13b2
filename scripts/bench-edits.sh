#!/usr/bin/env bash
# Shared editing over HTTP on a 1024^3 world: edit throughput and latency under 8 concurrent
# editors with and without group commit (--groups 1,32; 3 runs each, alternating), one editor's
# latency, propagation to 100 change-feed subscribers, brick reads (wrk) with and without edits.
# Installs wrk from Debian's packages (never CI). Prints Markdown tables.
set -euo pipefail
cd "$(dirname "$0")/.."
command -v wrk >/dev/null || { apt-get update -qq && apt-get install -y -qq wrk; }
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench edits --dir bench-out "$@"
