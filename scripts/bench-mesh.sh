#!/usr/bin/env bash
# Marching-cubes throughput next to VTK's vtkFlyingEdges3D and scikit-image's marching_cubes
# (installed from PyPI here, not by CI), on the 512^3 ellipsoid and world and the MNI152 T1 scan;
# plus the thesis's Tables 6-8 (threads, levels, adaptive LOD). Prints Markdown tables.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p bench-out
python3 -m pip install --quiet vtk scikit-image numpy
[ -f bench-out/mni152_t1.raw ] || python3 scripts/mni152_to_raw.py bench-out/mni152_t1.raw
cargo build --release --quiet -p isovox-server -p isovox-tools
./target/release/isovox-bench mesh --dir bench-out --peers --mri bench-out/mni152_t1.raw "$@"
