#!/usr/bin/env bash
# Fuzzes the HTTP API from its own OpenAPI document with Schemathesis (pinned below, from PyPI,
# in a venv under bench-out/): `isovox serve` on a small generated scene, every operation with
# schema-valid and schema-invalid inputs, checking that no answer is a server error (5xx) and
# that every answer conforms to the response schemas the document declares; with
# FUZZ_CHECKS=all also that schema-valid requests are accepted and schema-invalid ones refused,
# and that status codes, content types and headers are the documented ones. Exits with
# Schemathesis's status (1 too when the server panicked); reports land in bench-out/fuzz-api/.
# `server/tests/it/api_document.rs` runs it with FUZZ_CHECKS=all and a few examples per
# operation, in two parts (FUZZ_PART) side by side.
#
#   bash scripts/fuzz-api.sh            # a release build, 500 examples per operation and phase
#   bash scripts/fuzz-api.sh --install  # only install Schemathesis (what .ci/run does)
#
# FUZZ_PART splits a run in two: `edit-coverage` is only the coverage phase of `POST .../edits`
# (its term grammar is recursive: that phase alone is about 45,000 cases, most of a run's time),
# on the served volume; `rest` is every other operation and phase. Unset: both in one run.
#
# Environment: FUZZ_EXAMPLES (test cases per operation and phase, default 500), FUZZ_SEED
# (default 1), FUZZ_CHECKS (default not_a_server_error,response_schema_conformance; `all` adds
# status-code, content-type, header and negative/positive data checks), ISOVOX_BIN (the binary
# to serve with; default: build the release one), FUZZ_OUT (reports and the server's log,
# default bench-out/fuzz-api). Extra arguments go to `schemathesis run` (for example `--report
# har` to keep every request and response: large, or `--max-time 600`, which makes fuzzing
# repeat until the time is spent).
set -euo pipefail
cd "$(dirname "$0")/.."

schemathesis_version=4.32.5
examples=${FUZZ_EXAMPLES:-500}
seed=${FUZZ_SEED:-1}
checks=${FUZZ_CHECKS:-not_a_server_error,response_schema_conformance}
part=${FUZZ_PART:-all}
case "$part" in
    all | rest | edit-coverage) ;;
    *) echo "FUZZ_PART is all, rest or edit-coverage, not $part" >&2; exit 2 ;;
esac
venv=bench-out/fuzz-venv
out=${FUZZ_OUT:-bench-out/fuzz-api}

mkdir -p bench-out "$out"
if ! "$venv/bin/schemathesis" --version 2>/dev/null | grep -q "version $schemathesis_version\$"; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --upgrade pip
    "$venv/bin/pip" install --quiet "schemathesis==$schemathesis_version"
fi
echo "schemathesis: $("$venv/bin/schemathesis" --version)"
if [ "${1:-}" = "--install" ]; then
    exit 0
fi

if [ -n "${ISOVOX_BIN:-}" ]; then
    bin=$ISOVOX_BIN
else
    cargo build --release --quiet -p isovox-server
    bin=./target/release/isovox
fi

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
# u16 voxels: the document's bounds on `iso` and `k` ([0, 65535], +-65535) are then this
# volume's own [L, H]. A u8 volume narrows them to 255, which no schema can state per volume
# (it answers 400 or 422 beyond; tests/tests/it/http_read.rs checks that).
"$bin" generate scene -o "$work/data/demo.vod" --dims 128,64,128 --brick 16 --type u16

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
# The edit operation is fuzzed on the served volume only: the coverage phase does not draw path
# parameters from the dictionaries below, and with a generated name every one of its cases would
# be answered 404 before the body is read (unknown names are fuzzed on every other operation,
# which share that answer). FUZZ_PART=rest turns its coverage phase off (an operation's phase
# settings override the global ones); FUZZ_PART=edit-coverage runs only that phase (below).
edit_operation='parameters = { "path.name" = "demo" }'
if [ "$part" = rest ]; then
    edit_operation+=$'\nphases.coverage.enabled = false'
fi
#
# The change feed never ends: its answers are read for 1 s (or 3 events: hello and the first of
# a backlog), not for the whole request timeout.
# Schema-valid requests may get two answers beyond Schemathesis's defaults: 410 once a compaction
# (also fuzzed) dropped the versions a since= names, an answer that depends on state as the 404
# and 409 it expects by default do; and 422 from the model upload, whose body is the bytes of an
# STL, OBJ, PLY or GLB file: which bytes form a watertight model no schema can state (the
# document says so), so random bytes are refused.
cat >"$work/schemathesis.toml" <<EOF
[cache]
directory = "$(realpath "$out")/cache"

[dictionaries.names]
values = ["demo"]
[dictionaries.coords]
values = [0, 1, 2, 3]
[dictionaries.levels]
values = [0, 1, 2, 3]
[dictionaries.hashes]
values = $hashes

[checks.positive_data_acceptance]
expected-statuses = ["2xx", "3xx", "401", "403", "404", "409", "410", "429", "5xx"]

[[operations]]
include-path = "/v1/volumes/{name}/events"
request-timeout = 1
max-stream-events = 3

[[operations]]
include-path = "/v1/meshes"
checks.positive_data_acceptance.expected-statuses = ["2xx", "3xx", "401", "403", "404", "409", "422", "429", "5xx"]

# An edit (and an undo, which applies edits again) over the server's voxel budget is a 422: the
# budget depends on the term's geometry, which no schema can state.
[[operations]]
include-path = "/v1/volumes/{name}/edits"
checks.positive_data_acceptance.expected-statuses = ["2xx", "3xx", "401", "403", "404", "409", "410", "422", "429", "5xx"]
$edit_operation

# A batch of more keys than the document's maxItems is refused as 413 Content Too Large (its
# documented answer: the answer would be too large), not 400.
[[operations]]
include-path = "/v1/volumes/{name}/batch"
checks.negative_data_rejection.expected-statuses = ["400", "401", "403", "404", "405", "406", "409", "413", "415", "422", "428", "429", "5xx"]

[[operations]]
include-path = "/v1/volumes/{name}/undo"
checks.positive_data_acceptance.expected-statuses = ["2xx", "3xx", "401", "403", "404", "409", "410", "422", "429", "5xx"]

[parameters]
"path.name" = { dictionary = "names", probability = 0.7 }
"path.level" = { dictionary = "levels", probability = 0.5 }
"path.x" = { dictionary = "coords", probability = 0.5 }
"path.y" = { dictionary = "coords", probability = 0.5 }
"path.z" = { dictionary = "coords", probability = 0.5 }
"path.hash" = { dictionary = "hashes", probability = 0.5 }
EOF
part_args=()
if [ "$part" = edit-coverage ]; then
    part_args=(--phases coverage --include-name "POST /v1/volumes/{name}/edits")
fi

# The write routes (edits, compaction, mesh uploads) are fuzzed with the write token the server
# created on first start, so their validation is reached, not only the 401.
token=$(awk '/^demo/ {print $2}' "$work/data/tokens")
status=0
# Schemathesis's `all` includes max_response_time (10 s), which cannot be excluded by name: `all`
# here is every other check. How fast a (debug, shared, loaded) machine answers says nothing
# about the document; the benchmarks measure speed.
if [ "$checks" = all ]; then
    checks=not_a_server_error,status_code_conformance,content_type_conformance
    checks+=,response_headers_conformance,response_schema_conformance,negative_data_rejection
    checks+=,positive_data_acceptance,missing_required_header,unsupported_method
    checks+=,allow_header_conformance,use_after_free,ensure_resource_availability,ignored_auth
    checks+=,object_level_authorization
fi
# One worker. Schemathesis's workers are threads, and Hypothesis raises and restores the
# interpreter-wide recursion limit around each example: with two threads, one thread's restore
# can land under the other's `ast.parse` (Hypothesis parses sources to describe filters), which
# then fails, and Python 3.11 reports that failure as "SystemError: AST constructor recursion
# depth mismatch" (CPython gh-106905). CI failed on it once. FUZZ_WORKERS overrides.
"$venv/bin/schemathesis" --config-file "$work/schemathesis.toml" run "$base/openapi.json" \
    --header "Authorization: Bearer $token" \
    --checks "$checks" \
    --max-examples "$examples" \
    --seed "$seed" \
    --workers "${FUZZ_WORKERS:-1}" \
    --request-timeout 30 \
    --report junit \
    --report-dir "$out" \
    --no-color \
    "${part_args[@]}" \
    "$@" || status=$?

if grep -q "panicked\|ERROR" "$out/server.log"; then
    echo "the server logged errors or panics (see $out/server.log):" >&2
    grep "panicked\|ERROR" "$out/server.log" | head -20 >&2
    if grep -q "panicked" "$out/server.log"; then
        status=1
    fi
fi
echo "schemathesis exited with $status; reports in $out/"
exit "$status"
