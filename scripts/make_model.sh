#!/usr/bin/env bash
# Train the bundled model: `topseg datagen` renders a modeled synthetic dataset in which every
# frame draws its own camera mount (height 2.4-4.5 m, pitch and roll up to 10 deg, one of the
# supported sensors with its resolution and its own noise family), `topseg train` fits a
# forest on height above the floor into models/default.npz (the
# worker's, demo's, evaluate's and segment's default model). Both steps resume after an
# interruption; rerunning on the same dataset gives the same trees.
#
# The defaults are the paper's configuration (D=19, PC=300, R=K=100, linear splits) with
# these changes, measured in docs/forest.md and docs/results.md:
#   - TREES=4 and FRAMES_PER_TREE=6000 of 8000 frames (7200 after the 10 % validation split):
#     the data spans every mount and sensor. Two trees of 1600 frames scored 0.47-0.71 avg F1
#     across the mounts table, four of 2400 (of 5000) 0.52-0.77, four of 4000 (of 8000)
#     0.53-0.77 with +0.009 / +0.013 on the Kinect v1 / random-mount held-out sets, four of
#     6000 (of 8000) 0.555-0.791 with +0.008 / +0.018 on them and +0.0044 mean over the
#     mounts table. Of its trees, the third and fourth add +0.022 and +0.009 on the
#     random-mount set; a fifth was not tried (it would add nodes to walk on every unsure
#     pixel). The model is ~1.3 M nodes, 18 MB compressed: under the 25 MB we commit.
#   - ABSOLUTE_FRACTION=0.2: a fifth of the feature pool reads a probe's height above the
#     calibrated floor; on held-out frames it beat the paper's pure depth differences (avg F1
#     with the realtime CRF 0.606 vs 0.539 at F=160, measured on the fixed-mount model).
#   - Frames from a camera whose depth noise at the floor is 20 mm or more (stereo at range) are
#     smoothed before features are read (core/denoise.py), in training as in labelling. The
#     bundled model was trained before that (fifteenth session); this recipe's model with it
#     scored the same (mounts table mean 0.7292 vs 0.7279, held-out sets +0.007 / -0.006), so
#     the bundled one was kept: `make model` now gives a model of equal quality, not the same
#     trees.
#   - Since the seventeenth session the data has the time-of-flight model's dropout on dark hair
#     (the synthesiser passes the renderer's labels to the noise model) and, in 30 % of the
#     Kinect v2's frames, no depth outside a smaller circle (`tof:fov_cut=0.3`): the bundled
#     model was retrained on it (docs/results.md: 14 of 20 mounts-table cells within 0.03 of
#     the reference, 13 before; a cut across the walls no longer reads as legs). 52 minutes
#     with other work beside it: datagen 5.5 min (24.5 frames/s), training 46 min.
#   - Since the twentieth session a probe off the image reads the nearest pixel on the image's
#     edge (`topseg train --off-image nearest`, the default), not the background constant: a
#     person cut by the edge no longer reads as ending there. The bundled model was retrained
#     so on the seventeenth session's dataset (training 41 min beside other work;
#     docs/results.md, "Probes off the image").
#   - Since the twenty-first session a no-depth region touching the image's edge (the Kinect
#     v2's ring, a stereo camera's invalid band) reads as the surface beside it
#     (`topseg train --edge-gaps nearest`, the default). The bundled model was retrained so
#     on the same dataset (training 41 min beside the test suite; docs/results.md, "No-depth
#     regions at the image's edge").
#   - Since the twenty-third session a stereo camera's fattened edges are thinned before
#     features are read (core/fattening.py), in training as in labelling. The bundled model
#     is this recipe's output as it stands (twenty-fourth session: the defaults below on the
#     seed-0 dataset, training 38 min with other experiments beside it): over the mounts
#     table at 300 frames a cell it scores mean avg F1 0.7451 against the model before it
#     0.7418 (+0.0033, paired 95 % interval +0.0018..+0.0049; docs/results.md, "The mounts
#     table at 300 frames a cell").
#   - SENSORS=kinect_v1,kinect_v2,oak_d:2,realsense_d435:3 (twenty-fifth session): the stereo
#     cameras are drawn more often (`datagen --sensors NAME:N`), 3 of 7 frames from the D435
#     and 2 of 7 from the OAK-D, whose noise at range is what the forest finds hardest. Over
#     the mounts table (300 frames a cell) its mean avg F1 equals the model trained on the
#     four sensors drawn alike (0.7486 against 0.7484, paired interval -0.0012..+0.0016), the
#     stereo cells rise by up to 0.010 and the Kinect v1 cells fall by 0.003-0.009, so the
#     spread across cameras narrows (docs/results.md, "Stereo cameras drawn more often").
#     The bundled model is this recipe's output: `make model` rebuilds these trees.
# About 24 minutes on 2 cores, measured on a quiet machine (43 with other jobs beside it, fifteenth
# session: datagen 6 min, training 37): datagen 4 min (32 frames/s), training
# 19 min (two trees at a time, ~15 GB of the machine's memory in use at the peak).
#   FRAMES=8000 MOUNTS=random NOISE=sensor SENSORS=kinect_v1,kinect_v2,oak_d:2,realsense_d435:3 \
#   TREES=4 DEPTH=19 FRAMES_PER_TREE=6000 scripts/make_model.sh
set -euo pipefail
cd "$(dirname "$0")/.."
FRAMES=${FRAMES:-8000}
MOUNTS=${MOUNTS:-random}
NOISE=${NOISE:-sensor}
SENSORS=${SENSORS:-kinect_v1,kinect_v2,oak_d:2,realsense_d435:3}
SEED=${SEED:-0}
TREES=${TREES:-4}
DEPTH=${DEPTH:-19}
FRAMES_PER_TREE=${FRAMES_PER_TREE:-6000}
ABSOLUTE_FRACTION=${ABSOLUTE_FRACTION:-0.2}
DATA=${DATA:-data/default-train.zarr}
OUT=${OUT:-models/default.npz}
mkdir -p "$(dirname "$OUT")" "$(dirname "$DATA")"
SENSOR_ARGS=()  # the paper's fixed mount has one sensor
[ "$MOUNTS" = random ] && SENSOR_ARGS=(--sensors "$SENSORS")
.venv/bin/topseg datagen --mode modeled --frames "$FRAMES" --out "$DATA" --seed "$SEED" \
    --mounts "$MOUNTS" --noise "$NOISE" "${SENSOR_ARGS[@]}" --no-progress
.venv/bin/topseg train --data "$DATA" --out "$OUT" --trees "$TREES" --depth "$DEPTH" \
    --frames-per-tree "$FRAMES_PER_TREE" --absolute-fraction "$ABSOLUTE_FRACTION" --seed "$SEED"
du -h "$OUT"
