#!/usr/bin/env bash
# What checking stored payloads costs on the path that sends them as they are: brick requests
# per second with wrk (2 threads, 64 connections, random keys over a 512^3 world, lz4 bricks,
# `Accept: application/x-lz4`, the same request `isovox bench http` makes for its lz4 row),
# against a baseline built in target/bench-verify/, each server on a world it generated itself.
# The two servers take turns, ROUNDS times, so that a machine whose load drifts slows both
# alike; prints each run, the medians and the ratio. Installs wrk from Debian's packages (never
# CI). Baselines:
#   BASELINE=unchecked (default)  this commit with the checksum comparison taken out (the payload
#                                 is not hashed): the cost of the check alone
#   BASELINE=before               the last commit before payload checksums (8f9f679): the cost of
#                                 everything that changed since on this path
#
#   scripts/bench-verify.sh             # ROUNDS=5, SECONDS_PER_RUN=10
set -euo pipefail
cd "$(dirname "$0")/.."
ROUNDS=${ROUNDS:-5}
SECONDS_PER_RUN=${SECONDS_PER_RUN:-10}
BASELINE=${BASELINE:-unchecked}
OLD_SRC=target/bench-verify/$BASELINE-src
OLD_TARGET=target/bench-verify/target
WORK=$(mktemp -d /tmp/isovox-bench-verify.XXXXXX)
SERVERS=()
trap 'kill "${SERVERS[@]}" 2>/dev/null || true; rm -rf "$WORK"' EXIT

command -v wrk >/dev/null || { apt-get update -qq && apt-get install -y -qq wrk; }
CARGO_BUILD_JOBS=${CARGO_BUILD_JOBS:-2} cargo build --release -q -p isovox-server --bin isovox
echo "building the baseline ($BASELINE) in $OLD_SRC"
rm -rf "$OLD_SRC"
mkdir -p "$OLD_SRC"
case "$BASELINE" in
  unchecked)
    # The working tree as it is, with the one line that hashes a payload before it is sent as
    # it is replaced by "the checksum matches".
    git ls-files -z | xargs -0 tar -c | tar -x -C "$OLD_SRC"
    check='let computed = payload_check(payload);'
    grep -qF "$check" "$OLD_SRC/server/src/store/vod2/bricks.rs" \
      || { echo "server/src/store/vod2/bricks.rs no longer has \`$check\`: update this script" >&2; exit 1; }
    sed -i "s/$check/let computed = stored;/" "$OLD_SRC/server/src/store/vod2/bricks.rs" ;;
  before) git archive 8f9f67919b8c4b7f08cf47534a1dbf3f3524939c | tar -x -C "$OLD_SRC" ;;
  *) echo "BASELINE is unchecked or before, not $BASELINE" >&2; exit 2 ;;
esac
(cd "$OLD_SRC" && CARGO_TARGET_DIR="$PWD/../target" CARGO_BUILD_JOBS=${CARGO_BUILD_JOBS:-2} \
  cargo build --release -q -p isovox-server --bin isovox)

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
# start NAME BINARY: generates the world with that binary and serves it; sets PORT. (Not called
# in a command substitution: a server started in that subshell would escape the EXIT trap.)
start() {
  mkdir -p "$WORK/$1"
  "$2" generate world -o "$WORK/$1/world.vod" --dims 512,512,512 --brick 32 --codec lz4 >/dev/null
  PORT=$(free_port)
  "$2" serve --data "$WORK/$1" --addr "127.0.0.1:$PORT" > "$WORK/$1.log" 2>&1 &
  SERVERS+=($!)
  until curl -sf "http://127.0.0.1:$PORT/v1/volumes" >/dev/null; do sleep 0.2; done
}
start after target/release/isovox
NEW_PORT=$PORT
start "$BASELINE" "$OLD_TARGET/release/isovox"
OLD_PORT=$PORT

cat > "$WORK/lz4.lua" <<'EOF'
wrk.headers["Accept"] = "application/x-lz4"
math.randomseed(42)
request = function()
  local x, y, z = math.random(0, 15), math.random(0, 15), math.random(0, 15)
  return wrk.format("GET", "/v1/volumes/world/bricks/0/" .. x .. "/" .. y .. "/" .. z)
end
EOF
rps() { # rps PORT -> requests/s of one wrk run (fails on any non-2xx answer)
  local out
  out=$(wrk -t2 -c64 -d"${SECONDS_PER_RUN}s" -s "$WORK/lz4.lua" "http://127.0.0.1:$1")
  if grep -q "Non-2xx\|Socket errors" <<<"$out"; then
    echo "wrk saw errors against port $1:" >&2
    echo "$out" >&2
    return 1
  fi
  awk '/Requests\/sec:/ {print $2}' <<<"$out"
}
# One warm-up run each (page cache, the servers' caches).
rps "$NEW_PORT" >/dev/null
rps "$OLD_PORT" >/dev/null
after=(); before=()
for round in $(seq "$ROUNDS"); do
  a=$(rps "$NEW_PORT"); b=$(rps "$OLD_PORT")
  after+=("$a"); before+=("$b")
  echo "round $round: this build $a requests/s, $BASELINE $b requests/s"
done
python3 - "${after[*]}" "${before[*]}" "$BASELINE" <<'EOF'
import statistics, sys
after = [float(v) for v in sys.argv[1].split()]
before = [float(v) for v in sys.argv[2].split()]
a, b = statistics.median(after), statistics.median(before)
print(f"median: this build {a:.0f} requests/s, {sys.argv[3]} {b:.0f} requests/s; "
      f"this / {sys.argv[3]} = {a / b:.3f} (overhead {100 * (1 - a / b):.1f}%)")
EOF
