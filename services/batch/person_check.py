"""Fit a model's context prior (`core.context_prior`) and its two person checks
(`core.context_check`, then `core.person_check`) on a dataset from `topseg datagen` and write
them into the model file.

The context prior first. The model's forest labels every frame; up to PRIOR_CELLS_PER_FRAME
of its prior cells (those above the floor gate) are described by the context check's
features, each marked with the group (person, robot, object, furniture, background) most of
its pixels are in the truth. Three frames in four fit scikit-learn's histogram gradient
boosting, one set of trees per group (weighted by the cells' pixels); the fourth measures how
many of its cells' pixels the prior puts in the right group, against the forest's argmax.
`--prior off` fits none (the checks then judge the forest's own posteriors).

Then the context check, on the labels the CRF makes of the posteriors the prior leaves. The
model labels every frame (its forest and CRF, as the worker does); every cell holding body-part labels, and every cell it may restore
(`context_check.restore_cells`), is described by the context check's features and marked a
person's when most of the pixels the check would change (its body-part pixels; a restore
cell's robot, object and furniture pixels) are a person in the truth. Three frames in four fit
scikit-learn's histogram gradient boosting (weighted by those pixels); the fourth chooses the
thresholds: the strictest that still keeps `--context-keep` of the person pixels that lie in
body-part cells, and the most lenient at which the restore cells passing it are at least
`--restore-precision` a person's (pixel-weighted; `--restore off`: none is restored).

Then the person check, on the labels the context check leaves: every blob of body-part labels
is described by the check's features and marked a person when most of its pixels are a person
in the truth. Three frames in four fit scikit-learn's gradient-boosted trees (weighted by each
blob's area, so a blob counts by how much of the frame it is); the fourth chooses the
threshold: the strictest that still keeps `--keep` of the person pixels that lie in body-part
blobs.

The trees and thresholds go into the model header (`context_prior`, `context_check`,
`person_check`), with what the held-out frames measured; the forest is unchanged. Render the
dataset from another seed than the forest's training set, with the scenes the model will see
(`--mode cell`).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from topseg.core import labels as L
from topseg.core.bundled_model import MODEL_HELP, bundled_model_path
from topseg.core.context_check import IS_RESTORABLE, ContextCheck, cell_features
from topseg.core.context_prior import ALPHA, GROUPS, ContextPrior, group_truth
from topseg.core.errors import TopsegError
from topseg.core.forest.model_file import caller_header, load_model, save_model
from topseg.core.formats.dataset import open_dataset
from topseg.core.person_check import IS_PART, PersonCheck, TreeEnsemble
from topseg.core.scoring import dataset_frames
from topseg.core.segmenter import Segmenter
from topseg.core.stages.context_check import frame_cells
from topseg.core.stages.context_prior import frame_prior_cells
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
#: the context check's boosted trees: how many, how deep, the learning rate
CONTEXT_TREES, CONTEXT_DEPTH, CONTEXT_RATE = 150, 4, 0.1
#: the share of restored pixels that must be a person's on the held-out frames (chosen on the
#: validation cells: docs/results.md, "Choices measured")
RESTORE_PRECISION = 0.75
#: the context prior's boosted trees (one set per group): how many, how deep, the learning
#: rate; and how many cells of each frame it is fitted on at most (drawn at random)
PRIOR_TREES, PRIOR_DEPTH, PRIOR_RATE = 100, 6, 0.1
PRIOR_CELLS_PER_FRAME = 400
#: the header entries this command fits
CHECK_KEYS = (ContextPrior.HEADER_KEY, ContextCheck.HEADER_KEY, PersonCheck.HEADER_KEY)


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
    parser.add_argument(
        "--context-keep", type=finite(0.5, 1.0), default=0.98, metavar="P",
        help="the context check's threshold keeps this share of the held-out frames' person "
        "pixels that lie in body-part cells (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--prior", choices=("on", "off"), default="on",
        help="fit the context prior first, which the checks are then fitted after (off: "
        "none, as models before it)",
    )  # fmt: skip
    parser.add_argument(
        "--context", choices=("on", "off"), default="on",
        help="fit the context check (off: the person check alone, as models before it)",
    )  # fmt: skip
    parser.add_argument(
        "--restore", choices=("on", "off"), default="on",
        help="the context check also restores robot, object and furniture cells it finds a "
        "person's (off: it only rejects body-part cells, as checks before it)",
    )  # fmt: skip
    parser.add_argument(
        "--restore-precision", type=finite(0.5, 1.0), default=RESTORE_PRECISION, metavar="P",
        help="the restore threshold is the most lenient at which this share of the held-out "
        "frames' restored pixels are a person's (default: %(default)s)",
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
    # the model's own checks are refitted, so they are not read: one that reads other features
    # than this topseg computes (a model from an earlier version) is refitted too
    fitted = {k: v for k, v in caller_header(header).items() if k not in CHECK_KEYS}
    segmenter = Segmenter(forest, fitted, config, path=model)
    if segmenter.features is None:
        raise TopsegError(f"{model} reads raw depth: the person check needs heights")
    ds = open_dataset(args.data)
    n = len(ds) if args.frames is None else min(args.frames, len(ds))
    if n < HOLD_OUT:
        raise TopsegError(f"{args.data} has {n} frames; the check needs at least {HOLD_OUT}")
    if args.prior == "on":
        config = dataclasses.replace(
            config, grid=dataclasses.replace(config.grid, context_prior="on")
        )
        frames = tqdm(dataset_frames(ds, range(n)), total=n, desc="label (prior cells)",
                      unit="frame", disable=None)  # fmt: skip
        prior = fit_prior(gather_prior_cells(segmenter, frames, args.seed), args.seed)
        prior.validation.update(dataset=str(args.data), frames=n)
        fitted[ContextPrior.HEADER_KEY] = prior.to_header()
        print(describe_prior(prior.validation))
        segmenter = Segmenter(forest, fitted, config, path=model)
    if args.context == "on":
        frames = tqdm(dataset_frames(ds, range(n)), total=n, desc="label (cells)",
                      unit="frame", disable=None)  # fmt: skip
        restore = args.restore_precision if args.restore == "on" else None
        cells = gather_cells(segmenter, frames, restore is not None)
        context = fit_context(cells, args.context_keep, args.seed, restore)
        context.validation.update(dataset=str(args.data), frames=n)
        fitted[ContextCheck.HEADER_KEY] = context.to_header()
        print(describe_context(context.validation))
    segmenter = Segmenter(forest, fitted, config, path=model)
    frames = tqdm(dataset_frames(ds, range(n)), total=n, desc="label (blobs)", unit="frame",
                  disable=None)  # fmt: skip
    rows = gather_blobs(segmenter, frames)
    check = fit_check(rows, args.keep, args.seed)
    check.validation["dataset"] = str(args.data)
    check.validation["frames"] = n
    save_model(out, forest, {**fitted, PersonCheck.HEADER_KEY: check.to_header()})
    print(describe(check.validation))
    print(f"wrote {out}")
    return 0


def gather_prior_cells(segmenter: Segmenter, frames, seed: int = 0) -> dict[str, np.ndarray]:
    """The context prior's cells of every (depth, truth, mount) frame after the model's
    forest (every one above the floor, not only those it scores near people), at most
    PRIOR_CELLS_PER_FRAME of each drawn at random: their features, the truth
    group most of their valid pixels are of (`group`), those pixels' count (`weight`), the
    forest argmax's group of the most of them (`forest`) and the frame number."""
    columns: dict[str, list] = {k: [] for k in ("features", "group", "weight", "forest", "frame")}
    for i, (depth, truth, mount) in enumerate(frames):
        frame = FrameState(segmenter.plan(depth, None, f"frame {i}", mount), depth)
        segmenter.run(frame, upto="forest")
        found = frame_prior_cells(frame, near_people=False)
        if found is None:
            continue
        grid, rows, cols, valid = found
        step, forest = frame.plan.downsample, frame.summary.amax
        rng = np.random.default_rng([seed, i])
        pick = np.sort(rng.choice(rows.size, min(PRIOR_CELLS_PER_FRAME, rows.size), replace=False))
        rows, cols = rows[pick], cols[pick]
        counts = group_truth(truth[::step, ::step], valid, grid)[rows, cols]
        forest_counts = group_truth(forest, valid, grid)[rows, cols]
        for key, value in (("features", cell_features(grid, rows, cols)),
                           ("group", counts.argmax(axis=1)), ("weight", counts.sum(axis=1)),
                           ("forest", forest_counts.argmax(axis=1)),
                           ("frame", np.full(rows.size, i))):  # fmt: skip
            columns[key].append(value)
    if not columns["features"]:
        raise TopsegError("these frames hold no pixel above the floor")
    return {k: np.concatenate(v) for k, v in columns.items()}


def fit_prior(rows: dict[str, np.ndarray], seed: int = 0) -> ContextPrior:
    """Histogram boosted trees (one set per group, softmax) fitted on three frames in four,
    weighted by each cell's valid pixels; the prior with what the fourth measured: the share
    of its cells' pixels whose cell the prior and the forest's argmax put in the right group."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    x, group, weight = rows["features"], rows["group"], rows["weight"]
    held = held_frames(rows)
    missing = sorted(set(range(len(GROUPS))) - set(np.unique(group[~held]).tolist()))
    if missing:
        names = ", ".join(GROUPS[g] for g in missing)
        raise TopsegError(f"the fitting frames hold no cell of {names}: the prior needs all")
    clf = HistGradientBoostingClassifier(
        max_iter=PRIOR_TREES, max_depth=PRIOR_DEPTH, learning_rate=PRIOR_RATE,
        early_stopping=False, random_state=seed,
    )  # fmt: skip
    clf.fit(x[~held], group[~held], sample_weight=weight[~held])
    check_rows = x[held][:10_000]
    prior = ContextPrior(
        tuple(ensemble_from_histogram(clf, check_rows, k) for k in range(len(GROUPS))), ALPHA, {}
    )
    chosen = prior.probabilities(x[held]).argmax(axis=1)
    validation = {
        "cells": int(held.sum()),
        "cell_px_right": _share(weight[held] * (chosen == group[held]), weight[held]),
        "forest_cell_px_right": _share(weight[held] * (rows["forest"][held] == group[held]),
                                       weight[held]),
        "person_cell_px_right": _share(
            weight[held] * ((chosen == 0) & (group[held] == 0)), weight[held] * (group[held] == 0)
        ),
        "not_person_cell_px_called_person": _share(
            weight[held] * ((chosen == 0) & (group[held] != 0)), weight[held] * (group[held] != 0)
        ),
    }  # fmt: skip
    return dataclasses.replace(prior, validation=validation)


def gather_cells(segmenter: Segmenter, frames, restoring: bool = True) -> dict[str, np.ndarray]:
    """The cells the context check scores (`restoring`: restore cells too) in every (depth,
    truth, mount) frame after the model's CRF: their features, the pixels the check would
    change (`weight`), the share of those that are a person in the truth, the frame number
    and whether each is a restore cell."""
    columns: dict[str, list] = {k: [] for k in ("features", "weight", "share", "frame", "restore")}
    for i, frame, person in labelled(segmenter, frames, "crf"):
        found = frame_cells(frame, restoring)
        if found is None:
            continue
        grid, rows, cols, x, restorable = found
        cell, (hc, wc) = grid.cell, grid.parts.shape
        labels = frame.labels[: hc * cell, : wc * cell]
        person = person[: hc * cell, : wc * cell]
        changed = np.where(IS_RESTORABLE[labels], 2, IS_PART[labels].astype(np.int8))
        weight, share = np.zeros(rows.size), np.zeros(rows.size)
        for code, kind in ((1, ~restorable), (2, restorable)):
            mine = (changed == code).reshape(hc, cell, wc, cell).sum((1, 3))
            hits = ((changed == code) & person).reshape(hc, cell, wc, cell).sum((1, 3))
            weight[kind] = mine[rows[kind], cols[kind]]
            share[kind] = hits[rows[kind], cols[kind]] / np.maximum(weight[kind], 1)
        for key, value in (("features", x), ("weight", weight), ("share", share),
                           ("frame", np.full(rows.size, i)), ("restore", restorable)):  # fmt: skip
            columns[key].append(value)
    if not columns["features"]:
        raise TopsegError("the model labelled no body part in these frames")
    return {k: np.concatenate(v) for k, v in columns.items()}


def fit_context(
    rows: dict[str, np.ndarray], keep: float, seed: int = 0, restore: float | None = None
) -> ContextCheck:
    """Histogram boosted trees fitted on three frames in four, the threshold chosen on the
    fourth to keep `keep` of its person pixels in body-part cells and, with `restore`, the
    restore threshold at which its restored pixels are `restore` a person's; the check with
    what the fourth measured."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    if restore is None:  # restore cells are fitted on only when restoring
        rows = {k: v[~rows["restore"]] for k, v in rows.items()}
    x, weight = rows["features"], rows["weight"]
    person, held = held_out(rows, "cells that are people's and cells that are not")
    clf = HistGradientBoostingClassifier(
        max_iter=CONTEXT_TREES, max_depth=CONTEXT_DEPTH, learning_rate=CONTEXT_RATE,
        early_stopping=False, random_state=seed,
    )  # fmt: skip
    clf.fit(x[~held], person[~held], sample_weight=weight[~held])
    trees = ensemble_from_histogram(clf, x[held][:10_000])
    parts, more = held & ~rows["restore"], held & rows["restore"]
    threshold, _, kept = threshold_kept(
        trees.score(x[parts]), weight[parts], rows["share"][parts], keep
    )
    validation = {"keep": keep, "cells": int(parts.sum()), **kept}
    restore_threshold = None
    if restore is not None:
        restore_threshold, restored = threshold_restoring(
            trees.score(x[more]), weight[more], rows["share"][more], restore
        )
        validation.update(restore_precision=restore, restore_cells=int(more.sum()), **restored)
    return ContextCheck(trees, threshold, validation, restore_threshold)


def threshold_restoring(
    scores: np.ndarray, size: np.ndarray, share: np.ndarray, precision: float
) -> tuple[float, dict]:
    """On held-out restore cells of `size` pixels, `share` of them a person's: the lowest
    score threshold at which the pixels of the cells at or above it are at least `precision`
    a person's (above every score when no threshold reaches it), and what it restores: the
    share of the cells' person pixels and the share of the restored pixels that are a
    person's."""
    person = size * share
    order = np.argsort(-scores, kind="stable")
    hits, total = np.cumsum(person[order]), np.cumsum(size[order])
    good = np.flatnonzero(hits >= precision * np.maximum(total, 1e-12))
    if good.size == 0 or scores.size == 0:
        threshold = float(np.max(scores, initial=0.0)) + 1.0
    else:
        threshold = float(scores[order][good[-1]])
    passed = scores >= threshold
    restored = {
        "person_px_restored": _share(person[passed], person),
        "restored_px_person": _share(person[passed], size[passed]),
    }
    return threshold, restored


def labelled(segmenter: Segmenter, frames, upto: str):
    """(frame number, the frame after the stage `upto`, its truth's person pixels at the
    working resolution) of every (depth, truth, mount) frame."""
    for i, (depth, truth, mount) in enumerate(frames):
        frame = FrameState(segmenter.plan(depth, None, f"frame {i}", mount), depth)
        segmenter.run(frame, upto=upto)
        step = frame.plan.downsample
        yield i, frame, np.isin(truth[::step, ::step], L.HUMAN_IDS)


def gather_blobs(segmenter: Segmenter, frames) -> dict[str, np.ndarray]:
    """The body-part blobs of every (depth, truth, mount) frame after the model's CRF and
    context check: their features, area (cm2), person share in the truth and frame number."""
    features, area, share, frame_no = [], [], [], []
    for i, frame, person in labelled(segmenter, frames, "context_check"):
        found = frame_blobs(frame)
        if found is None:
            continue
        blobs = found[0]
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
    person, held = held_out(rows, "blobs that are people and blobs that are not")
    clf = GradientBoostingClassifier(
        n_estimators=N_TREES, max_depth=TREE_DEPTH, learning_rate=RATE, random_state=seed
    )
    clf.fit(x[~held], person[~held], sample_weight=np.maximum(rows["area"][~held], 1e-3))
    trees = ensemble_from_sklearn(clf, x[held])
    scores = trees.score(x[held])
    threshold, passed, kept = threshold_kept(scores, rows["area"][held], rows["share"][held], keep)
    validation = {
        "keep": keep,
        "blobs": int(held.sum()),
        **kept,
        "other_blobs_removed": _share(~person[held][~passed], ~person[held]),
        "person_blobs_kept": _share(person[held][passed], person[held]),
    }
    return PersonCheck(trees, threshold, validation)


def held_frames(rows: dict[str, np.ndarray]) -> np.ndarray:
    """Which rows lie in the held-out frames: every HOLD_OUT-th, by their `frame`."""
    return rows["frame"] % HOLD_OUT == HOLD_OUT - 1


def held_out(rows: dict[str, np.ndarray], kinds: str) -> tuple[np.ndarray, np.ndarray]:
    """(person, held): which rows are a person's (`PERSON_SHARE` of their pixels or more in
    the truth) and which lie in the held-out frames (every HOLD_OUT-th); TopsegError when
    the fitting frames lack either kind (`kinds` names both in the message)."""
    person = rows["share"] >= PERSON_SHARE
    held = held_frames(rows)
    if person[~held].all() or not person[~held].any():
        raise TopsegError(f"the fitting frames need {kinds}")
    return person, held


def threshold_kept(
    scores: np.ndarray, size: np.ndarray, share: np.ndarray, keep: float
) -> tuple[float, np.ndarray, dict]:
    """On held-out rows of `size` pixels (or area), `share` of them a person's: the threshold
    that keeps `keep` of the person's (`choose_threshold`), which rows pass it, and the shares
    of person pixels it keeps and of the others it removes."""
    person = size * share
    other = size * (1 - share)
    threshold = choose_threshold(scores, person, keep)
    passed = scores >= threshold
    kept = {
        "person_px_kept": _share(person[passed], person),
        "other_px_removed": _share(other[~passed], other),
    }
    return float(threshold), passed, kept


def choose_threshold(scores: np.ndarray, person_area: np.ndarray, keep: float) -> float:
    """The highest score threshold at which blobs scoring at or above it hold at least
    `keep` of `person_area`."""
    if person_area.sum() <= 0:
        raise TopsegError("the held-out frames hold no person in a body-part blob")
    order = np.argsort(-scores, kind="stable")
    held = np.cumsum(person_area[order]) / person_area.sum()
    first = int(np.searchsorted(held, keep - 1e-12))
    return float(scores[order][min(first, len(order) - 1)])


def ensemble_from_histogram(clf, check_rows: np.ndarray, k: int = 0) -> TreeEnsemble:
    """Class `k`'s trees of a fitted HistGradientBoostingClassifier (numeric features, no
    missing values; a binary one has one class of trees) as a `TreeEnsemble`; its scores on
    `check_rows` must equal `decision_function`'s (column k for more than two classes;
    TopsegError otherwise: the exported trees are read from the estimator's fitted
    predictors, which scikit-learn does not promise to keep)."""
    fields: dict[str, list] = {k: [] for k in ("feature", "threshold", "left", "right", "value")}
    roots, depth, base = [], 0, 0
    for predictors in clf._predictors:
        nodes = predictors[k].nodes
        roots.append(base)
        leaf = nodes["is_leaf"].astype(bool)
        fields["feature"].append(np.where(leaf, -1, nodes["feature_idx"]))
        fields["threshold"].append(np.where(leaf, 0.0, nodes["num_threshold"]))
        fields["left"].append(np.where(leaf, -1, nodes["left"].astype(np.int64) + base))
        fields["right"].append(np.where(leaf, -1, nodes["right"].astype(np.int64) + base))
        fields["value"].append(np.where(leaf, nodes["value"], 0.0))
        depth = max(depth, int(nodes["depth"].max()))
        base += len(nodes)
    arrays = {k: np.concatenate(v) for k, v in fields.items()}
    trees = TreeEnsemble(
        arrays["feature"].astype(np.int32), arrays["threshold"].astype(np.float64),
        arrays["left"].astype(np.int32), arrays["right"].astype(np.int32),
        arrays["value"].astype(np.float64), np.asarray(roots, np.int32),
        float(np.ravel(clf._baseline_prediction)[k]), 1.0, depth,
    )  # fmt: skip
    reference = clf.decision_function(check_rows)
    if reference.ndim == 2:
        reference = reference[:, k]
    if np.size(reference) and np.max(np.abs(trees.score(check_rows) - reference)) > 1e-6:
        raise TopsegError("the exported trees do not reproduce scikit-learn's scores")
    return trees


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
    trees = dataclasses.replace(partial, offset=offset)
    if offsets.size and np.max(np.abs(trees.score(check_rows) - reference)) > 1e-6:
        raise TopsegError("the exported trees do not reproduce scikit-learn's scores")
    return trees


def describe_prior(validation: dict) -> str:
    """What the held-out frames measured of the context prior, in one line."""
    return (
        f"context prior: on {validation['cells']} held-out cells, "
        f"{validation['cell_px_right']:.1%} of their pixels in cells put in the right group "
        f"(the forest's argmax {validation['forest_cell_px_right']:.1%}); person cells "
        f"found {validation['person_cell_px_right']:.1%}, other cells called a person "
        f"{validation['not_person_cell_px_called_person']:.1%}"
    )


def describe(validation: dict) -> str:
    """What the held-out frames measured, in one paragraph."""
    v = validation
    return (
        f"person check, held-out frames ({v['blobs']} blobs): keeps {v['person_px_kept']:.1%} "
        f"of person pixels in body-part blobs ({v['person_blobs_kept']:.1%} of person blobs); "
        f"removes {v['other_px_removed']:.1%} of the other pixels labelled as body parts "
        f"({v['other_blobs_removed']:.1%} of those blobs)"
    )


def describe_context(validation: dict) -> str:
    """What the context check's held-out frames measured, in one line."""
    v = validation
    line = (
        f"context check, held-out frames ({v['cells']} cells): keeps {v['person_px_kept']:.1%} "
        f"of person pixels in body-part cells; removes {v['other_px_removed']:.1%} of the "
        "other pixels labelled as body parts"
    )
    if "restore_cells" in v:
        line += (
            f"; restores {v['person_px_restored']:.1%} of the person pixels in the "
            f"{v['restore_cells']} cells it may restore, {v['restored_px_person']:.1%} of what "
            "it restores a person's"
        )
    return line


def _share(part: np.ndarray, whole: np.ndarray) -> float:
    """sum(part) / sum(whole), NaN-free (0 for an empty whole)."""
    total = float(np.sum(whole))
    return float(np.sum(part)) / total if total > 0 else 0.0


__all__ = [
    "choose_threshold",
    "ensemble_from_histogram",
    "ensemble_from_sklearn",
    "fit_check",
    "fit_context",
    "fit_prior",
    "gather_blobs",
    "gather_cells",
    "gather_prior_cells",
    "held_frames",
    "held_out",
    "labelled",
    "threshold_kept",
    "threshold_restoring",
]
