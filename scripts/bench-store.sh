#!/usr/bin/env bash
# Reproduces the thesis's Tables 3-5 (sizes, compression, load time) plus import throughput and
# open time, on generated data and on a real MRI scan (the MNI152 T1 template from nilearn's
# wheel on PyPI). Prints Markdown tables. Takes a few minutes; needs ~1 GB of disk in bench-out/.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p bench-out
[ -f bench-out/mni152_t1.raw ] || python3 scripts/mni152_to_raw.py bench-out/mni152_t1.raw
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench store --dir bench-out --mri bench-out/mni152_t1.raw --mri-dims 197,233,189 "$@"
