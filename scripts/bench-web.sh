#!/usr/bin/env bash
# The web viewer's cold load (web/bench/load.mjs): headless Chromium (Debian's, SwiftShader)
# loads the demo world from an empty cache over HTTP/1.1 and over HTTP/2 with TLS (a
# self-signed certificate made here), and reports time to first frame, time until every tile
# the camera needs is on screen, requests and bytes. Goals: first frame under 1 s, complete
# under 3 s on loopback.
#
# Then (web/bench/live.mjs) two pages on one server, default view and a close one (its camera is
# CLOSE in live.mjs), over HTTP/1.1 and over HTTP/2 with TLS: the close view's cold load (in
# view, complete, triangles, bytes), and 50 edits sent by page A, each timed to the first frame
# of page B that shows it (p50, p99), split into server, feed, fetch, decode and draw. Goals: p50
# under 150 ms, p99 under 400 ms, the close view complete under 5 s.
#
#   scripts/bench-web.sh [--runs N] [--width W --height H] [--screenshot docs/viewer.png]
#   EDITS=50 LIVE=only|no scripts/bench-web.sh    (only the live part, or none of it)
#   PROTOCOLS="h1 h2" scripts/bench-web.sh        (the live part's protocols: h1, h2 or both)
set -euo pipefail
cd "$(dirname "$0")/.."

command -v chromium >/dev/null || { apt-get update -qq && apt-get install -y -qq chromium >/dev/null; }
command -v openssl >/dev/null || { apt-get update -qq && apt-get install -y -qq openssl >/dev/null; }
(cd web && [ -d node_modules ] || npm ci --no-audit --no-fund)
cargo build --release -p isovox-server --bin isovox

tls=$(mktemp -d)
trap 'rm -rf "$tls"' EXIT
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 2 \
  -subj /CN=127.0.0.1 -addext "subjectAltName=IP:127.0.0.1" \
  -keyout "$tls/key.pem" -out "$tls/cert.pem" 2>/dev/null

if [ "${LIVE:-}" != only ]; then
  node web/bench/load.mjs --bin "$PWD/target/release/isovox" --cert "$tls/cert.pem" --key "$tls/key.pem" "$@"
fi
if [ "${LIVE:-}" != no ]; then
  for protocol in ${PROTOCOLS:-h1 h2}; do
    tls_args=()
    [ "$protocol" = h2 ] && tls_args=(--cert "$tls/cert.pem" --key "$tls/key.pem")
    node web/bench/live.mjs --bin "$PWD/target/release/isovox" --edits "${EDITS:-50}" "${tls_args[@]}"
  done
fi
