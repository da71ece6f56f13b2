#!/usr/bin/env bash
# The formats' figures (docs/benchmarks.md, "Formats"):
# 1. tensorstore's zarr3 driver reading whole levels through isovox serve's OME-Zarr view,
#    against the same chunks exported (isovox export --format zarr) and served as static files
#    by nginx; the same volume, the same client, rounds alternating, in one run.
# 2. isovox import throughput (MB/s of input voxels) for each format, from files written by the
#    field's own writers (zarr-python, cloud-volume, nibabel, tifffile).
# Installs nginx from Debian's packages and the pinned Python clients (tests/python/.venv);
# never run by CI. Usage: scripts/bench-formats.sh [--dims X,Y,Z] [--rounds N]
set -euo pipefail
cd "$(dirname "$0")/.."
command -v nginx >/dev/null || [ -x /usr/sbin/nginx ] || { apt-get update -qq && apt-get install -y -qq nginx; }
[ -x tests/python/.venv/bin/python ] || python3 -m venv tests/python/.venv
tests/python/.venv/bin/pip install -q --disable-pip-version-check -r tests/python/requirements.txt
cargo build --release --quiet -p isovox-server

dims=512,512,512
rounds=5
while [ $# -gt 0 ]; do
  case "$1" in
    --dims) dims=$2; shift 2 ;;
    --rounds) rounds=$2; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done

out=$(pwd)/bench-out/formats
rm -rf "$out" && mkdir -p "$out/data" "$out/static/v1/volumes/world"
bin=$(pwd)/target/release/isovox
$bin generate world -o "$out/data/world.vod" --dims "$dims" --brick 32 >/dev/null
$bin export "$out/data/world.vod" -o "$out/static/v1/volumes/world/zarr" --format zarr

isovox_port=17471
nginx_port=17472
# Each server in a session of its own, as a service manager would run it: nginx daemonizes into
# one, and with the kernel's autogroup scheduling (on by default) a server left in this script's
# session shares the client's CPU share instead of having its own. Measured: tensorstore's mean
# time to first byte from isovox was 408 us in the client's session against 88 us from nginx,
# 176 us against 117 us in its own.
setsid $bin serve --data "$out/data" --addr 127.0.0.1:$isovox_port 2>"$out/isovox.log" </dev/null &
isovox_pid=$!
cat >"$out/nginx.conf" <<EOF
worker_processes 2;
pid $out/nginx.pid;
error_log $out/nginx-error.log;
events { worker_connections 1024; }
http {
  access_log off;
  # Absent chunks (a third of a level's) are 404s by design: not errors worth a log line each
  # (the benchmark's rounds grew it by hundreds of MB), and a log write per request is work
  # the comparison should not charge nginx for.
  log_not_found off;
  sendfile on;
  tcp_nopush on;
  keepalive_requests 100000;
  open_file_cache max=100000 inactive=60s;
  open_file_cache_valid 60s;
  types { application/json json; }
  default_type application/octet-stream;
  client_body_temp_path $out/nginx-tmp;
  proxy_temp_path $out/nginx-tmp;
  fastcgi_temp_path $out/nginx-tmp;
  uwsgi_temp_path $out/nginx-tmp;
  scgi_temp_path $out/nginx-tmp;
  server {
    listen 127.0.0.1:$nginx_port;
    root $out/static;
  }
}
EOF
mkdir -p "$out/nginx-tmp"
nginx -c "$out/nginx.conf" -p "$out"
trap 'kill $isovox_pid 2>/dev/null; kill $(cat "$out/nginx.pid") 2>/dev/null' EXIT
sleep 1

reads=(--isovox "http://127.0.0.1:$isovox_port/v1/volumes/world/zarr"
  --nginx "http://127.0.0.1:$nginx_port/v1/volumes/world/zarr"
  --rounds "$rounds" --bin "$bin" --work "$out/imports" --raw-from "$out/data/world.vod")
tests/python/.venv/bin/python scripts/bench_formats.py "${reads[@]}"

# The same reads with the servers on the last core and the client on the others, as when they
# run on different machines: sharing two cores, the client's CPU (zstd decoding, and opening
# and closing connections when tensorstore's small per-thread pools overflow) decides as much
# as the server's.
if [ "$(nproc)" -ge 2 ]; then
  last=$(( $(nproc) - 1 ))
  taskset -a -p -c "$last" "$isovox_pid" >/dev/null
  for p in $(cat "$out/nginx.pid") $(pgrep -P "$(cat "$out/nginx.pid")"); do taskset -a -p -c "$last" "$p" >/dev/null; done
  taskset -c "0-$(( last - 1 ))" tests/python/.venv/bin/python scripts/bench_formats.py "${reads[@]}" \
    --reads-only --placement "servers on core $last, the client on the others"
fi
