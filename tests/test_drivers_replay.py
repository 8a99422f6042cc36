"""Replay of MCAP recordings, 16-bit PNG folders and fakenect dumps: content, pacing, looping."""

import time

import numpy as np
import pytest
from PIL import Image

from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.formats import wire
from topseg.core.formats.recording import RecordingWriter
from topseg.core.synth.procedural import procedural_frame
from topseg.drivers import SourceError, SourceOptions, open_source
from topseg.drivers.fakenect_dump import quantisation_step_mm, write_dump

FAST = SourceOptions(realtime=False)


SMALL = TopViewMount(KINECT_V1.scaled_to(160, 120), PAPER_MOUNT.height_mm)


def scene(rng, mount=SMALL):
    """A labelled procedural top-view frame (depth mm, labels) with some missing depth."""
    return procedural_frame(rng, mount, missing_fraction=0.01)


def record(path, frames, period_s=0.05, cell="default", camera="cam0", junk_at=None):
    t0 = 1_700_000_000_000_000_000
    with RecordingWriter(path) as w:
        for i, (depth, lab) in enumerate(frames):
            stamp = t0 + int(i * period_s * 1e9)
            if junk_at == i:
                w.write(wire.depth_key(cell, camera), b"\x93garbage", log_time_ns=stamp)
            f = wire.DepthFrame(
                depth, KINECT_V1.scaled_to(depth.shape[1], depth.shape[0]), i, stamp
            )
            w.write(wire.depth_key(cell, camera), wire.encode_depth(f), log_time_ns=stamp)
            lf = wire.LabelFrame(lab, i, stamp)
            w.write(wire.truth_key(cell, camera), wire.encode_labels(lf), log_time_ns=stamp + 1000)


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(0)
    return [scene(rng) for _ in range(5)]


def test_mcap_replay_gives_back_depth_and_truth(tmp_path, frames):
    path = tmp_path / "rec.mcap"
    record(path, frames, junk_at=2)
    with open_source(f"replay:{path}", FAST) as src:
        got = list(src.frames())
        assert src.finite and src.rejected == 1  # the garbage message was skipped and counted
    assert len(got) == len(frames)
    for i, ((depth, truth), f) in enumerate(zip(frames, got, strict=True)):
        np.testing.assert_array_equal(f.depth.depth, depth)
        np.testing.assert_array_equal(f.truth.labels, truth)
        assert f.depth.seq == f.truth.seq == i
        assert f.depth.stamp_ns == f.truth.stamp_ns  # truth carries its depth frame's stamp
        assert f.depth.intrinsics == KINECT_V1.scaled_to(160, 120)


def test_mcap_without_truth_and_picking_a_camera(tmp_path, frames):
    path = tmp_path / "two.mcap"
    with RecordingWriter(path) as w:  # two cameras in one recording, no truth
        for i, (depth, _) in enumerate(frames):
            for cam, d in (("a", depth), ("b", depth // 2)):
                f = wire.DepthFrame(d, KINECT_V1.scaled_to(160, 120), i, 1 + i)
                w.write(wire.depth_key("c", cam), wire.encode_depth(f))
    with open_source(f"replay:{path}#{wire.depth_key('c', 'b')}", FAST) as src:
        got = list(src.frames())
    assert [f.truth for f in got] == [None] * len(frames)
    np.testing.assert_array_equal(got[1].depth.depth, frames[1][0] // 2)
    with pytest.raises(SourceError, match="depth key"):
        open_source(f"replay:{path}#topseg/c/b/labels", FAST)


def test_realtime_pacing_and_as_fast_as_consumed(tmp_path, frames):
    path = tmp_path / "slow.mcap"
    record(path, frames, period_s=0.1)  # 10 fps: 0.4 s from first to last frame
    t0 = time.monotonic()
    with open_source(f"replay:{path}") as src:
        n = sum(1 for _ in src.frames())
    assert n == 5 and time.monotonic() - t0 >= 0.36
    slow = tmp_path / "veryslow.mcap"
    record(slow, frames, period_s=5.0)  # 20 s of recording ...
    t0 = time.monotonic()
    with open_source(f"replay:{slow}", FAST) as src:
        assert sum(1 for _ in src.frames()) == 5
    assert time.monotonic() - t0 < 10.0  # ... handed over without waiting


def test_loop_repeats_and_numbers_on(tmp_path, frames):
    path = tmp_path / "rec.mcap"
    record(path, frames, period_s=0.02)
    with open_source(f"replay:{path}", SourceOptions(loop=True)) as src:
        assert not src.finite
        it = src.frames()
        got = [next(it) for _ in range(2 * len(frames) + 1)]
        assert src.nominal_fps == pytest.approx(50.0)
    assert [f.depth.seq for f in got] == list(range(len(got)))
    for i, f in enumerate(got):
        np.testing.assert_array_equal(f.depth.depth, frames[i % len(frames)][0])
    stamps = [f.depth.stamp_ns for f in got]
    assert np.all(np.diff(stamps) > 0)
    # the seam between passes keeps a frame period
    assert stamps[len(frames)] - stamps[len(frames) - 1] >= 0.015e9


def test_png_folder(tmp_path, frames):
    folder = tmp_path / "pngs"
    folder.mkdir()
    for i, (depth, _) in enumerate(frames):
        Image.fromarray(depth).save(folder / f"frame_{i:04d}.png")
    (folder / "notes.txt").write_text("not a frame")
    t0 = time.monotonic()
    with open_source(f"replay:{folder}", SourceOptions(fps=25.0)) as src:
        got = list(src.frames())
    assert time.monotonic() - t0 >= 0.15  # 4 gaps of 40 ms
    assert len(got) == 5
    for (depth, _), f in zip(frames, got, strict=True):
        np.testing.assert_array_equal(f.depth.depth, depth)
        assert f.truth is None
    assert got[0].depth.intrinsics == KINECT_V1.scaled_to(160, 120)


def test_png_folder_refuses_8_bit(tmp_path):
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "a.png")
    with open_source(f"replay:{tmp_path}", FAST) as src, pytest.raises(SourceError, match="16-bit"):
        list(src.frames())


def test_fakenect_dump_replay(tmp_path):
    rng = np.random.default_rng(3)
    originals = [scene(rng, PAPER_MOUNT)[0] for _ in range(3)]
    write_dump(tmp_path / "dump", originals)
    with open_source(f"replay:{tmp_path / 'dump'}", FAST) as src:
        got = [f.depth.depth for f in src.frames()]
    assert len(got) == 3
    for orig, back in zip(originals, got, strict=True):
        err = np.abs(back.astype(int) - orig)
        assert np.all(err <= quantisation_step_mm(orig) // 2 + 1)
        np.testing.assert_array_equal(back == 0, orig == 0)


def test_what_is_not_replayable(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match=r"no \.png"):
        open_source(f"replay:{tmp_path / 'empty'}")
    (tmp_path / "x.mcap").write_bytes(b"hello world")
    with pytest.raises(SourceError, match="not an MCAP"):
        open_source(f"replay:{tmp_path / 'x.mcap'}")
    with RecordingWriter(tmp_path / "nodepth.mcap") as w:
        w.write(wire.stats_key(), b"x")
    with (
        open_source(f"replay:{tmp_path / 'nodepth.mcap'}") as src,
        pytest.raises(SourceError, match="no depth"),
    ):
        list(src.frames())


def test_input_frames_names_what_segment_writes(tmp_path, frames):
    """The reader `topseg segment` and the replay share: PNG files, folders and recordings."""
    from topseg.drivers.replay import input_frames, read_depth_png

    folder = tmp_path / "pngs"
    folder.mkdir()
    for i, (depth, _) in enumerate(frames[:2]):
        Image.fromarray(depth).save(folder / f"f{i}.png")
    got = list(input_frames(folder))
    assert [f.name for f in got] == ["f0", "f1"]
    assert got[0].intrinsics is None  # a PNG does not say its camera
    np.testing.assert_array_equal(got[1].depth, frames[1][0])
    np.testing.assert_array_equal(read_depth_png(folder / "f0.png"), frames[0][0])

    rec = tmp_path / "rec.mcap"
    record(rec, frames, junk_at=1)
    readers = []
    got = list(input_frames(rec, on_recording=readers.append))
    assert [f.name for f in got] == [f"rec_{i:06d}" for i in range(len(frames))]
    assert got[0].intrinsics == KINECT_V1.scaled_to(160, 120)
    np.testing.assert_array_equal(got[2].truth, frames[2][1])
    assert readers[0].rejected == 1 and readers[0].depth_key == wire.depth_key()

    (tmp_path / "empty").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    for path, message in [
        (tmp_path / "empty", r"no \.png"),
        (tmp_path / "absent.png", "not a readable PNG"),
        (tmp_path / "absent.mcap", "cannot read recording"),
        (tmp_path / "nowhere", "no such file"),
        (tmp_path / "notes.txt", "expected a .png"),
    ]:
        with pytest.raises(TopsegError, match=message):
            list(input_frames(path))


def test_recorded_mounts_reach_the_frames_of_replay_and_segment(tmp_path):
    """A recording made with a mount (v2 messages) hands it to every reader of its frames."""
    from topseg.drivers.replay import input_frames

    k = SMALL.intrinsics
    mounts = [TopViewMount(k, 3000.0 + 100 * i, 2.0, -1.0, "kinect_v2") for i in range(3)]
    rec = tmp_path / "mounted.mcap"
    with RecordingWriter(rec) as w:
        for i, m in enumerate(mounts):
            depth = np.full(k.shape, 2500 + i, np.uint16)
            frame = wire.DepthFrame(depth, k, i, 10**9 + i, "cam0", m if i != 1 else None)
            w.write(wire.depth_key(), wire.encode_depth(frame), 10**9 + i)
    expected = [mounts[0], None, mounts[2]]
    assert [f.mount for f in input_frames(rec)] == expected  # `topseg segment`'s reader
    with open_source(f"replay:{rec}", FAST) as src:
        got = [f.depth.mount for f in src.frames()]
        assert src.info()["mount"] == mounts[2].to_dict()
    assert got == expected


def test_a_truth_written_before_the_first_depth_frame_is_paired(tmp_path, frames):
    """Zenoh does not order the depth and truth keys: a recording may open with a truth,
    even another camera's; each frame still gets its own camera's truth."""
    from topseg.drivers.replay import RecordingFrames

    path = tmp_path / "truth-first.mcap"
    t0 = 1_700_000_000_000_000_000
    with RecordingWriter(path) as w:
        other = wire.LabelFrame(np.zeros_like(frames[0][1]), 0, t0)
        w.write(wire.truth_key("default", "cam9"), wire.encode_labels(other), log_time_ns=t0)
        for i, (depth, lab) in enumerate(frames):
            stamp = t0 + i * 50_000_000
            lf = wire.LabelFrame(lab, i, stamp)
            w.write(wire.truth_key("default", "cam0"), wire.encode_labels(lf), log_time_ns=stamp)
            f = wire.DepthFrame(depth, KINECT_V1.scaled_to(160, 120), i, stamp)
            w.write(wire.depth_key("default", "cam0"), wire.encode_depth(f), log_time_ns=stamp + 1)
    got = list(RecordingFrames(path))
    assert [g.seq for g in got] == list(range(len(frames)))
    for g, (_, lab) in zip(got, frames, strict=True):
        np.testing.assert_array_equal(g.truth, lab)


def test_a_truth_that_comes_after_later_depth_frames_is_paired(tmp_path, frames):
    """On a loaded machine a recorder can get a frame's truth after the next depth frames:
    each frame is held until its truth comes, up to `MAX_FRAMES_AWAITING_TRUTH` frames, and
    the frames still come in depth order. A truth later than that is not paired."""
    from topseg.drivers.replay import MAX_FRAMES_AWAITING_TRUTH, RecordingFrames

    path = tmp_path / "truth-late.mcap"
    t0 = 1_700_000_000_000_000_000
    late = {1: 3, 2: 1, 4: MAX_FRAMES_AWAITING_TRUTH + 1}  # seq -> depth frames it trails by
    k = KINECT_V1.scaled_to(160, 120)
    log = []  # (log time, key, payload)
    for i, (depth, lab) in enumerate(frames):
        stamp = t0 + i * 50_000_000
        log.append(
            (stamp, wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, k, i, stamp)))
        )
        at = stamp + late.get(i, 0) * 50_000_000 + 1
        log.append((at, wire.truth_key(), wire.encode_labels(wire.LabelFrame(lab, i, stamp))))
    for j in range(len(frames), len(frames) + MAX_FRAMES_AWAITING_TRUTH + 2):  # later frames
        depth = np.full(k.shape, 2000, np.uint16)
        stamp = t0 + j * 50_000_000
        log.append(
            (stamp, wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, k, j, stamp)))
        )
    with RecordingWriter(path) as w:
        for at, key, data in sorted(log, key=lambda x: x[0]):
            w.write(key, data, log_time_ns=at)
    got = list(RecordingFrames(path))
    assert [g.seq for g in got] == list(range(len(frames) + MAX_FRAMES_AWAITING_TRUTH + 2))
    for g, (_, lab) in zip(got, frames, strict=False):
        if g.seq == 4:
            assert g.truth is None  # too late
        else:
            np.testing.assert_array_equal(g.truth, lab)
    assert all(g.truth is None for g in got[len(frames) :])
