"""Segmentation scores as in the paper: a confusion matrix, per-class precision, recall and
F1, and their means (mAP, mAR, avg F1) over the scored labels, background apart: over all
twelve (robot and object included), and over the paper's ten (ids 1..10, suffix `_10`).
On data without robots or objects, and with a model that never predicts them, both agree.

Conventions (the same everywhere scores are printed):

- Rows of the confusion matrix are the truth, columns the prediction, ids 0..NUM_CLASSES-1.
- Pixels whose *truth* is NO_DEPTH are ignored: nobody can say what they are.
- A *prediction* of NO_DEPTH where the truth has a class (the live sensor lost depth the
  ground truth has) counts as background: a miss for that class, never a hit.
- 0/0 is undefined, not zero: precision of a class never predicted, recall of a class
  that never occurs, F1 of a class in neither, come out NaN (null in JSON, "-" in
  tables), and the means run over the classes where the value is defined. This is
  scikit-learn's `zero_division=np.nan`.
- Heads are also counted as blobs (`head_detections`), as a people counter downstream sees
  them: a patch of `head` on a shoulder is a false head there however few pixels it has.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass

import numpy as np

from topseg.core import labels as L
from topseg.core.errors import TopsegError

C = L.NUM_CLASSES


def _check(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if not np.issubdtype(a.dtype, np.integer):
        raise TopsegError(f"{name} labels must be integers, got {a.dtype}")
    bad = (a != L.NO_DEPTH) & ((a < 0) | (a >= C))
    if bad.any():
        raise TopsegError(
            f"{name} labels hold id {int(a[bad].flat[0])}, not a class (0..{C - 1}) "
            f"or no-depth ({L.NO_DEPTH})"
        )
    return a


def confusion_matrix(truth: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """(NUM_CLASSES, NUM_CLASSES) int64 counts: [truth id, predicted id], as documented above."""
    truth = _check("truth", truth)
    pred = _check("predicted", pred)
    if truth.shape != pred.shape:
        raise TopsegError(f"truth shape {truth.shape} differs from prediction {pred.shape}")
    keep = truth != L.NO_DEPTH
    t = truth[keep].astype(np.int64)
    p = pred[keep].astype(np.int64)
    p[p == L.NO_DEPTH] = L.BACKGROUND
    return np.bincount(t * C + p, minlength=C * C).reshape(C, C)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    out = np.full(num.shape, np.nan)
    np.divide(num, den, out=out, where=den > 0)
    return out


def pad_confusion(confusion: np.ndarray) -> np.ndarray:
    """A (k, k) confusion of the first k classes (one counted before the label table grew)
    as (NUM_CLASSES, NUM_CLASSES), the later classes' rows and columns zero."""
    cm = np.asarray(confusion, np.int64)
    if cm.ndim != 2 or cm.shape[0] != cm.shape[1] or not 2 <= cm.shape[0] <= C:
        raise TopsegError(f"a confusion matrix must be kxk with 2 <= k <= {C}, got {cm.shape}")
    missing = C - cm.shape[0]
    return np.pad(cm, ((0, missing), (0, missing)))


def scores(confusion: np.ndarray) -> dict:
    """Per-class and mean scores of a confusion matrix.

    Returns {"per_class": {name: {precision, recall, f1, support}} for ids 1..12,
    "background": {...} likewise, "mAP", "mAR", "avg_f1" (means over ids 1..12 where
    defined), "mAP_10", "mAR_10", "avg_f1_10" (means over the paper's ids 1..10 where
    defined), "accuracy" (all pixels), "pixels"}.
    """
    cm = np.asarray(confusion, np.int64)
    if cm.shape != (C, C):
        raise TopsegError(f"confusion matrix must be {C}x{C}, got {cm.shape}")
    tp = np.diag(cm).astype(np.float64)
    predicted = cm.sum(axis=0).astype(np.float64)
    support = cm.sum(axis=1)
    precision = _ratio(tp, predicted)
    recall = _ratio(tp, support.astype(np.float64))
    f1 = _ratio(2 * tp, predicted + support)

    def row(i: int) -> dict:
        return {
            "precision": float(precision[i]),
            "recall": float(recall[i]),
            "f1": float(f1[i]),
            "support": int(support[i]),
        }

    total = int(cm.sum())

    def mean(values: np.ndarray, ids: tuple[int, ...]) -> float:
        v = values[list(ids)]
        return float(np.mean(v[~np.isnan(v)])) if (~np.isnan(v)).any() else math.nan

    return {
        "per_class": {L.NAMES[i]: row(i) for i in L.SCORED_IDS},
        "background": row(L.BACKGROUND),
        "mAP": mean(precision, L.SCORED_IDS),
        "mAR": mean(recall, L.SCORED_IDS),
        "avg_f1": mean(f1, L.SCORED_IDS),
        "mAP_10": mean(precision, L.PAPER_SCORED_IDS),
        "mAR_10": mean(recall, L.PAPER_SCORED_IDS),
        "avg_f1_10": mean(f1, L.PAPER_SCORED_IDS),
        "accuracy": float(tp.sum() / total) if total else math.nan,
        "pixels": total,
    }


#: the keys of `scores` whose ten-class means `ten_class_scores` puts in their place
_TEN_CLASS_MEANS = ("mAP", "mAR", "avg_f1")


def ten_class_scores(s: dict) -> dict:
    """`scores` as the paper's ten-class tables read them: per-class rows for ids 1..10 only
    and "mAP", "mAR", "avg_f1" the means over them (no `_10` keys)."""
    out = {k: v for k, v in s.items() if not k.endswith("_10")}
    out["per_class"] = {L.NAMES[i]: s["per_class"][L.NAMES[i]] for i in L.PAPER_SCORED_IDS}
    for key in _TEN_CLASS_MEANS:
        out[key] = s[f"{key}_10"]
    return out


def avg_f1_draws(
    frame_confusions: np.ndarray,
    draws: int = 1000,
    seed: int = 0,
    ids: tuple[int, ...] = L.SCORED_IDS,
) -> np.ndarray:
    """(draws,) avg F1 over the classes `ids` (as `scores`; `L.PAPER_SCORED_IDS`: its
    "avg_f1_10") of bootstrap resamples of frames: each draw sums the
    confusions of N frames drawn with replacement from the (N, C, C) `frame_confusions`.
    The draws depend only on (N, draws, seed), so two sets of N frames scored with the same
    seed are resampled by the same frame indices: the difference of their draws is a paired
    bootstrap of the difference of their avg F1 (frame i of one set against frame i of the
    other). NaN for a draw where no scored class has an F1."""
    cm = np.asarray(frame_confusions, np.int64)
    if cm.ndim != 3 or cm.shape[1:] != (C, C) or len(cm) == 0:
        raise TopsegError(f"frame confusions must be (N >= 1, {C}, {C}), got {cm.shape}")
    if draws < 1:
        raise TopsegError(f"draws must be >= 1, got {draws}")
    n = len(cm)
    rng = np.random.default_rng(seed)
    counts = np.stack([np.bincount(rng.integers(0, n, n), minlength=n) for _ in range(draws)])
    summed = (counts @ cm.reshape(n, C * C)).reshape(draws, C, C)
    tp = np.diagonal(summed, axis1=1, axis2=2).astype(np.float64)
    den = (summed.sum(axis=1) + summed.sum(axis=2)).astype(np.float64)
    f1 = _ratio(2 * tp, den)[:, list(ids)]
    defined = ~np.isnan(f1)
    with np.errstate(invalid="ignore"):
        return np.where(defined, f1, 0.0).sum(axis=1) / defined.sum(axis=1)


def percentile(values, q: float) -> float | None:
    """Nearest-rank percentile (q in 0..100) of `values`; None when there are none.

    The smallest value with at least q % of the values at or below it: always one of the
    values (what operators expect of p50 / p99), numpy's `method="inverted_cdf"`.
    """
    ordered = sorted(float(v) for v in values)
    if not ordered:
        return None
    if not 0 <= q <= 100:
        raise ValueError(f"percentile q must be in 0..100, got {q}")
    rank = max(1, math.ceil(q / 100 * len(ordered)))
    return ordered[rank - 1]


def person_scores(confusion: np.ndarray) -> dict:
    """What a safety function downstream asks of a frame, from a (C, C) truth x prediction
    confusion: is a pixel a person (any body part) or not, whatever the part.

    person_precision, person_recall, person_f1 of "any body part" against the rest, and
    furniture_on_person: the share of person pixels labelled as furniture (NaN when undefined).
    """
    c = np.asarray(confusion, np.float64)
    person = np.zeros(c.shape[0], bool)
    person[list(L.HUMAN_IDS)] = True
    furniture = np.zeros(c.shape[0], bool)
    furniture[list(L.FURNITURE_IDS)] = True
    tp = c[np.ix_(person, person)].sum()
    fp = c[np.ix_(~person, person)].sum()
    fn = c[np.ix_(person, ~person)].sum()
    precision = _share(tp, tp + fp)
    recall = _share(tp, tp + fn)
    f1 = _share(2 * precision * recall, precision + recall)
    furn = _share(c[np.ix_(person, furniture)].sum(), c[person].sum())
    return {
        "person_precision": float(precision),
        "person_recall": float(recall),
        "person_f1": float(f1),
        "furniture_on_person": float(furn),
    }


#: Blobs smaller than this (pixels) are not counted as heads, found or predicted: the size
#: of a fingertip from 3 m, below what a head detector downstream would report
MIN_HEAD_BLOB_PX = 30
#: A predicted head blob is a correct detection when at least this share of it is true head
HEAD_HIT_SHARE = 0.5
#: A true head is found when at least this share of it is labelled head
HEAD_FOUND_SHARE = 0.3
#: Pixels without depth within this many pixels of a head join its blob: a head with holes
#: in it (time-of-flight cameras lose depth on dark hair) is one head, not several
HEAD_BRIDGE_PX = 4


def head_detections(truth: np.ndarray, pred: np.ndarray) -> tuple[int, int, int, int]:
    """Heads as blobs, as a people counter downstream sees them: (correct, predicted, found,
    true) for one frame. Blobs are 4-connected regions of `head` of MIN_HEAD_BLOB_PX pixels
    or more, joined across pixels without depth (the truth's NO_DEPTH) within HEAD_BRIDGE_PX
    of them; sizes and shares count head pixels only. A predicted blob is correct when
    HEAD_HIT_SHARE of it is true head, and a true head is found when HEAD_FOUND_SHARE of it
    is labelled head."""
    heads = HeadDetections()
    heads.add(truth, pred)
    return heads.correct, heads.predicted, heads.found, heads.true


def head_blobs(
    truth: np.ndarray, pred: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The blobs `head_detections` counts: ((share, at_border) of the predicted blobs,
    (share, at_border) of the true heads). A predicted blob's share is the part of it that
    is true head, a true head's the part labelled head; `at_border` says whether a blob
    touches the image's border, with its head pixels or the pixels without depth it is
    joined across (a person walking in or out of view; sensors often leave the outermost
    pixels without depth)."""
    from scipy import ndimage

    truth, pred = _check("truth", truth), _check("predicted", pred)
    if truth.shape != pred.shape:
        raise TopsegError(f"truth shape {truth.shape} differs from prediction {pred.shape}")
    true_head, pred_head = truth == L.HEAD, pred == L.HEAD
    no_depth = truth == L.NO_DEPTH

    def blob_shares(blobs_of: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        bridged = blobs_of
        if no_depth.any() and blobs_of.any():
            near = ndimage.binary_dilation(blobs_of, iterations=HEAD_BRIDGE_PX)
            bridged = blobs_of | (near & no_depth)
        blobs, n = ndimage.label(bridged)
        if n == 0:
            return np.zeros(0), np.zeros(0, bool)
        rim = np.concatenate([blobs[0], blobs[-1], blobs[:, 0], blobs[:, -1]])
        at_border = np.bincount(rim, minlength=n + 1)[1:] > 0  # bridged: a rim without depth
        blobs = np.where(blobs_of, blobs, 0)
        size = np.bincount(blobs.ravel(), minlength=n + 1)[1:]
        hits = np.bincount(blobs.ravel(), weights=other.ravel(), minlength=n + 1)[1:]
        kept = size >= MIN_HEAD_BLOB_PX
        return (hits / np.maximum(size, 1))[kept], at_border[kept]

    return blob_shares(pred_head, true_head), blob_shares(true_head, pred_head)


@dataclass
class HeadDetections:
    """`head_detections` summed over frames: precision (correct / predicted) and recall
    (found / true) of heads as blobs; the `border_*` counts are those of the blobs that
    touch the image's border (`head_blobs`), where a walking person's head is cut."""

    correct: int = 0
    predicted: int = 0
    found: int = 0
    true: int = 0
    border_correct: int = 0
    border_predicted: int = 0
    border_found: int = 0
    border_true: int = 0

    def add(self, truth: np.ndarray, pred: np.ndarray) -> None:
        """Count one frame's head blobs."""
        (p_share, p_border), (t_share, t_border) = head_blobs(truth, pred)
        hit, found = p_share >= HEAD_HIT_SHARE, t_share >= HEAD_FOUND_SHARE
        self.correct += int(hit.sum())
        self.predicted += int(p_share.size)
        self.found += int(found.sum())
        self.true += int(t_share.size)
        self.border_correct += int(hit[p_border].sum())
        self.border_predicted += int(p_border.sum())
        self.border_found += int(found[t_border].sum())
        self.border_true += int(t_border.sum())

    @property
    def precision(self) -> float:
        """Share of the predicted head blobs that are heads (NaN with none predicted)."""
        return _share(self.correct, self.predicted)

    @property
    def recall(self) -> float:
        """Share of the true heads found (NaN with none in the truth)."""
        return _share(self.found, self.true)

    @property
    def border_precision(self) -> float:
        """Precision of the predicted blobs that touch the image's border (NaN: none)."""
        return _share(self.border_correct, self.border_predicted)

    @property
    def border_recall(self) -> float:
        """Recall of the true heads that touch the image's border (NaN: none)."""
        return _share(self.border_found, self.border_true)

    def to_dict(self) -> dict:
        """Counts, precision and recall as JSON-able numbers (None for NaN)."""
        return {
            **asdict(self),
            "precision": _nan_to_none(self.precision),
            "recall": _nan_to_none(self.recall),
            "border_precision": _nan_to_none(self.border_precision),
            "border_recall": _nan_to_none(self.border_recall),
        }

    def summary(self) -> str:
        """One line: precision and recall with their counts, then those at the border."""
        return (
            f"head detections (blobs >= {MIN_HEAD_BLOB_PX} px): precision {_fmt(self.precision)} "
            f"({self.correct} of {self.predicted}), recall {_fmt(self.recall)} "
            f"({self.found} of {self.true}); at the image border: precision "
            f"{_fmt(self.border_precision)} ({self.border_correct} of {self.border_predicted}), "
            f"recall {_fmt(self.border_recall)} ({self.border_found} of {self.border_true})"
        )


def _share(part: float, whole: float) -> float:
    """part / whole; NaN when whole is 0, nothing to count (`_ratio` does it for arrays)."""
    return part / whole if whole else math.nan


def _fmt(x: float) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"


def _shown(name: str, r: dict) -> bool:
    """Whether `format_table` shows a class's row: always for the paper's ten, for robot and
    object when the truth holds them or the model predicted them."""
    paper = L.by_name(name).id in L.PAPER_SCORED_IDS
    return paper or r["support"] > 0 or not _missing(r["precision"])


def _missing(x) -> bool:
    """A score that is undefined (NaN, or None as JSON holds it)."""
    return x is None or (isinstance(x, float) and math.isnan(x))


def _means_differ(s: dict) -> bool:
    """Whether the means over all scored classes differ from the ten-class ones (scores
    without `_10` keys, read back from before the table grew, have the ten only)."""
    for key in _TEN_CLASS_MEANS:
        a, b = s[key], s.get(f"{key}_10", s[key])
        if not (a == b or (_missing(a) and _missing(b))):
            return True
    return False


def format_table(s: dict, title: str = "") -> str:
    """A plain-text table laid out like the paper's Table I: one row per class, P / R / F1,
    the ten-class means, and the means over all twelve classes where they differ."""
    rows = {name: r for name, r in s["per_class"].items() if _shown(name, r)}
    name_w = max(len(n) for n in (*rows, "background", "mean (1-10)"))
    head = f"{'class':<{name_w}}  {'P':>6} {'R':>6} {'F1':>6} {'pixels':>10}"
    rule = "-" * len(head)
    lines = [title] if title else []
    lines += [head, rule]
    for name, r in rows.items():
        p, rc, f = (_fmt(r[k]) for k in ("precision", "recall", "f1"))
        lines.append(f"{name:<{name_w}}  {p:>6} {rc:>6} {f:>6} {r['support']:>10}")
    lines.append(rule)
    ten = [_fmt(s.get(f"{key}_10", s[key])) for key in _TEN_CLASS_MEANS]
    lines.append(f"{'mean (1-10)':<{name_w}}  {ten[0]:>6} {ten[1]:>6} {ten[2]:>6}")
    if _means_differ(s):
        last = max(L.SCORED_IDS)
        means = [_fmt(s[key]) for key in _TEN_CLASS_MEANS]
        lines.append(f"{f'mean (1-{last})':<{name_w}}  {means[0]:>6} {means[1]:>6} {means[2]:>6}")
    b = s["background"]
    p, rc, f = (_fmt(b[k]) for k in ("precision", "recall", "f1"))
    lines.append(f"{'background':<{name_w}}  {p:>6} {rc:>6} {f:>6} {b['support']:>10}")
    lines.append(f"pixel accuracy {_fmt(s['accuracy'])} over {s['pixels']} pixels")
    return "\n".join(lines)


def _nan_to_none(x):
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, float) and math.isnan(x):
        return None
    return x


def to_json(s: dict, **extra) -> str:
    """Scores as strict JSON (NaN -> null); `extra` keys are added at the top level."""
    return json.dumps(_nan_to_none({**s, **extra}), allow_nan=False)


class ConfusionAccumulator:
    """Confusion counts summed over a stream of frames (evaluation, the live demo)."""

    def __init__(self) -> None:
        self.confusion = np.zeros((C, C), np.int64)
        self.frames = 0

    def add(self, truth: np.ndarray, pred: np.ndarray) -> np.ndarray:
        """Count one frame's labels against its truth; return that frame's confusion."""
        frame = confusion_matrix(truth, pred)
        self.confusion += frame
        self.frames += 1
        return frame

    def merge(self, other: ConfusionAccumulator) -> None:
        """Fold in counts gathered elsewhere (another worker or shard)."""
        self.confusion += other.confusion
        self.frames += other.frames

    def scores(self) -> dict:
        """`scores` of the counts so far, with the number of frames."""
        return {**scores(self.confusion), "frames": self.frames}

    def to_dict(self) -> dict:
        """The counts as JSON-able lists (to save or send)."""
        return {"confusion": self.confusion.tolist(), "frames": self.frames}

    @classmethod
    def from_dict(cls, d: dict) -> ConfusionAccumulator:
        """Counts saved by `to_dict`; TopsegError when they are not a valid matrix."""
        acc = cls()
        cm = np.asarray(d["confusion"], np.int64)
        square = cm.ndim == 2 and cm.shape[0] == cm.shape[1] and 2 <= cm.shape[0] <= C
        if not square or (cm < 0).any():
            raise TopsegError(
                f"a saved confusion matrix must be kxk non-negative counts, 2 <= k <= {C} "
                "(one saved before the label table grew is padded)"
            )
        acc.confusion = pad_confusion(cm)
        acc.frames = int(d["frames"])
        return acc
