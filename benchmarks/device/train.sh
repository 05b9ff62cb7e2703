#!/usr/bin/env bash
# On the device machine (carry .devpkgs .gl .meshes; see pack.sh, which copies every mesh in
# shared/, the bunny too, though training never reads it): fine-tunes the shipped networks
# with the large config's batch and poses and the shipped weights' recipe (regressor,
# end-to-end finetune and vertex gains from the shipped weights, the mesh mix, loss mask
# 0.02), on CUDA, and copies the weights and training.json to $OUT/train (the
# checkpoints stay there: too large to come back). Then, here: `benchmarks/enhance_meshes.py
# --mesh spot --mesh fandisk --weights DIR` decides whether the new weights replace the
# shipped ones (validation meshes only; never the bunny).
#
# Sized to one device call (10 minutes at most): SCALE multiplies every stage's steps and
# MINUTES caps each network stage; STAGES and NOISE (`--noise`) set the stages trained and the
# noise models drawn (default: all three). On an H100 the large config's pairs take about 2
# minutes with 14 workers and its regressor / finetune stages 3.0 / 5.8 minutes at SCALE 1, so
# SCALE 0.4 leaves time for the gains and the validation. Here, `LOCAL=1 CONFIG=small SCALE=0.002
# POSES=1 PROCEDURAL=1 WORKERS=2 DEVICE=cpu` checks the command line in a few minutes.
set -uo pipefail
if [ -z "${LOCAL:-}" ]; then
  source "$(dirname "$0")/setup.sh"
  export PYTHONPATH="/tmp/site:$(pwd)"
  python=python3
else
  python=.venv/bin/python
fi
out=${OUT:-.}
work=${WORK:-$(mktemp -d)}
poses=()
[ -n "${POSES:-}" ] && poses=(--poses "$POSES")
$python -c "from app.cli import main; main()" train --config "${CONFIG:-large}" \
  --init pipeline/enhance/weights --stages "${STAGES:-regressor,finetune,gain}" --mix mesh \
  --loss-mask 0.02 --lr 2e-4 --procedural "${PROCEDURAL:-12}" --workers "${WORKERS:-14}" \
  --seed "${SEED:-61}" --budget-scale "${SCALE:-0.4}" --minutes "${MINUTES:-2.5}" \
  --noise "${NOISE:-uniform,gaussian,laplace}" "${poses[@]}" --meshes "${MESHES:-.meshes}" \
  --device "${DEVICE:-cuda}" --out "$work" \
  2>&1 | tr '\r' '\n' | grep -v '^\s*$' | tail -60
status=${PIPESTATUS[0]}
mkdir -p "$out/train"
cp "$work"/*.safetensors "$work"/training.json "$out/train/" 2>/dev/null
ls -l "$out/train"
exit "$status"
