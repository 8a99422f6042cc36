"""Metrics against scikit-learn on random label maps, and the documented conventions."""

from __future__ import annotations

import json

import numpy as np
import pytest
from sklearn import metrics as skm

from topseg.core import labels as L
from topseg.core.errors import TopsegError
from topseg.core.metrics import (
    ConfusionAccumulator,
    HeadDetections,
    avg_f1_draws,
    confusion_matrix,
    format_table,
    head_blobs,
    head_detections,
    scores,
    ten_class_scores,
    to_json,
)

C = L.NUM_CLASSES
IDS = list(L.SCORED_IDS)


def random_maps(rng, shape=(48, 64), absent=(), no_depth=0.05):
    """Truth and a noisy prediction; `absent` classes never occur in the truth."""
    present = [i for i in range(C) if i not in absent]
    truth = rng.choice(present, size=shape).astype(np.uint8)
    pred = np.where(rng.random(shape) < 0.6, truth, rng.integers(0, C, shape)).astype(np.uint8)
    truth[rng.random(shape) < no_depth] = L.NO_DEPTH
    pred[rng.random(shape) < no_depth] = L.NO_DEPTH
    return truth, pred


def sklearn_view(truth, pred):
    """The convention written out: drop truth no-depth, predicted no-depth -> background."""
    keep = truth != L.NO_DEPTH
    t, p = truth[keep].astype(int), pred[keep].astype(int)
    p[p == L.NO_DEPTH] = L.BACKGROUND
    return t, p


@pytest.mark.parametrize("seed", range(5))
def test_confusion_matrix_matches_sklearn(seed):
    rng = np.random.default_rng(seed)
    truth, pred = random_maps(rng, absent=(L.PLANT,))
    t, p = sklearn_view(truth, pred)
    expected = skm.confusion_matrix(t, p, labels=list(range(C)))
    assert np.array_equal(confusion_matrix(truth, pred), expected)


@pytest.mark.parametrize("seed", range(5))
def test_scores_match_sklearn_including_absent_classes(seed):
    rng = np.random.default_rng(seed)
    # one class never in the truth; another never predicted; a third in neither
    truth, pred = random_maps(rng, absent=(L.HAND, L.STORAGE))
    pred[pred == L.CHAIR] = L.TABLE
    pred[pred == L.STORAGE] = L.TABLE
    t, p = sklearn_view(truth, pred)
    s = scores(confusion_matrix(truth, pred))

    prec, rec, f1, sup = skm.precision_recall_fscore_support(t, p, labels=IDS, zero_division=np.nan)
    for k, i in enumerate(IDS):
        r = s["per_class"][L.NAMES[i]]
        np.testing.assert_allclose(
            [r["precision"], r["recall"], r["f1"]], [prec[k], rec[k], f1[k]], equal_nan=True
        )
        assert r["support"] == sup[k]
    assert np.isnan(s["per_class"]["chair"]["precision"])  # never predicted: 0/0
    assert np.isnan(s["per_class"]["hand"]["recall"])  # never in the truth: 0/0
    assert np.isnan(s["per_class"]["storage"]["f1"])  # in neither
    assert s["per_class"]["hand"]["precision"] == 0.0  # predicted, always wrong

    for key, fn in (
        ("mAP", skm.precision_score),
        ("mAR", skm.recall_score),
        ("avg_f1", skm.f1_score),
    ):
        expected = fn(t, p, labels=IDS, average="macro", zero_division=np.nan)
        assert s[key] == pytest.approx(expected)
    bg = skm.precision_recall_fscore_support(t, p, labels=[0], zero_division=np.nan)
    assert s["background"]["precision"] == pytest.approx(bg[0][0])
    assert s["background"]["recall"] == pytest.approx(bg[1][0])
    assert s["accuracy"] == pytest.approx(skm.accuracy_score(t, p))


PAPER_IDS = list(L.PAPER_SCORED_IDS)


def paper_maps(rng):
    """Truth without robots or objects, and a prediction that never says robot or object
    (a model trained on the paper's classes)."""
    truth, pred = random_maps(rng, absent=L.OPEN_WORLD_IDS)
    pred[np.isin(pred, L.OPEN_WORLD_IDS)] = L.TABLE
    return truth, pred


@pytest.mark.parametrize("seed", range(3))
def test_twelve_and_ten_class_means_match_sklearn(seed):
    rng = np.random.default_rng(seed)
    truth, pred = random_maps(rng)
    t, p = sklearn_view(truth, pred)
    s = scores(confusion_matrix(truth, pred))
    assert [L.NAMES[i] for i in IDS][-2:] == ["robot", "object"] == list(s["per_class"])[-2:]
    for key, fn in (
        ("mAP", skm.precision_score),
        ("mAR", skm.recall_score),
        ("avg_f1", skm.f1_score),
    ):
        every = fn(t, p, labels=IDS, average="macro", zero_division=np.nan)
        ten = fn(t, p, labels=PAPER_IDS, average="macro", zero_division=np.nan)
        assert s[key] == pytest.approx(every) and s[f"{key}_10"] == pytest.approx(ten)
        assert s[key] != pytest.approx(s[f"{key}_10"])


def test_without_robots_or_objects_both_means_agree_and_tables_read_as_before():
    rng = np.random.default_rng(11)
    s = scores(confusion_matrix(*paper_maps(rng)))
    for key in ("mAP", "mAR", "avg_f1"):
        assert s[key] == s[f"{key}_10"]
    for name in ("robot", "object"):
        assert s["per_class"][name]["support"] == 0 and np.isnan(s["per_class"][name]["f1"])
    table = format_table(s)
    assert "robot" not in table and "object" not in table
    assert [line.split()[0] for line in table.splitlines()].count("mean") == 1
    ten = ten_class_scores(s)
    assert list(ten["per_class"]) == [L.NAMES[i] for i in PAPER_IDS]
    assert not any(key.endswith("_10") for key in ten)
    assert (ten["mAP"], ten["mAR"], ten["avg_f1"]) == (s["mAP_10"], s["mAR_10"], s["avg_f1_10"])


def test_a_table_shows_robot_and_object_rows_and_both_means_where_they_differ():
    rng = np.random.default_rng(12)
    truth, pred = random_maps(rng, absent=(L.OBJECT,))  # robots in the truth, objects predicted
    s = scores(confusion_matrix(truth, pred))
    lines = format_table(s).splitlines()
    rows = {line.split()[0]: line.split()[1:] for line in lines[2:] if line[0] != "-"}
    assert rows["robot"][3] == str(s["per_class"]["robot"]["support"]) != "0"
    assert rows["object"][1] == "-" and rows["object"][0] == "0.000"  # predicted, never there
    ten = next(line for line in lines if line.startswith("mean (1-10)")).split()[2:]
    every = next(line for line in lines if line.startswith("mean (1-12)")).split()[2:]
    assert ten == [f"{s[k]:.3f}" for k in ("mAP_10", "mAR_10", "avg_f1_10")]
    assert every == [f"{s[k]:.3f}" for k in ("mAP", "mAR", "avg_f1")]
    # scores read back from JSON written before the table grew: the ten-class means only
    old = json.loads(to_json(ten_class_scores(s)))
    assert "mean (1-12)" not in format_table(old) and "robot" not in format_table(old)


def test_a_confusion_saved_before_the_table_grew_is_read_padded():
    rng = np.random.default_rng(13)
    truth, pred = paper_maps(rng)
    whole = confusion_matrix(truth, pred)
    old = {"confusion": whole[: L.PAPER_NUM_CLASSES, : L.PAPER_NUM_CLASSES].tolist(), "frames": 3}
    acc = ConfusionAccumulator.from_dict(old)
    assert acc.frames == 3 and acc.confusion.shape == (C, C)
    np.testing.assert_array_equal(acc.confusion, whole)
    assert to_json(acc.scores()) == to_json({**scores(whole), "frames": 3})
    for bad in (np.zeros((C + 1, C + 1), int), np.zeros((11, 10), int), -np.ones((11, 11), int)):
        with pytest.raises(TopsegError, match="kxk non-negative"):
            ConfusionAccumulator.from_dict({"confusion": bad.tolist(), "frames": 1})


def test_bootstrap_draws_over_the_ten_classes_are_the_ten_class_avg_f1():
    rng = np.random.default_rng(14)
    frame = confusion_matrix(*random_maps(rng))
    draws = avg_f1_draws(frame[None], 3, ids=L.PAPER_SCORED_IDS)
    np.testing.assert_allclose(draws, scores(frame)["avg_f1_10"])
    assert scores(frame)["avg_f1_10"] != pytest.approx(scores(frame)["avg_f1"])


def test_no_depth_conventions():
    truth = np.array([[L.NO_DEPTH, L.HEAD, L.BACKGROUND, L.HEAD]], np.uint8)
    pred = np.array([[L.HEAD, L.NO_DEPTH, L.NO_DEPTH, L.HEAD]], np.uint8)
    cm = confusion_matrix(truth, pred)
    assert cm.sum() == 3  # the truth's no-depth pixel is ignored
    assert cm[L.HEAD, L.BACKGROUND] == 1  # a lost head pixel is a miss
    assert cm[L.BACKGROUND, L.BACKGROUND] == 1
    assert cm[L.HEAD, L.HEAD] == 1
    s = scores(cm)
    assert s["per_class"]["head"]["recall"] == 0.5
    assert s["per_class"]["head"]["precision"] == 1.0


def test_bad_input_is_refused():
    good = np.zeros((2, 2), np.uint8)
    with pytest.raises(TopsegError, match="id 13"):
        confusion_matrix(good, np.full((2, 2), 13, np.uint8))
    with pytest.raises(TopsegError, match="shape"):
        confusion_matrix(good, np.zeros((2, 3), np.uint8))
    with pytest.raises(TopsegError, match="integers"):
        confusion_matrix(good.astype(float), good)
    with pytest.raises(TopsegError, match="13x13"):
        scores(np.zeros((3, 3)))


def test_accumulator_sums_frames_and_round_trips():
    rng = np.random.default_rng(7)
    frames = [random_maps(rng) for _ in range(4)]
    a, b = ConfusionAccumulator(), ConfusionAccumulator()
    for truth, pred in frames[:2]:
        a.add(truth, pred)
    for truth, pred in frames[2:]:
        b.add(truth, pred)
    a.merge(b)
    whole = sum(confusion_matrix(t, p) for t, p in frames)
    assert np.array_equal(a.confusion, whole)
    assert a.frames == 4 and a.scores()["frames"] == 4
    again = ConfusionAccumulator.from_dict(json.loads(json.dumps(a.to_dict())))
    assert np.array_equal(again.confusion, whole) and again.frames == 4
    with pytest.raises(TopsegError):
        ConfusionAccumulator.from_dict({"confusion": [[1, 2]], "frames": 1})


def test_accumulator_add_returns_the_frames_own_confusion():
    rng = np.random.default_rng(9)
    truth, pred = random_maps(rng)
    acc = ConfusionAccumulator()
    acc.add(truth, pred)
    frame = acc.add(truth, pred)
    assert np.array_equal(frame, confusion_matrix(truth, pred))
    assert np.array_equal(acc.confusion, 2 * frame)


@pytest.mark.parametrize("seed", range(3))
def test_bootstrap_draws_are_avg_f1_of_frames_resampled_by_the_seeds_indices(seed):
    """The reference: draw the frame indices as the function does, sum those frames'
    confusions and score them with `scores`."""
    rng = np.random.default_rng(seed)
    n = 7
    frames = np.stack(
        [confusion_matrix(*random_maps(rng, absent=(L.PLANT,) if i % 2 else ())) for i in range(n)]
    )
    got = avg_f1_draws(frames, draws=25, seed=seed)
    draw_rng = np.random.default_rng(seed)
    want = [scores(frames[draw_rng.integers(0, n, n)].sum(axis=0))["avg_f1"] for _ in range(25)]
    np.testing.assert_allclose(got, want, rtol=1e-12)
    # paired: another set of n frames is resampled by the same indices
    other = frames[::-1].copy()
    draw_rng = np.random.default_rng(seed)
    idx = draw_rng.integers(0, n, n)
    assert avg_f1_draws(other, 1, seed)[0] == pytest.approx(
        scores(other[idx].sum(axis=0))["avg_f1"]
    )


def test_bootstrap_of_one_frame_is_its_own_score_and_bad_input_is_refused():
    rng = np.random.default_rng(4)
    frame = confusion_matrix(*random_maps(rng))
    draws = avg_f1_draws(frame[None], draws=5)
    np.testing.assert_allclose(draws, scores(frame)["avg_f1"])
    assert np.isnan(avg_f1_draws(np.zeros((3, C, C), np.int64), 2)).all()  # nothing scored
    with pytest.raises(TopsegError, match="frame confusions"):
        avg_f1_draws(np.zeros((C, C)), 2)
    with pytest.raises(TopsegError, match="frame confusions"):
        avg_f1_draws(np.zeros((0, C, C)), 2)
    with pytest.raises(TopsegError, match="draws"):
        avg_f1_draws(frame[None], 0)


def test_table_and_json():
    rng = np.random.default_rng(8)
    truth, pred = random_maps(rng, absent=(L.PLANT,))
    s = scores(confusion_matrix(truth, pred))
    table = format_table(s, title="Table I")
    lines = table.splitlines()
    assert lines[0] == "Table I"
    for name in L.NAMES:
        assert any(line.startswith(name) for line in lines)
    plant = next(line for line in lines if line.startswith("plant"))
    assert plant.split()[2] == "-"  # recall of an absent class: undefined, not 0
    assert f"{s['mAP']:.3f}" in table and f"{s['avg_f1']:.3f}" in table
    data = json.loads(to_json(s, mode="realtime"))
    assert data["mode"] == "realtime"
    assert data["per_class"]["plant"]["recall"] is None
    assert data["mAR"] == pytest.approx(s["mAR"])


def test_person_scores_pool_every_body_part_against_the_rest():
    from topseg.core import labels as L
    from topseg.core.metrics import person_scores

    c = np.zeros((L.NUM_CLASSES, L.NUM_CLASSES), np.int64)
    c[L.HEAD, L.BODY] = 30  # a wrong part is still a person pixel
    c[L.HEAD, L.HEAD] = 50
    c[L.LEGS, L.TABLE] = 10  # person labelled furniture
    c[L.LEGS, L.BACKGROUND] = 10
    c[L.BACKGROUND, L.HAND] = 20  # floor labelled person
    c[L.CHAIR, L.CHAIR] = 99
    s = person_scores(c)
    tp, fp, fn = 80, 20, 20
    assert s["person_precision"] == pytest.approx(tp / (tp + fp))
    assert s["person_recall"] == pytest.approx(tp / (tp + fn))
    assert s["person_f1"] == pytest.approx(2 * tp / (2 * tp + fp + fn))
    assert s["furniture_on_person"] == pytest.approx(10 / 100)
    assert np.isnan(person_scores(np.zeros_like(c))["person_f1"])


def heads_scene():
    """Truth: two heads (a 10 x 10 and an 8 x 8) and a head cut to 4 x 4 by the frame's edge
    (too small to count); the prediction finds the first head (60 % of it labelled head:
    found), misses the second, adds a patch on a shoulder (6 x 6), a speck (2 x 2, too small
    to count) and a blob mostly on the body that covers the first head's right edge."""
    truth = np.full((40, 60), L.BODY, np.uint8)
    pred = truth.copy()
    truth[2:12, 2:12] = L.HEAD
    truth[20:28, 30:38] = L.HEAD
    truth[0:4, 56:60] = L.HEAD
    pred[2:12, 2:6] = L.HEAD  # 40 px, all true head: a correct detection
    pred[30:36, 10:16] = L.HEAD  # 36 px on the body: a false head
    pred[38:40, 50:52] = L.HEAD  # 4 px: not counted
    pred[2:12, 10:18] = L.HEAD  # 80 px, 20 of them on the head: under half, a false head
    return truth, pred


def test_head_detections_count_blobs_not_pixels():
    truth, pred = heads_scene()
    assert head_detections(truth, pred) == (1, 3, 1, 2)
    assert head_detections(truth, truth) == (2, 2, 2, 2)
    none = np.full_like(truth, L.BODY)
    assert head_detections(none, none) == (0, 0, 0, 0)
    with pytest.raises(TopsegError, match="differs"):
        head_detections(truth, pred[:, :10])


def test_a_head_cut_by_holes_without_depth_is_one_head():
    truth = np.full((40, 60), L.BODY, np.uint8)
    truth[5:25, 5:25] = L.HEAD
    truth[5:25, 14:16] = L.NO_DEPTH  # a band of dark hair across the head: two halves
    pred = truth.copy()
    assert head_detections(truth, pred) == (1, 1, 1, 1)
    far = truth.copy()
    far[5:25, 11:21] = L.NO_DEPTH  # 10 px apart: more than HEAD_BRIDGE_PX from either side
    assert head_detections(far, far) == (2, 2, 2, 2)
    apart = np.full((40, 60), L.BODY, np.uint8)
    apart[5:25, 5:14] = L.HEAD
    apart[5:25, 16:25] = L.HEAD  # two heads 2 px apart with depth between: not joined
    assert head_detections(apart, apart) == (2, 2, 2, 2)


def test_head_detections_accumulate_and_say_nan_for_nothing_to_count():
    truth, pred = heads_scene()
    heads = HeadDetections()
    assert np.isnan(heads.precision) and np.isnan(heads.recall)
    assert heads.to_dict()["precision"] is None
    heads.add(truth, pred)
    heads.add(truth, truth)
    assert (heads.correct, heads.predicted, heads.found, heads.true) == (3, 5, 3, 4)
    assert heads.precision == pytest.approx(0.6) and heads.recall == pytest.approx(0.75)
    assert json.loads(json.dumps(heads.to_dict()))["recall"] == pytest.approx(0.75)
    assert "precision 0.600 (3 of 5), recall 0.750 (3 of 4)" in heads.summary()


def test_heads_at_the_image_border_are_counted_apart():
    truth = np.full((40, 60), L.BODY, np.uint8)
    truth[0:10, 20:30] = L.HEAD  # cut by the top border
    truth[20:30, 20:30] = L.HEAD  # inside the view
    pred = truth.copy()
    pred[0:10, 20:30] = L.BODY  # the cut head missed
    pred[30:40, 50:60] = L.HEAD  # a false head in the corner
    (p_share, p_border), (t_share, t_border) = head_blobs(truth, pred)
    assert t_border.tolist() == [True, False] and t_share.tolist() == [0.0, 1.0]
    assert p_border.tolist() == [False, True] and p_share.tolist() == [1.0, 0.0]
    heads = HeadDetections()
    heads.add(truth, pred)
    assert (heads.found, heads.true, heads.border_found, heads.border_true) == (1, 2, 0, 1)
    assert (heads.correct, heads.predicted) == (1, 2)
    assert (heads.border_correct, heads.border_predicted) == (0, 1)
    assert heads.border_recall == 0.0 and heads.border_precision == 0.0
    assert heads.to_dict()["border_recall"] == 0.0
    assert "at the image border: precision 0.000 (0 of 1), recall 0.000 (0 of 1)" in heads.summary()
    inner = HeadDetections()
    inner.add(truth[12:32, 10:45], pred[12:32, 10:45])  # no head touches this crop's border
    assert np.isnan(inner.border_recall) and inner.to_dict()["border_precision"] is None


def test_a_head_reaching_the_border_across_pixels_without_depth_is_at_the_border():
    truth = np.full((40, 60), L.BODY, np.uint8)
    truth[:, :2] = L.NO_DEPTH  # the sensor's outermost columns
    truth[10:20, 2:12] = L.HEAD
    (_, _), (_, t_border) = head_blobs(truth, truth)
    assert t_border.tolist() == [True]
    truth[:, :2] = L.BODY
    truth[10:20, 2:12] = L.BODY
    truth[10:20, 8:18] = L.HEAD  # 8 px from the border: inside the view
    assert head_blobs(truth, truth)[1][1].tolist() == [False]
