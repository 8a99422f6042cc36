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

from topseg.core.camera import PAPER_MOUNT, TopViewMount
from topseg.core.sensors import NAMES, get_sensor
from topseg.core.synth.synthesis import SENSOR_NOISE, SynthesisConfig, Synthesizer
from topseg.services.cli.options import finite

RENDERED, PROCEDURAL = "rendered", "procedural"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`--frames-from` (rendered or procedural), `--sensor` and `--height` (the camera)."""
    parser.add_argument(
        "--frames-from",
        choices=(RENDERED, PROCEDURAL),
        default=RENDERED,
        help="rendered modeled scenes with the sensor's noise (default) or procedural top views",
    )
    parser.add_argument(
        "--sensor",
        choices=NAMES,
        default=None,
        help="rendered frames: the camera's sensor, its resolution and noise (default "
        "kinect_v1, the paper's)",
    )
    parser.add_argument(
        "--height",
        type=finite(1.0, 8.0),
        default=None,
        metavar="M",
        help="rendered frames: the camera's height above the floor in metres, straight down "
        "(default 3.5, the paper's)",
    )


def bench_mount(args: argparse.Namespace | None = None):
    """The camera bench frames are seen from: the paper's Kinect v1, 640x480, 3.5 m above the
    floor, straight down, unless `args` name another `--sensor` or `--height`."""
    sensor = getattr(args, "sensor", None)
    height = getattr(args, "height", None)
    if sensor is None and height is None:
        return PAPER_MOUNT
    intrinsics = get_sensor(sensor).intrinsics if sensor else PAPER_MOUNT.intrinsics
    return TopViewMount(
        intrinsics,
        PAPER_MOUNT.height_mm if height is None else 1000.0 * height,
        sensor=sensor or PAPER_MOUNT.sensor,
    )


def rendered_frames(n: int, seed: int, mount=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(depth, truth)] of n modeled scenes rendered from `mount` with its sensor's noise."""
    mount = mount or bench_mount()
    config = SynthesisConfig(noise=SENSOR_NOISE, camera=mount, seed=seed)
    synth = Synthesizer(config)
    h, w = mount.intrinsics.shape  # a dataset's frames may be padded to its largest camera
    try:
        return [(f.depth[:h, :w], f.labels[:h, :w]) for f in (synth.render(i) for i in range(n))]
    finally:
        synth.close()


def bench_frames(
    kind: str, n: int, seed: int, mount=None
) -> tuple[list[tuple[np.ndarray, np.ndarray]], str]:
    """[(depth, truth)] of the chosen kind (rendered ones seen from `mount`, by default
    `bench_mount()`) and a phrase saying what they are."""
    if kind == PROCEDURAL:
        from topseg.core.synth import procedural

        rng = np.random.default_rng(seed)
        return [procedural.procedural_frame(rng) for _ in range(n)], "procedural top views"
    mount = mount or bench_mount()
    k = mount.intrinsics
    what = (
        f"rendered modeled scenes, {k.width}x{k.height} {mount.sensor} at "
        f"{mount.height_mm / 1000:.2f} m with its noise"
    )
    return rendered_frames(n, seed, mount), what
