#!/usr/bin/env bash
# On the device machine (carry .devpkgs .gl .meshes; see pack.sh): times the product's
# enhancement (the regressor) per mesh on CUDA with its stages, and the LDM beside it (JSON
# lines, also in $OUT/perf.jsonl; the light remesh started ahead, the default there, and once
# after the update for comparison), profiles one bunny
# ($OUT/prof_bunny.txt), times the light remesh's variants ($OUT/remesh_speed.json), then runs
# the tests that need CUDA.
# About 4 minutes on an H100, unpacking included.
set -uo pipefail
source "$(dirname "$0")/setup.sh"
out=${OUT:-.}
timed() {
  python3 benchmarks/enhance.py --perf-child --meshes .meshes --device cuda "$@" \
    2>>"$out/err.txt" | tee -a "$out/perf.jsonl"
}
timed --remesh-iterations 1
timed --remesh-iterations 1
timed --remesh-iterations 1 --remesh after
timed --remesh-iterations 0
timed --remesh-iterations 1 --profile "$out/prof_bunny.txt"
timed --remesh-iterations 1 --mesh beetle
timed --remesh-iterations 1 --method ldm
timed --remesh-iterations 1 --method ldm
python3 benchmarks/remesh_speed.py --meshes .meshes --repeats 1 --pieces 8 \
  2>>"$out/err.txt" | tee "$out/remesh_speed.json"
# The tests that need CUDA (skipped elsewhere), where the image has pytest.
if python3 -c "import pytest, hypothesis" 2>/dev/null; then
  python3 -m pytest -q -p no:cacheprovider tests/pipeline -k cuda 2>&1 | tail -5
fi
