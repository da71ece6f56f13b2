#!/usr/bin/env bash
# ICVG: primitive sampling speed (the paper's 72^3 shapes) and edit latency (1,000 carves of a
# radius-16 ellipsoid into 256^3-class and 1024^3-class worlds). Prints Markdown tables.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench icvg --dir bench-out "$@"
