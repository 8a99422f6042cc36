"""The CRF: labels minimising the Potts energy over the forest's posteriors (`core.crf`),
with the weight the frame's plan chose."""

from __future__ import annotations

from topseg.core.crf import segment_crf
from topseg.core.stages.base import CRFS_SHARE, Stage
from topseg.core.stages.plan import FrameState


class CRFStage(Stage):
    """`FrameState.labels` at the working resolution."""

    name = "crf"
    share = CRFS_SHARE

    def run(self, frame: FrameState) -> None:
        """Smooth the posteriors into labels."""
        fill = frame.fill if frame.lazy else None
        frame.labels = segment_crf(frame.proba, frame.depth, frame.plan.crf, frame.summary, fill)
