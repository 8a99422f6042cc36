"""Frame generators that datagen runs on its workers: name -> factory, and the factories.

A generator is a factory `make(config: dict, seed: int) -> FrameSource`, named by
`"module:function"` so that any worker process can import it; a `FrameSource` is a callable
`source(index) -> (depth u16 (H,W), labels u8 (H,W), scene dict)` with an optional
`close()`. A frame must depend only on (config, seed, index), never on what the source
rendered before, so a dataset is the same whatever the number of workers.

Built in:
- `synthesis`: the density-function scenes of `topseg.core.synth.synthesis` (the paper's data).
- `procedural`: `topseg.core.synth.procedural`'s analytic boxes, cylinders and spheres (fast to
  check the pipeline with; `non-modeled` draws one object alone, `modeled` 3..6).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import asdict
from typing import Any, Protocol

import numpy as np

from topseg.core import labels
from topseg.core.camera import metres_to_mm
from topseg.core.errors import TopsegError
from topseg.core.formats.dataset import frame_seed
from topseg.core.synth import procedural
from topseg.core.synth.noise import parse_noise
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

Frame = tuple[np.ndarray, np.ndarray, dict]

GENERATORS: dict[str, str] = {
    "synthesis": "topseg.services.batch.datagen.sources:synthesis_source",
    "procedural": "topseg.services.batch.datagen.sources:procedural_source",
}


class FrameSource(Protocol):
    """A generator: frame `index` of a dataset as a pure function of the index (resumable)."""

    def __call__(self, index: int) -> Frame: ...


def resolve(name: str) -> str:
    """A generator name (`GENERATORS`) or `module:function` -> `module:function`."""
    if name in GENERATORS:
        return GENERATORS[name]
    if ":" not in name:
        raise TopsegError(
            f"unknown generator {name!r}; use one of {', '.join(GENERATORS)} or module:function"
        )
    return name


#: Generator module paths that older datasets' headers name, and the module each is at; such
#: datasets still load.
MOVED_MODULES = {
    "topseg.services." + "datagen_sources": "topseg.services.batch.datagen.sources",
    "topseg.services." + "bench_datagen": "topseg.services.batch.bench.datagen",
}


def load_factory(target: str) -> Callable[[dict, int], FrameSource]:
    """Import the factory named `module:function`."""
    module_name, _, attr = target.partition(":")
    module_name = MOVED_MODULES.get(module_name, module_name)
    try:
        return getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise TopsegError(f"cannot load generator {target!r}: {exc}") from exc


#: share of freely placed people standing across an open edge of the view (cut by the image
#: border) in datasets with drawn mounts; the paper's fixed-mount datasets keep 0
EDGE_SHARE = 0.3


def generator_config(
    target: str,
    mode: str,
    noise: str,
    room: str | None,
    mounts: dict | None = None,
    cell: dict | None = None,
) -> dict:
    """The full, validated config a generator will get, as recorded in the dataset.

    `mounts` (a `MountDistribution.to_dict()`) draws each frame's camera mount, and people
    then walk in and out of view (EDGE_SHARE); None keeps the paper's fixed mount. `cell`
    (a partial `CellConfig` mapping) sets what `--mode cell` draws.
    """
    if target == GENERATORS["synthesis"]:
        from topseg.core.synth.cell_scenes import CellConfig
        from topseg.core.synth.density import DensityConfig
        from topseg.core.synth.synthesis import SynthesisConfig

        try:
            density = DensityConfig(
                human_edge_share=EDGE_SHARE if mounts is not None else 0.0,
                cell=CellConfig.from_dict(cell or {}),
            )
            return SynthesisConfig(
                mode=mode, noise=noise, room=room, mounts=mounts, density=density
            ).to_dict()
        except (TypeError, ValueError) as exc:
            raise TopsegError(f"bad synthesis settings: {exc}") from exc
    if mounts is not None:
        raise TopsegError(f"generator {target}: drawn mounts need the synthesis generator")
    if mode == "cell" or cell:
        raise TopsegError(f"generator {target}: --mode cell needs the synthesis generator")

    return {"mode": mode, "noise": parse_noise(noise).spec, "room": room}


def mount_summary(generator: dict) -> dict | None:
    """What the frames' mounts span for a synthesis generator's config (None: another
    generator; its frames come from the dataset's camera)."""
    if generator.get("factory") != GENERATORS["synthesis"]:
        return None

    return SynthesisConfig.from_dict(generator["config"]).mount_summary()


class _Synthesis:
    def __init__(self, config: dict, seed: int):
        self._synth = Synthesizer(SynthesisConfig.from_dict(config))
        self._seed = seed

    def __call__(self, index: int) -> Frame:
        frame = self._synth.render(frame_seed(self._seed, index))
        return frame.depth, frame.labels, frame.scene  # the scene carries the frame's mount

    def close(self) -> None:
        self._synth.close()


def synthesis_source(config: dict, seed: int) -> FrameSource:
    """The paper's scenes: one pybullet client per worker process, reused for every frame."""
    return _Synthesis(config, seed)


def procedural_source(config: dict, seed: int) -> FrameSource:
    """Analytic procedural scenes with the dataset's noise model (room is ignored)."""
    noise = parse_noise(config["noise"])
    n_objects = 1 if config["mode"] == "non-modeled" else None

    def source(index: int) -> Frame:
        rng = np.random.default_rng(frame_seed(seed, index))
        prims = procedural.random_scene(rng, n_objects=n_objects)
        depth_m, label = procedural.render(prims)
        depth = metres_to_mm(depth_m)
        depth = noise.apply(depth, rng, labels=label)
        label[depth == 0] = labels.NO_DEPTH
        scene: dict[str, Any] = {
            "generator": "procedural",
            "objects": [
                {"shape": type(p).__name__.lower(), **asdict(p), "class": labels.name_of(p.label)}
                for p in prims
            ],
        }
        return depth, label, scene

    return source
