#!/usr/bin/env bash
# dilate at radius 8, 32, 64 and 200 on a 256^3 world, over HTTP against `isovox serve` (release
# build, default limits): the stored volume dilated in place (union with a dilate of itself) and
# a sphere of radius 40 dilated into it. Each edit runs on a fresh server and a fresh copy of the
# volume. Prints a Markdown table: HTTP status and wall time per edit.
#
# BEFORE=path/to/an/older/isovox runs that binary on the same data in the same run and prints
# its figures beside; an edit that has not answered within MAX_TIME seconds (default 240) is
# shown as "> MAX_TIME s" (its server is then killed). WORKLOADS="volume sphere" picks the rows.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet -p isovox-server --bin isovox
AFTER=./target/release/isovox
BEFORE=${BEFORE:-}
MAX_TIME=${MAX_TIME:-240}
TOKEN=bench-morph-0123456789abcdef
WORK=$(mktemp -d)
SERVER_PID=
cleanup() {
    [ -n "$SERVER_PID" ] && kill -9 "$SERVER_PID" 2>/dev/null || true
    rm -rf "$WORK"
}
trap cleanup EXIT

"$AFTER" generate world -o "$WORK/world.vod" --dims 256,256,256 >/dev/null

# Starts BIN on a fresh copy of the world; sets URL and SERVER_PID.
start() {
    local bin=$1
    rm -rf "$WORK/data" && mkdir "$WORK/data"
    cp "$WORK/world.vod" "$WORK/data/w.vod"
    # The previous server's log must not be read for this one's address.
    rm -f "$WORK/log"
    ISOVOX_WRITE_TOKEN=$TOKEN "$bin" serve --data "$WORK/data" --addr 127.0.0.1:0 \
        2>"$WORK/log" >/dev/null &
    SERVER_PID=$!
    for _ in $(seq 200); do
        URL=$(grep -o 'http://[0-9.:]*' "$WORK/log" 2>/dev/null | head -1 || true)
        [ -n "$URL" ] && return 0
        sleep 0.05
    done
    echo "the server did not start:" >&2
    cat "$WORK/log" >&2
    exit 1
}

stop() {
    kill -9 "$SERVER_PID" 2>/dev/null || true
    wait "$SERVER_PID" 2>/dev/null || true
    SERVER_PID=
}

# Prints "STATUS SECONDS" for one edit with BIN (or "- > MAX_TIME" when it does not answer).
run() {
    local bin=$1 body=$2 out
    start "$bin"
    if out=$(curl -s -o "$WORK/answer" -w '%{http_code} %{time_total}' --max-time "$MAX_TIME" \
        -H "Authorization: Bearer $TOKEN" -H 'Content-Type: application/json' \
        -d "$body" "$URL/v1/volumes/w/edits"); then
        echo "$out"
    else
        echo "- >$MAX_TIME"
    fi
    stop
}

edit() {
    local arg=$1 r=$2
    echo "{\"op\": \"union\", \"term\": {\"dilate\": {\"radius\": $r, \"arg\": $arg}}}"
}

VOLUME='{"volume": {"name": "w", "origin": [0, 0, 0]}}'
SPHERE='{"ellipsoid": {"center": [128, 128, 128], "radii": [40, 40, 40]}}'

echo "### dilate on a 256^3 world (brick 32, u8), one edit per fresh server, 2 cores"
echo
if [ -n "$BEFORE" ]; then
    echo "| argument | radius | before: status | before: s | after: status | after: s | speed-up |"
    echo "|---|---:|---:|---:|---:|---:|---:|"
else
    echo "| argument | radius | status | s |"
    echo "|---|---:|---:|---:|"
fi
for name in ${WORKLOADS:-volume sphere}; do
    if [ $name = volume ]; then arg=$VOLUME; else arg=$SPHERE; fi
    for r in 8 32 64 200; do
        read -r status secs <<<"$(run "$AFTER" "$(edit "$arg" "$r")")"
        if [ -n "$BEFORE" ]; then
            read -r bstatus bsecs <<<"$(run "$BEFORE" "$(edit "$arg" "$r")")"
            speedup=$(python3 -c "
import sys
before, after = sys.argv[1], sys.argv[2]
if after.startswith('>'):
    print('-')
else:
    bound = '>' if before.startswith('>') else ''
    print(f'{bound}{float(before.lstrip(\">\")) / float(after):.0f}x')
" "$bsecs" "$secs")
            echo "| $name | $r | $bstatus | $bsecs | $status | $secs | $speedup |"
        else
            echo "| $name | $r | $status | $secs |"
        fi
    done
done
