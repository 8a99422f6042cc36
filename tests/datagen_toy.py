"""Cheap frame generators for the datagen tests (imported by Dask workers via `module:function`).

Frames are a noisy floor with a few labelled boxes and some dropouts, drawn from
`frame_seed(seed, index)` only, so they obey the same contract as the real generators at a
few milliseconds a frame.
"""

from __future__ import annotations

import os
import time

import numpy as np

from topseg.core import labels
from topseg.core.formats.dataset import frame_seed
from topseg.core.synth.noise import parse_noise

SHAPE = (480, 640)


def toy_frame(
    seed: int, index: int, noise: str = "gaussian:15"
) -> tuple[np.ndarray, np.ndarray, dict]:
    rng = np.random.default_rng(frame_seed(seed, index))
    depth = np.full(SHAPE, 3500, np.uint16)
    label = np.zeros(SHAPE, np.uint8)
    boxes = []
    for _ in range(int(rng.integers(1, 5))):
        y0, x0 = int(rng.integers(0, 400)), int(rng.integers(0, 560))
        h, w = int(rng.integers(20, 80)), int(rng.integers(20, 80))
        cls = int(rng.integers(1, labels.PAPER_NUM_CLASSES))  # the paper's classes
        top = int(rng.integers(1700, 3300))
        depth[y0 : y0 + h, x0 : x0 + w] = top
        label[y0 : y0 + h, x0 : x0 + w] = cls
        boxes.append({"class": labels.name_of(cls), "box": [y0, x0, h, w], "depth_mm": top})
    depth = parse_noise(noise).apply(depth, rng)
    depth[rng.random(SHAPE) < 0.01] = 0
    label[depth == 0] = labels.NO_DEPTH
    return depth, label, {"generator": "toy", "index": index, "objects": boxes}


def toy_source(config: dict, seed: int):
    return lambda index: toy_frame(seed, index, config["noise"])


def slow_source(config: dict, seed: int):
    """Like `toy_source` at about TOY_FRAME_S (env, default 0.05) seconds a frame."""
    delay = float(os.environ.get("TOY_FRAME_S", "0.05"))

    def source(index: int):
        time.sleep(delay)
        return toy_frame(seed, index, config["noise"])

    return source


def failing_source(config: dict, seed: int):
    """Breaks the frame contract at frame 5 (labels of the wrong dtype)."""

    def source(index: int):
        depth, label, scene = toy_frame(seed, index, config["noise"])
        return (depth, label.astype(np.int32), scene) if index == 5 else (depth, label, scene)

    return source


def crashing_source(config: dict, seed: int):
    """Kills its own worker process at frame 3, as a segfault in a renderer would."""
    import signal

    def source(index: int):
        if index == 3:
            os.kill(os.getpid(), signal.SIGKILL)
        return toy_frame(seed, index, config["noise"])

    return source
