"""One frame's path through the Segmenter as a list of stages.

`Segmenter.label` resolves a `FramePlan` once per frame (`plan.py`, through the model's input
adapter in `readers.py`), then runs `STAGES` in order over one `FrameState`:

  pre          range to depth, holes filled, decimation, edge thinning, smoothing
  model_input  heights, offset scales and the floor gate (or a depth model's raw depth)
  background   pixels that match the static cell's recorded background join the floor gate
  forest       the forest's posteriors (lazy on a grid)
  context_prior what each cell is, judged from the posteriors around it, folded into them
  crf          the Potts CRF
  context_check body-part pixels of cells the model's context check says are not a person's
               take another class
  person_check body-part blobs the model's person check says are not people take another class
  surfaces     robot and object pixels on one continuous surface take its majority class
  post         island rules, labels brought back to the frame's resolution

Every stage is timed by `run_stages` and counts what it changed in `FrameState.counts` under
the names it declares (`Stage.counters`), so callers report every stage and counter without
naming them. A new stage is one module here and one line in `STAGES`.
"""

from __future__ import annotations

import time

from topseg.core.stages.background import BackgroundStage
from topseg.core.stages.base import FORESTS_SHARE, Stage, StageModel
from topseg.core.stages.context_check import ContextCheckStage
from topseg.core.stages.context_prior import ContextPriorStage
from topseg.core.stages.crf import CRFStage
from topseg.core.stages.forest import ForestStage
from topseg.core.stages.model_input import ModelInputStage
from topseg.core.stages.person_check import PersonCheckStage
from topseg.core.stages.plan import FramePlan, FrameState
from topseg.core.stages.post import PostStage
from topseg.core.stages.pre import PreStage
from topseg.core.stages.surfaces import SurfaceVoteStage

#: the stages, in the order a frame goes through them
STAGES: tuple[type[Stage], ...] = (
    PreStage,
    ModelInputStage,
    BackgroundStage,
    ForestStage,
    ContextPriorStage,
    CRFStage,
    ContextCheckStage,
    PersonCheckStage,
    SurfaceVoteStage,
    PostStage,
)

__all__ = [
    "FORESTS_SHARE",
    "STAGES",
    "FramePlan",
    "FrameState",
    "Stage",
    "StageModel",
    "build_stages",
    "counter_names",
    "run_stages",
]


def build_stages(model: StageModel) -> tuple[Stage, ...]:
    """One instance of every registered stage for a loaded model (stages may keep buffers)."""
    return tuple(cls(model) for cls in STAGES)


def counter_names(stages: tuple[Stage, ...]) -> tuple[str, ...]:
    """Every counter the stages keep, in stage order."""
    return tuple(name for stage in stages for name in stage.counters)


def run_stages(stages: tuple[Stage, ...], frame: FrameState) -> dict[str, float]:
    """Run `stages` over `frame` in order; the milliseconds each took, by stage name."""
    ms: dict[str, float] = {}
    for stage in stages:
        t0 = time.perf_counter()
        stage.run(frame)
        ms[stage.name] = 1000.0 * (time.perf_counter() - t0)
    return ms
