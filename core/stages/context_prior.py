"""The context prior (`core.context_prior`): before the CRF, every cell above the floor gate
is scored from the forest's posteriors around it and its group probabilities are folded into
its pixels' posteriors. Off without a prior in the model, with `--context-prior off` and for
a model that reads raw depth (no heights)."""

from __future__ import annotations

import numpy as np

from topseg.core.context_check import CellGrid, cell_grid
from topseg.core.context_prior import PRIOR_CELL_PX, apply_prior, prior_cells
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
        found = frame_prior_cells(frame) if self.active(frame) else None
        if found is not None:
            grid, rows, cols, valid = found
            cells = int(rows.size)
            changed = apply_prior(
                self.model.context_prior, grid, rows, cols, frame.fill(None), valid,
                frame.summary,
            )  # fmt: skip
        frame.counts.update(prior_cells=cells, prior_changed_px=changed)

    def active(self, frame: FrameState) -> bool:
        """Whether this frame gets the prior."""
        return (
            self.model.context_prior is not None
            and self.model.config.grid.context_prior == "on"
            and frame.plan.work_mount is not None
        )


def frame_prior_cells(
    frame: FrameState, near_people: bool = True
) -> tuple[CellGrid, np.ndarray, np.ndarray, np.ndarray] | None:
    """The prior's cell grid of `frame` after its forest (every posterior stored, the
    forest's argmax as its labels), with the (rows, cols) of its cells (`prior_cells`: the
    ones it scores, or with `near_people` False every one above the floor, what `topseg
    person-check` fits it on) and the pixels above the floor gate; None without such a
    cell."""
    valid = frame.inp.above_floor()
    grid = cell_grid(
        frame.summary.amax, valid, frame.heights(), frame.depth, frame.fill(None),
        frame.plan.work_mount.intrinsics.fx, PRIOR_CELL_PX,
    )  # fmt: skip
    if grid is None:
        return None
    rows, cols = prior_cells(grid, near_people)
    return (grid, rows, cols, valid) if rows.size else None
