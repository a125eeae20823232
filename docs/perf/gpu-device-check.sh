#!/usr/bin/env bash
# The hardware GPU check of issue 26, as one prepared command for a lent device machine (an
# NVIDIA H100 or H200; see the device tool's README): GPU time at paper scale and on ICT FaceKit
# up to 16,384 unique heads, f32 and f16 deltas, f32, q16 and q16r output (residuals coded on the
# device), the HTTP path with the GPU engine, and what the card reported while it ran. About 5
# minutes on the device.
#
# Prepare here (the device has neither ../shared nor, perhaps, Rust):
#
#   cargo build --release --locked
#   mkdir -p .device && grep -qx '/.device/' .git/info/exclude || echo /.device/ >> .git/info/exclude
#   strip -o .device/crowdmorph target/release/crowdmorph          # 28 MB instead of 167
#   cp ../shared/data/ict-facekit/ict_facekit_53.glb .device/
#   # and the Vulkan loader, as the device README says (.gl, carried too)
#
# Then one `run`, carry [".device", ".gl"], timeout_s 600 (its steps' own timeouts add up to
# 590 s; a normal run takes about 5 minutes):
#
#   for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig; bash docs/perf/gpu-device-check.sh
#
# Everything lands in $OUT (at most 8 files come back): the figures go into README's
# performance table and a docs/perf file of the day, beside the lavapipe ones.
set -uo pipefail
OUT=${OUT:-/tmp/gpu-check}
mkdir -p "$OUT"
BIN=${BIN:-.device/crowdmorph}
ICT=${ICT:-.device/ict_facekit_53.glb}
# Smaller values make a dry run on lavapipe: UNIQUE=1,8 HEADS=8 BENCH_SECONDS=0.2 HTTP_SECONDS=1.
# (Not SECONDS: bash's own SECONDS is the shell's age in whole seconds, always set, so
# ${SECONDS:-2} gave bench gpu --seconds 0 or 1 instead of 2.)
UNIQUE=${UNIQUE:-1,100,4096,16384}
HEADS=${HEADS:-1024}
SECONDS_EACH=${BENCH_SECONDS:-2}
HTTP_SECONDS=${HTTP_SECONDS:-5}
if ! "$BIN" --version >/dev/null 2>&1; then
  echo "the carried binary does not run here; building" >&2
  cargo build --release --locked >"$OUT/build.txt" 2>&1 || { echo "no binary, no cargo" >&2; exit 1; }
  BIN=target/release/crowdmorph
fi
if ! ldconfig -p | grep -q libvulkan; then
  echo "no Vulkan loader: carry .gl (see the device README)" >&2
fi
export NODEVICE_SELECT=1

{
  nvidia-smi --query-gpu=name,memory.total,clocks.max.sm,clocks.max.mem,pcie.link.gen.max,pcie.link.width.max,driver_version --format=csv
  nvidia-smi -q -d CLOCK,PERFORMANCE | head -60
} >"$OUT/nvidia-smi.txt" 2>&1
nvidia-smi dmon -s put -d 1 >"$OUT/dmon.txt" 2>&1 &
DMON=$!

# The rig's residency and the adapter the engine picked (auto must pick the hardware GPU).
"$BIN" inspect "$ICT" --backend auto --json >"$OUT/inspect.json" 2>"$OUT/log.txt"

# GPU time, copy+map and host apart, up to 16,384 unique heads: paper scale and ICT, with f32
# deltas (q16, q16r and f32 output) and f16 deltas (q16 output). Memory: most of the card.
MEM=$((60 << 30))
{
  for run in "--format q16" "--format q16r" "--format f32" "--format q16 --gpu-deltas f16"; do
    echo "== bench gpu $run"
    # shellcheck disable=SC2086
    timeout 110 "$BIN" bench gpu --backend gpu --rig "$ICT" --unique "$UNIQUE" \
      --max-gpu-memory $MEM $run --seconds "$SECONDS_EACH"
  done
} >"$OUT/bench-gpu.txt" 2>>"$OUT/log.txt"

# End to end through HTTP with the GPU engine: 1,024 unique ICT heads a request, 8 connections.
{
  for fmt in q16 q16r f32; do
    echo "== bench http --format $fmt"
    timeout 50 "$BIN" bench http --rig "$ICT" --heads "$HEADS" --unique "$HEADS" --format $fmt \
      --clients 8 --backend gpu --max-gpu-memory $MEM --seconds "$HTTP_SECONDS"
  done
} >"$OUT/bench-http.txt" 2>>"$OUT/log.txt"

kill "$DMON" 2>/dev/null
# bench gpu writes each row to stderr as it is measured: a step stopped by its timeout keeps the
# rows it finished here (its table on stdout is printed only at the end).
grep "^bench gpu: " "$OUT/log.txt" >"$OUT/bench-gpu-rows.txt" || true
# CPU fallbacks are WARN lines: "GPU memory budget full: ... ran on the CPU engine".
grep -c "ran on the CPU engine" "$OUT/log.txt" >"$OUT/fallbacks.txt" || true
tail -c 200000 "$OUT/log.txt" >"$OUT/log-tail.txt" && rm -f "$OUT/log.txt"
ls -la "$OUT"
