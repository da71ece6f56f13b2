#!/usr/bin/env bash
# The server's resident memory (RssAnon, beyond the page cache) while a client walks every brick
# of a 2048^3 world once in random order. Generates the world on first run. Prints a table.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench memory --dir bench-out "$@"
