"""The forest: class posteriors of every pixel, walked on the plan's grid.

The posteriors buffer is reused across frames of one size (one Segmenter serves one thread).
On a grid only the posteriors the CRF reads are stored (`lazy`); `FrameState.fill` stores the
rest when asked, and only until the next frame overwrites the buffer.
"""

from __future__ import annotations

import numpy as np

from topseg.core.crf import segment_argmax
from topseg.core.crf.argmax import Summary
from topseg.core.errors import TopsegError
from topseg.core.forest.inputs import ModelInput
from topseg.core.forest.predict import fill_posteriors, predict_proba
from topseg.core.stages.base import Stage, StageModel
from topseg.core.stages.plan import FrameState


class ForestStage(Stage):
    """`FrameState.proba`, `summary`, `fill` and the forest's own labels."""

    name = "forest"

    def __init__(self, model: StageModel) -> None:
        super().__init__(model)
        self._out: np.ndarray | None = None
        self._summary: Summary | None = None  # the CRF's per-pixel view of _out
        self._frame = 0  # counts writes into _out (a frame's `fill` serves only its own)

    def predict(self, inp: ModelInput, stride: int, lazy: bool = False) -> np.ndarray:
        """The posteriors of `inp` into the reused buffer (on the grid `stride`)."""
        shape = (*inp.shape, self.model.forest.n_classes)
        if self._out is None or self._out.shape != shape:
            self._out = np.empty(shape, np.float32)
            self._summary = Summary.empty(inp.shape)  # filled with _out, read by the CRF
        self._frame += 1
        config = self.model.config
        return predict_proba(
            self.model.forest,
            inp,
            out=self._out,
            stride=stride,
            summary=self._summary,
            lazy=lazy,
            adaptive=config.grid.adaptive,
            early_exit=config.grid.early_exit,
        )

    def run(self, frame: FrameState) -> None:
        """Walk the trees on the frame's grid."""
        inp, stride = frame.inp, frame.plan.stride
        proba = self.predict(inp, stride, lazy=stride > 1)
        frame.proba, frame.summary, frame.lazy = proba, self._summary, stride > 1
        # closures over the frame's parts, never the frame itself: a frame that held itself
        # would be freed by the cycle collector only, frames later
        fill = frame.fill = self._filler(inp, proba, stride)
        frame.working_forest_labels = lambda: segment_argmax(fill(None), inp.values > 0)

    def _filler(self, inp: ModelInput, proba: np.ndarray, stride: int):
        """`fill(mask)`: store the posteriors a grid left out at `mask` (None: all), for
        this frame only."""
        frame, filled = self._frame, [stride == 1]

        def fill(mask: np.ndarray | None = None) -> np.ndarray:
            if self._frame != frame:
                raise TopsegError(
                    "Segmentation.proba of an earlier frame: the Segmenter has labelled "
                    "another since (copy proba before the next label)"
                )
            if not filled[0]:
                fill_posteriors(inp, proba, stride, mask)
                filled[0] = mask is None
            return proba

        return fill
