"""The model input: what the forest reads of the pre-processed frame, built by the model's
input adapter (heights, offset scales and the floor gate; or a depth model's raw depth)."""

from __future__ import annotations

from topseg.core.stages.base import Stage
from topseg.core.stages.plan import FrameState


class ModelInputStage(Stage):
    """`FrameState.inp` from `forest_depth`, by the model's adapter (`readers`)."""

    name = "model_input"

    def run(self, frame: FrameState) -> None:
        """Build the frame's model input."""
        frame.inp = self.model.reader.model_input(frame.forest_depth, frame.plan)
