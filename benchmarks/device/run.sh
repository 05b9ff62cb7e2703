#!/usr/bin/env bash
# On the device machine (carry .devpkgs .gl .meshes; see pack.sh): unpacks the carried
# packages outside the image's own, then times the LDM per mesh on CUDA (JSON lines; also
# under $OUT/perf.jsonl when the device tool gives an $OUT), then the light remesh in
# pieces against one child ($OUT/remesh_speed.json).
set -euo pipefail
source "$(dirname "$0")/setup.sh"
out=${OUT:-.}/perf.jsonl
timed() { python3 benchmarks/enhance.py --perf-child --meshes .meshes "$@" 2>/dev/null | tee -a "$out"; }
for r in 0 0 1; do timed --device cuda --remesh-iterations "$r"; done
for r in 0 1; do timed --device cuda --remesh-iterations "$r" --mesh beetle; done
timed --device cpu --remesh-iterations 0
# The light remesh's kernel in one child against one piece per core (16 there).
python3 benchmarks/remesh_speed.py --meshes .meshes --repeats 3 2>/dev/null \
  | tee "${OUT:-.}/remesh_speed.json"
