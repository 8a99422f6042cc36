#!/usr/bin/env bash
# Train the bundled model, models/default.npz (the default model of every command): `topseg
# datagen --mode cell` renders 9000 frames of robot cells (robot arms, cell objects, furniture
# and zero to two people; a share of them the paper's modeled scenes), each with its own camera
# mount (2.4-4.5 m, pitch and roll up to 10 deg) and sensor, the stereo cameras drawn more
# often, with that sensor's noise; `topseg train` fits 4 trees of 6000 frames, depth 19, a
# fifth of the feature pool reading absolute height; then `topseg person-check` fits the
# model's context prior and its two checks (the context check, then the person check) on
# CHECK_FRAMES more cells from another seed, each check keeping 98 % of the person pixels of its
# held-out frames (the context check also restores cells it finds a person's, at 75 %
# precision). Every step resumes after an interruption, and the same datasets give the same
# model. Why these numbers: docs/results.md ("Choices measured").
# About 70 minutes on 2 quiet cores (~15 GB at the peak).
# Every variable below can be set, e.g.
#   FRAMES=9000 MODE=cell MOUNTS=random NOISE=sensor SENSORS=kinect_v1,kinect_v2,oak_d:2,realsense_d435:3 \
#   TREES=4 DEPTH=19 FRAMES_PER_TREE=6000 CHECK_FRAMES=2400 scripts/make_model.sh
set -euo pipefail
cd "$(dirname "$0")/.."
FRAMES=${FRAMES:-9000}
MODE=${MODE:-cell}
MOUNTS=${MOUNTS:-random}
NOISE=${NOISE:-sensor}
SENSORS=${SENSORS:-kinect_v1,kinect_v2,oak_d:2,realsense_d435:3}
SEED=${SEED:-0}
TREES=${TREES:-4}
DEPTH=${DEPTH:-19}
FRAMES_PER_TREE=${FRAMES_PER_TREE:-6000}
ABSOLUTE_FRACTION=${ABSOLUTE_FRACTION:-0.2}
CHECK_FRAMES=${CHECK_FRAMES:-2400}
DATA=${DATA:-data/default-train.zarr}
CHECK_DATA=${CHECK_DATA:-data/default-check.zarr}
OUT=${OUT:-models/default.npz}
mkdir -p "$(dirname "$OUT")" "$(dirname "$DATA")"
SENSOR_ARGS=()  # the paper's fixed mount has one sensor
[ "$MOUNTS" = random ] && SENSOR_ARGS=(--sensors "$SENSORS")
.venv/bin/topseg datagen --mode "$MODE" --frames "$FRAMES" --out "$DATA" --seed "$SEED" \
    --mounts "$MOUNTS" --noise "$NOISE" "${SENSOR_ARGS[@]}" --no-progress
.venv/bin/topseg train --data "$DATA" --out "$OUT" --trees "$TREES" --depth "$DEPTH" \
    --frames-per-tree "$FRAMES_PER_TREE" --absolute-fraction "$ABSOLUTE_FRACTION" --seed "$SEED"
.venv/bin/topseg datagen --mode "$MODE" --frames "$CHECK_FRAMES" --out "$CHECK_DATA" \
    --seed "$((SEED + 1))" --mounts "$MOUNTS" --noise "$NOISE" "${SENSOR_ARGS[@]}" --no-progress
.venv/bin/topseg person-check --model "$OUT" --data "$CHECK_DATA" --seed "$SEED"
du -h "$OUT"
