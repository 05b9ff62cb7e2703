#!/usr/bin/env bash
# On the device machine (carry .devpkgs .gl .meshes .base; see pack.sh and pack_base.sh): the
# bunny's LDM enhancement on CUDA, the light remesh ahead (the default there), timed for an
# earlier commit's code (.base/, with this tree's weights) and for this tree, alternating on
# one machine, each run a fresh process (JSON lines, also in $OUT/ab.jsonl); then this tree
# warmed up at the timed shapes (a worker's second mesh: `--warm-up full`); with its networks
# kept from before the warm-up (`--networks kept`, as a worker keeps them between jobs), after
# either warm-up; a worker's steady state (both) with the kernel's pieces from 12.5 k faces
# rather than 25 k (16 pieces on the bunny rather than 8, where the host has 16 cores);
# a worker's steady state with the self-check (`--self-check`);
# without the remesh, on beetle and profiled ($OUT/prof_bunny.txt); each variant's min /
# median / max ($OUT/summary.json, `summary.py`); and the tests that need CUDA. About 6
# minutes on an H100 or H200, unpacking included.
set -uo pipefail
source "$(dirname "$0")/setup.sh"
out=${OUT:-.}
here=$(pwd)
timed() {  # LABEL DIR ARGS...
  local label=$1 dir=$2
  shift 2
  (cd "$dir" && python3 benchmarks/enhance.py --perf-child --meshes "$here/.meshes" \
    --device cuda --weights "$here/pipeline/enhance/weights" "$@" 2>>"$out/err.txt") |
    sed "s/^{/{\"code\": \"$label\", /" | tee -a "$out/ab.jsonl"
}
base="base $(cut -c1-7 .base/COMMIT)"
for _ in 1 2; do
  timed "$base" .base
  timed tree .
done
timed tree .
timed tree . --warm-up full
timed tree . --warm-up full
timed tree . --networks kept
for _ in 1 2; do
  timed tree . --warm-up full --networks kept
  timed tree . --warm-up full --networks kept --min-piece-faces 12500
done
timed tree . --warm-up full --networks kept --self-check
timed tree . --remesh-iterations 0
timed tree . --mesh beetle
timed tree . --profile "$out/prof_bunny.txt"
python3 "$here/benchmarks/device/summary.py" "$out/ab.jsonl" | tee "$out/summary.json"
if python3 -c "import pytest, hypothesis" 2>/dev/null; then
  python3 -m pytest -q -p no:cacheprovider tests/pipeline -k cuda 2>&1 | tail -5
fi
