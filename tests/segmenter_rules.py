"""The Segmenter's island rules applied by hand, with its default constants: the tests that
rebuild its labels from the forest or the CRF (legacy path, segmenter, worker, segment) share
this one call, so a new rule argument is added in one place."""

import numpy as np

from topseg.core import segmenter_config as S
from topseg.core.context_check import (
    BODY_PARTS,
    cell_features,
    cell_grid,
    part_cells,
    rejected_pixels,
    restore_cells,
    restored_pixels,
)
from topseg.core.context_prior import PRIOR_CELL_PX, apply_prior, prior_cells
from topseg.core.crf.argmax import Summary, argmax_confidence
from topseg.core.islands import (
    EDGE_HEAD_SHARE,
    ISLAND_EDGE_PX,
    SATELLITE_RADIUS_CM,
    edge_shares,
    island_areas,
    relabel_islands,
)
from topseg.core.person_check import IS_PART, REPLACEMENT, blob_features, relabel_blobs
from topseg.core.person_check_kernels import relabel_rejected
from topseg.core.surfaces import surface_step_mm, vote_surfaces, voting_table

#: the Segmenter's default minimum areas, per class
AREAS = island_areas(S.MIN_HEAD_CM2, S.MIN_FURNITURE_CM2, S.MIN_PLANT_CM2)


def relabel_as_the_segmenter(labels, depth, k):
    """The Segmenter's island rules on `labels`, in place (depth and intrinsics `k` measure
    the blobs): (small blobs relabelled per class, satellite heads relabelled)."""
    return relabel_islands(
        labels, depth, k, AREAS, S.SATELLITE_HEAD_CM2, SATELLITE_RADIUS_CM,
        ISLAND_EDGE_PX, edge_shares(EDGE_HEAD_SHARE),
    )  # fmt: skip


def prior_as_the_segmenter(proba, depth, inp, mount, prior):
    """The Segmenter's context prior on the forest's posteriors, in place (working-resolution
    depth, model input and mount; None: a model without one): pixels whose argmax moved."""
    if prior is None:
        return 0
    valid = inp.above_floor()
    summary = Summary(*argmax_confidence(proba, depth > 0))
    grid = cell_grid(summary.amax, valid, mount.height_map_mm(depth), depth, proba,
                     mount.intrinsics.fx, PRIOR_CELL_PX)  # fmt: skip
    rows, cols = prior_cells(grid) if grid is not None else ((), ())
    if len(rows) == 0:
        return 0
    return apply_prior(prior, grid, rows, cols, proba, valid, summary)


def check_context_as_the_segmenter(labels, depth, inp, proba, mount, check):
    """The Segmenter's context check on `labels` after its CRF, in place (working-resolution
    depth, model input, posteriors and mount; None: a model without one): pixels
    relabelled (rejected and restored; none in a frame without a body-part label)."""
    if check is None or not IS_PART[labels].any():
        return 0
    valid = inp.above_floor()
    grid = cell_grid(labels, valid, mount.height_map_mm(depth), depth, proba, mount.intrinsics.fx)
    if grid is None:
        return 0
    (part_rows, part_cols), (more_rows, more_cols) = part_cells(grid), restore_cells(grid)
    rows, cols = np.r_[part_rows, more_rows], np.r_[part_cols, more_cols]
    restorable = np.arange(rows.size) >= part_rows.size
    people = check.judge(cell_features(grid, rows, cols), restorable)
    out, marks = ~people & ~restorable, np.array([False, True])
    rejected = rejected_pixels(grid, rows[out], cols[out], labels)
    n = relabel_rejected(labels, rejected, marks, proba, REPLACEMENT)
    back = people & restorable
    restored = restored_pixels(grid, rows[back], cols[back], labels)
    return n + relabel_rejected(labels, restored, marks, proba, BODY_PARTS)


def check_people_as_the_segmenter(labels, depth, proba, mount, check):
    """The Segmenter's person check on `labels` after its CRF, in place (working-resolution
    depth, posteriors and mount): (blobs, pixels) relabelled."""
    blobs = blob_features(
        labels, depth, mount.height_map_mm(depth), proba, mount.intrinsics, mount.height_mm
    )
    if blobs.count == 0:
        return 0, 0
    return relabel_blobs(labels, blobs, check.people(blobs), proba)


def vote_as_the_segmenter(labels, depth, mount, n_classes):
    """The Segmenter's surface vote on `labels` after its person check, in place
    (working-resolution depth and mount of a model of `n_classes`): (pixels, surfaces)."""
    return vote_surfaces(labels, depth, surface_step_mm(mount.sensor), voting_table(n_classes))
