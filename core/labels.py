"""The label table (DESIGN section 2): ids, names and colours. The only place it lives.

Everything that needs a label id, a name or a colour imports it from here: training,
metrics, the viewer's AnnotationContext, the overlays written by `topseg segment`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Label:
    """One row of the table: the id written in label images, its name and RGB colour."""

    id: int
    name: str
    color: tuple[int, int, int]


BACKGROUND = 0
HEAD = 1
BODY = 2
UPPER_ARM = 3
LOWER_ARM = 4
HAND = 5
LEGS = 6
CHAIR = 7
PLANT = 8
STORAGE = 9
TABLE = 10
ROBOT = 11
OBJECT = 12
NO_DEPTH = 255

LABELS: tuple[Label, ...] = (
    Label(BACKGROUND, "background", (40, 40, 40)),
    Label(HEAD, "head", (230, 25, 75)),
    Label(BODY, "body", (245, 130, 48)),
    Label(UPPER_ARM, "upper-arm", (255, 225, 25)),
    Label(LOWER_ARM, "lower-arm", (210, 245, 60)),
    Label(HAND, "hand", (60, 180, 75)),
    Label(LEGS, "legs", (70, 240, 240)),
    Label(CHAIR, "chair", (0, 130, 200)),
    Label(PLANT, "plant", (145, 30, 180)),
    Label(STORAGE, "storage", (240, 50, 230)),
    Label(TABLE, "table", (170, 110, 40)),
    Label(ROBOT, "robot", (140, 140, 255)),
    Label(OBJECT, "object", (120, 160, 150)),
)
NO_DEPTH_LABEL = Label(NO_DEPTH, "no-depth", (0, 0, 0))

#: The most classes a model can know (ids 0..NUM_CLASSES-1); NO_DEPTH is never a class.
#: A model knows its own `n_classes` <= NUM_CLASSES, the first rows of the table.
NUM_CLASSES = len(LABELS)
#: The classes of the paper's experiments (ids 0..10), all a model trained on them knows.
PAPER_NUM_CLASSES = TABLE + 1
#: Ids the means (mAP, mAR, avg F1) run over: everything but background.
SCORED_IDS: tuple[int, ...] = tuple(lab.id for lab in LABELS if lab.id != BACKGROUND)
#: Ids the paper's ten-class means run over (1..10).
PAPER_SCORED_IDS: tuple[int, ...] = tuple(i for i in SCORED_IDS if i < PAPER_NUM_CLASSES)
HUMAN_IDS: tuple[int, ...] = (HEAD, BODY, UPPER_ARM, LOWER_ARM, HAND, LEGS)
FURNITURE_IDS: tuple[int, ...] = (CHAIR, PLANT, STORAGE, TABLE)
#: The classes beyond the paper's closed world: a robot arm, and anything else in the cell.
OPEN_WORLD_IDS: tuple[int, ...] = (ROBOT, OBJECT)

NAMES: tuple[str, ...] = tuple(lab.name for lab in LABELS)
_BY_NAME = {lab.name: lab for lab in (*LABELS, NO_DEPTH_LABEL)}


def by_name(name: str) -> Label:
    """The label called `name`; a KeyError lists the valid names."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"unknown label {name!r}; known: {', '.join(_BY_NAME)}") from None


def name_of(label_id: int) -> str:
    """The name of a label id (NO_DEPTH included); a KeyError for an id not in the table."""
    if label_id == NO_DEPTH:
        return NO_DEPTH_LABEL.name
    if 0 <= label_id < NUM_CLASSES:
        return LABELS[label_id].name
    raise KeyError(f"unknown label id {label_id}")


def palette() -> np.ndarray:
    """A (256, 3) uint8 lookup table: label id -> RGB; unknown ids are magenta."""
    lut = np.zeros((256, 3), np.uint8)
    lut[:] = (255, 0, 255)
    for lab in (*LABELS, NO_DEPTH_LABEL):
        lut[lab.id] = lab.color
    return lut


def colorize(labels: np.ndarray) -> np.ndarray:
    """Colour a (H, W) uint8 label image as (H, W, 3) RGB."""
    return palette()[np.asarray(labels, np.uint8)]


def table_classes(table: object) -> int | None:
    """How many classes a label table as `as_json` writes it (a model header's, a dataset's)
    names, when it is the first rows of today's table plus no-depth: a table written before
    the table grew is such a prefix. None for anything else."""
    if not isinstance(table, list) or not 3 <= len(table) <= NUM_CLASSES + 1:
        return None
    n_classes = len(table) - 1
    return n_classes if table == as_json(n_classes) else None


def as_json(n_classes: int = NUM_CLASSES) -> list[dict]:
    """The table as plain data, for model headers and the `info` queryable: the first
    `n_classes` classes (what a model knows) and no-depth."""
    if not 2 <= n_classes <= NUM_CLASSES:
        raise ValueError(f"n_classes must be in [2, {NUM_CLASSES}], got {n_classes}")
    return [
        {"id": lab.id, "name": lab.name, "color": list(lab.color)}
        for lab in (*LABELS[:n_classes], NO_DEPTH_LABEL)
    ]
