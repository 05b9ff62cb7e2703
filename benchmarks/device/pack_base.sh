#!/usr/bin/env bash
# Packs an earlier commit's pipeline/ and benchmarks/ (its weights left out: ab.sh gives it
# this tree's) into .base/ (ignored via .git/info/exclude), for benchmarks/device/ab.sh to time
# against this tree on the same device machine. Usage: pack_base.sh COMMIT
set -euo pipefail
cd "$(dirname "$0")/../.."
grep -qx "/.base/" .git/info/exclude 2>/dev/null || echo "/.base/" >> .git/info/exclude
rm -rf .base && mkdir .base
git archive "$1" pipeline benchmarks ':!pipeline/enhance/weights/*.safetensors' | tar -x -C .base
git rev-parse "$1" > .base/COMMIT
du -sh .base
