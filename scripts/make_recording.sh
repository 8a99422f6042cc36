#!/usr/bin/env bash
# Write the bundled demo recording: synthetic robot cells (robot arms, cell objects, furniture,
# people; a share of them the paper's modeled scenes) with ground truth (depth + truth
# channels, 1/FPS apart, in the ROS 2 form of `topseg record`) rendered by the synthetic
# driver, for `replay:recordings/demo.mcap`.
# Kinect noise (quantised disparity) keeps it ~65 KB a frame; gaussian noise is ~5x that.
# Deterministic: the same FRAMES/SPEC give the same frames (only the stamps differ). Atomic.
#   FRAMES=300 SPEC=cell,seed=1,noise=kinect FPS=30 OUT=recordings/demo.mcap scripts/make_recording.sh
set -euo pipefail
cd "$(dirname "$0")/.."
FRAMES=${FRAMES:-300}
SPEC=${SPEC:-cell,seed=1,noise=kinect}
FPS=${FPS:-30}
OUT=${OUT:-recordings/demo.mcap}
mkdir -p "$(dirname "$OUT")"
.venv/bin/python - "$OUT" "$FRAMES" "$SPEC" "$FPS" <<'PY'
import sys
from topseg.drivers.synthetic import record
out, frames, spec, fps = sys.argv[1], int(sys.argv[2]), sys.argv[3], float(sys.argv[4])
print(f"make_recording: {frames} frames of synthetic:{spec} -> {record(out, frames, spec, fps)}")
PY
du -h "$OUT"
