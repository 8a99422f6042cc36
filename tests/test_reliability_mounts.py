"""Mounts that do not fit their camera, "no reading" depth, odd recording keys, misleading
calibration refusals: each made for real (mount files on disk, `topseg driver`, `worker`,
`segment` and `calibrate` as processes, Zenoh on loopback) and checked against what
docs/reliability.md says."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from netutil import Services, free_port, wait_for
from PIL import Image
from test_calibration import K as SMALL_K
from test_calibration import frames_of

from topseg.core import labels as L
from topseg.core.calibration import check_floor
from topseg.core.camera import KINECT_V1, TopViewMount, check_mount, without_no_reading
from topseg.core.errors import ConfigError
from topseg.core.formats import recording, wire
from topseg.core.formats.mount_file import read_mount_file
from topseg.core.synth.procedural import procedural_frame

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "recordings" / "demo.mcap"
SMALL = KINECT_V1.scaled_to(160, 120)


def topseg(*args, timeout=300):
    return subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def demo_frames(n: int) -> list[wire.DepthFrame]:
    """The first `n` depth frames of the bundled recording (640x480, their mount 3.5 m)."""
    out = []
    for msg in recording.read_messages(DEMO):
        if msg.key.endswith("/depth"):
            out.append(wire.decode_depth(msg.data))
            if len(out) == n:
                break
    return out


def demo_truth(n: int) -> dict[int, np.ndarray]:
    """{seq: truth labels} of the first `n` truth frames of the bundled recording."""
    out = {}
    for msg in recording.read_messages(DEMO):
        if msg.key.endswith("/truth"):
            truth = wire.decode_labels(msg.data)
            out[truth.seq] = truth.labels
            if len(out) == n:
                break
    return out


def person(labels: np.ndarray) -> np.ndarray:
    """Pixels of any body part."""
    return (labels >= L.HEAD) & (labels <= L.LEGS)


def write_mount(path: Path, mount: TopViewMount | dict) -> Path:
    """A mount file as `topseg calibrate` writes it (its `mount` is what is read)."""
    d = mount.to_dict() if isinstance(mount, TopViewMount) else mount
    path.write_text(json.dumps({"topseg_mount": 1, "mount": d}))
    return path


def sane_numbers(line: str) -> bool:
    """No number in `line` written with more than 12 digits (a `%.1f` of 1e300 has 301)."""
    return all(len(n) <= 12 for n in re.findall(r"\d+", line))


# ------------------------------------------------- one validation of a mount (file and wire)


def bad_mounts() -> dict[str, dict]:
    """Mount maps no camera can have, by what is wrong."""
    good = TopViewMount(SMALL, 3120.0, 2.0, -1.0).to_dict()
    k = good["intrinsics"]
    return {
        "height 50 mm": {**good, "height_mm": 50.0},
        "height 60 m": {**good, "height_mm": 60_000.0},
        "height 1e9 mm": {**good, "height_mm": 1e9},
        "cx 1e12": {**good, "intrinsics": {**k, "cx": 1e12}},
        "fx 1e300": {**good, "intrinsics": {**k, "fx": 1e300}},
        "fx 1.0": {**good, "intrinsics": {**k, "fx": 1.0}},
        "noise_scale 100": {**good, "noise_scale": 100.0},
    }


WHAT = {
    "height 50 mm": "height_mm",
    "height 60 m": "height_mm",
    "height 1e9 mm": "height_mm",
    "cx 1e12": "cx",
    "fx 1e300": "fx",
    "fx 1.0": "fx",
    "noise_scale 100": "noise_scale",
}


@pytest.mark.parametrize("what", list(WHAT))
def test_a_mount_no_camera_can_have_is_refused_alike_from_a_file_and_from_the_wire(tmp_path, what):
    d = bad_mounts()[what]
    path = write_mount(tmp_path / "m.json", d)
    with pytest.raises(ConfigError) as exc:
        read_mount_file(path)
    line = str(exc.value)
    assert "\n" not in line and str(path) in line and WHAT[what] in line, line
    assert sane_numbers(line), line
    depth = wire.DepthFrame(np.zeros(SMALL.shape, np.uint16), SMALL)
    msg = json.loads(json.dumps(d))
    raw = msgpack.unpackb(wire.encode_depth(depth))
    raw["mount"] = msg
    with pytest.raises(wire.WireError, match=WHAT[what]):
        wire.decode_depth(msgpack.packb(raw))


def test_good_mounts_pass_the_one_validation():
    for mount in (
        TopViewMount(SMALL, 3120.0, 2.0, -1.0),
        TopViewMount(KINECT_V1, 2400.0, 10.0, -10.0, "kinect_v1", 0.35),
        TopViewMount(KINECT_V1.scaled_to(64, 48), 4500.0),
    ):
        assert check_mount(mount) is mount


# ------------------------------------------------------- a mount that disagrees with the frames


def test_check_floor_on_the_demo_frames():
    frame = demo_frames(1)[0]
    right = frame.mount
    assert check_floor(frame.depth, right).agrees is True
    low = check_floor(frame.depth, replace(right, height_mm=2500.0))
    assert low.agrees is False and low.below_share > 0.9
    assert re.search(r"2\.50 m above the floor, the depth about 3\.[45]\d m", low.reason())
    high = check_floor(frame.depth, replace(right, height_mm=4500.0))
    assert high.agrees is False and "nothing in view comes within" in high.reason()
    nothing = np.full(right.intrinsics.shape, 65535, np.uint16)
    assert check_floor(nothing, right).agrees is None  # no reading: no verdict


@pytest.mark.slow
def test_segment_refuses_a_mount_file_at_the_wrong_height_for_the_demo_recording(tmp_path):
    mount = write_mount(tmp_path / "low.json", replace(demo_frames(1)[0].mount, height_mm=2500.0))
    out = tmp_path / "out"
    r = topseg("segment", DEMO, "--mount", mount, "--out", out, "--crf", "none")
    assert r.returncode == 2, r.stderr
    refusals = [ln for ln in r.stderr.splitlines() if "disagrees with its frames" in ln]
    assert len(refusals) == 1, r.stderr
    assert f"mount file {mount} disagrees" in refusals[0]
    assert re.search(r"2\.50 m above the floor, the depth about 3\.[45]\d m", refusals[0])
    assert "300 frames not labelled: their mount disagrees" in r.stderr
    assert "Traceback" not in r.stderr
    assert not list(out.glob("*.png"))  # nothing labelled through a floor that is not there


@pytest.mark.slow
def test_segment_refuses_a_recordings_own_wrong_mount_unless_told_to_estimate(tmp_path):
    frames = demo_frames(2)
    rec = tmp_path / "wrong.mcap"
    with recording.RecordingWriter(rec) as w:
        for f in frames:  # recorded by a driver started with a wrong mount file
            low = replace(f.mount, height_mm=2500.0)
            w.write(wire.depth_key(), wire.encode_depth(replace(f, mount=low)))
    r = topseg("segment", rec, "--out", tmp_path / "a", "--crf", "none")
    assert r.returncode == 2, r.stderr
    assert "the recording's mount disagrees with its frames" in r.stderr
    assert "--estimate-mount" in r.stderr
    assert not list((tmp_path / "a").glob("*.png"))
    r = topseg("segment", rec, "--out", tmp_path / "b", "--crf", "none", "--estimate-mount")
    assert r.returncode == 0, r.stderr
    height = re.search(r"estimated mount: height (\d+\.\d+) m", r.stdout)
    assert height and abs(float(height.group(1)) - 3.5) < 0.06, r.stdout
    labels = np.asarray(Image.open(tmp_path / "b" / "wrong_000000_labels.png"))
    assert np.isin(labels, [L.HEAD, L.BODY]).sum() > 1000  # people, not floor


# ---------------------------------------------------------------- depth 65535: no reading


def test_65535_reads_as_no_depth_not_as_floor():
    from topseg.core.segmenter import Segmenter

    frame = demo_frames(1)[0]
    seg = Segmenter.from_file(None, crf="none")
    blank = np.full(frame.depth.shape, 65535, np.uint16)
    labels = seg.label(blank, frame.intrinsics, "blank", frame.mount).labels
    assert np.all(labels == L.NO_DEPTH)  # was: all background, "empty floor"
    band = frame.depth.copy()
    band[:, :100] = 65535
    labels = seg.label(band, frame.intrinsics, "band", frame.mount).labels
    assert np.all(labels[:, :100] == L.NO_DEPTH)
    assert without_no_reading(frame.depth) is frame.depth  # nothing to change: no copy


@pytest.mark.slow
def test_worker_refuses_a_wire_mount_that_disagrees_estimates_and_reads_65535_as_no_depth():
    """A real worker fed the demo's frames carrying a mount 1 m too low (a driver started
    with a wrong mount file): it says so, estimates the mount from the frames and labels
    people; then a frame of 65535 only is labelled no-depth, not floor."""
    frames = demo_frames(4)
    port, cell = free_port(), "mnt1"
    services = Services()
    try:
        tap = services.tap(port, cell)
        labels: list[wire.LabelFrame] = []
        tap.session.declare_subscriber(
            wire.labels_key(cell, "cam0"),
            lambda s: labels.append(wire.decode_labels(s.payload.to_bytes())),
        )
        worker = services(
            "worker", "--zenoh-port", port, "--cameras", f"{cell}/cam0", "--lossless",
            "--crf", "none",
        )  # fmt: skip
        worker.wait_line("worker ready", 180)
        pub = tap.session.declare_publisher(
            wire.depth_key(cell, "cam0"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        wait_for(lambda: pub.matching_status.matching, 60, "the worker's subscriber")
        for i, f in enumerate(frames):
            low = replace(f.mount, height_mm=2500.0)
            pub.put(wire.encode_depth(replace(f, seq=i, frame_id="cam0", mount=low)))
        wait_for(lambda: len(labels) >= len(frames), 120, "labels of the demo frames")
        blank = np.full(frames[0].depth.shape, 65535, np.uint16)
        low = replace(frames[0].mount, height_mm=2500.0)
        pub.put(wire.encode_depth(replace(frames[0], depth=blank, seq=9, mount=low)))
        wait_for(lambda: any(lab.seq == 9 for lab in labels), 60, "labels of the blank frame")
        wait_for(lambda: any(s.get("mount") for s in tap.stats), 10, "stats with the mount")
        assert worker.stop() == 0, worker.err
    finally:
        services.close()
    err = worker.err
    assert err.count("the frames' mount disagrees with their depth") == 1, err
    assert re.search(r"2\.50 m above the floor, the depth about 3\.[45]\d m", err)
    mount = [s["mount"] for s in tap.stats if s.get("mount")][-1]
    assert mount["source"] == "estimated" and abs(mount["height_mm"] - 3500.0) < 60, mount
    truth = demo_truth(len(frames))
    found = sum(
        np.sum(person(lab.labels) & person(truth[lab.seq])) for lab in labels if lab.seq < 9
    )
    share = found / sum(np.sum(person(t)) for t in truth.values())
    assert share > 0.7, share  # labelled through the estimate: people found, not erased
    blank_labels = next(lab for lab in labels if lab.seq == 9).labels
    assert np.all(blank_labels == L.NO_DEPTH)


# ----------------------------------------------------------- the driver checks before Zenoh


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory):
    """Six 160x120 frames of a camera 3.12 m up, tilted as the good mount says."""
    mount = TopViewMount(SMALL, 3120.0, 2.0, -1.0)
    rng = np.random.default_rng(3)
    path = tmp_path_factory.mktemp("rec") / "small.mcap"
    with recording.RecordingWriter(path) as w:
        for i in range(6):
            depth, _ = procedural_frame(rng, mount)
            t = 1_000_000_000 + 20_000_000 * i
            w.write(wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, SMALL, i, t)), t)
    return path, mount


@pytest.mark.slow
def test_the_driver_refuses_a_mount_that_does_not_fit_before_it_joins_zenoh(
    small_recording, tmp_path
):
    rec, mount = small_recording
    files = {what: write_mount(tmp_path / f"{i}.json", d) for i, (what, d) in enumerate(
        bad_mounts().items())}  # fmt: skip
    files["for 640x480 frames"] = write_mount(
        tmp_path / "size.json", replace(mount, intrinsics=KINECT_V1)
    )
    files["hung 1 m too low"] = write_mount(tmp_path / "low.json", replace(mount, height_mm=2100.0))
    port, cell = free_port(), "mnt2"
    services = Services()
    try:
        tokens: list[str] = []
        tap = services.tap(port, cell)
        tap.session.liveliness().declare_subscriber(
            f"topseg/{cell}/**", lambda s: tokens.append(str(s.key_expr)), history=True
        )
        for what, path in files.items():
            driver = services(
                "driver", "--zenoh-port", port, "--cell", cell, "--camera", "bad",
                "--source", f"replay:{rec}", "--loop", "--mount", path,
            )  # fmt: skip
            assert driver.proc.wait(60) == 2, (what, driver.err)
            driver.kill()
            last = driver.err.strip().splitlines()[-1]
            assert last.startswith("topseg driver: error: mount file " + str(path)), (what, last)
            assert sane_numbers(last) and "Traceback" not in driver.err, (what, driver.err)
            assert "publishing" not in driver.err, (what, driver.err)
            if what == "for 640x480 frames":
                assert "is for 640x480 frames but the source sends 160x120" in last
            if what == "hung 1 m too low":
                assert "disagrees with the frames of" in last and "2.10 m above" in last
        # a driver whose mount fits: its token is the later message the test waits for
        good = services(
            "driver", "--zenoh-port", port, "--cell", cell, "--camera", "good",
            "--source", f"replay:{rec}", "--loop", "--mount", write_mount(tmp_path / "ok.json", mount),
        )  # fmt: skip
        wait_for(lambda: any("/good/" in t for t in tokens), 60, "the good driver's token")
        assert good.stop() == 0, good.err
    finally:
        services.close()
    assert not [t for t in tokens if "/bad/" in t], tokens  # no bad driver ever joined


def test_segment_refuses_a_mount_file_with_focal_length_1(tmp_path, small_recording):
    rec, _ = small_recording
    path = write_mount(tmp_path / "fx.json", bad_mounts()["fx 1.0"])
    r = topseg("segment", rec, "--mount", path, "--out", tmp_path / "out")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "fx 1 px" in lines[0] and str(path) in lines[0], r.stderr


# -------------------------------------------------------------- recording keys: one bad channel


@pytest.mark.slow
def test_one_bad_channel_is_skipped_with_a_line_and_the_others_are_labelled(tmp_path):
    mount = TopViewMount(SMALL, 3120.0, 2.0, -1.0)
    rng = np.random.default_rng(4)
    rec = tmp_path / "keys.mcap"
    keys = [
        wire.depth_key("cell", "c1"),
        "topseg/cell/" + "x" * 300 + "/depth",  # a 300-character camera name
        "topseg/cell/\x1b[2Jcam\x1b[31m/depth",  # escape codes in the key
        wire.depth_key("cell", "c2"),
    ]
    with recording.RecordingWriter(rec) as w:
        for seq in range(2):
            for key in keys:
                depth, _ = procedural_frame(rng, mount)
                w.write(key, wire.encode_depth(wire.DepthFrame(depth, SMALL, seq, mount=mount)))
    out = tmp_path / "out"
    r = topseg("segment", rec, "--out", out, "--crf", "none")
    assert r.returncode == 2, r.stderr
    assert "\x1b" not in r.stderr + r.stdout  # escaped: nothing reaches the terminal raw
    skipped = [ln for ln in r.stderr.splitlines() if "skipped a channel of" in ln]
    assert len(skipped) == 2, r.stderr
    assert all(len(ln) < 400 for ln in skipped), skipped
    assert "2 recording channels not read" in r.stderr and "cannot write" not in r.stderr
    names = sorted(p.name for p in out.glob("*_labels.png"))
    assert names == [f"keys_cell-{c}_00000{s}_labels.png" for c in ("c1", "c2") for s in (0, 1)]


def test_a_replay_of_a_recording_whose_first_channel_is_bad_reads_the_next(tmp_path, caplog):
    from topseg.drivers.replay import RecordingFrames

    rec = tmp_path / "first.mcap"
    depth = np.full(SMALL.shape, 3000, np.uint16)
    with recording.RecordingWriter(rec) as w:
        w.write(
            "topseg/cell/\x1b[31mcam/depth", wire.encode_depth(wire.DepthFrame(depth, SMALL, 0))
        )
        w.write(wire.depth_key("cell", "ok"), wire.encode_depth(wire.DepthFrame(depth, SMALL, 1)))
    with caplog.at_level("INFO"):
        got = list(RecordingFrames(rec))
    assert [f.seq for f in got] == [1] and got[0].key == wire.depth_key("cell", "ok")
    assert "\x1b" not in caplog.text and "a depth channel not read" in caplog.text


# ------------------------------------------------------------------------ calibrate misleads


def table_frames(rows, cols, n=5):
    """Frames of a still camera 3 m over a 750 mm table covering rows x cols of the view."""
    table = ((slice(*rows), slice(*cols)), 750.0)
    return frames_of(TopViewMount(SMALL_K, 3000.0), n=n, cover=0.0, tables=(table,))


def png_folder(folder: Path, frames) -> Path:
    folder.mkdir()
    for i, depth in enumerate(frames):
        Image.fromarray(depth).save(folder / f"f{i:02d}.png")
    return folder


@pytest.mark.parametrize(
    ("rows", "cols", "share"), [((0, 240), (0, 290), 91), ((3, 237), (8, 312), 93)]
)
@pytest.mark.slow
def test_calibrate_over_a_table_covering_most_of_the_view_says_so(tmp_path, rows, cols, share):
    folder = png_folder(tmp_path / "cam", table_frames(rows, cols))
    r = topseg(
        "calibrate", "--source", f"replay:{folder}", "--frames", 5, "--out", tmp_path / "m.json"
    )
    assert r.returncode == 2, r.stdout  # (at 93 % the table top was taken for the floor)
    line = r.stderr.strip().splitlines()[-1]
    assert "hold the camera still" not in line, line
    assert "aim it at more floor" in line and "table" in line, line
    assert not (tmp_path / "m.json").exists()


def test_calibrate_on_frames_of_two_sizes_says_which_in_one_line(tmp_path):
    big = frames_of(TopViewMount(SMALL_K, 3000.0), n=2)
    small = frames_of(TopViewMount(KINECT_V1.scaled_to(160, 120), 3000.0), n=2)
    folder = png_folder(tmp_path / "mixed", [*big, *small])
    r = topseg(
        "calibrate", "--source", f"replay:{folder}", "--frames", 4, "--out", tmp_path / "m.json"
    )
    assert r.returncode == 2
    line = r.stderr.strip().splitlines()[-1]
    assert "Intrinsics(" not in r.stderr, r.stderr
    assert "frame 1 is 320x240, frame 3 160x120" in line, line
