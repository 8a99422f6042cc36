#!/usr/bin/env bash
# Train the bundled model: `topseg datagen` renders a modeled synthetic dataset, `topseg train`
# fits a small forest on it into models/default.npz (the demo's and bench's default model).
# Both steps resume after an interruption. Scale with the variables (defaults: a small model,
# minutes on 2 cores; the paper's scale is FRAMES=20000 TREES=3 DEPTH=20):
#   FRAMES=200 NOISE=kinect TREES=3 DEPTH=16 OUT=models/default.npz scripts/make_model.sh
set -euo pipefail
cd "$(dirname "$0")/.."
FRAMES=${FRAMES:-200}
TREES=${TREES:-3}
DEPTH=${DEPTH:-16}
SEED=${SEED:-0}
NOISE=${NOISE:-kinect}
DATA=${DATA:-data/default-train.zarr}
OUT=${OUT:-models/default.npz}
mkdir -p "$(dirname "$OUT")" "$(dirname "$DATA")"
.venv/bin/topseg datagen --mode modeled --frames "$FRAMES" --out "$DATA" --seed "$SEED" --noise "$NOISE" --no-progress
.venv/bin/topseg train --data "$DATA" --out "$OUT" --trees "$TREES" --depth "$DEPTH" \
    --frames-per-tree "$FRAMES" --seed "$SEED"
du -h "$OUT"
