#!/usr/bin/env bash
# The "Many viewers" figures of docs/benchmarks.md: isovox-load against isovox serve on a large
# world, the streamers' octree descent (the default) against streaming without it (--no-descent), runs
# alternating in one server's life so that both see the same warm or cold caches.
#
#   scripts/bench-load.sh                 # DIMS=2048 (a 2048^3 world, brick 16), 50 viewers, 20 s
#   DIMS=512 VIEWERS=10 DURATION=5 scripts/bench-load.sh   # a quick check of the script
#   WORLD=path/to/world.vod scripts/bench-load.sh          # an existing world (copied, not edited)
#
# For each run it prints the load tester's report (routes with bytes, first tile per viewer,
# grid regions asked and those caused by edits) and keeps its JSON in $OUT.
set -euo pipefail
cd "$(dirname "$0")/.."
DIMS=${DIMS:-2048}
VIEWERS=${VIEWERS:-50}
DURATION=${DURATION:-20}
OUT=${OUT:-bench-out/load}
WORK=$(mktemp -d /tmp/isovox-bench-load.XXXXXX)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$WORK"' EXIT
trap 'status=$?; echo "bench-load.sh: line $LINENO: \`$BASH_COMMAND\` exited with status $status" >&2' ERR
mkdir -p "$OUT"

CARGO_BUILD_JOBS=2 cargo build --release -q -p isovox-server --bin isovox -p isovox-tools --bin isovox-load
BIN=${CARGO_TARGET_DIR:-target}/release

mkdir -p "$WORK/data"
if [ -n "${WORLD:-}" ]; then
  cp "$WORLD" "$WORK/data/w.vod"
else
  echo "generating a ${DIMS}^3 world (brick 16)"
  $BIN/isovox generate world -o "$WORK/data/w.vod" --dims "$DIMS,$DIMS,$DIMS" --brick 16 >/dev/null
fi
TOKEN=bench-load-0123456789abcdef
echo "t $TOKEN write" > "$WORK/tokens"
PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
$BIN/isovox serve --data "$WORK/data" --token-file "$WORK/tokens" --addr "127.0.0.1:$PORT" \
  > "$WORK/serve.log" 2>&1 &
SERVER=$!
until curl -sf "http://127.0.0.1:$PORT/v1/volumes/w" >/dev/null; do sleep 0.2; done

# CPU seconds (user + system) process $1 has used so far.
cpu_seconds() { awk -v hz="$(getconf CLK_TCK)" '{printf "%.1f", ($14 + $15) / hz}' "/proc/$1/stat"; }

# run NAME ARGS...: one isovox-load run, its report on stdout and in $OUT/NAME.json, then the CPU
# time the server and the load tester used during it (they share the machine's cores).
run() {
  local name=$1
  shift
  echo
  echo "### $name: isovox-load --viewers $VIEWERS --duration $DURATION $*"
  local before
  before=$(cpu_seconds "$SERVER")
  # `times` in the subshell: the CPU time of its one child, the load tester.
  ( $BIN/isovox-load --url "http://127.0.0.1:$PORT" --volume w --viewers "$VIEWERS" \
      --duration "$DURATION" --token "$TOKEN" --json "$OUT/$name.json" "$@" || true
    times > "$WORK/load-cpu" )
  echo "CPU during the run: server $(python3 -c "print(round($(cpu_seconds "$SERVER") - $before, 1))") s," \
    "load tester $(python3 -c "import re,sys; print(round(sum(int(m)*60+float(s) for m,s in re.findall(r'(\d+)m([\d.]+)s', sys.argv[1])), 1))" "$(tail -1 "$WORK/load-cpu")") s (user + system)"
}

# Viewers only, bricks then meshes: without the descent ("flat"), with, with, without; for
# meshes also, inside each pair, every tile asked for, empty ones included (--fetch-empty-tiles).
every() { if [ "$1" = meshes ]; then run "meshes-every-$2" --tiles meshes --no-descent --fetch-empty-tiles; fi; }
for tiles in bricks meshes; do
  run "$tiles-flat-1" --tiles "$tiles" --no-descent
  every "$tiles" 1
  run "$tiles-descent-1" --tiles "$tiles"
  run "$tiles-descent-2" --tiles "$tiles"
  every "$tiles" 2
  run "$tiles-flat-2" --tiles "$tiles" --no-descent
done
# With 2 editors at 1 edit/s each: grid regions caused by edits.
run "edits-flat" --tiles bricks --editors 2 --edit-rate 1 --no-descent
run "edits-descent" --tiles bricks --editors 2 --edit-rate 1
run "edits-meshes-descent" --tiles meshes --editors 2 --edit-rate 1
