"""What every stage is: a name, the counters it keeps, the headline figure its time adds to."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

from topseg.core.segmenter_config import SegmenterConfig

if TYPE_CHECKING:
    from topseg.core.background import BackgroundModel
    from topseg.core.context_check import ContextCheck
    from topseg.core.context_prior import ContextPrior
    from topseg.core.forest.tree import Forest
    from topseg.core.person_check import PersonCheck
    from topseg.core.stages.plan import FrameState
    from topseg.core.stages.readers import ModelReader

#: the headline figures a stage's time adds to: the forest's share (everything up to and with
#: the walk of the trees) and the CRF's (the CRF and what follows it)
FORESTS_SHARE = "forest"
CRFS_SHARE = "crf"


@dataclass(frozen=True)
class StageModel:
    """What stages are built from: the loaded forest, its input adapter, the run settings,
    the recorded background of a static cell, the model's context and person checks and its
    context prior (None: none)."""

    forest: Forest
    reader: ModelReader
    config: SegmenterConfig
    background: BackgroundModel | None = None
    person_check: PersonCheck | None = None
    context_check: ContextCheck | None = None
    context_prior: ContextPrior | None = None


class Stage:
    """One step of a frame's path. Subclasses set `name`, `counters` and `share` and
    implement `run`, which reads and updates a `FrameState` in place."""

    name: ClassVar[str]
    #: the counters this stage adds to `FrameState.counts` (every frame sets each of them)
    counters: ClassVar[tuple[str, ...]] = ()
    #: which headline figure (`Timings.forest_ms` or `crf_ms`) this stage's time adds to
    share: ClassVar[str] = FORESTS_SHARE

    def __init__(self, model: StageModel) -> None:
        self.model = model

    def run(self, frame: FrameState) -> None:
        """Do this stage's work on `frame`."""
        raise NotImplementedError
