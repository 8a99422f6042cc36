"""scripts/ceiling_proxy.py: frames from one ceiling, labelled by `topseg segment` with no
mount, scored as the real frames of issue 14 are."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from topseg.core import labels as L

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "ceiling_proxy.py"


def test_renders_segments_with_no_mount_and_scores_one_line_a_height(tmp_path):
    r = subprocess.run(
        [sys.executable, str(SCRIPT), "--out", str(tmp_path), "--heights", "3.3", "--frames", "2"],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    (line,) = r.stdout.strip().splitlines()
    got = json.loads(line)
    assert got["height_m"] == 3.3 and got["noise"] == "tof"
    assert 0.0 <= got["avg_f1"] <= 1.0 and got["true_heads"] >= 0 <= got["predicted_heads"]
    folder = tmp_path / "3.3m"
    depth = np.asarray(Image.open(folder / "frames" / "0001.png"))
    assert depth.shape == (480, 640) and depth.dtype == np.uint16
    # the floor 3.3 m down, seen through the Kinect v1's time-of-flight stand-in
    assert 3100 < np.median(depth[depth > 0]) < 3500
    labels = np.asarray(Image.open(folder / "pred" / "0001_labels.png"))
    truth = np.asarray(Image.open(folder / "truth" / "0001.png"))
    assert labels.shape == truth.shape == depth.shape
    assert set(np.unique(labels)) <= set(range(L.NUM_CLASSES)) | {L.NO_DEPTH}
