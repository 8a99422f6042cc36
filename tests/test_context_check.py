"""The context check: its cell kernels against numpy references on random frames, the
exported histogram trees against scikit-learn, the model header and the stage."""

import numpy as np
import pytest
from reference import cell_channels_reference, cell_features_reference
from sklearn.ensemble import HistGradientBoostingClassifier

from topseg.core import context_check as C
from topseg.core import context_check_kernels as K
from topseg.core import labels as L
from topseg.core.errors import TopsegError
from topseg.core.forest.model_file import ModelFileError, load_model
from topseg.core.person_check import TreeEnsemble
from topseg.core.segmenter import Segmenter
from topseg.services.batch.person_check import (
    ensemble_from_histogram,
    fit_context,
    threshold_restoring,
)


def random_cells_frame(seed, shape=(50, 66)):
    """Random labels (blocky, with body parts), validity, heights (mm, a few NaN) and depth (mm)."""
    rng = np.random.default_rng(seed)
    coarse = rng.choice([0, 1, 2, 5, 6, 7, 9, 11, 12], size=(shape[0] // 5 + 1, shape[1] // 5 + 1))
    labels = np.kron(coarse, np.ones((5, 5), np.uint8))[: shape[0], : shape[1]].astype(np.uint8)
    flip = rng.random(shape) < 0.1
    labels[flip] = rng.integers(0, 13, size=flip.sum())
    valid = rng.random(shape) < 0.8
    heights = rng.uniform(0.0, 2000.0, shape).astype(np.float32)
    heights[rng.random(shape) < 0.05] = np.nan  # no height
    depth = rng.integers(1500, 4000, shape).astype(np.uint16)
    proba = rng.dirichlet(np.ones(L.NUM_CLASSES), shape).astype(np.float32)
    return labels, valid, heights, depth, proba


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("cell", [1, 2, 4])
def test_cell_channels_match_the_block_reference(seed, cell):
    frame = random_cells_frame(seed)
    tables = (C.CHANNEL_TABLE, C.POSTERIOR_TABLE)
    got = K.cell_channels(*frame, cell, *tables)
    want = cell_channels_reference(*frame, cell, *tables)
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)
    assert got[0].shape[2] == K.CHANNELS
    # a model of fewer classes: the posterior columns read the classes it has
    fewer = K.cell_channels(*frame[:4], frame[4][..., :10].copy(), cell, *tables)
    np.testing.assert_allclose(
        fewer[0], cell_channels_reference(*frame[:4], frame[4][..., :10], cell, *tables)[0],
        rtol=1e-5, atol=1e-6,
    )  # fmt: skip


@pytest.mark.parametrize("seed", range(4))
def test_cell_features_match_the_box_reference(seed):
    rng = np.random.default_rng(seed)
    chan = rng.random((23, 31, K.CHANNELS)).astype(np.float32)
    per_cm = rng.uniform(0.05, 0.6, (23, 31)).astype(np.float32)  # rings reach off the grid
    rows, cols = rng.integers(0, 23, 40), rng.integers(0, 31, 40)
    rings, boxes = np.asarray(C.RINGS_CM), np.asarray(C.BOXES_CM)
    got = K.cell_features(chan, per_cm, rows, cols, rings, boxes, C._SINES, C._COSINES)
    want = cell_features_reference(
        chan, per_cm, rows, cols, rings, boxes, C._SINES, C._COSINES, K.HEIGHT
    )
    assert got.shape == (40, len(C.FEATURES))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_cell_grid_scales_cells_by_depth_and_marks_rejected_body_parts():
    labels, valid, heights, depth, proba = random_cells_frame(7, (48, 64))
    grid = C.cell_grid(labels, valid, heights, depth, proba, C.REFERENCE_FOCAL_PX / 2)
    assert grid.cell == C.CELL_PX // 2 and grid.channels.shape[:2] == (24, 32)
    assert [C.cell_side(f) for f in (570.3, 365.0, 285.0, 100.0)] == [4, 3, 2, 1]
    block = depth[:2, :2][valid[:2, :2]].astype(float)
    if block.size:
        assert grid.cells_per_cm[0, 0] == pytest.approx(
            C.REFERENCE_FOCAL_PX / 2 * 10.0 / block.mean() / 2, rel=1e-5
        )
    rows, cols = C.part_cells(grid)
    assert (grid.parts[rows, cols] > 0).all() and rows.size == (grid.parts > 0).sum()
    people = np.arange(rows.size) % 3 > 0
    marked = C.rejected_pixels(grid, rows[~people], cols[~people], labels)
    want = np.zeros(labels.shape, bool)
    for r, c in zip(rows[~people], cols[~people], strict=True):
        want[2 * r : 2 * r + 2, 2 * c : 2 * c + 2] = True
    np.testing.assert_array_equal(marked.astype(bool), want & np.isin(labels, L.HUMAN_IDS))
    assert C.cell_grid(labels, np.zeros_like(valid), heights, depth, proba, 500.0) is None


@pytest.mark.parametrize("seed", range(3))
def test_restore_cells_are_the_cells_without_body_parts_the_forest_finds_person_like(seed):
    labels, valid, heights, depth, proba = random_cells_frame(seed, (48, 64))
    person = proba[..., list(L.HUMAN_IDS)].sum(axis=2)
    grid = C.cell_grid(labels, valid, heights, depth, proba, C.REFERENCE_FOCAL_PX / 2)
    rows, cols = C.restore_cells(grid)
    want = set()
    for r in range(0, 48, 2):
        for c in range(0, 64, 2):
            lab, ok = labels[r : r + 2, c : c + 2], valid[r : r + 2, c : c + 2]
            mean_person = person[r : r + 2, c : c + 2][ok].mean() if ok.any() else 0.0
            if (
                not np.isin(lab, L.HUMAN_IDS).any()
                and C.IS_RESTORABLE[lab[ok]].any()
                and mean_person >= C.RESTORE_FLOOR - 1e-6
            ):
                want.add((r // 2, c // 2))
    assert set(zip(rows.tolist(), cols.tolist(), strict=True)) == want and want
    marked = C.restored_pixels(grid, rows, cols, labels)
    chosen = np.zeros(labels.shape, bool)
    for r, c in want:
        chosen[2 * r : 2 * r + 2, 2 * c : 2 * c + 2] = True
    np.testing.assert_array_equal(marked.astype(bool), chosen & C.IS_RESTORABLE[labels])


def test_the_restore_threshold_is_the_most_lenient_at_the_asked_precision():
    # scores high to low: person shares 1, 1, 0.5, 0, 1 over cells of 10 pixels each
    scores = np.array([0.1, 3.0, 2.0, 1.0, 0.5])
    size = np.full(5, 10.0)
    share = np.array([1.0, 1.0, 1.0, 0.5, 0.0])
    threshold, v = threshold_restoring(scores, size, share, precision=0.8)
    assert threshold == 1.0  # 25 of 30 pixels down to 1.0; 25 of 40 below
    assert v["person_px_restored"] == pytest.approx(25 / 35)
    assert v["restored_px_person"] == pytest.approx(25 / 30)
    threshold, v = threshold_restoring(scores, size, np.zeros(5), precision=0.8)
    assert threshold > scores.max() and v["person_px_restored"] == 0.0


@pytest.mark.parametrize("seed", range(2))
def test_exported_histogram_trees_score_as_scikit_learn(seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(3000, 9)).astype(np.float32)
    y = x[:, 0] + 0.5 * x[:, 3] ** 2 > 0.4
    clf = HistGradientBoostingClassifier(max_iter=30, max_depth=4, random_state=seed).fit(x, y)
    trees = ensemble_from_histogram(clf, x[:100])
    fresh = rng.normal(size=(500, 9)).astype(np.float32)
    np.testing.assert_allclose(trees.score(fresh), clf.decision_function(fresh), atol=1e-9)
    again = TreeEnsemble.from_dict(trees.to_dict(), 9)
    np.testing.assert_array_equal(again.score(fresh), trees.score(fresh))


def test_fit_context_keeps_the_asked_share_on_held_out_frames():
    rng = np.random.default_rng(1)
    n = 4000
    x = rng.normal(size=(n, 12)).astype(np.float32)  # the fit reads any number of features
    share = (x[:, 0] > 0).astype(float)
    restore = np.arange(n) % 3 == 0
    rows = {"features": x, "weight": rng.integers(1, 16, n).astype(float), "share": share,
            "frame": np.arange(n) // 10, "restore": restore}  # fmt: skip
    check = fit_context(rows, keep=0.95)
    v = check.validation
    assert v["person_px_kept"] >= 0.95 and v["other_px_removed"] > 0.9
    held = rows["frame"] % 4 == 3
    assert v["cells"] == (held & ~restore).sum()
    assert check.restore_threshold is None and "restore_cells" not in v
    restoring = fit_context(rows, keep=0.95, restore=0.9)
    v = restoring.validation
    assert v["restore_cells"] == (held & restore).sum() and v["restored_px_person"] >= 0.9
    assert v["person_px_restored"] > 0.8
    judged = restoring.judge(x[held], restore[held])
    assert (judged[restore[held]] == (restoring.trees.score(x[held & restore])
                                      >= restoring.restore_threshold)).all()  # fmt: skip
    with pytest.raises(TopsegError, match="cells that are people's and cells that are not"):
        fit_context({**rows, "share": np.ones(n)}, keep=0.95)


def constant_check(threshold):
    """A one-leaf check scoring 0 everywhere."""
    trees = TreeEnsemble(np.array([-1], np.int32), np.zeros(1), np.array([-1], np.int32),
                         np.array([-1], np.int32), np.zeros(1), np.zeros(1, np.int32),
                         0.0, 1.0, 0)  # fmt: skip
    return C.ContextCheck(trees, threshold, {})


@pytest.fixture(scope="module")
def bundled():
    """The bundled model's forest and header, loaded once."""
    from topseg.core.bundled_model import bundled_model_path

    return load_model(bundled_model_path())


def with_context(bundled, score_threshold, **entry_changes):
    """A Segmenter of the bundled forest with a constant context check (and no person check,
    which would judge what the context check leaves)."""
    forest, header = bundled
    entry = {**constant_check(score_threshold).to_header(), **entry_changes}
    keep = {k: v for k, v in header.items() if k != "person_check"}
    return Segmenter(forest, {**keep, C.ContextCheck.HEADER_KEY: entry}, crf="realtime")


def test_the_stage_relabels_the_body_parts_of_cells_the_check_rejects(bundled):
    from topseg.services.batch.experiment.mounts import cell_mount
    from topseg.services.batch.experiment.open_world import render_cells

    reject_all = with_context(bundled, 1.0)
    keep_all = with_context(bundled, -1.0)
    header = {k: v for k, v in keep_all.header.items() if k != C.ContextCheck.HEADER_KEY}
    unchecked = Segmenter(keep_all.forest, header, crf="realtime")
    assert reject_all.context_check is not None and unchecked.context_check is None
    assert "context_check" in reject_all.stage_names
    seen = 0
    for depth, _, mount, _, _ in render_cells(cell_mount("kinect_v1", 3.0, 0.0), 3, seed=99):
        base = unchecked.label(depth, mount=mount)
        np.testing.assert_array_equal(keep_all.label(depth, mount=mount).labels, base.labels)
        before, after = (upto(seg, depth, mount, stage)
                         for seg, stage in ((reject_all, "crf"), (reject_all, "context_check")))  # fmt: skip
        # every body-part pixel lies in a cell the check scores, so none is left; each takes
        # a class that is neither a body part nor background
        assert not np.isin(after.labels, L.HUMAN_IDS).any()
        changed = after.labels != before.labels
        np.testing.assert_array_equal(changed, np.isin(before.labels, L.HUMAN_IDS))
        assert not np.isin(after.labels[changed], (L.BACKGROUND, *L.HUMAN_IDS)).any()
        assert after.counts["not_person_cell_px"] == changed.sum()
        seen += changed.sum()
        assert base.counts["not_person_cells"] == 0
    assert seen > 0


def test_the_stage_restores_the_cells_the_check_finds_a_persons(bundled):
    from topseg.services.batch.experiment.mounts import cell_mount
    from topseg.services.batch.experiment.open_world import render_cells

    restore = {"restore_threshold": -1.0, "restore_floor": C.RESTORE_FLOOR}
    restore_all = with_context(bundled, -1.0, **restore)  # keeps every body part too
    no_restore = with_context(bundled, -1.0)
    assert restore_all.context_check.restore_threshold == -1.0
    assert no_restore.context_check.restore_threshold is None
    seen = 0
    for depth, _, mount, _, _ in render_cells(cell_mount("kinect_v1", 3.0, 0.0), 3, seed=99):
        before = upto(restore_all, depth, mount, "crf")
        grid = C.cell_grid(before.labels, (before.inp.values > 0) & ~before.inp.floor,
                           before.heights(), before.depth, before.fill(None),
                           before.plan.work_mount.intrinsics.fx)  # fmt: skip
        rows, cols = C.restore_cells(grid)
        want = C.restored_pixels(grid, rows, cols, before.labels).astype(bool)
        after = upto(restore_all, depth, mount, "context_check")
        changed = after.labels != before.labels
        np.testing.assert_array_equal(changed, want)
        assert np.isin(after.labels[changed], L.HUMAN_IDS).all()
        assert after.counts["restored_cell_px"] == changed.sum()
        assert after.counts["restored_cells"] == rows.size
        assert after.counts["not_person_cells"] == 0
        unchanged = upto(no_restore, depth, mount, "context_check")
        np.testing.assert_array_equal(unchanged.labels, before.labels)
        assert unchanged.counts["restored_cells"] == 0
        seen += changed.sum()
    assert seen > 0


def upto(seg, depth, mount, stage):
    """The frame after `stage`."""
    from topseg.core.stages.plan import FrameState

    frame = FrameState(seg.plan(depth, None, "frame", mount), depth)
    seg.run(frame, upto=stage)
    return frame


def test_a_model_whose_context_check_reads_other_features_is_refused(bundled):
    with pytest.raises(ModelFileError, match="other cell features"):
        with_context(bundled, 0.0, features=["a", "b"])
    with pytest.raises(ModelFileError, match="other cell features"):
        with_context(bundled, 0.0, cell_px=C.CELL_PX + 1)
    with pytest.raises(ModelFileError, match="threshold"):
        with_context(bundled, 0.0, threshold="x")
    with pytest.raises(ModelFileError, match="restores other cells"):
        with_context(bundled, 0.0, restore_threshold=1.0, restore_floor=C.RESTORE_FLOOR / 2)
    with pytest.raises(ModelFileError, match="restore threshold"):
        with_context(bundled, 0.0, restore_threshold="x", restore_floor=C.RESTORE_FLOOR)


def test_a_restoring_check_round_trips_through_the_header():
    check = constant_check(0.5)
    again = C.ContextCheck.from_header({"context_check": check.to_header()})
    assert again.restore_threshold is None and "restore_threshold" not in check.to_header()
    restoring = C.ContextCheck(check.trees, 0.5, {"a": 1}, restore_threshold=1.25)
    entry = restoring.to_header()
    assert entry["restore_floor"] == C.RESTORE_FLOOR
    again = C.ContextCheck.from_header({"context_check": entry})
    assert (again.threshold, again.restore_threshold, again.validation) == (0.5, 1.25, {"a": 1})
