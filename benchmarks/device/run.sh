#!/usr/bin/env bash
# On the device machine (carry .devpkgs .gl .meshes; see pack.sh): unpacks the carried
# packages outside the image's own, then times the LDM per mesh on CUDA (JSON lines; also
# under $OUT/perf.jsonl when the device tool gives an $OUT), then the light remesh in
# pieces against one child ($OUT/remesh_speed.json).
set -euo pipefail
mkdir -p /tmp/site /tmp/gl
tar -C /tmp/site -xJf .devpkgs/site312.tar.xz
for f in .gl/*.deb; do dpkg -x "$f" /tmp/gl; done
# Neither plotly nor Mitsuba is there, and only the ray caster is used.
sed -i -E 's/^(from \.draw_plotly|from \.to_mitsuba)/pass  # &/' \
  /tmp/site/open3d/visualization/__init__.py
export LD_LIBRARY_PATH=/tmp/gl/usr/lib/x86_64-linux-gnu:/tmp/gl/lib/x86_64-linux-gnu
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
out=${OUT:-.}/perf.jsonl
nvidia-smi -L
timed() { python3 benchmarks/enhance.py --perf-child --meshes .meshes "$@" 2>/dev/null | tee -a "$out"; }
for r in 0 0 1; do timed --device cuda --remesh-iterations "$r"; done
for r in 0 1; do timed --device cuda --remesh-iterations "$r" --mesh beetle; done
timed --device cpu --remesh-iterations 0
# The light remesh's kernel in one child against one piece per core (16 there).
python3 benchmarks/remesh_speed.py --meshes .meshes --repeats 3 2>/dev/null \
  | tee "${OUT:-.}/remesh_speed.json"
