"""The Zarr dataset: layout, writer, reader, resume bookkeeping and damage reports."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from datagen_toy import toy_frame

from topseg.core import labels
from topseg.core.errors import TopsegError
from topseg.core.formats import dataset as D

GEN = {
    "factory": "datagen_toy:toy_source",
    "config": {"mode": "modeled", "noise": "none", "room": None},
}


def attrs(frames=6, seed=7, **kw):
    base = dict(seed=seed, mode="modeled", noise="none", room=None, generator=GEN, frames=frames)
    return D.make_attrs(**{**base, **kw})


def fill(path, frames=6, complete=None, seed=7):
    """A store with every frame written and the frames in `complete` flagged."""
    with D.DatasetWriter.open(path, attrs(frames, seed)) as w:
        fw = D.FrameWriter(path)
        for i in range(frames):
            fw.write(i, *toy_frame(seed, i, "none"))
        w.mark_complete(range(frames) if complete is None else complete)


def test_frame_seed_is_a_pure_function_of_seed_and_index():
    assert D.frame_seed(3, 10) == D.frame_seed(3, 10)
    seeds = {D.frame_seed(s, i) for s in range(20) for i in range(50)}
    assert len(seeds) == 20 * 50
    assert all(0 <= s < 2**64 for s in seeds)
    with pytest.raises(ValueError):
        D.frame_seed(-1, 0)


def test_round_trip_shows_only_complete_frames(tmp_path):
    path = tmp_path / "ds.zarr"
    fill(path, frames=6, complete=[0, 2, 3, 5])
    ds = D.open_dataset(path)
    assert len(ds) == 4
    assert ds.indices.tolist() == [0, 2, 3, 5]
    assert ds.complete.tolist() == [True, False, True, True, False, True]
    assert ds.depth.shape == (4, 480, 640) and ds.depth.dtype == np.uint16
    assert ds.labels.shape == (4, 480, 640) and ds.labels.dtype == np.uint8
    for k, i in enumerate(ds.indices):
        depth, lab, scene = toy_frame(7, int(i), "none")
        np.testing.assert_array_equal(ds.depth[k], depth)
        np.testing.assert_array_equal(ds.labels[k], lab)
        assert ds.scene(k) == scene
    np.testing.assert_array_equal(ds.depth[-1], toy_frame(7, 5, "none")[0])
    np.testing.assert_array_equal(
        ds.labels[1:3], np.stack([toy_frame(7, i, "none")[1] for i in (2, 3)])
    )
    np.testing.assert_array_equal(
        ds.depth[[3, 0]], np.stack([toy_frame(7, i, "none")[0] for i in (5, 0)])
    )
    np.testing.assert_array_equal(ds.depth[0, 10:20, 5], toy_frame(7, 0, "none")[0][10:20, 5])
    assert np.asarray(ds.labels).shape == (4, 480, 640)
    with pytest.raises(IndexError):
        ds.depth[4]
    a = ds.attrs
    assert (a["seed"], a["mode"], a["noise"], a["frames"]) == (7, "modeled", "none", 6)
    assert a["generator"] == GEN
    assert a["topseg_dataset"] == {"format": D.FORMAT, "version": D.FORMAT_VERSION}
    assert a["labels"] == labels.as_json()
    assert a["camera"]["height_mm"] == 3500.0


def test_chunks_are_one_frame_each_and_compressed(tmp_path):
    path = tmp_path / "ds.zarr"
    fill(path, frames=3)
    meta = json.loads((path / "depth" / "zarr.json").read_text())
    assert meta["chunk_grid"]["configuration"]["chunk_shape"] == [1, 480, 640]
    assert [c["name"] for c in meta["codecs"]] == ["bytes", "blosc", "crc32c"]
    size = (path / "depth" / "c.0.0.0").stat().st_size
    assert size < 480 * 640 * 2 / 2


def test_resume_lists_unflagged_frames_and_keeps_the_rest(tmp_path):
    path = tmp_path / "ds.zarr"
    fill(path, frames=6, complete=[0, 1, 4])
    partial = path / "depth" / "c.2.0.0.deadbeef.partial"
    partial.write_bytes(b"half a chunk")  # what a SIGKILL mid-write leaves
    with D.DatasetWriter.open(path, attrs(6)) as w:
        assert w.todo().tolist() == [2, 3, 5]
        assert not partial.exists()
        w.mark_complete([3])
        assert w.todo().tolist() == [2, 5]
    assert D.open_dataset(path).indices.tolist() == [0, 1, 3, 4]


def test_resume_refuses_other_settings_and_fewer_frames(tmp_path):
    path = tmp_path / "ds.zarr"
    fill(path, frames=4)
    with pytest.raises(D.DatasetError, match=r"seed: stored 7, asked 8"):
        D.DatasetWriter.open(path, attrs(4, seed=8))
    with pytest.raises(D.DatasetError, match="noise"):
        D.DatasetWriter.open(path, attrs(4, noise="gaussian:15"))
    with pytest.raises(D.DatasetError, match="holds 4 frames"):
        D.DatasetWriter.open(path, attrs(3))


def test_resume_can_grow_a_dataset(tmp_path):
    path = tmp_path / "ds.zarr"
    fill(path, frames=3)
    with D.DatasetWriter.open(path, attrs(5)) as w:
        assert w.frames == 5
        assert w.todo().tolist() == [3, 4]
        fw = D.FrameWriter(path)
        for i in (3, 4):
            fw.write(i, *toy_frame(7, i, "none"))
        w.mark_complete([3, 4])
    ds = D.open_dataset(path)
    assert len(ds) == 5 and ds.attrs["frames"] == 5
    np.testing.assert_array_equal(ds.depth[4], toy_frame(7, 4, "none")[0])
    np.testing.assert_array_equal(ds.depth[1], toy_frame(7, 1, "none")[0])


def test_frames_may_hold_robots_and_objects(tmp_path):
    path = tmp_path / "ds.zarr"
    depth, lab, scene = toy_frame(7, 0, "none")
    lab = np.where(lab == labels.BACKGROUND, labels.ROBOT, lab).astype(np.uint8)
    lab[:10][depth[:10] > 0] = labels.OBJECT
    with D.DatasetWriter.open(path, attrs(1)) as w:
        D.FrameWriter(path).write(0, depth, lab, scene)
        w.mark_complete([0])
    assert set(np.unique(D.open_dataset(path).labels[0])) >= {labels.ROBOT, labels.OBJECT}
    with pytest.raises(D.DatasetError, match=r"unknown label ids \[13\]"):
        D.FrameWriter(path).write(0, depth, np.where(lab == labels.ROBOT, 13, lab), scene)


def test_a_dataset_made_before_the_label_table_grew_resumes_with_its_classes(tmp_path):
    path = tmp_path / "ds.zarr"
    old = attrs(3)
    old["labels"] = labels.as_json(labels.PAPER_NUM_CLASSES)
    with D.DatasetWriter.open(path, old) as w:
        D.FrameWriter(path).write(0, *toy_frame(7, 0, "none"))
        w.mark_complete([0])
    with D.DatasetWriter.open(path, attrs(3)) as w:  # today's table: it resumes
        assert w.todo().tolist() == [1, 2]
        fw = D.FrameWriter(path)
        depth, lab, scene = toy_frame(7, 1, "none")
        fw.write(1, depth, lab, scene)
        robot = np.where(lab == labels.BACKGROUND, labels.ROBOT, lab).astype(np.uint8)
        with pytest.raises(D.DatasetError, match=r"unknown label ids \[11\]"):
            fw.write(2, depth, robot, scene)  # a class the dataset's table does not name
    assert D.open_dataset(path).attrs["labels"] == labels.as_json(labels.PAPER_NUM_CLASSES)
    foreign = attrs(3)
    foreign["labels"] = [{**row, "name": "x"} for row in labels.as_json()]
    with pytest.raises(D.DatasetError, match="labels: stored"):
        D.DatasetWriter.open(path, foreign)


def test_one_writer_at_a_time(tmp_path):
    path = tmp_path / "ds.zarr"
    with D.DatasetWriter.open(path, attrs(2)):
        with pytest.raises(D.DatasetError, match="another process"):
            D.DatasetWriter.open(path, attrs(2))
    D.DatasetWriter.open(path, attrs(2)).close()


def test_frames_that_break_the_contract_are_refused(tmp_path):
    path = tmp_path / "ds.zarr"
    D.DatasetWriter.open(path, attrs(2)).close()
    fw = D.FrameWriter(path)
    depth, lab, scene = toy_frame(7, 0, "none")
    cases = [
        ((depth.astype(np.int32), lab, scene), "depth is int32"),
        (
            (np.pad(depth, ((0, 1), (0, 0))), np.pad(lab, ((0, 1), (0, 0))), scene),
            r"expected uint16\(480, 640\)",
        ),
        ((depth[:-1], lab[:, :-1], scene), r"expected uint16\(480, 640\)"),
        ((depth, lab.astype(np.uint16), scene), "labels are uint16"),
        ((depth, np.where(lab == 0, 42, lab).astype(np.uint8), scene), r"unknown label ids \[42\]"),
        ((np.where(depth == 0, 1, depth).astype(np.uint16), lab, scene), "NO_DEPTH exactly where"),
        ((depth, lab, {"x": np.float64("nan")}), "not plain JSON"),
        ((depth, lab, {"x": object()}), "not plain JSON"),
    ]
    for frame, message in cases:
        with pytest.raises(D.DatasetError, match=message):
            fw.write(0, *frame)
    with pytest.raises(D.DatasetError, match="outside"):
        fw.write(2, depth, lab, scene)


def test_bad_places_are_clear_errors(tmp_path):
    with pytest.raises(D.DatasetError, match="does not exist"):
        D.DatasetWriter.open(tmp_path / "nope" / "ds.zarr", attrs(2))
    (tmp_path / "file").write_text("x")
    with pytest.raises(D.DatasetError, match="not a directory"):
        D.DatasetWriter.open(tmp_path / "file", attrs(2))
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(D.DatasetError, match="not empty"):
        D.DatasetWriter.open(tmp_path / "busy", attrs(2))
    assert (tmp_path / "busy" / "notes.txt").read_text() == "mine"
    assert issubclass(D.DatasetError, TopsegError)


def test_os_errors_become_one_line_with_advice(tmp_path):
    full = D.dataset_os_error(
        OSError(28, "No space left on device", "/x/depth/c/1"), tmp_path, "writing"
    )
    assert "no space left" in str(full) and "/x/depth/c/1" in str(full) and "rerun" in str(full)
    denied = D.dataset_os_error(
        PermissionError(13, "Permission denied", "/ro"), tmp_path, "creating"
    )
    assert "no permission" in str(denied) and "--out" in str(denied)


def test_reader_reports_what_is_not_a_dataset(tmp_path):
    with pytest.raises(D.DatasetError, match="no dataset at"):
        D.open_dataset(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(D.DatasetError, match=r"no zarr\.json"):
        D.open_dataset(tmp_path / "empty")
    import zarr

    zarr.open_group(str(tmp_path / "other"), mode="w").attrs["x"] = 1
    with pytest.raises(D.DatasetError, match="not a topseg dataset"):
        D.open_dataset(tmp_path / "other")
    path = tmp_path / "ds.zarr"
    fill(path, frames=2)
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["topseg_dataset"]["version"] = 99
    (path / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(D.DatasetError, match="format version 99"):
        D.open_dataset(path)
    (path / "zarr.json").write_text('{"zarr_format": 3, "node_')
    with pytest.raises(D.DatasetError, match="damaged Zarr metadata"):
        D.open_dataset(path)


def test_reader_reports_a_damaged_chunk(tmp_path):
    path = tmp_path / "ds.zarr"
    fill(path, frames=3)
    chunk = path / "labels" / "c.1.0.0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    ds = D.open_dataset(path)
    np.testing.assert_array_equal(ds.labels[0], toy_frame(7, 0, "none")[1])
    with pytest.raises(D.DatasetError, match=r"frame 1 of 'labels' is damaged"):
        ds.labels[1]
    with pytest.raises(D.DatasetError, match="damaged"):
        ds.labels[0:3]


def test_reader_reports_a_missing_chunk_and_a_missing_array(tmp_path):
    path = tmp_path / "ds.zarr"
    fill(path, frames=3)
    os.unlink(path / "depth" / "c.2.0.0")
    with pytest.raises(
        D.DatasetError, match=r"1 complete frame\(s\) lack their 'depth' chunk \(frames 2\)"
    ):
        D.open_dataset(path)
    path2 = tmp_path / "ds2.zarr"
    fill(path2, frames=2)
    for f in sorted(Path(path2 / "scene").rglob("*"), reverse=True):
        f.unlink() if f.is_file() else f.rmdir()
    (path2 / "scene").rmdir()
    with pytest.raises(D.DatasetError, match="'scene' array is missing"):
        D.open_dataset(path2)


def test_a_creation_cut_short_is_finished_on_resume(tmp_path):
    import shutil

    path = tmp_path / "ds.zarr"
    D.DatasetWriter.open(path, attrs(3)).close()
    shutil.rmtree(path / "complete")  # created last: a killed creation lacks it
    shutil.rmtree(path / "scene")
    with D.DatasetWriter.open(path, attrs(3)) as w:
        assert w.todo().tolist() == [0, 1, 2]
    assert len(D.open_dataset(path)) == 0


def test_direct_chunk_writes_are_the_bytes_zarr_writes(tmp_path):
    from topseg.core.formats.zarr_chunks import ChunkWriter

    path = tmp_path / "ds.zarr"
    D.DatasetWriter.open(path, attrs(4)).close()
    import zarr

    group = zarr.open_group(str(path), mode="r+")
    rng = np.random.default_rng(0)
    depth, lab, _ = toy_frame(7, 0, "none")
    frames = {
        "depth": [depth, rng.integers(0, 65536, (480, 640)).astype(np.uint16), np.zeros((480, 640), np.uint16)],
        "labels": [lab, rng.integers(0, 11, (480, 640)).astype(np.uint8), np.zeros((480, 640), np.uint8)],
        "scene": [np.array(['{"pose":"sitzend","ü":[1,2.5]}'], object), np.array(["{}"], object),
                  np.array([json.dumps({"x": list(range(500))})], object)],
    }  # fmt: skip
    for name, values in frames.items():
        arr = group[name].with_config({"write_empty_chunks": True})
        direct = ChunkWriter.for_array(path / name)
        assert direct is not None
        for i, value in enumerate(values):
            coords = (i, 0, 0) if name != "scene" else (i,)
            arr[i] = value if name != "scene" else value[0]
            by_zarr = direct.chunk_path(coords).read_bytes()
            assert direct.encode(value) == by_zarr
            direct.write(coords, value)
            assert direct.chunk_path(coords).read_bytes() == by_zarr
            got = arr[i]
            assert got == value[0] if name == "scene" else np.array_equal(got, value)


def test_arrays_of_another_layout_are_written_through_zarr(tmp_path):
    import zarr
    from zarr.codecs import GzipCodec

    from topseg.core.formats.zarr_chunks import ChunkWriter

    path = tmp_path / "ds.zarr"
    D.DatasetWriter.open(path, attrs(2)).close()
    group = zarr.open_group(str(path), mode="r+")
    group.create_array(
        "depth", shape=(2, 480, 640), chunks=(1, 480, 640), dtype="uint16",
        compressors=GzipCodec(), fill_value=0, overwrite=True,
    )  # fmt: skip
    assert ChunkWriter.for_array(path / "depth") is None
    assert ChunkWriter.for_array(path / "labels") is not None
    fw = D.FrameWriter(path)
    for i in range(2):
        fw.write(i, *toy_frame(7, i, "none"))
    with D.DatasetWriter.open(path, attrs(2)) as w:
        w.mark_complete([0, 1])
    ds = D.open_dataset(path)
    np.testing.assert_array_equal(ds.depth[1], toy_frame(7, 1, "none")[0])
    np.testing.assert_array_equal(ds.labels[1], toy_frame(7, 1, "none")[1])


def test_smaller_frames_are_stored_top_left_and_each_frame_keeps_its_mount(tmp_path):
    from topseg.core.camera import PAPER_MOUNT, TopViewMount
    from topseg.core.sensors import get_sensor

    path = tmp_path / "ds.zarr"
    small = TopViewMount(get_sensor("kinect_v2").intrinsics, 2650.0, 4.0, -9.5, "kinect_v2")
    oak = TopViewMount(get_sensor("oak_d").intrinsics, 4400.0, -1.0, 2.0, "oak_d")
    frames = []
    for i, mount in enumerate((small, oak, None)):
        h, w = (mount or PAPER_MOUNT).intrinsics.shape
        rng = np.random.default_rng(i)
        depth = rng.integers(1, 5000, (h, w)).astype(np.uint16)
        depth[:3] = 0
        lab = rng.integers(0, labels.NUM_CLASSES, (h, w)).astype(np.uint8)
        lab[depth == 0] = labels.NO_DEPTH
        scene = {"i": i} if mount is None else {"i": i, "mount": mount.to_dict()}
        frames.append((depth, lab, scene))
    mounts = {"height_mm": [2400.0, 4500.0], "tilt_deg": 14.1, "sensors": ["kinect_v2", "oak_d"],
              "resolutions": [[512, 424], [640, 400]]}  # fmt: skip
    with D.DatasetWriter.open(path, attrs(3, mounts=mounts)) as w:
        fw = D.FrameWriter(path)
        for i, f in enumerate(frames):
            fw.write(i, *f)
        w.mark_complete(range(3))
    ds = D.open_dataset(path)
    assert ds.depth.shape == (3, 480, 640)
    assert ds.mount(0) == small and ds.mount(1) == oak
    assert ds.mount(2) == PAPER_MOUNT  # no mount of its own: the dataset's camera
    for k, (depth, lab, _) in enumerate(frames):
        h, w = depth.shape
        full_d, full_l = ds.depth[k], ds.labels[k]
        np.testing.assert_array_equal(full_d[:h, :w], depth)
        np.testing.assert_array_equal(full_l[:h, :w], lab)
        assert not full_d[h:].any() and not full_d[:, w:].any()
        assert np.all(full_l[h:] == labels.NO_DEPTH) and np.all(full_l[:, w:] == labels.NO_DEPTH)
        got_d, got_l, got_m = ds.frame(k)
        np.testing.assert_array_equal(got_d, depth)
        np.testing.assert_array_equal(got_l, lab)
        assert got_m.intrinsics.shape == (h, w)
    assert ds.mount_summary() == mounts


def test_datasets_made_before_mounts_read_their_camera(tmp_path):
    from topseg.core.camera import PAPER_MOUNT

    path = tmp_path / "ds.zarr"
    old = attrs(2)
    del old["mounts"]
    old["camera"] = {"intrinsics": PAPER_MOUNT.intrinsics.to_dict(), "height_mm": 3500.0}
    with D.DatasetWriter.open(path, old) as w:
        fw = D.FrameWriter(path)
        for i in range(2):
            fw.write(i, *toy_frame(7, i, "none"))
        w.mark_complete(range(2))
    ds = D.open_dataset(path)
    assert ds.mount(1) == PAPER_MOUNT
    assert ds.mount_summary() == {
        "height_mm": [3500.0, 3500.0], "tilt_deg": 0.0, "sensors": ["kinect_v1"],
        "resolutions": [[640, 480]],
    }  # fmt: skip
