"""The person check: blob features against a per-blob numpy reference, the tree ensemble
against scikit-learn, the threshold choice, relabelling, the model header and the stage."""

import numpy as np
import pytest
from scipy import ndimage
from sklearn.ensemble import GradientBoostingClassifier

from tests.reference import tree_ensemble_reference
from topseg.core import labels as L
from topseg.core.camera import Intrinsics
from topseg.core.errors import TopsegError
from topseg.core.forest.model_file import ModelFileError, caller_header, load_model, save_model
from topseg.core.person_check import (
    FEATURES,
    MAX_TREE_DEPTH,
    MIN_EXTENT_M,
    NO_HEAD_MM,
    RING_PX,
    TALL_MM,
    TOP_MM,
    GroupedTrees,
    PersonCheck,
    TreeEnsemble,
    blob_features,
    relabel_blobs,
)
from topseg.core.person_check_kernels import label8
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.services.batch.person_check import (
    choose_threshold,
    ensemble_from_sklearn,
    fit_check,
)

K = Intrinsics(64, 48, 50.0, 52.0, 31.5, 23.5)


def random_frame(seed):
    """Blocky random labels with holes, depth, heights and posteriors on a 48x64 frame."""
    rng = np.random.default_rng(seed)
    coarse = rng.choice(
        [0, 1, 2, 3, 6, 7, 11, 12, 255],
        size=(12, 16),
        p=[0.3, 0.06, 0.14, 0.06, 0.1, 0.08, 0.1, 0.1, 0.06],
    )
    labels = np.kron(coarse, np.ones((4, 4), np.uint8)).astype(np.uint8)
    flip = rng.random(labels.shape) < 0.05
    labels[flip] = rng.choice([0, 2, 5, 11], size=flip.sum())
    depth = rng.integers(1500, 3500, size=labels.shape).astype(np.uint16)
    depth[labels == 255] = 0
    heights = np.where(depth > 0, 3000.0 - depth + rng.normal(0, 20, depth.shape), np.nan)
    proba = rng.dirichlet(np.ones(13), size=labels.shape).astype(np.float32)
    return labels, depth, heights.astype(np.float32), proba


def reference_features(labels, depth, heights, proba, k, camera_mm):
    """One row per 8-connected body-part blob, computed blob by blob with plain numpy."""
    image, n = ndimage.label(np.isin(labels, L.HUMAN_IDS), structure=np.ones((3, 3), bool))
    area = (depth / 10.0) ** 2 / (k.fx * k.fy)
    h = np.where(depth > 0, np.nan_to_num(heights), 0.0).astype(np.float64)
    rows_, cols_ = np.indices(labels.shape)
    rows = []
    for b in range(1, n + 1):
        m = image == b
        a = area[m]
        tot = a.sum()
        valid = depth[m] > 0
        hv = h[m][valid]
        hmax, hmin = (hv.max(), hv.min()) if hv.size else (0.0, 0.0)
        mean = (a * h[m]).sum() / tot
        std = np.sqrt(max((a * h[m] ** 2).sum() / tot - mean**2, 0))
        top = (a * (h[m] > hmax - TOP_MM)).sum() / tot
        parts = [a[labels[m] == c].sum() / tot for c in L.HUMAN_IDS]
        post = proba[m].astype(np.float64).mean(axis=0)
        head = labels[m] == L.HEAD
        ha = a[head].sum()
        head_below = (a[head] * h[m][head]).sum() / ha - hmax if ha > 0 else NO_HEAD_MM
        z = depth[m] / 1000.0
        x, y = (cols_[m] - k.cx) * z / k.fx, (rows_[m] - k.cy) * z / k.fy
        cov = np.cov(np.stack([x, y]), aweights=a, bias=True) if tot > 0 else np.zeros((2, 2))
        ev = np.sqrt(np.maximum(np.linalg.eigvalsh(cov), 0))
        grown = np.zeros_like(m)
        for dr in range(-RING_PX, RING_PX + 1):
            for dc in range(-RING_PX, RING_PX + 1):
                grown |= np.roll(np.roll(np.pad(m, RING_PX), dr, 0), dc, 1)[
                    RING_PX:-RING_PX, RING_PX:-RING_PX
                ]
        # a ring pixel belongs to the highest-numbered blob whose window reaches it
        later = np.zeros_like(m)
        for other in range(b + 1, n + 1):
            o = image == other
            g = ndimage.binary_dilation(o, np.ones((2 * RING_PX + 1,) * 2, bool))
            later |= g
        ring = grown & (image == 0) & ~later
        rl, rv = labels[ring], depth[ring] > 0
        nr = max(ring.sum(), 1)
        rh = h[ring][rv]
        comp, _ = ndimage.label((depth > 0) & (labels != 0) & (labels != 255), np.ones((3, 3)))
        c = comp[m].max()
        ca = area[comp == c].sum()
        rows.append([
            np.log1p(tot), hmax, mean, std, hmin, hmax - hmin, top, *parts,
            sum(p > 0.05 for p in parts), *post, post[list(L.HUMAN_IDS)].sum(),
            post[list(L.FURNITURE_IDS)].sum(), np.log1p(ha), head_below,
            ev[1], ev[0], ev[1] / max(ev[0], MIN_EXTENT_M),
            (rl == L.ROBOT).sum() / nr, (rl == L.OBJECT).sum() / nr,
            np.isin(rl, L.FURNITURE_IDS).sum() / nr, (rl == 0).sum() / nr, (~rv).sum() / nr,
            rh.sum() / max(rv.sum(), 1), rh.max() - hmax if rh.size else 0.0,
            (rh > TALL_MM).sum() / max(rv.sum(), 1),
            np.log(ca / tot) if c else 0.0,
            *((area[(comp == c) & sel].sum() / ca if c else 0.0) for sel in (
                labels == L.ROBOT, labels == L.OBJECT, np.isin(labels, L.FURNITURE_IDS))),
            camera_mm, camera_mm / k.fx,
        ])  # fmt: skip
    return image, np.array(rows).reshape(n, len(FEATURES))


@pytest.mark.parametrize("seed", range(6))
def test_blob_features_match_a_per_blob_reference(seed):
    labels, depth, heights, proba = random_frame(seed)
    blobs = blob_features(labels, depth, heights, proba, K, 3000.0)
    image, expected = reference_features(labels, depth, heights, proba, K, 3000.0)
    assert blobs.count == expected.shape[0] > 0
    np.testing.assert_array_equal(blobs.image, image)
    np.testing.assert_allclose(blobs.features, expected, rtol=1e-6, atol=1e-4)


@pytest.mark.parametrize("seed", range(8))
def test_label8_numbers_components_as_scipy_does(seed):
    rng = np.random.default_rng(seed)
    density = rng.uniform(0.2, 0.7)
    mask = rng.random((int(rng.integers(1, 60)), int(rng.integers(1, 60)))) < density
    image, n = label8(mask)
    want, m = ndimage.label(mask, structure=np.ones((3, 3), bool))
    assert n == m
    np.testing.assert_array_equal(image, want)


def test_a_frame_without_body_parts_has_no_blobs():
    labels, depth, heights, proba = random_frame(0)
    labels[np.isin(labels, L.HUMAN_IDS)] = L.OBJECT
    blobs = blob_features(labels, depth, heights, proba, K, 3000.0)
    assert blobs.count == 0 and blobs.features.shape == (0, len(FEATURES))


def fitted(seed=0, n=400, f=6):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, f))
    y = x[:, 0] + 0.5 * x[:, 1] * x[:, 2] + rng.normal(0, 0.3, n) > 0
    clf = GradientBoostingClassifier(n_estimators=20, max_depth=3, random_state=seed)
    clf.fit(x, y, sample_weight=rng.random(n) + 0.1)
    return clf, x


@pytest.mark.parametrize("seed", range(3))
def test_exported_trees_score_as_scikit_learn(seed):
    clf, x = fitted(seed)
    trees = ensemble_from_sklearn(clf, x[:50])
    fresh = np.random.default_rng(seed + 10).normal(size=(300, x.shape[1]))
    np.testing.assert_allclose(trees.score(fresh), clf.decision_function(fresh), atol=1e-9)
    again = TreeEnsemble.from_dict(trees.to_dict(), x.shape[1])
    np.testing.assert_array_equal(again.score(fresh), trees.score(fresh))


def random_trees(seed, n_trees=6, n_features=5, max_depth=5):
    """Linked trees of uneven depth (leaves at every level) in `TreeEnsemble`'s arrays."""
    rng = np.random.default_rng(seed)
    feature, threshold, left, right, value, roots = [], [], [], [], [], []

    def grow(level):
        node = len(feature)
        for column in (feature, threshold, left, right, value):
            column.append(-1 if column in (feature, left, right) else 0.0)
        if level < max_depth and rng.random() < 0.75:
            feature[node] = int(rng.integers(n_features))
            threshold[node] = float(rng.choice([rng.normal(), 0.0]))  # ties with x too
            left[node] = grow(level + 1)
            right[node] = grow(level + 1)
        else:
            value[node] = float(rng.normal())
        return node

    for _ in range(n_trees):
        roots.append(grow(0))
    i32 = lambda a: np.asarray(a, np.int32)  # noqa: E731
    return (i32(feature), np.asarray(threshold), i32(left), i32(right), np.asarray(value),
            i32(roots))  # fmt: skip


@pytest.mark.parametrize("seed", range(6))
def test_scores_equal_a_walk_of_the_linked_trees(seed):
    arrays = random_trees(seed)
    trees = TreeEnsemble(*arrays, 0.25, 0.5, 5)
    rng = np.random.default_rng(seed + 100)
    x = rng.choice([-1.0, 0.0, 1.0], size=(200, 5)) * rng.random((200, 5))
    x[rng.random(x.shape) < 0.1] = np.nan  # missing features go right, as scikit-learn's
    x[rng.random(x.shape) < 0.1] = 0.0  # on a threshold: goes left
    expected = 0.25 + 0.5 * tree_ensemble_reference(x, *arrays)
    np.testing.assert_array_equal(trees.score(x), expected)
    np.testing.assert_array_equal(trees.score(x[:0]), np.zeros(0))


@pytest.mark.parametrize("seed", range(4))
def test_grouped_scores_equal_each_ensembles_walk_of_its_linked_trees(seed):
    rng = np.random.default_rng(seed + 200)
    arrays = [random_trees(seed * 10 + k, n_trees=int(rng.integers(1, 9)),
                           max_depth=int(rng.integers(1, 6))) for k in range(3)]  # fmt: skip
    ensembles = [TreeEnsemble(*a, float(rng.normal()), float(rng.random()), 5) for a in arrays]
    n = int(rng.integers(1, 40))  # blocks of rows and a ragged last one
    x = rng.choice([-1.0, 0.0, 1.0], size=(n, 5)) * rng.random((n, 5))
    x[rng.random(x.shape) < 0.1] = np.nan
    x[rng.random(x.shape) < 0.1] = 0.0
    expected = np.stack([e.offset + e.rate * tree_ensemble_reference(x, *a)
                         for e, a in zip(ensembles, arrays, strict=True)], axis=1)  # fmt: skip
    got = GroupedTrees.of(tuple(ensembles)).scores(x)
    np.testing.assert_array_equal(got, expected)
    assert GroupedTrees.of(tuple(ensembles)).scores(x[:0]).shape == (0, 3)


def test_trees_sharing_nodes_or_too_deep_are_refused():
    feature, threshold, left, right, value, roots = random_trees(0, n_trees=2, max_depth=3)
    with pytest.raises(TopsegError, match="share nodes"):
        TreeEnsemble(feature, threshold, left, right, value, np.array([roots[0], roots[0]]),
                     0.0, 1.0, 3)  # fmt: skip
    n = MAX_TREE_DEPTH + 2  # a chain: each inner node's left child is the next inner node
    feature = np.r_[np.zeros(n - 1, np.int32), -1, -np.ones(n - 1, np.int32)].astype(np.int32)
    left = np.r_[np.arange(1, n), -1, -np.ones(n - 1)].astype(np.int32)
    right = np.r_[np.arange(n, 2 * n - 1), -1, -np.ones(n - 1)].astype(np.int32)
    chain = (feature, np.zeros(2 * n - 1), left, right, np.ones(2 * n - 1), np.array([0], np.int32))
    with pytest.raises(TopsegError, match="deep"):
        TreeEnsemble(*chain, 0.0, 1.0, n - 1)


def test_trees_that_read_out_of_bounds_are_refused():
    clf, x = fitted()
    d = ensemble_from_sklearn(clf, x[:10]).to_dict()
    with pytest.raises(TopsegError, match="out of bounds"):
        TreeEnsemble.from_dict(d, 2)  # reads feature indices up to 5
    broken = {**d, "left": [len(d["left"]) + 5] * len(d["left"])}
    with pytest.raises(TopsegError, match="out of bounds"):
        TreeEnsemble.from_dict(broken, x.shape[1])
    inner = int(np.flatnonzero(np.asarray(d["feature"]) >= 0)[0])
    looping = {**d, "left": [*d["left"]]}
    looping["left"][inner] = inner  # a node that is its own child would walk forever
    with pytest.raises(TopsegError, match="out of bounds"):
        TreeEnsemble.from_dict(looping, x.shape[1])
    with pytest.raises(TopsegError, match="differ in length"):
        TreeEnsemble.from_dict({**d, "value": d["value"][:-1]}, x.shape[1])
    with pytest.raises(TopsegError, match="malformed"):
        TreeEnsemble.from_dict({**d, "roots": "x"}, x.shape[1])


def test_threshold_keeps_the_asked_share_of_person_area():
    scores = np.array([3.0, 2.0, 1.0, 0.0, -1.0])
    area = np.array([10.0, 40.0, 30.0, 0.0, 20.0])
    assert choose_threshold(scores, area, 0.5) == 2.0  # 50 of 100
    assert choose_threshold(scores, area, 0.8) == 1.0
    assert choose_threshold(scores, area, 0.81) == -1.0
    with pytest.raises(TopsegError):
        choose_threshold(scores, np.zeros(5), 0.9)


def test_fit_check_measures_its_held_out_frames():
    rng = np.random.default_rng(1)
    n = 800
    x = rng.normal(size=(n, len(FEATURES)))
    share = (x[:, 0] > 0).astype(float)
    rows = {"features": x, "area": rng.random(n) * 100 + 1, "share": share,
            "frame": np.arange(n) // 4}  # fmt: skip
    check = fit_check(rows, keep=0.95)
    v = check.validation
    assert v["person_px_kept"] >= 0.95 and v["other_px_removed"] > 0.9
    assert v["blobs"] == n // 4


def test_rejected_blobs_take_their_best_class_that_is_not_a_body_part_nor_background():
    labels, depth, heights, proba = random_frame(3)
    blobs = blob_features(labels, depth, heights, proba, K, 3000.0)
    people = np.arange(blobs.count) % 2 == 0
    out = labels.copy()
    n_blobs, n_px = relabel_blobs(out, blobs, people, proba)
    rejected = np.isin(blobs.image, np.flatnonzero(~people) + 1)
    assert n_blobs == (~people).sum() and n_px == rejected.sum() > 0
    assert not np.isin(out[rejected], (*L.HUMAN_IDS, L.BACKGROUND)).any()
    np.testing.assert_array_equal(out[~rejected], labels[~rejected])
    others = [c for c in range(1, 13) if c not in L.HUMAN_IDS]
    r, c = np.argwhere(rejected)[0]
    assert out[r, c] == others[int(np.argmax(proba[r, c, others]))]


@pytest.fixture(scope="module")
def bundled():
    """The bundled model's forest and header, loaded once."""
    from topseg.core.bundled_model import bundled_model_path

    return load_model(bundled_model_path())


def with_check(bundled, threshold, features=None):
    """A Segmenter of the bundled forest with a one-tree check scoring 0 everywhere (and no
    context check, which the same switch turns off)."""
    forest, header = bundled
    trees = TreeEnsemble(np.array([-1], np.int32), np.zeros(1), np.array([-1], np.int32),
                         np.array([-1], np.int32), np.zeros(1), np.zeros(1, np.int32),
                         0.0, 1.0, 0)  # fmt: skip
    entry = PersonCheck(trees, threshold, {}).to_header()
    if features is not None:
        entry["features"] = features
    keep = {k: v for k, v in header.items() if k != "context_check"}
    return Segmenter(forest, {**keep, "person_check": entry}, crf="realtime")


@pytest.fixture(scope="module")
def cell_frame():
    from topseg.services.batch.experiment.mounts import cell_mount
    from topseg.services.batch.experiment.open_world import render_cells

    frames = render_cells(cell_mount("kinect_v1", 3.0, 0.0), 3, seed=99)
    return frames


def test_the_stage_relabels_blobs_the_check_rejects(bundled, cell_frame):
    reject_all = with_check(bundled, 1.0)
    keep_all = with_check(bundled, -1.0)
    off = SegmenterConfig(crf=reject_all.config.crf, post=_post(person_check="off"))
    plain = Segmenter(reject_all.forest, reject_all.header, off)  # no check
    header = {k: v for k, v in reject_all.header.items() if k != "person_check"}
    unchecked = Segmenter(reject_all.forest, header, crf="realtime")  # a model without one
    assert unchecked.person_check is None
    seen = 0
    for depth, _, mount, _, _ in cell_frame:
        base = plain.label(depth, mount=mount)
        rejected = reject_all.label(depth, mount=mount)
        assert not np.isin(rejected.labels, L.HUMAN_IDS).any()
        assert (
            rejected.counts["not_people_blobs"] > 0 or not np.isin(base.labels, L.HUMAN_IDS).any()
        )
        seen += rejected.counts["not_people_blobs"]
        np.testing.assert_array_equal(keep_all.label(depth, mount=mount).labels, base.labels)
        assert base.counts["not_people_blobs"] == 0
        np.testing.assert_array_equal(unchecked.label(depth, mount=mount).labels, base.labels)
    assert seen > 0


def _post(**kw):
    from dataclasses import replace

    return replace(SegmenterConfig().post, **kw)


def test_a_model_whose_check_reads_other_features_is_refused(bundled):
    with pytest.raises(ModelFileError, match="other blob features"):
        with_check(bundled, 0.0, features=["something", "else"])


@pytest.mark.slow
def test_person_check_command_writes_a_check_the_segmenter_uses(tmp_path):
    """datagen -> person-check -> a model file whose check the Segmenter loads and runs."""
    import subprocess
    import sys
    from pathlib import Path

    from topseg.core.bundled_model import bundled_model_path

    topseg = str(Path(sys.executable).with_name("topseg"))
    data, out = tmp_path / "cells.zarr", tmp_path / "checked.npz"
    made = subprocess.run(
        [topseg, "-q", "datagen", "--mode", "cell", "--frames", "16", "--out", str(data),
         "--seed", "3", "--workers", "1", "--no-progress"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    fit = subprocess.run(
        [topseg, "-q", "person-check", "--data", str(data), "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert fit.returncode == 0, fit.stderr
    assert "person check, held-out frames" in fit.stdout
    assert "context check, held-out frames" in fit.stdout and "restores" in fit.stdout
    assert "context prior: on" in fit.stdout
    forest, header = load_model(out)
    original, original_header = load_model(bundled_model_path())
    np.testing.assert_array_equal(forest.posteriors, original.posteriors)
    assert header["person_check"]["validation"]["frames"] == 16
    assert header["context_check"]["validation"]["frames"] == 16
    assert header["context_prior"]["validation"]["frames"] == 16

    def without_checks(h):
        fitted = ("person_check", "context_check", "context_prior")
        return {k: v for k, v in h.items() if k not in fitted}

    assert without_checks(header) == without_checks(original_header)
    seg = Segmenter.from_file(out)
    assert seg.person_check is not None and seg.person_check.validation["blobs"] > 0
    assert seg.context_check is not None and seg.context_check.validation["cells"] > 0
    assert seg.context_check.restore_threshold is not None
    assert seg.context_prior is not None and seg.context_prior.validation["cells"] > 0
    # (a check fitted with --restore off, that only rejects: test_context_check's fit; one
    # more fit here costs half a minute whatever its size, sklearn binning weighted rows)
    # --context off: the person check alone, and the input model's context check dropped,
    # even one that reads other features than this topseg computes (an older version's)
    stale, alone = tmp_path / "stale.npz", tmp_path / "alone.npz"
    old_entry = {**header["context_check"], "features": ["an", "older", "set"]}
    save_model(stale, forest, {**caller_header(header), "context_check": old_entry})
    with pytest.raises(ModelFileError, match="other cell features"):
        Segmenter.from_file(stale)
    fit = subprocess.run(
        [topseg, "-q", "person-check", "--model", str(stale), "--data", str(data), "--out",
         str(alone), "--context", "off", "--prior", "off"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert fit.returncode == 0, fit.stderr
    assert "context check" not in fit.stdout and "context prior" not in fit.stdout
    seg = Segmenter.from_file(alone)
    assert seg.context_check is None and seg.person_check is not None
    assert seg.context_prior is None


def test_person_check_refuses_a_dataset_too_small_in_one_line(tmp_path, data):
    import subprocess
    import sys
    from pathlib import Path

    topseg = str(Path(sys.executable).with_name("topseg"))
    fit = subprocess.run(
        [topseg, "person-check", "--data", str(data), "--frames", "3", "--out",
         str(tmp_path / "m.npz")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert fit.returncode == 2
    assert fit.stderr.strip().count("\n") == 0 and "--frames" in fit.stderr
    assert not (tmp_path / "m.npz").exists()
