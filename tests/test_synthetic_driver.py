"""The synthetic driver: spec options, deterministic frames with truth, pacing off."""

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer
from topseg.drivers import SourceOptions, open_source
from topseg.drivers.base import SourceError
from topseg.drivers.synthetic import parse_options


def test_parse_options_reads_mode_and_settings():
    assert parse_options(None) == {}
    assert parse_options("non-modeled,seed=3") == {"mode": "non-modeled", "seed": 3}
    assert parse_options("room=office, noise=none") == {"room": "office", "noise": "none"}


@pytest.mark.parametrize("arg", ["bogus", "seed=x", "colour=red"])
def test_bad_options_name_the_problem(arg):
    with pytest.raises(SourceError, match="synthetic"):
        parse_options(arg)


def test_bad_config_value_is_a_source_error():
    with pytest.raises(SourceError, match="room"):
        open_source("synthetic:room=nowhere", SourceOptions())


@pytest.mark.slow
def test_frames_match_the_synthesizer_and_carry_truth():
    with open_source("synthetic:seed=5", SourceOptions(realtime=False)) as src:
        got = []
        for frame in src.frames():
            got.append(frame)
            if len(got) == 3:
                break
        assert not src.finite and src.intrinsics is not None
    with Synthesizer(SynthesisConfig(seed=5)) as synth:
        want = [synth.render(i) for i in range(3)]
    for i, (g, w) in enumerate(zip(got, want, strict=True)):
        assert g.depth.seq == g.truth.seq == i
        assert g.depth.stamp_ns == g.truth.stamp_ns > 0
        np.testing.assert_array_equal(g.depth.depth, w.depth)
        np.testing.assert_array_equal(g.truth.labels, w.labels)
        assert np.all(g.truth.labels[g.depth.depth == 0] == labels.NO_DEPTH)
    assert not np.array_equal(got[0].depth.depth, got[1].depth.depth)


@pytest.mark.slow
def test_a_random_mount_stream_carries_its_mount_on_every_frame():
    from topseg.core.camera import PAPER_MOUNT

    src = open_source("synthetic:mount=random,sensor=oak_d,seed=2", SourceOptions(realtime=False))
    try:
        frames = [f for f, _ in zip(src.frames(), range(2), strict=False)]
    finally:
        src.close()
    mount = frames[0].depth.mount
    assert mount.sensor == "oak_d" and 2400 <= mount.height_mm <= 4500
    for f in frames:
        assert f.depth.mount == mount and f.depth.depth.shape == (400, 640)
    plain = open_source("synthetic", SourceOptions(realtime=False))
    try:
        assert next(iter(plain.frames())).depth.mount == PAPER_MOUNT
    finally:
        plain.close()
    with pytest.raises(SourceError, match="paper or random"):
        parse_options("mount=tilted")
