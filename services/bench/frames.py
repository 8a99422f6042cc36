"""The frames the forest and CRF benches time: rendered modeled scenes with sensor noise.

By default `rendered_frames` draws modeled scenes from the density function, renders them
from one camera (the paper's Kinect v1 mount unless another is given) and adds that sensor's
own noise model: what the bundled model labels live. `procedural_frames` gives the quick
procedural top views instead (`--frames-from procedural`), for benches that train a forest on
the spot.
"""

from __future__ import annotations

import argparse

import numpy as np

RENDERED, PROCEDURAL = "rendered", "procedural"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`--frames-from` (rendered or procedural)."""
    parser.add_argument(
        "--frames-from",
        choices=(RENDERED, PROCEDURAL),
        default=RENDERED,
        help="rendered modeled scenes with the sensor's noise (default) or procedural top views",
    )


def bench_mount():
    """The camera bench frames are seen from: the paper's Kinect v1, 640x480, straight down."""
    from topseg.core.camera import PAPER_MOUNT

    return PAPER_MOUNT


def rendered_frames(n: int, seed: int, mount=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(depth, truth)] of n modeled scenes rendered from `mount` with its sensor's noise."""
    from topseg.core.synth.synthesis import SENSOR_NOISE, SynthesisConfig, Synthesizer

    config = SynthesisConfig(noise=SENSOR_NOISE, camera=mount or bench_mount(), seed=seed)
    synth = Synthesizer(config)
    try:
        return [(f.depth, f.labels) for f in (synth.render(i) for i in range(n))]
    finally:
        synth.close()


def bench_frames(kind: str, n: int, seed: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], str]:
    """[(depth, truth)] of the chosen kind and a phrase saying what they are."""
    if kind == PROCEDURAL:
        from topseg.core.synth import procedural

        rng = np.random.default_rng(seed)
        return [procedural.procedural_frame(rng) for _ in range(n)], "procedural top views"
    mount = bench_mount()
    k = mount.intrinsics
    what = (
        f"rendered modeled scenes, {k.width}x{k.height} {mount.sensor} at "
        f"{mount.height_mm / 1000:.2f} m with its noise"
    )
    return rendered_frames(n, seed, mount), what
