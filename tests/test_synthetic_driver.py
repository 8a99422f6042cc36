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
