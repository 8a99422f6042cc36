"""The context prior: its fold kernel against a numpy reference on random frames, the
exported multi-class trees against scikit-learn, the model header, the fit and the stage."""

import numpy as np
import pytest
from reference import fold_prior_reference
from sklearn.ensemble import HistGradientBoostingClassifier

from topseg.core import context_check as C
from topseg.core import context_prior as P
from topseg.core import labels as L
from topseg.core.context_prior_kernels import fold_prior
from topseg.core.crf.argmax import argmax_confidence
from topseg.core.errors import TopsegError
from topseg.core.forest.model_file import ModelFileError, load_model
from topseg.core.person_check import TreeEnsemble
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.services.batch.person_check import ensemble_from_histogram, fit_prior


def random_fold_case(seed, shape=(37, 50), cell=4, classes=L.NUM_CLASSES):
    """Random posteriors, validity, group probabilities and the cells that have them."""
    rng = np.random.default_rng(seed)
    proba = rng.dirichlet(np.full(classes, 0.3), shape).astype(np.float32)
    valid = rng.random(shape) < 0.7
    hc, wc = shape[0] // cell, shape[1] // cell
    groups = rng.dirichlet(np.ones(len(P.GROUPS)), (hc, wc)).astype(np.float32)
    has_prior = rng.random((hc, wc)) < 0.8
    return proba, valid, groups, has_prior


def test_the_prior_scores_cells_above_the_floor_near_some_person_mass():
    rng = np.random.default_rng(3)
    labels = np.full((40, 48), L.BACKGROUND, np.uint8)
    proba = np.zeros((40, 48, L.NUM_CLASSES), np.float32)
    proba[..., L.OBJECT] = 1.0
    proba[8:16, 16:24, L.OBJECT] = 1.0 - P.PERSON_MASS_GATE
    proba[8:16, 16:24, L.HEAD] = P.PERSON_MASS_GATE  # the cell at (1, 2)
    heights = rng.uniform(300.0, 900.0, labels.shape).astype(np.float32)
    valid = np.ones(labels.shape, bool)
    valid[:, 40:] = False  # the last column of cells stands on the floor
    depth = np.full(labels.shape, 3000.0, np.float32)
    grid = C.cell_grid(labels, valid, heights, depth, proba, C.REFERENCE_FOCAL_PX, 8)
    rows, cols = P.prior_cells(grid)
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [
        (r, c) for r in range(3) for c in range(1, 4)
    ]
    proba[8:16, 16:24, L.HEAD] = 0.9 * P.PERSON_MASS_GATE  # below the gate: nothing
    grid = C.cell_grid(labels, valid, heights, depth, proba, C.REFERENCE_FOCAL_PX, 8)
    assert P.prior_cells(grid)[0].size == 0
    assert P.prior_cells(grid, near_people=False)[0].size == 5 * 5  # what it is fitted on
    proba[..., L.HEAD] = 0.5  # a person everywhere: every cell above the floor
    grid = C.cell_grid(labels, valid, heights, depth, proba, C.REFERENCE_FOCAL_PX, 8)
    assert P.prior_cells(grid)[0].size == 5 * 5


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize(("cell", "alpha"), [(1, 1.0), (4, 0.5), (5, 2.0), (4, 0.0)])
def test_fold_prior_matches_the_block_reference(seed, cell, alpha):
    proba, valid, groups, has_prior = random_fold_case(seed, cell=cell)
    want, want_amax = fold_prior_reference(
        proba, valid, cell, groups, has_prior, P.CLASS_GROUP, alpha, P.EPS
    )
    before = proba.copy()
    amax, pmax, psecond = argmax_confidence(proba, np.ones(valid.shape, bool))
    old_amax = amax.copy()
    changed = fold_prior(proba, valid, cell, groups, has_prior, P.CLASS_GROUP, alpha, P.EPS,
                         amax, pmax, psecond)  # fmt: skip
    np.testing.assert_allclose(proba, want, rtol=1e-5, atol=1e-6)
    # the summary follows the posteriors it changed; the others keep the forest's
    np.testing.assert_allclose(pmax, proba.max(axis=2), rtol=1e-6)
    moved = (proba != before).any(axis=2)
    np.testing.assert_array_equal(amax[moved], want_amax[moved])
    assert changed == int((amax != old_amax).sum())
    if alpha == 0.0:
        np.testing.assert_allclose(proba, before, rtol=1e-6)
        assert changed == 0
    np.testing.assert_allclose(proba.sum(axis=2), 1.0, rtol=1e-5)


def test_with_alpha_one_a_cells_mean_group_mass_nearly_becomes_its_prior():
    proba, valid, groups, has_prior = random_fold_case(7, cell=4)
    valid[:] = True
    amax, pmax, psecond = argmax_confidence(proba, valid)
    fold_prior(proba, valid, 4, groups, has_prior, P.CLASS_GROUP, 1.0, 1e-9, amax, pmax, psecond)
    hc, wc = has_prior.shape
    onehot = np.eye(len(P.GROUPS))[P.CLASS_GROUP]
    mass = (proba[: hc * 4, : wc * 4] @ onehot).reshape(hc, 4, wc, 4, -1).mean(axis=(1, 3))
    # each pixel is normalised again after the weighting, so the mean is not exact
    assert np.abs(mass[has_prior] - groups[has_prior]).mean() < 0.05


def multiclass_fit(seed=0, n=3000, features=None):
    """A small multi-class histogram fit on random rows of five separable groups."""
    rng = np.random.default_rng(seed)
    f = features or len(C.FEATURES)
    x = rng.normal(size=(n, f)).astype(np.float32)
    y = np.clip(np.floor(x[:, 0] * 1.5 + 2.5 + 0.3 * x[:, 5]), 0, 4).astype(int)
    clf = HistGradientBoostingClassifier(max_iter=20, max_depth=3, random_state=seed)
    return clf.fit(x, y), x, y


def test_exported_multiclass_trees_give_scikit_learns_probabilities():
    clf, x, _ = multiclass_fit()
    prior = P.ContextPrior(
        tuple(ensemble_from_histogram(clf, x[:100], k) for k in range(5)), P.ALPHA, {}
    )
    fresh = np.random.default_rng(9).normal(size=(400, x.shape[1])).astype(np.float32)
    np.testing.assert_allclose(prior.probabilities(fresh), clf.predict_proba(fresh), atol=1e-6)
    again = P.ContextPrior.from_header(
        {P.ContextPrior.HEADER_KEY: prior.to_header()}
    )  # fmt: skip
    np.testing.assert_array_equal(again.probabilities(fresh), prior.probabilities(fresh))
    assert again.alpha == P.ALPHA
    assert P.ContextPrior.from_header({}) is None


def test_fit_prior_measures_its_held_out_cells_and_needs_every_group():
    # twelve features, not the cells' 168: the fit reads any number, and scikit-learn bins
    # weighted rows feature by feature (half a minute for 168 under 200k rows)
    _, x, y = multiclass_fit(1, n=4000, features=12)
    n = y.size
    rng = np.random.default_rng(2)
    forest = np.where(rng.random(n) < 0.5, y, rng.integers(0, 5, n))  # a worse guess
    rows = {"features": x, "group": y, "weight": rng.integers(1, 64, n), "forest": forest,
            "frame": np.arange(n) // 20}  # fmt: skip
    prior = fit_prior(rows)
    v = prior.validation
    assert v["cells"] == (rows["frame"] % 4 == 3).sum()
    assert v["cell_px_right"] > v["forest_cell_px_right"]
    assert 0.0 <= v["not_person_cell_px_called_person"] < v["person_cell_px_right"] <= 1.0
    with pytest.raises(TopsegError, match="no cell of robot"):
        fit_prior({**rows, "group": np.where(y == 1, 2, y)})


def constant_prior(person_logit, alpha=P.ALPHA):
    """A prior of one-leaf trees: every cell scores `person_logit` for person, 0 for the rest."""

    def leaf(value):
        return TreeEnsemble(np.array([-1], np.int32), np.zeros(1), np.array([-1], np.int32),
                            np.array([-1], np.int32), np.zeros(1), np.zeros(1, np.int32),
                            float(value), 1.0, 0)  # fmt: skip

    return P.ContextPrior(tuple(leaf(person_logit if g == 0 else 0.0) for g in range(5)),
                          alpha, {})  # fmt: skip


def test_a_prior_header_that_reads_other_cells_or_is_malformed_is_refused():
    entry = constant_prior(0.0).to_header()
    key = P.ContextPrior.HEADER_KEY
    for change, match in (
        ({"features": ["a"]}, "other cells"),
        ({"cell_px": P.PRIOR_CELL_PX + 1}, "other cells"),
        ({"groups": ["person", "rest"]}, "other cells"),
        ({"trees": entry["trees"][:2]}, "5 tree ensembles"),
        ({"alpha": "x"}, "alpha"),
        ({"alpha": 9.0}, "alpha"),
    ):
        with pytest.raises(TopsegError, match=match):
            P.ContextPrior.from_header({key: {**entry, **change}})
    with pytest.raises(TopsegError, match="not a table"):
        P.ContextPrior.from_header({key: [1]})


@pytest.fixture(scope="module")
def bundled():
    """The bundled model's forest and header, loaded once."""
    from topseg.core.bundled_model import bundled_model_path

    return load_model(bundled_model_path())


def with_prior(bundled, prior, **config):
    """A Segmenter of the bundled forest with `prior` (None: none) and no checks after the
    CRF, which would judge what the prior leaves."""
    forest, header = bundled
    keep = {k: v for k, v in header.items()
            if k not in ("person_check", "context_check", P.ContextPrior.HEADER_KEY)}  # fmt: skip
    if prior is not None:
        keep[P.ContextPrior.HEADER_KEY] = prior.to_header()
    grid = SegmenterConfig().grid
    from dataclasses import replace

    cfg = SegmenterConfig(grid=replace(grid, **config), check_camera=False)
    return Segmenter(forest, keep, cfg, crf="realtime")


def test_the_stage_moves_posteriors_towards_the_cells_prior_and_off_leaves_them(bundled):
    from topseg.services.batch.experiment.mounts import cell_mount
    from topseg.services.batch.experiment.open_world import render_cells

    plain = with_prior(bundled, None)
    people = with_prior(bundled, constant_prior(8.0, alpha=1.0))
    off = with_prior(bundled, constant_prior(8.0, alpha=1.0), context_prior="off")
    assert people.context_prior is not None and plain.context_prior is None
    assert "context_prior" in people.stage_names
    moved = 0
    for depth, _, mount, _, _ in render_cells(cell_mount("kinect_v2", 3.2, 2.0), 3, seed=5):
        base = plain.label(depth, mount=mount)
        np.testing.assert_array_equal(off.label(depth, mount=mount).labels, base.labels)
        assert base.counts["prior_cells"] == 0
        seen = people.label(depth, mount=mount)
        assert seen.counts["prior_cells"] > 0
        # every cell says "a person" (0.997): above the floor, body parts only grow
        human = np.isin(seen.labels, L.HUMAN_IDS).sum()
        assert human >= np.isin(base.labels, L.HUMAN_IDS).sum()
        moved += human - np.isin(base.labels, L.HUMAN_IDS).sum()
        assert seen.counts["prior_changed_px"] > 0
    assert moved > 0


def test_a_model_without_a_prior_labels_as_before_with_the_switch_either_way(bundled):
    from topseg.services.batch.experiment.mounts import cell_mount
    from topseg.services.batch.experiment.open_world import render_cells

    on, off = with_prior(bundled, None), with_prior(bundled, None, context_prior="off")
    for depth, _, mount, _, _ in render_cells(cell_mount("oak_d", 2.8, 0.0), 2, seed=6):
        got = on.label(depth, mount=mount)
        np.testing.assert_array_equal(got.labels, off.label(depth, mount=mount).labels)
        assert got.counts["prior_cells"] == 0 and got.counts["prior_changed_px"] == 0


def test_a_model_whose_prior_is_malformed_is_refused_naming_the_file(bundled, tmp_path):
    from topseg.core.forest.model_file import caller_header, save_model

    forest, header = bundled
    bad = {**constant_prior(0.0).to_header(), "features": ["old"]}
    path = tmp_path / "bad.npz"
    save_model(path, forest, {**caller_header(header), P.ContextPrior.HEADER_KEY: bad})
    with pytest.raises(ModelFileError, match=r"bad\.npz.*other cells"):
        Segmenter.from_file(path)
