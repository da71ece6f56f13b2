#!/usr/bin/env bash
# The figures of docs/scaling.md: Isovox on an object store (moto's S3 on loopback, served by
# scripts/s3-server.py), replicas, and nginx in front.
#
#   scripts/bench-scaling.sh            # DIMS=2048 (a 2048^3 world, brick 16); DIMS=512 is quicker
#   PROFILE=dev DIMS=256 scripts/bench-scaling.sh   # a quick check of the script, no figures
#   EDITS_ONLY=1 DIMS=512 scripts/bench-scaling.sh  # up to the edit figures, without nginx and the load
#
# Prints: the cold start of a replica (until it serves the volume's metadata) and what it fetched
# doing so; range requests and bytes fetched per cold brick; the delay from an acknowledged edit
# on one replica to its event on another (p50/p99); edits per second with writers on two
# replicas; and, during a streaming load from isovox-load (50 viewers, bricks), errors and each
# viewer's first tile (of any kind, and the first that draws) on two cold replicas, then through
# nginx in front of both and against one alone: the share of requests nginx answers without
# reaching a replica, the load's throughput both ways, and what the replicas answered on the
# level route; last, 50 viewers streaming mesh tiles through nginx twice: with nothing of them
# cached anywhere, then again with nginx holding what the first run fetched.
set -euo pipefail
cd "$(dirname "$0")/.."
DIMS=${DIMS:-2048}
WORK=${WORK:-$(mktemp -d /tmp/isovox-bench-scaling.XXXXXX)}
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$WORK"' EXIT
# A failing command stops the script (set -e); say which, so that no stage ends in silence.
trap 'status=$?; echo "bench-scaling.sh: line $LINENO: \`$BASH_COMMAND\` exited with status $status" >&2' ERR

if ! target/s3-venv/bin/python -c 'import moto.server' 2>/dev/null; then
  python3 -m venv target/s3-venv
  target/s3-venv/bin/pip install -q 'moto[server]==5.2.5'
fi
command -v nginx >/dev/null || { apt-get update -qq && apt-get install -y -qq nginx >/dev/null; }
PROFILE=${PROFILE:-release}
CARGO_BUILD_JOBS=2 cargo build --profile "$PROFILE" -q -p isovox-server --bin isovox -p isovox-tools --bin isovox-load
BIN=target/$([ "$PROFILE" = dev ] && echo debug || echo "$PROFILE")

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
S3_PORT=$(free_port)
target/s3-venv/bin/python scripts/s3-server.py "$S3_PORT" isovox-bench > "$WORK/s3.log" 2>&1 &
until grep -q ready "$WORK/s3.log"; do sleep 0.2; done
export AWS_ENDPOINT=http://127.0.0.1:$S3_PORT AWS_ACCESS_KEY_ID=isovox AWS_SECRET_ACCESS_KEY=isovox-secret \
  AWS_REGION=us-east-1 AWS_ALLOW_HTTP=true
STORE=s3://isovox-bench/vols

echo "generating a ${DIMS}^3 world (brick 16) and importing it into the store"
$BIN/isovox generate world -o "$WORK/w.vod" --dims "$DIMS,$DIMS,$DIMS" --brick 16 >/dev/null
$BIN/isovox import "$WORK/w.vod" -o "$STORE/w"
rm -f "$WORK/w.vod"

TOKEN=bench-scaling-0123456789
echo "t $TOKEN write" > "$WORK/tokens"
replica() { # replica NAME PORT
  mkdir -p "$WORK/$1"
  $BIN/isovox serve --store "$STORE" --data "$WORK/$1" --token-file "$WORK/tokens" \
    --addr "127.0.0.1:$2" --follow-ms 50 --edit-rate 100000 > "$WORK/$1.log" 2>&1 &
}
A=$(free_port); B=$(free_port)

python3 - "$BIN" "$WORK" "$A" "$B" "$TOKEN" "$DIMS" <<'EOF'
import json, random, subprocess, sys, threading, time, urllib.error, urllib.request
bin_, work, a, b, token, dims = sys.argv[1:]
a, b, dims = int(a), int(b), int(dims)

def get(url, timeout=30):
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return r.read()

def metric(port, name):
    for line in get(f"http://127.0.0.1:{port}/metrics").decode().splitlines():
        if line.startswith(name + " "):
            return int(float(line.split()[1]))
    return 0

def edit(port, origin):
    body = json.dumps({"op": "union", "term": {"cuboid": {"origin": origin, "size": [8, 8, 8]}}}).encode()
    req = urllib.request.Request(f"http://127.0.0.1:{port}/v1/volumes/w/edits", body,
        {"Content-Type": "application/json", "Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.loads(r.read())

def start(name, port, *more):
    t0 = time.perf_counter()
    subprocess.run(["mkdir", "-p", f"{work}/{name}"])
    log = open(f"{work}/{name}.log", "w")
    p = subprocess.Popen([f"{bin_}/isovox", "serve", "--store", "s3://isovox-bench/vols", "--data", f"{work}/{name}",
        "--token-file", f"{work}/tokens", "--addr", f"127.0.0.1:{port}", "--follow-ms", "50",
        "--edit-rate", "100000", *more], stdout=subprocess.DEVNULL, stderr=log)
    while True:
        try:
            get(f"http://127.0.0.1:{port}/v1/volumes/w", timeout=1)
            return p, time.perf_counter() - t0
        except Exception:
            time.sleep(0.005)

subprocess.run(["mkdir", "-p", f"{work}/a", f"{work}/b"])
# Without the index prefetch, so that what the start and each cold brick fetch is theirs alone.
pa, cold = start("a", a, "--prefetch-index-mb", "0")
print(f"cold start: serving the {dims}^3 volume's metadata {cold*1000:.0f} ms after launch; "
      f"fetched {metric(a, 'isovox_store_fetched_bytes_total')} bytes in "
      f"{metric(a, 'isovox_store_fetches_total')} range requests (header page, head commit, checkpoint fixed part)")

# The index prefetch of a replica started with the defaults: when its fetches stop.
import socket
with socket.socket() as sock:
    sock.bind(("127.0.0.1", 0))
    p_port = sock.getsockname()[1]
pp, _ = start("p", p_port)
t0, last, quiet = time.perf_counter(), None, None
while quiet is None or time.perf_counter() - quiet < 0.5:
    now = (metric(p_port, "isovox_store_fetches_total"), metric(p_port, "isovox_store_fetched_bytes_total"))
    if now != last:
        last, quiet = now, time.perf_counter()
    time.sleep(0.01)
print(f"index prefetch: {last[1]} bytes in {last[0]} range requests (the open's included), "
      f"done within {(quiet - t0) * 1000:.0f} ms of the metadata being served")
pp.terminate(); pp.wait()

grid = (dims + 15) // 16
rng = random.Random(1)
f0, r0 = metric(a, "isovox_store_fetched_bytes_total"), metric(a, "isovox_store_fetches_total")
n = 500
for _ in range(n):
    get(f"http://127.0.0.1:{a}/v1/volumes/w/bricks/0/{rng.randrange(grid)}/{rng.randrange(grid)}/{rng.randrange(grid)}")
f1, r1 = metric(a, "isovox_store_fetched_bytes_total"), metric(a, "isovox_store_fetches_total")
print(f"cold bricks: {n} random level-0 bricks fetched {(f1-f0)/n:.0f} bytes and {(r1-r0)/n:.2f} range requests each")

pb, _ = start("b", b)
# Edit on a, event on b: delay from a's acknowledgement to b's event.
events = {}
def follow():
    with urllib.request.urlopen(f"http://127.0.0.1:{b}/v1/volumes/w/events", timeout=600) as r:
        for line in r:
            if line.startswith(b"data:") and b'"changed"' in line:
                events[json.loads(line[5:])["version"]] = time.perf_counter()
threading.Thread(target=follow, daemon=True).start()
time.sleep(0.5)
acked = {}
for i in range(100):
    res = edit(a, [16 * (i % 20), dims - 10, 16 * (i // 20)])
    acked[res["version"]] = time.perf_counter()
    time.sleep(0.02)
time.sleep(1.0)
delays = sorted(max(0.0, events[v] - t) * 1000 for v, t in acked.items() if v in events)
missing = len(acked) - len(delays)
q = lambda p: delays[min(len(delays) - 1, int(p * len(delays)))]
print(f"edit on replica a -> event on replica b: p50 {q(0.5):.1f} ms, p99 {q(0.99):.1f} ms "
      f"({len(delays)} events, {missing} missing; follow interval 50 ms)")

# Editors on both replicas for 10 s: with group commit (the default: a replica's waiting edits
# become one segment and one head PUT), then with --edit-group 1 (one commit per edit), each
# way on a fresh pair of replicas, in turn.
def edit_rate(ports, per_replica, seconds=10):
    count = {p: 0 for p in ports}; busy = [0]; stop = time.perf_counter() + seconds
    def writer(port, k):
        i = 0
        while time.perf_counter() < stop:
            try:
                edit(port, [16 * ((i * 7 + k) % (dims // 16)), dims - 20, 16 * ((i * 3 + k) % (dims // 16))])
                count[port] += 1
            except urllib.error.HTTPError as e:
                if e.code != 503:
                    raise
                busy[0] += 1  # the group lost the head race 16 times in a row
            i += 1
    ts = [threading.Thread(target=writer, args=(p, k)) for k, p in enumerate(ports * per_replica)]
    [t.start() for t in ts]; [t.join() for t in ts]
    return sum(count.values()) / seconds, busy[0], [count[p] / seconds for p in ports]

pa.kill(); pb.kill()
import os, socket
def free():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); port = s.getsockname()[1]; s.close(); return port
# "every segment an object" (--inline-kb 0): no segment rides in the head, so each commit is a
# segment PUT and a head PUT, and catching up a head GET and a segment GET; one commit per edit
# that way is the protocol without either groups or segments in the head.
ways = (("groups", ()), ("one per edit", ("--edit-group", "1")),
        ("groups, every segment an object", ("--inline-kb", "0")),
        ("one per edit, every segment an object", ("--edit-group", "1", "--inline-kb", "0")))
# What the store answered, from moto's request log: (method, the volume's object kind, status).
import re
def store_requests():
    counts = {}
    line_re = re.compile(r'"(GET|PUT|HEAD|POST|DELETE) /isovox-bench/vols/w/([a-z]+)[^"]*" (\d+)')
    with open(f"{work}/s3.log", errors="replace") as log:
        for line in log:
            m = line_re.search(re.sub(r"\x1b\[[0-9;]*m", "", line))
            if m:
                counts[m.groups()] = counts.get(m.groups(), 0) + 1
    return counts
rates = {}
for per_replica in (2, 8):
    for w, (label, more) in enumerate(ways):
        ports = [free(), free()]
        procs = [start(f"e{per_replica}{w}{i}", port, *more)[0] for i, port in enumerate(ports)]
        before = store_requests()
        rate, busy, each = edit_rate(ports, per_replica)
        after = store_requests()
        for p in procs:
            p.kill()
        n = lambda method, kind, status=None: sum(v - before.get(k, 0) for k, v in after.items()
                                                  if k[:2] == (method, kind) and status in (None, k[2]))
        groups = n("PUT", "head", "200")
        total = sum(v - before.get(k, 0) for k, v in after.items())
        rates[(per_replica, label)] = rate
        print(f"edits with {per_replica} editors on each of 2 replicas, {label}: {rate:.1f} edits/s on one volume "
              f"({' + '.join(f'{r:.1f}' for r in each)} by replica; {busy} answered 503 after losing the head race 16 times)")
        print(f"  the store: {groups} commits (head PUTs answered 200), {total} requests "
              f"({total / max(groups, 1):.1f} a commit): head PUTs refused {n('PUT', 'head', '412')}, "
              f"segment PUTs {n('PUT', 'seg')}, head GETs {n('GET', 'head')} ({n('GET', 'head', '304')} answered 304), "
              f"segment GETs {n('GET', 'seg')}, turns {n('GET', 'turn') + n('PUT', 'turn')}")
    r = lambda label: rates[(per_replica, label)]
    print(f"  group commit / one commit per edit, {per_replica} editors per replica: "
          f"{r('groups') / r('one per edit'):.2f}x; against one commit per edit with every segment an object: "
          f"{r('groups') / r('one per edit, every segment an object'):.2f}x "
          f"(segments in the head: {r('groups') / r('groups, every segment an object'):.2f}x with groups, "
          f"{r('one per edit') / r('one per edit, every segment an object'):.2f}x one per edit)")
EOF
[ -n "${EDITS_ONLY:-}" ] && exit 0  # the edit figures alone

# nginx in front of two replicas, streaming load through it, then against one replica alone.
# Both replicas are warmed first by the same load run against each directly (nginx's cache
# stays empty): those two runs are cold starts (50 viewers on a replica that has fetched
# nothing but the volume's metadata), and the two later runs differ by nginx alone.
R=$(free_port); R2=$(free_port); N=$(free_port)
replica r "$R"
replica r2 "$R2"
until curl -sf "http://127.0.0.1:$R/v1/volumes/w" >/dev/null; do sleep 0.1; done
until curl -sf "http://127.0.0.1:$R2/v1/volumes/w" >/dev/null; do sleep 0.1; done
mkdir -p "$WORK/nginx"
# Run as root, nginx's workers would be "nobody", who cannot enter the private work directory
# (mktemp -d makes it 0700): every cached location then answers 500 (cache files: permission
# denied). They run as this user instead (nginx ignores the directive when not run as root).
cat > "$WORK/nginx/nginx.conf" <<EOF
user $(id -un) $(id -gn);
worker_processes 2; daemon off; pid $WORK/nginx/pid; error_log $WORK/nginx/error.log;
events { worker_connections 4096; }
http { access_log off;
  client_body_temp_path $WORK/nginx/b; proxy_temp_path $WORK/nginx/p; fastcgi_temp_path $WORK/nginx/f;
  uwsgi_temp_path $WORK/nginx/u; scgi_temp_path $WORK/nginx/s;
  proxy_cache_path $WORK/nginx/cache levels=1:2 keys_zone=isovox:64m max_size=8g inactive=30d use_temp_path=off;
  upstream isovox { server 127.0.0.1:$R; server 127.0.0.1:$R2; keepalive 64; }
  server { listen 127.0.0.1:$N; include $PWD/docker/nginx/isovox-locations.conf; } }
EOF
nginx -c "$WORK/nginx/nginx.conf" -p "$WORK/nginx/" -e "$WORK/nginx/error.log" &
NGINX=$!
until curl -sf "http://127.0.0.1:$N/v1/volumes/w" >/dev/null; do
  kill -0 "$NGINX" 2>/dev/null || { echo "nginx did not start:" >&2; cat "$WORK/nginx/error.log" >&2; exit 1; }
  sleep 0.1
done

# A replica's counters, from its /metrics, as JSON: requests for bricks and blobs ("tiles",
# any status), for mesh tiles and strips ("meshes") and level requests by status ("levels_200",
# "levels_503", ...).
counters() { # counters PORT
  curl -sf "http://127.0.0.1:$1/metrics" | python3 -c '
import json, re, sys
c = {"tiles": 0, "meshes": 0}
for line in sys.stdin:
    m = re.match(r"isovox_requests_total\{route=\"/v1/volumes/\{name\}/([a-z]+)/[^\"]*\",status=\"(\d+)\"\} (\S+)", line)
    if m:
        route, status, n = m.group(1), m.group(2), int(float(m.group(3)))
        if route in ("blobs", "bricks"):
            c["tiles"] += n
        elif route == "meshes":
            c["meshes"] += n
        elif route == "levels":
            c["levels_" + status] = c.get("levels_" + status, 0) + n
print(json.dumps(c))'
}
# A replica's open connections every half second while a load runs (one number a line).
sample_connections() { # sample_connections PORT FILE
  while :; do
    curl -sf "http://127.0.0.1:$1/metrics" | awk '/^isovox_connections_open /{print $2}' >> "$2" || true
    sleep 0.5
  done
}
# isovox-load exits 1 when any request failed during the run: its figures still count, printed
# with the errors it saw, so a failing run is visible rather than silently fatal.
load() { # load URL NAME REPLICA_PORT [ISOVOX-LOAD ARGS...]
  local status=0
  sample_connections "$3" "$WORK/$2.connections" &
  local sampler=$!
  $BIN/isovox-load --url "$1" --volume w --viewers 50 --duration 20 --json "$WORK/$2.json" "${@:4}" > "$WORK/$2.txt" 2>&1 || status=$?
  if [ "$status" -eq 1 ] && [ -s "$WORK/$2.json" ]; then
    echo "isovox-load against $1 counted errors:" >&2
    python3 - "$WORK/$2.json" >&2 <<'EOF'
import json, sys
for e in json.load(open(sys.argv[1]))["errors"]:
    print(f"  {e['count']} x {e['source']}: {e['kind']}")
EOF
  elif [ "$status" -ne 0 ]; then
    echo "isovox-load against $1 failed (status $status):" >&2
    cat "$WORK/$2.txt" >&2
    exit "$status"
  fi
  kill "$sampler"
}
load "http://127.0.0.1:$R" cold-replica-1 "$R"
load "http://127.0.0.1:$R2" cold-replica-2 "$R2"
counters "$R" > "$WORK/c0.json"
counters "$R2" > "$WORK/e0.json"
load "http://127.0.0.1:$N" through-nginx "$R"
counters "$R" > "$WORK/c1.json"
counters "$R2" > "$WORK/e1.json"
load "http://127.0.0.1:$R2" replica-alone "$R2"
counters "$R2" > "$WORK/d1.json"
counters "$R" > "$WORK/m0.json"
load "http://127.0.0.1:$N" meshes-through-nginx "$R" --tiles meshes
counters "$R" > "$WORK/m1.json"
counters "$R2" > "$WORK/n1.json"
load "http://127.0.0.1:$N" meshes-through-nginx-again "$R" --tiles meshes
counters "$R" > "$WORK/m2.json"
counters "$R2" > "$WORK/n2.json"
python3 - "$WORK" <<'EOF'
import json, sys
work = sys.argv[1]
def read(name):
    return json.load(open(f"{work}/{name}"))
c0, c1, e0, e1 = read("c0.json"), read("c1.json"), read("e0.json"), read("e1.json")
d0, d1 = e1, read("d1.json")
def tiles(r):
    return sum(x["requests"] for x in r["routes"] if x["route"] in ("brick", "blob"))
for name in ("cold-replica-1", "cold-replica-2", "through-nginx", "replica-alone",
             "meshes-through-nginx", "meshes-through-nginx-again"):
    r = read(f"{name}.json")
    f, d, st = r["streamers"]["first_tile_ms"], r["streamers"]["first_drawn_ms"], r["streamers"]
    print(f"{name}: {r['errors_total']} errors, first tile p50 {f['p50']:.0f} / p99 {f['p99']:.0f} / "
          f"max {f['max']:.0f} ms over {f['samples']} viewers ({st['without_tile']} without a tile), "
          f"first tile that draws p50 {d['p50']:.0f} / p99 {d['p99']:.0f} / max {d['max']:.0f} ms "
          f"over {d['samples']} viewers, {r['total']['requests_per_s']:.0f} req/s")
through, alone = read("through-nginx.json"), read("replica-alone.json")
asked = tiles(through)
reached = (c1["tiles"] - c0["tiles"]) + (e1["tiles"] - e0["tiles"])
if asked:
    print(f"nginx answered {100.0 * (1 - reached / asked):.1f}% of {asked} brick and blob requests "
          f"without the replicas ({reached} reached them)")
    def all_levels(before, after):
        return sum(after[k] - before.get(k, 0) for k in after if k.startswith("levels_"))
    asked_all = through["total"]["requests"]
    reached_all = reached + all_levels(c0, c1) + all_levels(e0, e1)
    print(f"nginx answered {100.0 * (1 - reached_all / asked_all):.1f}% of all {asked_all} requests "
          f"(bricks, blobs, level grids) without the replicas ({reached_all} reached them)")
else:
    asked_for = ", ".join(f"{x['requests']} {x['route']} ({x['outcomes'].get('503', 0)} answered 503)"
                          for x in through["routes"] if x["requests"])
    print(f"no share of brick and blob requests to report: through nginx the viewers asked for no "
          f"brick or blob in 20 s, only: {asked_for}")
t, a = through["total"]["requests_per_s"], alone["total"]["requests_per_s"]
print(f"isovox-load, 50 viewers for 20 s: {t:.0f} req/s through nginx, {a:.0f} req/s against the replica alone "
      f"({t / a:.2f}x); errors: {through['errors_total']} through nginx, {alone['errors_total']} alone")
def levels(before, after):
    d = {k[len("levels_"):]: after[k] - before.get(k, 0) for k in after if k.startswith("levels_")}
    return ", ".join(f"{n} x {s}" for s, n in sorted(d.items()) if n) or "none"
def peak(name):
    seen = [int(float(l)) for l in open(f"{work}/{name}.connections") if l.strip()]
    return max(seen, default=0)
print(f"level requests at the replicas: {levels(c0, c1)} and {levels(e0, e1)} through nginx, "
      f"{levels(d0, d1)} alone; open connections at the first replica, at most: "
      f"{peak('through-nginx')} through nginx, {peak('replica-alone')} alone")
# Meshes through nginx: every request a run made against those that reached a replica (the
# second replica's counters before the first meshes run are d1: the run against it alone ended
# there).
def meshes_share(name, before, after, before2, after2):
    r = read(f"{name}.json")
    asked_all = r["total"]["requests"]
    def counted(b, a):
        return sum(a[k] - b.get(k, 0) for k in a if k in ("tiles", "meshes") or k.startswith("levels_"))
    reached_all = counted(before, after) + counted(before2, after2)
    asked = sum(x["requests"] for x in r["routes"] if x["route"] in ("mesh", "strip"))
    reached = after["meshes"] - before["meshes"] + after2["meshes"] - before2["meshes"]
    print(f"{name}: nginx answered {100.0 * (1 - reached_all / max(asked_all, 1)):.1f}% of all "
          f"{asked_all} requests ({reached_all} reached the replicas), "
          f"{100.0 * (1 - reached / max(asked, 1)):.1f}% of {asked} mesh tiles and strips; "
          f"level requests at the replicas: {levels(before, after)} and {levels(before2, after2)}")
m0, m1, n1, m2, n2 = (read(f"{n}.json") for n in ("m0", "m1", "n1", "m2", "n2"))
meshes_share("meshes-through-nginx", m0, m1, d1, n1)
meshes_share("meshes-through-nginx-again", m1, m2, n1, n2)
EOF
