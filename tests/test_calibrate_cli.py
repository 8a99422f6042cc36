"""`topseg calibrate` as an operator runs it: a replayed camera in, figures, mount file, picture."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image
from test_calibration import K, frames_of

from topseg.core.camera import TopViewMount
from topseg.core.formats import recording, wire
from topseg.core.formats.mount_file import read_mount_document
from topseg.core.sensors import get_sensor


def calibrate(*args):
    return subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "calibrate", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def figure(stdout: str, name: str) -> float:
    """The number on the printed line that starts with `name`."""
    match = re.search(rf"^{name}\s+([-+]?\d+(?:\.\d+)?)", stdout, re.MULTILINE)
    assert match, f"no {name!r} line in:\n{stdout}"
    return float(match.group(1))


@pytest.fixture(scope="module")
def png_folder(tmp_path_factory):
    """Six 320x240 depth PNGs (Kinect v1 optics scaled) of a tilted floor with boxes."""
    folder = tmp_path_factory.mktemp("cam")
    truth = TopViewMount(K, 3250.0, 6.0, -4.0)
    for i, depth in enumerate(frames_of(truth, n=6, cover=0.35)):
        Image.fromarray(depth).save(folder / f"f{i:02d}.png")
    return folder


@pytest.mark.slow
def test_calibrate_a_replayed_camera(png_folder, tmp_path):
    out = tmp_path / "etc" / "topseg" / "cell1.json"  # folders made as needed
    r = calibrate("--source", f"replay:{png_folder}", "--frames", 5, "--out", out)
    assert r.returncode == 0, r.stderr
    assert abs(figure(r.stdout, "height") - 3250.0) < 10
    assert abs(figure(r.stdout, "pitch") - 6.0) < 0.1
    assert abs(figure(r.stdout, "roll") + 4.0) < 0.1
    assert 5 < figure(r.stdout, "residual") < 25
    assert 40 < figure(r.stdout, "floor") < 70
    assert "frames     5 of 5" in r.stdout
    assert "320x240" in r.stdout and "sensor     unknown" in r.stdout

    doc = read_mount_document(out)
    mount = doc["mount"]
    assert mount.intrinsics == K
    assert abs(mount.height_mm - 3250.0) < 10
    assert doc["fit"]["frames_used"] == 5
    picture = out.with_suffix(".png")
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(picture) as img:
        assert img.width > img.height > 200  # three panels side by side


@pytest.mark.slow
def test_calibrate_a_recording_of_another_sensor(tmp_path):
    oak = get_sensor("oak_d")
    truth = TopViewMount(oak.intrinsics, 2700.0, -3.0, 8.0, "oak_d")
    rec = tmp_path / "oak.mcap"
    w = recording.RecordingWriter(rec)
    for i, depth in enumerate(frames_of(truth, n=4, cover=0.3, sigma_mm_per_m2=3.0)):
        w.write(wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, oak.intrinsics, seq=i)))
    w.close()
    out, pic = tmp_path / "oak-mount.json", tmp_path / "pictures" / "oak.png"
    pic.parent.mkdir()
    r = calibrate("--source", f"replay:{rec}", "--sensor", "oak_d", "--out", out, "--picture", pic)
    assert r.returncode == 0, r.stderr
    assert "sensor     oak_d" in r.stdout and "640x400" in r.stdout
    assert "smoothing  " in r.stdout  # whether its frames are smoothed before the forest
    assert "frames     4 of 4" in r.stdout  # the recording ended before the default 60
    mount = read_mount_document(out)["mount"]
    assert mount.sensor == "oak_d" and mount.intrinsics == oak.intrinsics
    assert abs(mount.height_mm - 2700.0) < 10
    assert abs(mount.pitch_deg + 3.0) < 0.15 and abs(mount.roll_deg - 8.0) < 0.15
    assert pic.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_png_frames_take_the_named_sensors_optics(tmp_path):
    """A PNG says no optics: `--sensor` of the frames' size gives them, so a D435's frames
    are not back-projected with a Kinect v1's focal length (the tilt would come out wrong)."""
    d435 = get_sensor("realsense_d435")
    truth = TopViewMount(d435.intrinsics, 3000.0, 4.0, -3.0, "realsense_d435")
    folder = tmp_path / "d435"
    folder.mkdir()
    for i, depth in enumerate(frames_of(truth, n=4, cover=0.3)):
        Image.fromarray(depth).save(folder / f"f{i:02d}.png")
    out = tmp_path / "d435.json"
    r = calibrate("--source", f"replay:{folder}", "--sensor", "realsense_d435", "--out", out)
    assert r.returncode == 0, r.stderr
    assert "PNG frames say no optics: using the realsense_d435's (fx 385.0)" in r.stdout
    assert "thinning   on: 1 px" in r.stdout
    mount = read_mount_document(out)["mount"]
    assert mount.intrinsics == d435.intrinsics and mount.edge_thinning
    assert abs(mount.pitch_deg - 4.0) < 0.15 and abs(mount.roll_deg + 3.0) < 0.15
    # a camera whose own filters clean its edges: the mount file says so
    clean = tmp_path / "d435-clean.json"
    r = calibrate(
        "--source", f"replay:{folder}", "--sensor", "realsense_d435", "--no-edge-thinning",
        "--out", clean,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "thinning   off: the mount says its edges are not fattened" in r.stdout
    assert json.loads(clean.read_text())["mount"]["edge_thinning"] is False
    assert read_mount_document(clean)["mount"] == replace(mount, edge_thinning=False)
    # without --sensor: the supported sensor of their size, as `topseg segment` reads them
    r = calibrate("--source", f"replay:{folder}", "--out", out)
    assert r.returncode == 0, r.stderr
    assert "using the kinect_v1's (fx 570.3)" in r.stdout and "sensor     kinect_v1" in r.stdout
    assert read_mount_document(out)["mount"].sensor == "kinect_v1"
    # a sensor of another size is refused in one line, as segment refuses it, not guessed
    line = error_line(calibrate("--source", f"replay:{folder}", "--sensor", "oak_d", "--out", out))
    assert "640x480 frames that say no intrinsics, but the oak_d's are 640x400" in line
    # --sensor unknown keeps the guess (320x240 frames of no supported size get it anyway)
    r = calibrate("--source", f"replay:{folder}", "--sensor", "unknown", "--out", out)
    assert r.returncode == 0, r.stderr
    assert "assuming a Kinect v1's scaled to 640x480" in r.stdout


def error_line(r) -> str:
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = [line for line in r.stderr.splitlines() if line.startswith("topseg calibrate: error")]
    assert len(lines) == 1, r.stderr
    return lines[0]


@pytest.mark.slow
def test_refusals_are_one_line(png_folder, tmp_path):
    empty = tmp_path / "dark"
    empty.mkdir()
    for i in range(3):
        Image.fromarray(np.zeros(K.shape, np.uint16)).save(empty / f"{i}.png")
    line = error_line(calibrate("--source", f"replay:{empty}", "--out", tmp_path / "m.json"))
    assert "no depth" in line

    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    line = error_line(
        calibrate("--source", f"replay:{png_folder}", "--out", blocked / "sub" / "m.json")
    )
    assert "cannot create" in line

    line = error_line(
        calibrate(
            "--source",
            f"replay:{png_folder}",
            "--sensor",
            "kinect_v9",
            "--out",
            tmp_path / "m.json",
        )
    )
    assert "unknown sensor 'kinect_v9'" in line
    assert not (tmp_path / "m.json").exists()


def test_edge_thinning_is_the_flag_else_the_frames_mount_else_on():
    from topseg.core.calibration import MountEstimate
    from topseg.services.live.calibrate import with_edge_thinning

    d435 = get_sensor("realsense_d435")
    fitted = TopViewMount(d435.intrinsics, 3000.0, sensor="realsense_d435")
    est = MountEstimate(fitted, 9.0, 0.8, 10, 10, 1.0, 0.1, "2026-11-28T00:00:00Z")
    recorded = replace(fitted, height_mm=3100.0, edge_thinning=False)
    assert with_edge_thinning(est, None, None).mount.edge_thinning is True
    assert with_edge_thinning(est, None, recorded).mount.edge_thinning is False
    assert with_edge_thinning(est, True, recorded).mount.edge_thinning is True
    assert with_edge_thinning(est, False, None).mount == replace(fitted, edge_thinning=False)


def test_the_calibration_bench_counts_robots_and_objects_as_covering_the_floor():
    from topseg.core import labels
    from topseg.services.batch.bench.calibrate import floor_cover

    mount = TopViewMount(K, 3000.0)
    depth = np.full(K.shape, 3000, np.uint16)  # a level camera 3 m above the floor
    lab = np.zeros(K.shape, np.uint8)
    half = K.width // 2
    depth[:, :half], lab[:, :half] = 2000, labels.ROBOT  # a robot 1 m tall on half of it
    assert floor_cover(depth, lab, mount) == pytest.approx(0.5)
    lab[:, :half] = labels.OBJECT
    assert floor_cover(depth, lab, mount) == pytest.approx(0.5)
