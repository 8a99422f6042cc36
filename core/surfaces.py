"""One surface, one thing: pixels of the robot and object classes that lie on one continuous
surface take that surface's majority class.

The forest labels each pixel from depth differences within about +-14 cm. From above, the top
of a large robot link at a low ceiling fills much of the image, and its middle is as flat as a
box's lid, so the forest and the CRF leave it a patchwork of `robot` and `object`. A robot
link, a cabinet or a drum is one rigid thing: its surface seen from above is continuous, and a
different thing beside it is almost always at another height. So the pixels labelled robot or
object are joined into surfaces: 4-neighbours whose depths differ by at most `step_mm` (a
multiple of the sensor's depth noise there, at least `MIN_STEP_MM`), and each surface takes
the class most of its pixels hold. Body parts, furniture and background are never changed and
never join a surface.

`surface_step_mm` gives the step for a sensor; `vote_surfaces` relabels in place. The kernel's
numpy reference is `tests/reference.py::vote_surfaces_reference`.
"""

from __future__ import annotations

from functools import lru_cache

import numba
import numpy as np

from topseg.core import labels as L
from topseg.core.sensors import depth_sigma_mm
from topseg.core.union_find import find_root

#: the classes that vote: what one rigid thing in the cell is labelled as
VOTING_IDS: tuple[int, ...] = L.OPEN_WORLD_IDS
#: two neighbours are on one surface when their depths differ by at most this many sigma of
#: the sensor's depth noise at their depth
STEP_SIGMAS = 2.0
#: ... and never less than this (mm): a surface sloping away from the camera
MIN_STEP_MM = 40.0
#: the step table's depth bins (mm) and its reach
STEP_BIN_MM = 10
STEP_MAX_MM = 12000


@lru_cache(maxsize=16)
def surface_step_mm(sensor: str, sigmas: float = STEP_SIGMAS) -> np.ndarray:
    """float32 table of the largest depth step (mm) within one surface, per STEP_BIN_MM of
    depth up to STEP_MAX_MM, for `sensor`'s noise (read-only)."""
    depth = np.arange(0, STEP_MAX_MM + STEP_BIN_MM, STEP_BIN_MM, dtype=np.float32)
    step = np.maximum(np.float32(sigmas) * depth_sigma_mm(depth, sensor), MIN_STEP_MM)
    step = step.astype(np.float32)
    step.flags.writeable = False
    return step


@numba.njit(cache=True)
def _joins(depth, r0, c0, r1, c1, step):
    """Whether two voting pixels lie on one surface: both with depth, within the step."""
    a = depth[r0, c0]
    b = depth[r1, c1]
    if a <= 0 or b <= 0:
        return False
    i = int(min(a, b)) // STEP_BIN_MM
    limit = step[min(i, step.shape[0] - 1)]
    return abs(np.float32(a) - np.float32(b)) <= limit


@numba.njit(cache=True)
def _vote(labels, depth, voting, step):
    """The kernel of `vote_surfaces`: (pixels relabelled, surfaces that changed)."""
    rows, cols = labels.shape
    n = rows * cols
    parent = np.arange(n, dtype=np.int32)
    for r in range(rows):
        for c in range(cols):
            if not voting[labels[r, c]] or depth[r, c] <= 0:
                continue
            here = r * cols + c
            if c > 0 and voting[labels[r, c - 1]] and _joins(depth, r, c, r, c - 1, step):
                a, b = find_root(parent, here), find_root(parent, here - 1)
                if a != b:
                    parent[max(a, b)] = min(a, b)
            if r > 0 and voting[labels[r - 1, c]] and _joins(depth, r, c, r - 1, c, step):
                a, b = find_root(parent, here), find_root(parent, here - cols)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    n_classes = voting.shape[0]
    counts = np.zeros((n, 2), np.int32)  # per root: votes for the first and the second id
    ids = np.full(2, -1, np.int32)
    for k in range(n_classes):
        if voting[k]:
            if ids[0] < 0:
                ids[0] = k
            else:
                ids[1] = k
    for r in range(rows):
        for c in range(cols):
            lab = labels[r, c]
            if voting[lab] and depth[r, c] > 0:
                root = find_root(parent, r * cols + c)
                counts[root, 0 if lab == ids[0] else 1] += 1
    changed = 0
    surfaces = 0
    seen = np.zeros(n, np.bool_)
    for r in range(rows):
        for c in range(cols):
            lab = labels[r, c]
            if not voting[lab] or depth[r, c] <= 0:
                continue
            root = find_root(parent, r * cols + c)
            first, second = counts[root, 0], counts[root, 1]
            if first == second:  # a tie leaves the surface as it is
                continue
            winner = ids[0] if first > second else ids[1]
            if lab != winner:
                labels[r, c] = winner
                changed += 1
                if not seen[root]:
                    seen[root] = True
                    surfaces += 1
    return changed, surfaces


def voting_table(n_classes: int) -> np.ndarray:
    """bool table over label ids (256 entries): True for the classes that vote, when the
    model has both of them (a model without robot and object classes votes on nothing)."""
    table = np.zeros(256, np.bool_)
    if max(VOTING_IDS) < n_classes:
        table[list(VOTING_IDS)] = True
    return table


def vote_surfaces(
    labels: np.ndarray, depth: np.ndarray, step_mm: np.ndarray, voting: np.ndarray
) -> tuple[int, int]:
    """Relabel, in place, the voting pixels of (H, W) uint8 `labels` to the majority class of
    the continuous surface they lie on (module docstring); `depth` in mm (0: none, never
    voting), `step_mm` a `surface_step_mm` table, `voting` a `voting_table`. Exactly two
    classes vote. Returns (pixels relabelled, surfaces that changed)."""
    if labels.shape != np.shape(depth):
        raise ValueError(f"labels {labels.shape} and depth {np.shape(depth)} differ in shape")
    if labels.dtype != np.uint8:
        raise ValueError(f"labels must be uint8, got {labels.dtype}")
    if int(voting.sum()) not in (0, 2):
        raise ValueError(f"exactly two classes vote, got {int(voting.sum())}")
    if not voting.any():
        return 0, 0
    changed, surfaces = _vote(labels, np.asarray(depth), voting, step_mm)
    return int(changed), int(surfaces)


def warm_up_surfaces(shape: tuple[int, int]) -> None:
    """Compile (or load from numba's cache) the vote's kernel for the depth types the stages
    hand it (uint16 working depth, float32 smoothed depth), on a small frame."""
    labels = np.full(shape, L.ROBOT, np.uint8)
    labels[: shape[0] // 2] = L.OBJECT
    voting = voting_table(L.NUM_CLASSES)
    step = surface_step_mm("kinect_v1")
    for dtype in (np.uint16, np.float32):
        vote_surfaces(labels.copy(), np.full(shape, 2000, dtype), step, voting)
