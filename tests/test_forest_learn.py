"""Learnability: a forest trained on procedural top-view scenes labels held-out ones."""

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount
from topseg.core.crf import CRFConfig, segment_crf
from topseg.core.forest import (
    FeatureConfig,
    TrainConfig,
    predict_labels,
    predict_proba,
    train_forest,
)
from topseg.core.synth import procedural

# half resolution keeps the test fast; a 32 px patch here spans what 64 px do at 640x480
MOUNT = TopViewMount(KINECT_V1.scaled_to(320, 240), PAPER_MOUNT.height_mm)


@pytest.fixture(scope="module")
def scenes():
    rng = np.random.default_rng(2016)
    train = procedural.procedural_frames(rng, 30, MOUNT, missing_fraction=0.002)
    test = procedural.procedural_frames(rng, 8, MOUNT, missing_fraction=0.002)
    return train, test


def score(forest, test, crf_mode=None):
    depth, truth = test
    if crf_mode is None:
        pred = np.stack([predict_labels(forest, d) for d in depth])
    else:
        config = CRFConfig(mode=crf_mode)
        pred = np.stack([segment_crf(predict_proba(forest, d), d, config) for d in depth])
    assert np.all(pred[depth == 0] == labels.NO_DEPTH)
    m = truth != labels.NO_DEPTH
    accuracy = float((pred[m] == truth[m]).mean())
    recalls = [float((pred[truth == c] == c).mean()) for c in np.unique(truth[m])]
    return accuracy, recalls


def config(**features):
    return TrainConfig(
        n_trees=3,
        max_depth=16,
        pixels_per_frame=1000,
        features=FeatureConfig(patch_px=32, **features),
    )


def test_forest_reaches_95_percent_pixel_accuracy(scenes):
    """With part of the pool comparing probes against a fixed depth (height above floor)."""
    train, test = scenes
    forest = train_forest(*train, config(absolute_fraction=0.2), seed=0)
    accuracy, recalls = score(forest, test)
    assert accuracy >= 0.95
    # every class is learnt, not only the floor (which would leave some class at 0): the
    # weakest class's recall is 0.69-0.74 over seeds 0-2 with probes off the image reading
    # the edge or the background alike, so the bar sits below that spread
    assert min(recalls) >= 0.65
    for mode in ("realtime", "exact"):  # the CRF does not lower it
        crf_accuracy, _ = score(forest, test, mode)
        assert crf_accuracy >= accuracy, mode


def test_paper_features_learn_every_class(scenes):
    """Pure depth differences (the paper's pool) confuse flat interiors with the floor,
    so only a weaker bar: every class far above chance."""
    train, test = scenes
    forest = train_forest(*train, config(), seed=0)
    accuracy, recalls = score(forest, test)
    majority = float(np.mean(test[1][test[1] != labels.NO_DEPTH] == labels.BACKGROUND))
    assert accuracy > majority
    assert np.mean(recalls) >= 0.6 and min(recalls) >= 0.25
