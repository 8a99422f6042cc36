"""The context prior (`core.context_prior`): before the CRF, every cell above the floor gate
is scored from the forest's posteriors around it and its group probabilities are folded into
its pixels' posteriors. Off without a prior in the model, with `--context-prior off` and for
a model that reads raw depth (no heights)."""

from __future__ import annotations

from topseg.core.context_prior import apply_prior
from topseg.core.stages.base import FORESTS_SHARE, Stage
from topseg.core.stages.plan import FrameState


class ContextPriorStage(Stage):
    """Fold the model's context prior into the forest's posteriors and their summary."""

    name = "context_prior"
    counters = ("prior_cells", "prior_changed_px")
    share = FORESTS_SHARE

    def run(self, frame: FrameState) -> None:
        """Score the frame's cells, reweight its posteriors (every one stored first)."""
        cells = changed = 0
        if self.active(frame):
            inp = frame.inp
            proba = frame.fill(None)
            cells, changed = apply_prior(
                self.model.context_prior, proba, (inp.values > 0) & ~inp.floor,
                frame.summary.amax, frame.heights(), frame.depth,
                frame.plan.work_mount.intrinsics.fx, frame.summary,
            )  # fmt: skip
        frame.counts.update(prior_cells=cells, prior_changed_px=changed)

    def active(self, frame: FrameState) -> bool:
        """Whether this frame gets the prior."""
        return (
            self.model.context_prior is not None
            and self.model.config.grid.context_prior == "on"
            and frame.plan.work_mount is not None
            and frame.summary is not None
        )
