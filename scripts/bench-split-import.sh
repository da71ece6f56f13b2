#!/usr/bin/env bash
# The split-import figures of docs/scaling.md: a DIMS^3 world imported into moto's S3 on loopback
# (scripts/s3-server.py) by one process, and by 4 concurrent `--part I/4` processes plus the
# `--finish`, from RAW and from OME-Zarr; every level of the two volumes is compared.
#
#   scripts/bench-split-import.sh              # DIMS=512
#   PROFILE=dev DIMS=128 scripts/bench-split-import.sh   # a quick check of the script
set -euo pipefail
cd "$(dirname "$0")/.."
DIMS=${DIMS:-512}
WORK=${WORK:-$(mktemp -d /tmp/isovox-bench-split.XXXXXX)}
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$WORK"' EXIT

if ! target/s3-venv/bin/python -c 'import moto.server' 2>/dev/null; then
  python3 -m venv target/s3-venv
  target/s3-venv/bin/pip install -q 'moto[server]==5.2.5'
fi
PROFILE=${PROFILE:-release}
CARGO_BUILD_JOBS=2 cargo build --profile "$PROFILE" -q -p isovox-server --bin isovox
I=$PWD/target/$([ "$PROFILE" = dev ] && echo debug || echo "$PROFILE")/isovox

PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
target/s3-venv/bin/python scripts/s3-server.py "$PORT" isovox-split > "$WORK/s3.log" 2>&1 &
until grep -q ready "$WORK/s3.log"; do sleep 0.2; done
export AWS_ENDPOINT=http://127.0.0.1:$PORT AWS_ACCESS_KEY_ID=isovox AWS_SECRET_ACCESS_KEY=isovox-secret \
  AWS_REGION=us-east-1 AWS_ALLOW_HTTP=true
cd "$WORK"
$I generate world -o w.vod --dims "$DIMS,$DIMS,$DIMS" >/dev/null
$I export w.vod -o w.raw >/dev/null
$I export w.vod --format zarr -o w.zarr >/dev/null
now() { date +%s.%N; }
secs() { echo "$2 - $1" | bc; }
run=0
for input in "w.raw --dims $DIMS,$DIMS,$DIMS --type u8" "w.zarr"; do
  run=$((run + 1))
  B=s3://isovox-split/run$run
  # shellcheck disable=SC2086  # the input's arguments are words
  {
    t0=$(now); $I import $input -o "$B/single" >/dev/null; t1=$(now)
    pids=""
    for i in 0 1 2 3; do $I import $input -o "$B/split" --part "$i/4" >/dev/null 2>&1 & pids="$pids $!"; done
    # shellcheck disable=SC2086
    wait $pids
    t2=$(now); $I import --finish -o "$B/split" >/dev/null 2>&1; t3=$(now)
  }
  levels=$($I inspect w.vod --json | python3 -c 'import json,sys; print(len(json.load(sys.stdin)["levels"]))')
  for l in $(seq 0 $((levels - 1))); do
    $I export "$B/single" -o s.raw --level "$l" >/dev/null
    $I export "$B/split" -o p.raw --level "$l" >/dev/null
    cmp -s s.raw p.raw || { echo "level $l differs" >&2; exit 1; }
  done
  echo "${input%% *}: single import $(secs "$t0" "$t1") s; 4 parts $(secs "$t1" "$t2") s + finish $(secs "$t2" "$t3") s; levels 0-$((levels - 1)) equal"
done
