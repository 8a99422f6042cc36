"""The context check: is each small patch of body-part labels part of a person, seen with
what surrounds it up to 80 cm away?

The forest reads a pixel's depth within a hand's width, so the top of a robot's wrist, a
drum's rim or a box's corner can come out as a body part, and a crouching person's back as a
box. After the CRF, the frame is cut into cells (`CELL_PX` pixels square at a Kinect v1's
focal length, `cell_side`), each
described by what its labels are (person, head, robot, object, furniture, background), how
high it stands and what the forest's posteriors over it say, before the CRF chose one label
(`context_check_kernels.cell_channels`). A cell holding body-part labels is
then described by its own channels and, on rings 12 to 75 cm around it, the mean, highest and
lowest of the same channels in eight directions (`cell_features`, distances measured on the
floor at the cell's depth), and scored by a boosted tree ensemble the model file carries
(`ContextCheck`, fitted by `topseg person-check` on the model's own labels of rendered cells).
The body-part pixels of a cell scoring under `threshold` take their most probable class that
is neither a body part nor background. The same trees also score the cells that hold no body
part but robot, object or furniture labels where the forest's mean person posterior is at
least `RESTORE_FLOOR` (`restore_cells`: a crouching back the CRF called a box): with a
`restore_threshold`, those scoring at or above it give their robot, object and furniture
pixels their most probable body part. The blob-level person check runs after it.

Everything here is pure: numpy and the kernels of `context_check_kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from topseg.core import context_check_kernels as K
from topseg.core import labels as L
from topseg.core.errors import TopsegError
from topseg.core.person_check import IS_PART, TreeEnsemble, check_entry, finite_threshold

#: a cell is this many pixels square at a focal length of REFERENCE_FOCAL_PX (a Kinect v1's
#: 640 x 480), and proportionally fewer at a shorter working focal length (at least 1)
CELL_PX = 4
REFERENCE_FOCAL_PX = 570.3
#: rings around a cell (cm on the floor at the cell's depth) and the box read on each (cm)
RINGS_CM = (12.0, 25.0, 45.0, 75.0)
BOXES_CM = (6.0, 10.0, 16.0, 24.0)
#: directions read on every ring
DIRECTIONS = 8
_ANGLES = np.arange(DIRECTIONS) * (2 * np.pi / DIRECTIONS)
_SINES, _COSINES = np.sin(_ANGLES), np.cos(_ANGLES)
#: a cell without body-part labels is scored for restoring when the forest's mean person
#: posterior over it is at least this
RESTORE_FLOOR = 0.1
#: label -> whether the check may restore it to a body part (robot, object, furniture)
IS_RESTORABLE = np.zeros(256, np.bool_)
IS_RESTORABLE[[L.ROBOT, L.OBJECT, *L.FURNITURE_IDS]] = True
#: class -> whether a restored pixel may take it (the body parts)
BODY_PARTS = np.zeros(L.NUM_CLASSES, np.bool_)
BODY_PARTS[list(L.HUMAN_IDS)] = True
#: label -> the six label columns of a cell's channels (person, head, robot, object,
#: furniture, background)
CHANNEL_TABLE = np.zeros((256, K.LABEL_COLUMNS), np.float32)
CHANNEL_TABLE[list(L.HUMAN_IDS), 0] = 1.0
CHANNEL_TABLE[L.HEAD, 1] = 1.0
CHANNEL_TABLE[L.ROBOT, 2] = 1.0
CHANNEL_TABLE[L.OBJECT, 3] = 1.0
CHANNEL_TABLE[list(L.FURNITURE_IDS), 4] = 1.0
CHANNEL_TABLE[L.BACKGROUND, K.BACKGROUND_COLUMN] = 1.0
#: class -> the five posterior columns: the label columns but background
POSTERIOR_TABLE = CHANNEL_TABLE[: L.NUM_CLASSES, : K.POSTERIOR_COLUMNS].copy()
#: the channels `restore_cells` reads: robot to furniture labels, the person posterior
_ROBOT_COLUMN, _FURNITURE_COLUMN = 2, 4
_CHANNEL_NAMES = (
    "person", "head", "robot", "object", "furniture", "background", "height",
    "p_person", "p_head", "p_robot", "p_object", "p_furniture",
)  # fmt: skip
#: what each feature row holds, in order; a model file's check names them and must match
FEATURES: tuple[str, ...] = (
    *(f"cell_{n}" for n in _CHANNEL_NAMES),
    *(f"near_{n}" for n in _CHANNEL_NAMES),
    *(
        f"ring{int(r)}_{stat}_{n}"
        for r in RINGS_CM
        for stat in ("mean", "max", "min")
        for n in _CHANNEL_NAMES
    ),
)


@dataclass(frozen=True)
class CellGrid:
    """A frame cut into cells: `channels` (hc, wc, CHANNELS) float32, `cells_per_cm`
    (hc, wc) float32 (cells per cm on the floor at each cell's depth), `parts` (hc, wc) int32
    body-part pixels, `cell` working pixels per cell side."""

    channels: np.ndarray
    cells_per_cm: np.ndarray
    parts: np.ndarray
    cell: int


def cell_side(fx: float, cell_px: int = CELL_PX) -> int:
    """Working pixels a cell's side spans at the working focal length `fx` (px), for cells
    `cell_px` pixels square at REFERENCE_FOCAL_PX."""
    return max(1, round(cell_px * fx / REFERENCE_FOCAL_PX))


def cell_grid(
    labels: np.ndarray,
    valid: np.ndarray,
    heights_mm: np.ndarray,
    depth_mm: np.ndarray,
    proba: np.ndarray,
    fx: float,
    cell_px: int = CELL_PX,
) -> CellGrid | None:
    """The cells of a working frame: its labels, which pixels have depth above the floor
    gate (`valid`), their heights above the floor (NaN: none), depth (mm) and the forest's
    posteriors (H, W, classes), and the working focal length; cells `cell_px` pixels square
    at REFERENCE_FOCAL_PX. None without a valid pixel in a whole cell."""
    cell = cell_side(fx, cell_px)
    chan, depth_sum, n_valid, parts = K.cell_channels(
        labels, valid, heights_mm, depth_mm, proba, cell, CHANNEL_TABLE, POSTERIOR_TABLE
    )
    if not n_valid.any():
        return None
    frame_depth = depth_sum.sum() / n_valid.sum()
    mean_depth = np.where(n_valid > 0, depth_sum / np.maximum(n_valid, 1), frame_depth)
    per_cm = (fx * 10.0 / np.maximum(mean_depth, 1.0) / cell).astype(np.float32)
    return CellGrid(chan, per_cm, parts, cell)


def cell_features(grid: CellGrid, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(n, len(FEATURES)) float32 features of the cells at (rows, cols)."""
    return K.cell_features(
        grid.channels, grid.cells_per_cm, np.asarray(rows, np.int64), np.asarray(cols, np.int64),
        np.asarray(RINGS_CM), np.asarray(BOXES_CM), _SINES, _COSINES,
    )  # fmt: skip


def part_cells(grid: CellGrid) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the cells holding body-part labels: the ones the check scores."""
    return np.nonzero(grid.parts > 0)


def restore_cells(grid: CellGrid) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the cells the check scores for restoring: no body-part label, some
    robot, object or furniture label, and a mean person posterior of RESTORE_FLOOR or more."""
    chan = grid.channels
    restorable = chan[..., _ROBOT_COLUMN : _FURNITURE_COLUMN + 1].sum(axis=2) > 0
    person = chan[..., K.PERSON_POSTERIOR] >= RESTORE_FLOOR
    return np.nonzero((grid.parts == 0) & restorable & person)


@dataclass(frozen=True)
class ContextCheck:
    """A fitted context check: the body-part pixels of a cell whose `TreeEnsemble` score is
    below `threshold` (a logit) are not a person's; the cells of `restore_cells` scoring at
    or above `restore_threshold` are (None: none is restored, as checks fitted before
    restoring). `validation` holds what the fit measured on its held-out frames."""

    trees: TreeEnsemble
    threshold: float
    validation: dict
    restore_threshold: float | None = None

    #: the model header's key
    HEADER_KEY = "context_check"

    def judge(self, features: np.ndarray, restorable: np.ndarray) -> np.ndarray:
        """(n,) bool: which cells of these feature rows are a person's, a row of a cell of
        `restore_cells` (`restorable` True) only when it passes `restore_threshold`; one
        scoring pass over both kinds."""
        scores = self.trees.score(features)
        if self.restore_threshold is None:
            return np.where(restorable, False, scores >= self.threshold)
        return np.where(restorable, scores >= self.restore_threshold, scores >= self.threshold)

    def to_header(self) -> dict[str, Any]:
        """The header entry (`HEADER_KEY`): cell size, features named, trees, threshold,
        validation."""
        entry = {
            "cell_px": CELL_PX,
            "features": list(FEATURES),
            "threshold": self.threshold,
            "trees": self.trees.to_dict(),
            "validation": self.validation,
        }
        if self.restore_threshold is not None:
            entry.update(restore_threshold=self.restore_threshold, restore_floor=RESTORE_FLOOR)
        return entry

    @classmethod
    def from_header(cls, header: dict[str, Any]) -> ContextCheck | None:
        """The check a model header carries (None: none). TopsegError when it is malformed
        or reads features this topseg does not compute."""
        entry = header.get(cls.HEADER_KEY)
        if entry is None:
            return None
        if not isinstance(entry, dict):
            raise TopsegError("the model's context check is not a table")
        if entry.get("features") != list(FEATURES) or entry.get("cell_px") != CELL_PX:
            raise TopsegError(
                "the model's context check reads other cell features than this topseg "
                "computes (refit it: `topseg person-check`)"
            )
        restore = entry.get("restore_threshold")
        if restore is not None:
            if entry.get("restore_floor") != RESTORE_FLOOR:
                raise TopsegError(
                    "the model's context check restores other cells than this topseg scores "
                    "(refit it: `topseg person-check`)"
                )
            restore = finite_threshold(restore, "context check restore threshold")
        return cls(*check_entry(entry, "context check", len(FEATURES)), restore)


def restored_pixels(
    grid: CellGrid, rows: np.ndarray, cols: np.ndarray, labels: np.ndarray
) -> np.ndarray:
    """(H, W) uint8: 1 at the robot, object and furniture pixels of the cells (rows, cols),
    0 elsewhere."""
    return K.cells_to_pixels(_chosen(grid, rows, cols), labels, grid.cell, IS_RESTORABLE)


def rejected_pixels(
    grid: CellGrid, rows: np.ndarray, cols: np.ndarray, labels: np.ndarray
) -> np.ndarray:
    """(H, W) uint8: 1 at the body-part pixels of the cells (rows, cols), 0 elsewhere."""
    return K.cells_to_pixels(_chosen(grid, rows, cols), labels, grid.cell, IS_PART)


def _chosen(grid: CellGrid, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(hc, wc) bool: True at the cells (rows, cols)."""
    chosen = np.zeros(grid.parts.shape, np.bool_)
    chosen[rows, cols] = True
    return chosen


def warm_up_context(depth: np.ndarray, check: ContextCheck) -> None:
    """Compile (or load from numba's cache) the check's kernels on a small frame of `depth`'s
    shape with body-part labels, writable and read-only (as frames off the wire are)."""
    labels = np.full(depth.shape, L.OBJECT, np.uint8)
    labels[: depth.shape[0] // 2, : depth.shape[1] // 2] = L.BODY
    valid = np.ones(depth.shape, np.bool_)
    heights = np.full(depth.shape, 1000.0, np.float32)
    proba = np.full((*depth.shape, L.NUM_CLASSES), 1.0 / L.NUM_CLASSES, np.float32)
    read_only = np.full(depth.shape, 2000, np.uint16)
    read_only.flags.writeable = False
    for frame in (np.full(depth.shape, 2000, np.uint16), read_only):
        grid = cell_grid(labels, valid, heights, frame, proba, 500.0)
        rows, cols = part_cells(grid)
        people = check.judge(cell_features(grid, rows, cols), np.zeros(rows.size, np.bool_))
        rejected_pixels(grid, rows[~people], cols[~people], labels)
        restored_pixels(grid, rows[people], cols[people], labels)
