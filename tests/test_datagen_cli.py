"""`topseg datagen` as a subprocess: SIGKILL and resume, bad places, a full disk, preview."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from datagen_toy import toy_frame

from topseg.core import labels as label_table
from topseg.core.formats import dataset as D
from topseg.services.batch.datagen import preview as datagen_preview

TOPSEG = str(Path(sys.executable).with_name("topseg"))
TESTS = str(Path(__file__).parent)


def env(**extra) -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = TESTS + os.pathsep + e.get("PYTHONPATH", "")
    e.update(extra)
    return e


def datagen_args(out, frames, generator="datagen_toy:slow_source", *more) -> list[str]:
    return [TOPSEG, "-q", "datagen", "--generator", generator, "--frames", str(frames), "--out", str(out),
            "--seed", "11", "--noise", "gaussian:10", "--workers", "2", "--chunk", "2", *more]  # fmt: skip


def n_complete(path: Path) -> int:
    try:
        return len(D.open_dataset(path))
    except D.DatasetError:
        return 0


def assert_frames_whole(path: Path, expect_all: int | None = None) -> int:
    ds = D.open_dataset(path)
    if expect_all is not None:
        assert ds.indices.tolist() == list(range(expect_all))
    for k, i in enumerate(ds.indices):
        depth, lab, scene = toy_frame(11, int(i), "gaussian:10")
        np.testing.assert_array_equal(ds.depth[k], depth)
        np.testing.assert_array_equal(ds.labels[k], lab)
        assert ds.scene(k) == scene
    return len(ds)


def test_a_killed_run_resumes_to_the_same_frames(tmp_path):
    out, frames = tmp_path / "ds.zarr", 40
    proc = subprocess.Popen(
        datagen_args(out, frames), env=env(TOY_FRAME_S="0.1"), start_new_session=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while n_complete(out) < 6 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)  # the client, mid-run: no handler, no cleanup
        proc.wait(30)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # and whatever of its workers is left
    assert proc.returncode == -signal.SIGKILL
    had = assert_frames_whole(out)
    assert 6 <= had < frames
    rerun = subprocess.run(
        datagen_args(out, frames), env=env(TOY_FRAME_S="0"), capture_output=True, text=True
    )
    assert rerun.returncode == 0, rerun.stderr
    assert f"({had} were already complete)" in rerun.stdout
    assert_frames_whole(out, expect_all=frames)
    again = subprocess.run(datagen_args(out, frames), env=env(), capture_output=True, text=True)
    assert again.returncode == 0 and "already complete" in again.stdout


def one_error_line(result: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("topseg datagen: error: ")
    return lines[0]


@pytest.mark.slow
def test_out_in_a_missing_folder_creates_it(tmp_path):
    out = tmp_path / "no" / "such" / "ds.zarr"
    done = subprocess.run(datagen_args(out, 4), env=env(), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert_frames_whole(out, expect_all=4)


@pytest.mark.slow
def test_a_bad_path_is_one_clear_line(tmp_path):
    (tmp_path / "f").write_text("x")
    line = one_error_line(
        subprocess.run(
            datagen_args(tmp_path / "f" / "sub" / "ds.zarr", 4),
            env=env(),
            capture_output=True,
            text=True,
        )
    )
    assert "cannot create the folder" in line and str(tmp_path / "f" / "sub") in line
    line = one_error_line(
        subprocess.run(datagen_args(tmp_path / "f", 4), env=env(), capture_output=True, text=True)
    )
    assert "not a directory" in line
    line = one_error_line(
        subprocess.run(
            datagen_args(tmp_path / "d.zarr", 4, "nope:missing"),
            env=env(),
            capture_output=True,
            text=True,
        )
    )
    assert "cannot load generator" in line
    line = one_error_line(
        subprocess.run(datagen_args(tmp_path / "d.zarr", 4, "synthesis", "--noise", "loud"), env=env(),
                       capture_output=True, text=True)
    )  # fmt: skip
    assert "unknown noise" in line


def in_namespace(script: str) -> list[str]:
    """`sh -c script` in a new user + mount namespace (mounts without root), or skip."""
    if shutil.which("unshare") is None:
        pytest.skip("needs unshare(1)")
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"user namespaces unavailable: {probe.stderr.decode().strip()}")
    return ["unshare", "-rm", "sh", "-c", script]


def test_a_read_only_place_is_one_clear_line(tmp_path):
    mnt = tmp_path / "ro"
    mnt.mkdir()
    args = " ".join(datagen_args(mnt / "ds.zarr", 4))
    cmd = in_namespace(f"mount -t tmpfs -o ro,size=1m none {mnt} && exec {args}")
    line = one_error_line(subprocess.run(cmd, env=env(), capture_output=True, text=True))
    assert "read-only file system" in line and str(mnt) in line


@pytest.mark.slow
def test_a_full_disk_stops_cleanly_and_keeps_complete_frames(tmp_path):
    mnt = tmp_path / "small"
    mnt.mkdir()
    out = mnt / "ds.zarr"
    check = tmp_path / "check.py"
    check.write_text(
        "import sys\n"
        f"sys.path.insert(0, {TESTS!r})\n"
        "from test_datagen_cli import assert_frames_whole\n"
        f"print('complete', assert_frames_whole(__import__('pathlib').Path({str(out)!r})))\n"
    )
    args = " ".join(datagen_args(out, 40, "datagen_toy:toy_source"))
    cmd = in_namespace(
        f"mount -t tmpfs -o size=3m none {mnt} && {{ {args}; echo rc=$?; }} && {sys.executable} {check}"
    )
    result = subprocess.run(cmd, env=env(), capture_output=True, text=True, timeout=300)
    assert "rc=2" in result.stdout, result.stdout + result.stderr
    last = [ln for ln in result.stderr.splitlines() if ln.strip()][-1]
    assert last.startswith("topseg datagen: error: no space left on the device")
    assert "free some space and rerun" in last
    kept = int(result.stdout.split("complete ")[-1])
    assert 0 < kept < 40


def test_preview_writes_a_png_of_the_expected_size(tmp_path):
    from PIL import Image

    path = tmp_path / "set.zarr"
    attrs = D.make_attrs(
        seed=11, mode="modeled", noise="gaussian:10", room=None, frames=5,
        generator={"factory": "datagen_toy:toy_source", "config": {}},
    )  # fmt: skip
    with D.DatasetWriter.open(path, attrs) as w:
        fw = D.FrameWriter(path)
        for i in range(5):
            fw.write(i, *toy_frame(11, i, "gaussian:10"))
        w.mark_complete(range(5))
    result = subprocess.run(
        [TOPSEG, "datagen", "preview", str(path), "--count", "4", "--cols", "3", "--scale", "4"],
        env=env(), capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    png = tmp_path / "set-preview.png"
    image = np.asarray(Image.open(png).convert("RGB"))
    # 4 tiles of 160x120 frames in 3 columns: (2*160 + 4) x (120 + 16) each, 12 px apart
    assert image.shape == (12 + 2 * (136 + 12) + 20, 12 + 3 * (324 + 12), 3)
    # first tile's labels: frame 0 coloured exactly; its depth shows no-depth in dark red
    depth, lab, _ = toy_frame(11, 0, "gaussian:10")
    np.testing.assert_array_equal(
        image[28 : 28 + 120, 176 : 176 + 160], label_table.colorize(lab[::4, ::4])
    )
    holes = depth[::4, ::4] == 0
    assert holes.any()
    assert (image[28 : 28 + 120, 12 : 12 + 160][holes] == datagen_preview.NO_DEPTH_RGB).all()


def test_preview_of_an_empty_dataset_is_an_error(tmp_path):
    path = tmp_path / "empty.zarr"
    attrs = D.make_attrs(seed=1, mode="modeled", noise="none", room=None, frames=2,
                         generator={"factory": "x:y", "config": {}})  # fmt: skip
    D.DatasetWriter.open(path, attrs).close()
    result = subprocess.run(
        [TOPSEG, "datagen", "preview", str(path)], capture_output=True, text=True
    )
    assert result.returncode == 2 and "no complete frames" in result.stderr


ARM_URDF = """<?xml version="1.0"?>
<robot name="two_link">
  <link name="base"><collision><geometry><cylinder radius="0.12" length="0.3"/></geometry>
    <origin xyz="0 0 0.15"/></collision></link>
  <link name="upper"><collision><geometry><box size="0.1 0.1 0.6"/></geometry>
    <origin xyz="0 0 0.3"/></collision></link>
  <link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 1 0"/>
    <limit lower="-1.5" upper="1.5" effort="1" velocity="1"/></joint>
  <joint name="j2" type="fixed"><parent link="upper"/><child link="tool"/>
    <origin xyz="0 0 0.6"/></joint>
</robot>
"""


@pytest.mark.slow
def test_cells_with_a_users_own_robot_render_it_as_robot(tmp_path):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(ARM_URDF)
    out = tmp_path / "cell.zarr"
    run = subprocess.run(
        [TOPSEG, "-q", "datagen", "--mode", "cell", "--frames", "6", "--out", str(out), "--seed", "2",
         "--robot-urdf", str(urdf), "--robots", "none", "--workers", "1", "--no-progress"],
        env=env(), capture_output=True, text=True,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    ds = D.open_dataset(out)
    robots = [r for k in range(len(ds)) for r in ds.scene(k).get("robots", [])]
    assert robots and all(r["name"] == str(urdf) for r in robots)
    assert any((ds.labels[k] == label_table.ROBOT).any() for k in range(len(ds)))


def test_a_bad_robot_urdf_is_one_clear_line_before_any_frame(tmp_path):
    out = tmp_path / "cell.zarr"
    run = subprocess.run(
        [TOPSEG, "datagen", "--mode", "cell", "--frames", "2", "--out", str(out),
         "--robot-urdf", str(tmp_path / "missing.urdf")],
        env=env(), capture_output=True, text=True,
    )  # fmt: skip
    assert "missing.urdf" in one_error_line(run) and not out.exists()
    run = subprocess.run(
        [TOPSEG, "datagen", "--frames", "2", "--out", str(out), "--robots", "panda"],
        env=env(), capture_output=True, text=True,
    )  # fmt: skip
    assert "need --mode cell" in one_error_line(run)


def test_a_preview_caption_counts_robots_people_and_every_kind_of_object():
    from topseg.services.batch.datagen.preview import caption

    scene = {
        "human": {"pose": "kneeling"},
        "extra_humans": [{"pose": "lying"}],
        "robots": [{"name": "random:3"}, {"name": "panda"}],
        "objects": [{}, {}, {}],
        "mesh_objects": [{}],
        "relations": [{}],
    }
    assert caption(4, scene) == "#4  kneeling  +1 people  2 robots  4 objects  1 relations"
    assert caption(0, {"objects": []}) == "#0  0 objects"  # a paper scene's record as before
