"""Fit a model's person check (`core.person_check`) on a dataset from `topseg datagen` and
write it into the model file.

The model labels every frame (its forest and CRF, as the worker does); every blob of body-part
labels is described by the check's features and marked a person when most of its pixels are
a person in the truth. Three frames in four fit scikit-learn's gradient-boosted trees
(weighted by each blob's area, so a blob counts by how much of the frame it is); the fourth
chooses the threshold: the strictest that still keeps `--keep` of the person pixels that lie
in body-part blobs. The trees and threshold go into the model header (`person_check`), with
what the held-out frames measured; the forest is unchanged. Render the dataset from another
seed than the forest's training set, with the scenes the model will see (`--mode cell`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from topseg.core import labels as L
from topseg.core.bundled_model import MODEL_HELP, bundled_model_path
from topseg.core.errors import TopsegError
from topseg.core.forest.model_file import caller_header, load_model, save_model
from topseg.core.formats.dataset import open_dataset
from topseg.core.person_check import PersonCheck, TreeEnsemble
from topseg.core.scoring import dataset_frames
from topseg.core.segmenter import Segmenter
from topseg.core.stages.person_check import frame_blobs
from topseg.core.stages.plan import FrameState
from topseg.services.cli.options import (
    add_segmenter_arguments,
    finite,
    int_range,
    segmenter_config,
)

#: every HOLD_OUT-th frame chooses the threshold and measures the check; the rest fit it
HOLD_OUT = 4
#: a blob is a person when at least this share of its pixels are one in the truth
PERSON_SHARE = 0.5
#: the boosted trees: how many, how deep, the learning rate
N_TREES, TREE_DEPTH, RATE = 150, 3, 0.1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """--model, --data, --out, --frames, --keep and the Segmenter's settings up to the CRF."""
    parser.add_argument("--model", type=Path, default=None, help=MODEL_HELP)
    parser.add_argument(
        "--data", required=True, type=Path,
        help="dataset from `topseg datagen` (another seed than the model's training set)",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, default=None,
        help="model file to write (default: --model, rewritten in place)",
    )  # fmt: skip
    parser.add_argument(
        "--frames", type=int_range(HOLD_OUT), default=None, help="use only the first N frames"
    )
    parser.add_argument(
        "--keep", type=finite(0.5, 1.0), default=0.98, metavar="P",
        help="the threshold keeps this share of the held-out frames' person pixels that lie "
        "in body-part blobs (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="the boosted trees' seed")
    # the check is fitted on labels as the CRF leaves them: the island rules, the check
    # itself and a background come after it or not at all
    add_segmenter_arguments(parser, ("pre", "grid", "crf"))


def run(args: argparse.Namespace) -> int:
    """Label the dataset, fit the check, choose its threshold, write the model."""
    from tqdm import tqdm

    model = args.model or bundled_model_path()
    out = args.out or model
    forest, header = load_model(model)
    config = segmenter_config(args, check_camera=False)
    segmenter = Segmenter(forest, header, config, path=model)
    if segmenter.features is None:
        raise TopsegError(f"{model} reads raw depth: the person check needs heights")
    ds = open_dataset(args.data)
    n = len(ds) if args.frames is None else min(args.frames, len(ds))
    if n < HOLD_OUT:
        raise TopsegError(f"{args.data} has {n} frames; the check needs at least {HOLD_OUT}")
    frames = tqdm(dataset_frames(ds, range(n)), total=n, desc="label", unit="frame",
                  disable=None)  # fmt: skip
    rows = gather_blobs(segmenter, frames)
    check = fit_check(rows, args.keep, args.seed)
    check.validation["dataset"] = str(args.data)
    check.validation["frames"] = n
    save_model(out, forest, {**caller_header(header), PersonCheck.HEADER_KEY: check.to_header()})
    print(describe(check.validation))
    print(f"wrote {out}")
    return 0


def gather_blobs(segmenter: Segmenter, frames) -> dict[str, np.ndarray]:
    """The body-part blobs of every (depth, truth, mount) frame after the model's CRF: their
    features, area (cm2), person share in the truth and frame number."""
    features, area, share, frame_no = [], [], [], []
    for i, (depth, truth, mount) in enumerate(frames):
        frame = FrameState(segmenter.plan(depth, None, f"frame {i}", mount), depth)
        segmenter.run(frame, upto="crf")
        found = frame_blobs(frame)
        if found is None:
            continue
        blobs = found[0]
        step = frame.plan.downsample
        person = np.isin(truth[::step, ::step], L.HUMAN_IDS)
        counts = np.bincount(blobs.image.ravel(), minlength=blobs.count + 1)[1:]
        hits = np.bincount(blobs.image.ravel(), person.ravel(), blobs.count + 1)[1:]
        features.append(blobs.features)
        area.append(blobs.area_cm2)
        share.append(hits / np.maximum(counts, 1))
        frame_no.append(np.full(blobs.count, i))
    if not features:
        raise TopsegError("the model labelled no body-part blob in these frames")
    return {
        "features": np.concatenate(features),
        "area": np.concatenate(area),
        "share": np.concatenate(share),
        "frame": np.concatenate(frame_no),
    }


def fit_check(rows: dict[str, np.ndarray], keep: float, seed: int = 0) -> PersonCheck:
    """Boosted trees fitted on three frames in four, the threshold chosen on the fourth to
    keep `keep` of its person pixels; the check with what the fourth measured."""
    from sklearn.ensemble import GradientBoostingClassifier

    x = rows["features"]  # finite: `blob_features` makes them so
    person = rows["share"] >= PERSON_SHARE
    held = rows["frame"] % HOLD_OUT == HOLD_OUT - 1
    if person[~held].all() or not person[~held].any():
        raise TopsegError("the fitting frames need blobs that are people and blobs that are not")
    clf = GradientBoostingClassifier(
        n_estimators=N_TREES, max_depth=TREE_DEPTH, learning_rate=RATE, random_state=seed
    )
    clf.fit(x[~held], person[~held], sample_weight=np.maximum(rows["area"][~held], 1e-3))
    trees = ensemble_from_sklearn(clf, x[held])
    scores = trees.score(x[held])
    person_area = rows["area"][held] * rows["share"][held]
    other_area = rows["area"][held] * (1 - rows["share"][held])
    threshold = choose_threshold(scores, person_area, keep)
    passed = scores >= threshold
    validation = {
        "keep": keep,
        "blobs": int(held.sum()),
        "person_px_kept": _share(person_area[passed], person_area),
        "other_px_removed": _share(other_area[~passed], other_area),
        "other_blobs_removed": _share(~person[held][~passed], ~person[held]),
        "person_blobs_kept": _share(person[held][passed], person[held]),
    }
    return PersonCheck(trees, float(threshold), validation)


def choose_threshold(scores: np.ndarray, person_area: np.ndarray, keep: float) -> float:
    """The highest score threshold at which blobs scoring at or above it hold at least
    `keep` of `person_area`."""
    if person_area.sum() <= 0:
        raise TopsegError("the held-out frames hold no person in a body-part blob")
    order = np.argsort(-scores, kind="stable")
    held = np.cumsum(person_area[order]) / person_area.sum()
    first = int(np.searchsorted(held, keep - 1e-12))
    return float(scores[order][min(first, len(order) - 1)])


def ensemble_from_sklearn(clf, check_rows: np.ndarray) -> TreeEnsemble:
    """A fitted binary GradientBoostingClassifier as a `TreeEnsemble`; its scores on
    `check_rows` must equal `decision_function`'s (TopsegError otherwise)."""
    fields: dict[str, list] = {k: [] for k in ("feature", "threshold", "left", "right", "value")}
    roots, depth = [], 0
    for est in clf.estimators_[:, 0]:
        t = est.tree_
        base = sum(len(v) for v in fields["value"])
        roots.append(base)
        leaf = t.children_left < 0
        fields["feature"].append(np.where(leaf, -1, t.feature))
        fields["threshold"].append(np.where(leaf, 0.0, t.threshold))
        fields["left"].append(np.where(leaf, -1, t.children_left + base))
        fields["right"].append(np.where(leaf, -1, t.children_right + base))
        fields["value"].append(t.value[:, 0, 0])
        depth = max(depth, int(t.max_depth))
    arrays = {k: np.concatenate(v) for k, v in fields.items()}
    partial = TreeEnsemble(
        arrays["feature"].astype(np.int32), arrays["threshold"].astype(np.float64),
        arrays["left"].astype(np.int32), arrays["right"].astype(np.int32),
        arrays["value"].astype(np.float64), np.asarray(roots, np.int32),
        0.0, float(clf.learning_rate), depth,
    )  # fmt: skip
    reference = clf.decision_function(check_rows)
    offsets = reference - partial.score(check_rows)
    offset = float(np.median(offsets)) if offsets.size else 0.0
    trees = TreeEnsemble(**{**partial.__dict__, "offset": offset})
    if offsets.size and np.max(np.abs(trees.score(check_rows) - reference)) > 1e-6:
        raise TopsegError("the exported trees do not reproduce scikit-learn's scores")
    return trees


def describe(validation: dict) -> str:
    """What the held-out frames measured, in one paragraph."""
    v = validation
    return (
        f"person check, held-out frames ({v['blobs']} blobs): keeps {v['person_px_kept']:.1%} "
        f"of person pixels in body-part blobs ({v['person_blobs_kept']:.1%} of person blobs); "
        f"removes {v['other_px_removed']:.1%} of the other pixels labelled as body parts "
        f"({v['other_blobs_removed']:.1%} of those blobs)"
    )


def _share(part: np.ndarray, whole: np.ndarray) -> float:
    """sum(part) / sum(whole), NaN-free (0 for an empty whole)."""
    total = float(np.sum(whole))
    return float(np.sum(part)) / total if total > 0 else 0.0


__all__ = ["choose_threshold", "ensemble_from_sklearn", "fit_check", "gather_blobs"]
