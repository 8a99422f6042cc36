"""The context check (`core.context_check`): body-part pixels of cells that the model's
context check says are not a person's take their most probable other class, and, where the
check restores, the robot, object and furniture pixels of cells it says are a person's take
their most probable body part. It runs on frames holding body-part labels, when the person
check does (the same switch, `--person-check`), and only with a check in the model."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topseg.core.context_check import (
    BODY_PARTS,
    cell_features,
    cell_grid,
    part_cells,
    rejected_pixels,
    restore_cells,
    restored_pixels,
)
from topseg.core.person_check import IS_PART, REPLACEMENT
from topseg.core.person_check_kernels import relabel_rejected
from topseg.core.stages.base import CRFS_SHARE, Stage
from topseg.core.stages.person_check import checks_run
from topseg.core.stages.plan import FrameState

#: `relabel_rejected`'s table for a 0/1 image: pixels marked 1 are relabelled
_MARKED = np.array([False, True])


class ContextCheckStage(Stage):
    """Relabel the body-part pixels of cells that are not a person's, and restore the cells
    that are, at the working resolution."""

    name = "context_check"
    counters = ("not_person_cells", "not_person_cell_px", "restored_cells", "restored_cell_px")
    share = CRFS_SHARE

    def run(self, frame: FrameState) -> None:
        """Score every cell of `frame.labels` holding body parts, relabel the ones that fail;
        restore the cells of `restore_cells` that pass."""
        done = Checked()
        if self.active(frame):
            done = check_cells(frame, self.model.context_check)
        frame.counts.update(
            not_person_cells=done.rejected_cells, not_person_cell_px=done.rejected_px,
            restored_cells=done.restored_cells, restored_cell_px=done.restored_px,
        )  # fmt: skip

    def active(self, frame: FrameState) -> bool:
        """Whether this frame gets the check."""
        return self.model.context_check is not None and checks_run(self.model, frame)


@dataclass(frozen=True)
class Checked:
    """What the check changed in a frame: cells and pixels rejected, cells and pixels
    restored."""

    rejected_cells: int = 0
    rejected_px: int = 0
    restored_cells: int = 0
    restored_px: int = 0


def frame_cells(frame: FrameState, restoring: bool):
    """The cell grid of `frame` after its CRF, with the (rows, cols) of the cells the check
    scores (those holding body parts, then, `restoring`, those of `restore_cells`), their
    features and which of them are restore cells (what the check scores and what `topseg
    person-check` fits it on); None without a body-part pixel."""
    labels = frame.labels
    if not IS_PART[labels].any():
        return None
    mount = frame.plan.work_mount
    valid = frame.inp.above_floor()
    heights = frame.heights()
    proba = frame.fill(None)  # every posterior: the rings read cells all over the frame
    grid = cell_grid(labels, valid, heights, frame.depth, proba, mount.intrinsics.fx)
    if grid is None:
        return None
    part_rows, part_cols = part_cells(grid)
    more_rows, more_cols = restore_cells(grid) if restoring else (part_rows[:0], part_cols[:0])
    rows, cols = np.concatenate([part_rows, more_rows]), np.concatenate([part_cols, more_cols])
    restorable = np.arange(rows.size) >= part_rows.size
    return grid, rows, cols, cell_features(grid, rows, cols), restorable


def check_cells(frame: FrameState, check) -> Checked:
    """Run `check` over `frame` after its CRF: what it relabelled."""
    found = frame_cells(frame, check.restore_threshold is not None)
    if found is None:
        return Checked()
    grid, rows, cols, features, restorable = found
    people = check.judge(features, restorable)
    rejected, restored = ~people & ~restorable, people & restorable
    proba = frame.fill(None)  # every posterior, filled already by `frame_cells`
    rejected_px = restored_px = 0
    if rejected.any():
        marked = rejected_pixels(grid, rows[rejected], cols[rejected], frame.labels)
        rejected_px = relabel_rejected(frame.labels, marked, _MARKED, proba, REPLACEMENT)
    if restored.any():
        marked = restored_pixels(grid, rows[restored], cols[restored], frame.labels)
        restored_px = relabel_rejected(frame.labels, marked, _MARKED, proba, BODY_PARTS)
    return Checked(int(rejected.sum()), int(rejected_px), int(restored.sum()), int(restored_px))
