"""The context check (`core.context_check`): body-part pixels of cells that the model's
context check says are not a person's take their most probable other class. It runs when the
person check does (the same switch, `--person-check`), and only with a check in the model."""

from __future__ import annotations

import numpy as np

from topseg.core.context_check import cell_features, cell_grid, part_cells, rejected_pixels
from topseg.core.person_check import IS_PART, REPLACEMENT
from topseg.core.person_check_kernels import relabel_rejected
from topseg.core.stages.base import CRFS_SHARE, Stage
from topseg.core.stages.person_check import checks_run
from topseg.core.stages.plan import FrameState

#: `relabel_rejected`'s table for a 0/1 image: pixels marked 1 are relabelled
_MARKED = np.array([False, True])


class ContextCheckStage(Stage):
    """Relabel the body-part pixels of cells that are not a person's, at the working
    resolution."""

    name = "context_check"
    counters = ("not_person_cells", "not_person_cell_px")
    share = CRFS_SHARE

    def run(self, frame: FrameState) -> None:
        """Score every cell of `frame.labels` holding body parts, relabel the ones that fail."""
        cells, px = 0, 0
        if self.active(frame):
            cells, px = check_cells(frame, self.model.context_check)
        frame.counts.update(not_person_cells=cells, not_person_cell_px=px)

    def active(self, frame: FrameState) -> bool:
        """Whether this frame gets the check."""
        return self.model.context_check is not None and checks_run(self.model, frame)


def frame_cells(frame: FrameState):
    """The cell grid of `frame` after its CRF, with the (rows, cols) of its cells holding
    body parts and their features (what the check scores and what `topseg person-check`
    fits it on); None without a body-part pixel."""
    labels = frame.labels
    if not IS_PART[labels].any():
        return None
    mount = frame.plan.work_mount
    valid = (frame.inp.values > 0) & ~frame.inp.floor
    heights = frame.heights()
    proba = frame.fill(None)  # every posterior: the rings read cells all over the frame
    grid = cell_grid(labels, valid, heights, frame.depth, proba, mount.intrinsics.fx)
    if grid is None:
        return None
    rows, cols = part_cells(grid)
    return grid, rows, cols, cell_features(grid, rows, cols)


def check_cells(frame: FrameState, check) -> tuple[int, int]:
    """Run `check` over `frame` after its CRF: (cells, pixels) relabelled."""
    found = frame_cells(frame)
    if found is None:
        return 0, 0
    grid, rows, cols, features = found
    people = check.people(features)
    if people.all():
        return 0, 0
    marked = rejected_pixels(grid, rows, cols, people, frame.labels)
    proba = frame.fill(None)  # every posterior, filled already by `frame_cells`
    px = relabel_rejected(frame.labels, marked, _MARKED, proba, REPLACEMENT)
    return int((~people).sum()), int(px)
