"""The context prior: what each patch of the frame is, judged from the forest's posteriors up
to 75 cm around it, folded back into the posteriors before the CRF (auto-context, Tu and Bai
2010).

The forest reads a pixel's depth within a hand's width, so a robot's wrist, a drum's rim or
a crouching back are each read without what stands around them. Before the CRF, the frame is
cut into cells (`PRIOR_CELL_PX` pixels square at a Kinect v1's focal length) and every cell
holding a pixel above the floor gate is described as the context check describes its cells
(`context_check.cell_features`: the forest's own argmax labels, heights and posteriors of
the cell and of rings 12 to 75 cm around it). Boosted trees the model file carries, one per
group, score each cell; their softmax is the cell's probability of being a person, the
robot, an object, furniture or background (`GROUPS`). That is folded into the cell's pixels
(`context_prior_kernels.fold_prior`): each class's posterior is weighted by
((q_g + EPS) / (m_g + EPS)) ** alpha, with q_g the cell's probability of the class's group
g and m_g the forest's mean posterior mass in g over the cell, and normalised again. With
alpha 1 the cell's mean group masses become q (nearly); alpha tempers it. Within a group the
forest's own shares stand: the prior says "a person", the forest still says which part.

Everything here is pure: numpy and the kernels of `context_prior_kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from topseg.core import labels as L
from topseg.core.context_check import FEATURES, CellGrid, cell_features
from topseg.core.context_check_kernels import HEIGHT, PERSON_POSTERIOR
from topseg.core.context_prior_kernels import fold_prior
from topseg.core.crf.argmax import Summary
from topseg.core.errors import TopsegError
from topseg.core.person_check import GroupedTrees, TreeEnsemble

#: what a cell may be, in the order of the prior's trees
GROUPS: tuple[str, ...] = ("person", "robot", "object", "furniture", "background")
#: class -> its group's index in GROUPS
CLASS_GROUP = np.full(L.NUM_CLASSES, GROUPS.index("background"), np.int64)
CLASS_GROUP[list(L.HUMAN_IDS)] = GROUPS.index("person")
CLASS_GROUP[L.ROBOT] = GROUPS.index("robot")
CLASS_GROUP[L.OBJECT] = GROUPS.index("object")
CLASS_GROUP[list(L.FURNITURE_IDS)] = GROUPS.index("furniture")
#: a prior cell is this many pixels square at a Kinect v1's focal length (~4.5 cm at 3.5 m)
PRIOR_CELL_PX = 8
#: how far a cell's group probabilities move its pixels' posteriors (0: not at all; 1: the
#: cell's mean group masses become them), chosen on validation cells (docs/results.md,
#: "Choices measured")
ALPHA = 0.5
#: the prior scores only cells near some person mass of the forest's (`prior_cells`): half
#: of the cells above the floor, and the same figures on validation cells as scoring them
#: all (docs/results.md, "Choices measured")
PERSON_MASS_GATE = 0.05
#: keeps a group the forest gives no mass from dividing by zero, and a group the prior gives
#: none from being ruled out
EPS = 0.02


def prior_cells(grid: CellGrid, near_people: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the cells holding a pixel above the floor gate (a mean height above
    0); `near_people`, only those where the forest gives a person some mass, a mean person
    posterior of PERSON_MASS_GATE or more in the cell or one of its eight neighbours (the
    ones the prior scores; it is fitted on them all)."""
    above = grid.channels[..., HEIGHT] > 0
    if not near_people:
        return np.nonzero(above)
    person = np.pad(grid.channels[..., PERSON_POSTERIOR], 1)
    hc, wc = grid.parts.shape
    around = np.max(
        [person[i : i + hc, j : j + wc] for i in range(3) for j in range(3)], axis=0
    )  # fmt: skip
    return np.nonzero(above & (around >= PERSON_MASS_GATE))


def group_truth(truth: np.ndarray, valid: np.ndarray, grid: CellGrid) -> np.ndarray:
    """(hc, wc, G) how many valid pixels of each cell are of each group in the truth labels
    (at the working resolution)."""
    hc, wc = grid.parts.shape
    cell = grid.cell
    truth = truth[: hc * cell, : wc * cell]
    valid = valid[: hc * cell, : wc * cell]
    group = np.where(truth < L.NUM_CLASSES, CLASS_GROUP[np.minimum(truth, L.NUM_CLASSES - 1)], -1)
    counts = np.zeros((hc, wc, len(GROUPS)), np.int64)
    for g in range(len(GROUPS)):
        mine = (group == g) & valid
        counts[..., g] = mine.reshape(hc, cell, wc, cell).sum((1, 3))
    return counts


@dataclass(frozen=True)
class ContextPrior:
    """A fitted context prior: one `TreeEnsemble` per group (their softmax is a cell's group
    probabilities), the `alpha` it is folded in with, and what the fit measured on its
    held-out frames (`validation`)."""

    trees: tuple[TreeEnsemble, ...]
    alpha: float
    validation: dict
    #: the trees stacked for scoring in one pass
    grouped: GroupedTrees = field(init=False, repr=False, compare=False)

    #: the model header's key
    HEADER_KEY = "context_prior"

    def __post_init__(self) -> None:
        if len(self.trees) != len(GROUPS):
            raise TopsegError(f"the context prior needs {len(GROUPS)} tree ensembles")
        if not 0.0 <= self.alpha <= 4.0:
            raise TopsegError(f"the context prior's alpha must be in [0, 4], got {self.alpha}")
        object.__setattr__(self, "grouped", GroupedTrees.of(self.trees))

    def probabilities(self, features: np.ndarray) -> np.ndarray:
        """(n, G) float32 group probabilities of the (n, F) cell feature rows."""
        scores = self.grouped.scores(features)
        odds = np.exp(scores - scores.max(axis=1, keepdims=True, initial=-np.inf))
        return (odds / odds.sum(axis=1, keepdims=True)).astype(np.float32)

    def to_header(self) -> dict[str, Any]:
        """The header entry (`HEADER_KEY`)."""
        return {
            "cell_px": PRIOR_CELL_PX,
            "groups": list(GROUPS),
            "features": list(FEATURES),
            "alpha": self.alpha,
            "trees": [trees.to_dict() for trees in self.trees],
            "validation": self.validation,
        }

    @classmethod
    def from_header(cls, header: dict[str, Any]) -> ContextPrior | None:
        """The prior a model header carries (None: none). TopsegError when it is malformed
        or reads other cells or features than this topseg computes."""
        entry = header.get(cls.HEADER_KEY)
        if entry is None:
            return None
        if not isinstance(entry, dict):
            raise TopsegError("the model's context prior is not a table")
        if (
            entry.get("features") != list(FEATURES)
            or entry.get("cell_px") != PRIOR_CELL_PX
            or entry.get("groups") != list(GROUPS)
        ):
            raise TopsegError(
                "the model's context prior reads other cells than this topseg computes "
                "(refit it: `topseg person-check`)"
            )
        trees = entry.get("trees")
        if not isinstance(trees, list) or len(trees) != len(GROUPS):
            raise TopsegError(f"the model's context prior needs {len(GROUPS)} tree ensembles")
        try:
            alpha = float(entry["alpha"])
        except (KeyError, TypeError, ValueError):
            raise TopsegError("the model's context prior has no alpha") from None
        ensembles = tuple(TreeEnsemble.from_dict(t, len(FEATURES)) for t in trees)
        validation = entry.get("validation") or {}
        if not isinstance(validation, dict):
            raise TopsegError("the model's context prior's validation is not a table")
        return cls(ensembles, alpha, validation)


def apply_prior(
    prior: ContextPrior,
    grid: CellGrid,
    rows: np.ndarray,
    cols: np.ndarray,
    proba: np.ndarray,
    valid: np.ndarray,
    summary: Summary,
) -> int:
    """Score the prior's cells (rows, cols) of `grid` (`stages.context_prior.frame_prior_cells`) and fold
    their group probabilities into the posteriors `proba` of the `valid` pixels and into
    their `summary`, in place: how many pixels' argmax changed."""
    groups = np.zeros((*grid.parts.shape, len(GROUPS)), np.float32)
    groups[rows, cols] = prior.probabilities(cell_features(grid, rows, cols))
    has_prior = np.zeros(grid.parts.shape, np.bool_)
    has_prior[rows, cols] = True
    changed = fold_prior(
        proba, valid, grid.cell, groups, has_prior, CLASS_GROUP, np.float64(prior.alpha),
        np.float64(EPS), summary.amax, summary.pmax, summary.psecond,
    )  # fmt: skip
    return int(changed)
