"""datagen on real local Dask clusters: determinism across worker counts, errors from workers."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from datagen_toy import toy_frame

from topseg.core.errors import TopsegError
from topseg.core.formats import dataset as D
from topseg.services.batch import datagen
from topseg.services.batch.datagen.sources import GENERATORS, generator_config, load_factory

HAVE_SYNTHESIS = importlib.util.find_spec("topseg.core.synth.synthesis") is not None
GENERATOR_NAMES = ["datagen_toy:slow_source"] + (["synthesis"] if HAVE_SYNTHESIS else [])


@pytest.fixture(scope="module")
def one_worker():
    with datagen.dask_client(workers=1) as client:
        yield client


@pytest.fixture(scope="module")
def two_workers():
    with datagen.dask_client(workers=2) as client:
        yield client


def writer_for(path, name, frames, seed=5, mode="modeled", noise="gaussian:15"):
    target = GENERATORS.get(name, name)
    generator = {"factory": target, "config": generator_config(target, mode, noise, None)}
    attrs = D.make_attrs(
        seed=seed, mode=mode, noise=noise, room=None, generator=generator, frames=frames
    )
    return D.DatasetWriter.open(path, attrs)


@pytest.mark.slow
@pytest.mark.parametrize("name", GENERATOR_NAMES)
def test_same_seed_same_frames_whatever_the_workers(tmp_path, one_worker, two_workers, name):
    frames, seed = 9, 5
    stores = {}
    for n, client in ((1, one_worker), (2, two_workers)):
        path = tmp_path / f"w{n}.zarr"
        writer = writer_for(path, name, frames, seed)
        with writer:
            stats = datagen.generate(writer, client, chunk=2, progress=False)
        assert stats["frames"] == frames and stats["workers"] == n
        assert stats["workers_used"] == n  # the 2-worker run really split the frames
        assert stats["frames_per_s"] > 0
        stores[n] = D.open_dataset(path)
    a, b = stores[1], stores[2]
    assert len(a) == len(b) == frames
    np.testing.assert_array_equal(a.depth[:], b.depth[:])
    np.testing.assert_array_equal(a.labels[:], b.labels[:])
    assert [a.scene(k) for k in range(frames)] == [b.scene(k) for k in range(frames)]
    # and equal to the generator called here, in this process, out of order
    source = load_factory(GENERATORS.get(name, name))(a.attrs["generator"]["config"], seed)
    for i in (7, 0, 4):
        depth, labels, _ = source(i)
        np.testing.assert_array_equal(a.depth[i], depth)
        np.testing.assert_array_equal(a.labels[i], labels)
    if hasattr(source, "close"):
        source.close()
    # another seed gives other frames
    writer = writer_for(tmp_path / "other.zarr", name, 2, seed + 1)
    with writer:
        datagen.generate(writer, two_workers, chunk=1, progress=False)
    assert not np.array_equal(D.open_dataset(tmp_path / "other.zarr").depth[0], a.depth[0])


def test_resume_renders_only_missing_frames(tmp_path, two_workers):
    path = tmp_path / "ds.zarr"
    writer = writer_for(path, "datagen_toy:toy_source", 7, noise="none")
    with writer:
        fw = D.FrameWriter(path)
        for i in (0, 3):
            fw.write(i, *toy_frame(5, i, "none"))
        writer.mark_complete([0, 3])
        stats = datagen.generate(writer, two_workers, chunk=3, progress=False)
    assert stats["frames"] == 5
    ds = D.open_dataset(path)
    assert ds.indices.tolist() == list(range(7))
    for i in range(7):
        np.testing.assert_array_equal(ds.depth[i], toy_frame(5, i, "none")[0])


def test_a_bad_frame_from_a_worker_stops_the_run_and_keeps_what_was_done(tmp_path, two_workers):
    path = tmp_path / "ds.zarr"
    writer = writer_for(path, "datagen_toy:failing_source", 12, noise="none")
    with writer, pytest.raises(D.DatasetError, match="frame 5: labels are int32"):
        datagen.generate(writer, two_workers, chunk=1, progress=False)
    ds = D.open_dataset(path)
    assert 5 not in ds.indices
    for k, i in enumerate(ds.indices):
        np.testing.assert_array_equal(ds.labels[k], toy_frame(5, int(i), "none")[1])


@pytest.mark.slow
def test_the_cli_runs_on_an_existing_scheduler(tmp_path, two_workers):
    import os
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "ds.zarr"
    topseg = str(Path(sys.executable).with_name("topseg"))
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parent))
    args = [topseg, "-q", "datagen", "--generator", "datagen_toy:toy_source", "--frames", "6",
            "--out", str(out), "--seed", "5", "--noise", "none", "--chunk", "2"]  # fmt: skip
    address = two_workers.scheduler.address
    result = subprocess.run(
        [*args, "--scheduler", address], env=env, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr
    assert "on 2 workers" in result.stdout
    ds = D.open_dataset(out)
    for i in range(6):
        np.testing.assert_array_equal(ds.depth[i], toy_frame(5, i, "none")[0])
    bad = subprocess.run(
        [*args, "--out", str(tmp_path / "b.zarr"), "--scheduler", "tcp://127.0.0.1:9"],
        env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert bad.returncode == 2
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in bad.stderr


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_SYNTHESIS, reason="topseg.core.synth.synthesis not in the tree yet")
def test_the_default_generator_records_its_full_config(tmp_path, two_workers):
    from topseg import __version__
    from topseg.core.synth.synthesis import SynthesisConfig

    path = tmp_path / "ds.zarr"
    with writer_for(path, "synthesis", 4, seed=3, mode="non-modeled", noise="kinect") as w:
        datagen.generate(w, two_workers, chunk=2, progress=False)
    ds = D.open_dataset(path)
    a = ds.attrs
    assert (a["seed"], a["mode"], a["noise"], a["topseg_version"]) == (
        3,
        "non-modeled",
        "kinect",
        __version__,
    )
    config = SynthesisConfig.from_dict(a["generator"]["config"])
    assert config.to_dict() == SynthesisConfig(mode="non-modeled", noise="kinect").to_dict()
    for k in range(4):
        scene = ds.scene(k)
        assert scene["mode"] == "non-modeled"
        assert (ds.labels[k] != 0).any()  # something of the scene is in view


@pytest.mark.slow
def test_a_crashing_worker_is_a_clear_error_and_keeps_what_was_done(tmp_path):
    import dask

    from topseg.core.errors import TopsegError

    path = tmp_path / "ds.zarr"
    writer = writer_for(path, "datagen_toy:crashing_source", 8, noise="none")
    with (
        dask.config.set({"distributed.scheduler.allowed-failures": 0}),
        datagen.dask_client(workers=1) as client,
        writer,
        pytest.raises(TopsegError, match=r"worker process died .* rerun the same command"),
    ):
        datagen.generate(writer, client, chunk=2, progress=False)
    ds = D.open_dataset(path)
    assert 3 not in ds.indices and 2 not in ds.indices
    for k, i in enumerate(ds.indices):
        np.testing.assert_array_equal(ds.depth[k], toy_frame(5, int(i), "none")[0])


def test_a_mixed_sensor_dataset_pads_small_frames_and_keeps_each_mount(tmp_path):
    """Drawn mounts (the datagen default): frames of every sensor in one 480 x 640 store,
    smaller ones top-left and padded, each frame's mount read back by Dataset.mount."""
    import argparse

    from topseg.core import labels
    from topseg.services.batch.datagen.sources import mount_summary

    args = argparse.Namespace(mounts=None, sensors="kinect_v2,oak_d,kinect_v1")
    target = GENERATORS["synthesis"]
    mounts = datagen.mount_distribution(args, target)
    assert mounts["sensors"] == ["kinect_v2", "oak_d", "kinect_v1"]
    generator = {
        "factory": target,
        "config": generator_config(target, "modeled", "sensor", None, mounts),
    }
    attrs = D.make_attrs(
        seed=3, mode="modeled", noise="sensor", room=None, generator=generator, frames=8,
        mounts=mount_summary(generator),
    )  # fmt: skip
    path = tmp_path / "mixed.zarr"
    with D.DatasetWriter.open(path, attrs) as w:
        todo = w.todo().tolist()
        datagen.render_chunk(str(path), "k", generator, 3, todo)
        w.mark_complete(todo)
    ds = D.open_dataset(path)
    assert ds.attrs["mounts"]["resolutions"] == [[512, 424], [640, 400], [640, 480]]
    sensors = set()
    for k in range(len(ds)):
        depth, _lab, mount = ds.frame(k)
        sensors.add(mount.sensor)
        h, w = mount.intrinsics.shape
        assert depth.shape == (h, w) and ds.scene(k)["mount"] == mount.to_dict()
        assert not ds.depth[k][h:].any() and not ds.depth[k][:, w:].any()
        assert np.all(ds.labels[k][h:] == labels.NO_DEPTH)
        assert np.all(ds.labels[k][:, w:] == labels.NO_DEPTH)
        assert (
            2400 <= mount.height_mm <= 4500 and max(abs(mount.pitch_deg), abs(mount.roll_deg)) <= 10
        )
    assert len(sensors) >= 2
    assert (
        datagen.mount_distribution(argparse.Namespace(mounts="paper", sensors=None), target) is None
    )
    with pytest.raises(Exception, match="needs --mounts random"):
        datagen.mount_distribution(argparse.Namespace(mounts="paper", sensors="oak_d"), target)


def test_sensor_weights_repeat_a_sensor_in_the_draw_list():
    """`--sensors oak_d:2,kinect_v1`: oak_d drawn twice as often, so about 2/3 of the mounts
    are OAK-D; the dataset's summary names each sensor once; bad weights are refused."""
    import argparse

    from topseg.core.synth.synthesis import MountDistribution, mount_summary

    assert datagen.weighted_sensors("oak_d:2, kinect_v1,") == ("oak_d", "oak_d", "kinect_v1")
    args = argparse.Namespace(mounts="random", sensors="oak_d:2,kinect_v1")
    d = MountDistribution.from_dict(datagen.mount_distribution(args, GENERATORS["synthesis"]))
    rng = np.random.default_rng(5)
    drawn = [d.draw(rng).sensor for _ in range(3000)]
    assert abs(drawn.count("oak_d") / 3000 - 2 / 3) < 0.03
    assert mount_summary(d, None)["sensors"] == ["oak_d", "kinect_v1"]
    for bad in ("oak_d:0", "oak_d:x", "oak_d:101", "oak_d:1.5"):
        with pytest.raises(TopsegError, match="whole number from 1 to 100"):
            datagen.weighted_sensors(bad)
    with pytest.raises(TopsegError, match="kinect_v3"):
        datagen.mount_distribution(
            argparse.Namespace(mounts="random", sensors="kinect_v3:2"), GENERATORS["synthesis"]
        )
