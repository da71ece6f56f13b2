#!/usr/bin/env bash
# Marching-cubes throughput next to VTK's vtkFlyingEdges3D and scikit-image's marching_cubes
# (installed from PyPI into a venv under bench-out/, not by CI), on the 512^3 ellipsoid and world
# and the MNI152 T1 scan, the current kernel and the previous one taking turns; plus the
# thesis's Tables 6-8 (threads, levels, adaptive LOD). Prints Markdown tables.
# Arguments go to `isovox-bench mesh` (`--kernels-only`: the first table alone).
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p bench-out
[ -x bench-out/venv/bin/python3 ] || python3 -m venv bench-out/venv
bench-out/venv/bin/python3 -m pip install --quiet vtk scikit-image numpy
# The benchmark runs the peers with `python3`: the venv's.
export PATH="$PWD/bench-out/venv/bin:$PATH"
[ -f bench-out/mni152_t1.raw ] || python3 scripts/mni152_to_raw.py bench-out/mni152_t1.raw
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench mesh --dir bench-out --peers --mri bench-out/mni152_t1.raw "$@"
