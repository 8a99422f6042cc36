"""The static cell of a rendered scene as `topseg calibrate --background` would record it:
the scene without people and robots (a robot arm moves), rendered BACKGROUND_FRAMES times
with the sensor's noise and fitted (`background.fit_background`)."""

from __future__ import annotations

import numpy as np

from topseg.core.background import BackgroundModel, fit_background
from topseg.core.synth.scene import Scene
from topseg.core.synth.sequences import CellSequence
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

#: noisy frames of the empty scene a background is fitted from
BACKGROUND_FRAMES = 8


def static_background(synth: Synthesizer, scene: dict, mount, seed: int = 0) -> BackgroundModel:
    """The background of `scene` (a `Scene` dict) seen from `mount` by `synth`'s sensor:
    its scene without people and robots, BACKGROUND_FRAMES frames with noise."""
    empty = Scene.from_dict(scene)
    empty.human, empty.extra_humans, empty.robots = None, [], []
    empty.relations = []
    rng = np.random.default_rng([seed, 0x6267])
    frames = [synth.render_scene(Scene.from_dict(empty.to_dict()), rng).depth
              for _ in range(BACKGROUND_FRAMES)]  # fmt: skip
    return fit_background(frames, mount.intrinsics, sensor=mount.sensor, mount=mount)


def sequence_background(seq: CellSequence, camera: int = 0) -> BackgroundModel:
    """The static cell of a rendered cell sequence as its camera `camera` (an index into its
    cameras) records it: the scene at its start (the table and the parts on it) without
    people or the robot."""
    config = SynthesisConfig(noise=seq.config.noise, camera=seq.mount, seed=seq.seed)
    scene = seq.seen_from(seq.scene_at(0.0), camera)
    with Synthesizer(config, warm=False) as synth:
        return static_background(synth, scene.to_dict(), seq.mount, seed=seq.seed)


__all__ = ["BACKGROUND_FRAMES", "sequence_background", "static_background"]
