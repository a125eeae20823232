#!/usr/bin/env bash
# The measurements of docs/perf/2026-12-07-workspace.md. Usage, for each commit in its own
# fresh worktree (same machine, nothing else running):
#   git worktree add --detach /tmp/ws-before 9ae19fa
#   docs/perf/2026-12-07-workspace.sh /tmp/ws-before before \
#       src/server/routes/frames.rs src/engine/cpu/mod.rs src/rig/clip.rs src/rig/pose.rs \
#       "cargo test --locked --lib --no-default-features rig::"
#   git worktree add --detach /tmp/ws-after 41274f5
#   docs/perf/2026-12-07-workspace.sh /tmp/ws-after after \
#       crates/server/src/routes/frames.rs crates/engine/src/cpu/mod.rs \
#       crates/core/src/rig/clip.rs crates/core/src/rig/pose.rs "cargo test --locked -p crowdmorph-core"
# Writes OUT/<label>/times.txt (seconds per step) and a log per step.
# The runtime rows of "one job per home" are by hand: `cargo build --release --locked` at each
# commit, the binaries copied to /tmp/cm-old and /tmp/cm-new, then A B A B:
#   for run in 1 2; do for v in old new; do
#     /tmp/cm-$v bench sessions --seconds 5 --json; /tmp/cm-$v bench http --backend cpu --seconds 3 --json
#   done; done
set -u
dir=$1; label=$2; route=$3; engine=$4; rigf=$5; datafile=$6; datatest=$7
out=${OUT:-/tmp/ws-perf}/$label; mkdir -p "$out"
cd "$dir"; export CARGO_TARGET_DIR=$dir/target
t() { local name=$1; shift; local s; s=$(date +%s.%N); "$@" > "$out/$name.log" 2>&1; local rc=$?
      printf '%s %.1f rc=%s\n' "$name" "$(echo "$(date +%s.%N) - $s" | bc)" "$rc" | tee -a "$out/times.txt"; }
# One statement added to the body of the file's first public function.
edit() { python3 - "$1" "$2" <<'PY'
import re, sys
p, n = sys.argv[1], sys.argv[2]
t = open(p).read()
m = re.search(r"\n\s*pub (async )?fn [a-z_0-9]+", t)
i = t.index("{\n", m.end()) + 2
open(p, "w").write(t[:i] + f"    std::hint::black_box({n}u32);\n" + t[i:])
PY
}
rm -rf "$dir/target"
t release-cold cargo build --release --locked
t test-build-cold cargo test --workspace --locked --no-run
t test-run cargo test --workspace --locked
n=0
for f in "$route" "$engine" "$rigf"; do
  n=$((n+1)); touch "$f"; t "touch-$n" cargo test --workspace --locked --no-run
done
n=0
for f in "$route" "$engine" "$rigf"; do
  n=$((n+1)); edit "$f" "$n"; t "edit-$n" cargo test --workspace --locked --no-run
done
edit "$datafile" 9; t data-crate-test bash -c "$datatest"
git checkout -- "$route" "$engine" "$rigf" "$datafile"
