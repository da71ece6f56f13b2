#!/usr/bin/env bash
# Fuzzes the HTTP API from its own OpenAPI document with Schemathesis (from PyPI, in a venv under
# bench-out/; not run by CI): a release `isovox serve` on a small generated scene, every
# operation with schema-valid and schema-invalid inputs, checking that no answer is a server
# error (5xx) and that every answer conforms to the response schemas the document declares.
# Takes a few minutes. Exits with Schemathesis's status; reports land in bench-out/fuzz-api/.
#
# Environment: FUZZ_EXAMPLES (test cases per operation and phase, default 500), FUZZ_SEED
# (default 1), FUZZ_CHECKS (default not_a_server_error,response_schema_conformance; `all` adds
# status-code, content-type, header and negative/positive data checks). Extra arguments go to
# `schemathesis run` (for example `--report har` to keep every request and response: large, or
# `--max-time 600`, which makes fuzzing repeat until the time is spent).
set -euo pipefail
cd "$(dirname "$0")/.."

examples=${FUZZ_EXAMPLES:-500}
seed=${FUZZ_SEED:-1}
checks=${FUZZ_CHECKS:-not_a_server_error,response_schema_conformance}
venv=bench-out/fuzz-venv
out=bench-out/fuzz-api

mkdir -p bench-out "$out"
if [ ! -x "$venv/bin/schemathesis" ]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --upgrade pip
    "$venv/bin/pip" install --quiet schemathesis
fi
echo "schemathesis: $("$venv/bin/schemathesis" --version)"

cargo build --release --quiet -p isovox-server
bin=./target/release/isovox

work=$(mktemp -d)
server_pid=""
cleanup() {
    if [ -n "$server_pid" ] && kill -0 "$server_pid" 2>/dev/null; then
        kill "$server_pid" 2>/dev/null || true
        wait "$server_pid" 2>/dev/null || true
    fi
    rm -rf "$work"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

mkdir -p "$work/data"
"$bin" generate scene -o "$work/data/demo.vod" --dims 128,64,128 --brick 16

# A free port on the loopback interface.
port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
base="http://127.0.0.1:$port"
"$bin" serve --data "$work/data" --addr "127.0.0.1:$port" --edit-rate 100000 >"$out/server.log" 2>&1 &
server_pid=$!
for _ in $(seq 1 100); do
    if curl -fsS "$base/healthz" >/dev/null 2>&1; then
        break
    fi
    if ! kill -0 "$server_pid" 2>/dev/null; then
        echo "the server exited; its log:" >&2
        cat "$out/server.log" >&2
        exit 1
    fi
    sleep 0.1
done
curl -fsS "$base/healthz" >/dev/null

# Values that reach past the 404s: the served volume's name, brick coordinates inside its grid,
# and content hashes of real bricks (from its level-1 grid). Generated values still get their
# share, so unknown names, hashes and coordinates are fuzzed too.
hashes=$(curl -fsS "$base/v1/volumes/demo/levels/1" |
    python3 -c 'import json, sys; g = json.load(sys.stdin); print(json.dumps(sorted({b["hash"] for b in g["bricks"]})[:16]))')
cat >"$work/schemathesis.toml" <<EOF
[cache]
directory = "$PWD/$out/cache"

[dictionaries.names]
values = ["demo"]
[dictionaries.coords]
values = [0, 1, 2, 3]
[dictionaries.levels]
values = [0, 1, 2, 3]
[dictionaries.hashes]
values = $hashes

[parameters]
"path.name" = { dictionary = "names", probability = 0.7 }
"path.level" = { dictionary = "levels", probability = 0.5 }
"path.x" = { dictionary = "coords", probability = 0.5 }
"path.y" = { dictionary = "coords", probability = 0.5 }
"path.z" = { dictionary = "coords", probability = 0.5 }
"path.hash" = { dictionary = "hashes", probability = 0.5 }
EOF

# The write routes (edits, compaction, mesh uploads) are fuzzed with the write token the server
# created on first start, so their validation is reached, not only the 401.
token=$(awk '/^demo/ {print $2}' "$work/data/tokens")
status=0
"$venv/bin/schemathesis" --config-file "$work/schemathesis.toml" run "$base/openapi.json" \
    --header "Authorization: Bearer $token" \
    --checks "$checks" \
    --max-examples "$examples" \
    --seed "$seed" \
    --workers 2 \
    --request-timeout 30 \
    --report junit \
    --report-dir "$out" \
    --no-color \
    "$@" || status=$?

if grep -q "panicked\|ERROR" "$out/server.log"; then
    echo "the server logged errors or panics (see $out/server.log):" >&2
    grep "panicked\|ERROR" "$out/server.log" | head -20 >&2
fi
echo "schemathesis exited with $status; reports in $out/"
exit "$status"
