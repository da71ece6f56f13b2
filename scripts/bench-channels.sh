#!/usr/bin/env bash
# The channels' figures (docs/benchmarks.md, "Channels"): mode downsampling against tinybrain,
# label storage against compressed_segmentation + gzip, edits/s with a material channel against
# density alone. Installs the Python peers (pinned in scripts/bench-channels-requirements.txt)
# into bench-out/channels-venv; never run by CI.
# Usage: scripts/bench-channels.sh [isovox-bench channels flags: --size, --world, --runs, ...]
set -euo pipefail
cd "$(dirname "$0")/.."
venv=bench-out/channels-venv
[ -x $venv/bin/python ] || python3 -m venv $venv
$venv/bin/pip install -q --disable-pip-version-check -r scripts/bench-channels-requirements.txt
cargo build --release --quiet -p isovox-tools --bin isovox-bench
target/release/isovox-bench channels --python $venv/bin/python "$@"
