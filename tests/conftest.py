"""Fixtures shared by the service tests."""

import numpy as np
import pytest

from topseg.core.formats import dataset as D
from topseg.core.synth import procedural


@pytest.fixture(scope="session")
def data(tmp_path_factory):
    """A 12-frame procedural dataset written through the real dataset writer."""
    path = tmp_path_factory.mktemp("train") / "ds.zarr"
    n = 12
    attrs = D.make_attrs(
        seed=5,
        mode="procedural",
        noise="gaussian:10",
        room=None,
        generator={"name": "procedural"},
        frames=n,
    )
    rng = np.random.default_rng(5)
    with D.DatasetWriter.open(path, attrs) as w:
        fw = D.FrameWriter(path)
        for i in range(n):
            depth, labels = procedural.procedural_frame(rng)
            fw.write(i, depth, labels, {"index": i})
        w.mark_complete(range(n))
    return path
