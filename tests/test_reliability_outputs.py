"""Operators' output faults (docs/reliability.md), with real processes and file systems:
`topseg segment` never lets two inputs' outputs collide (a recording of several cameras,
one spanning a driver restart, PNGs of the same name in two folders, and a last guard), and
a write that fails (a read-only folder, a full tmpfs) gives one line, a count of what was
written, nothing half-written and exit 2; `evaluate --json` and `train --out` likewise.

Read-only and size-limited folders are real mounts in a private mount namespace, made as
tests/test_reliability_disk.py makes them (skipped where `unshare` is not allowed)."""

import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from test_segment import model, segment  # noqa: F401 (a fixture)
from test_train_service import SMALL

from topseg.core import forest
from topseg.core.camera import KINECT_V1
from topseg.core.formats import recording, wire
from topseg.core.synth import procedural

CLI = [sys.executable, "-m", "topseg.services.cli"]


def unshare_prefix() -> list[str]:
    """The `unshare` prefix of a private mount namespace, or skip."""
    if shutil.which("unshare") is None:
        pytest.skip("needs unshare(1)")
    for prefix in (["unshare", "-m"], ["unshare", "-rm"]):
        if subprocess.run([*prefix, "true"], capture_output=True).returncode == 0:
            return prefix
    pytest.skip("mount namespaces unavailable")


def in_namespace(script: str) -> subprocess.CompletedProcess:
    """Run a shell script in a private mount namespace (its mounts go with it)."""
    return subprocess.run(
        [*unshare_prefix(), "sh", "-c", script], capture_output=True, text=True, timeout=300
    )


def read_only(folder) -> str:
    """Shell that makes `folder` a read-only bind mount of itself (root cannot write it)."""
    return f"mount --bind {folder} {folder} && mount -o remount,ro,bind {folder}"


def frames(n: int, seed: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [procedural.procedural_frame(rng)[0] for _ in range(n)]


def write_recording(path, messages) -> None:
    """messages: (key, seq, depth) in order."""
    with recording.RecordingWriter(path) as w:
        for i, (key, seq, depth) in enumerate(messages):
            w.write(key, wire.encode_depth(wire.DepthFrame(depth, KINECT_V1, seq)), 10**9 + i)


def one_error_line(stderr: str, command: str) -> str:
    lines = [ln for ln in stderr.splitlines() if "error" in ln.lower()]
    assert len(lines) == 1 and lines[0].startswith(f"topseg {command}: error: "), stderr
    assert "Traceback" not in stderr
    return lines[0]


@pytest.mark.slow
def test_every_camera_of_a_recording_is_segmented_under_its_own_names(model, tmp_path):  # noqa: F811
    path, trained = model
    depth = frames(6)
    cams = [wire.depth_key("c1", "cam0"), wire.depth_key("c1", "cam1")]
    write_recording(tmp_path / "r.mcap", [(cams[i % 2], i // 2, d) for i, d in enumerate(depth)])
    out = tmp_path / "out"
    r = segment(tmp_path / "r.mcap", "--model", path, "--out", out, "--crf", "none")
    assert r.returncode == 0, r.stderr
    assert "segmented 6 frames" in r.stdout
    for cam in cams:  # the summary: frames per camera and where they went
        assert f"r.mcap {cam}: 3 frames" in r.stdout, r.stdout
    for i, d in enumerate(depth):
        name = f"r_c1-cam{i % 2}_{i // 2:06d}"
        got = np.asarray(Image.open(out / f"{name}_labels.png"))
        np.testing.assert_array_equal(got, forest.predict_labels(trained, d))
        assert (out / f"{name}_overlay.png").exists()
    assert len(list(out.iterdir())) == 12


def test_a_recording_across_a_driver_restart_keeps_every_frame(model, tmp_path):  # noqa: F811
    path, trained = model
    depth = frames(5)
    seqs = [0, 1, 2, 0, 1]  # the driver restarted after seq 2
    key = wire.depth_key()
    write_recording(tmp_path / "r.mcap", [(key, s, d) for s, d in zip(seqs, depth, strict=True)])
    out = tmp_path / "out"
    r = segment(tmp_path / "r.mcap", "--model", path, "--out", out, "--crf", "none")
    assert r.returncode == 0, r.stderr
    names = ["r_000000", "r_000001", "r_000002", "r_000000-2", "r_000001-2"]
    for name, d in zip(names, depth, strict=True):
        got = np.asarray(Image.open(out / f"{name}_labels.png"))
        np.testing.assert_array_equal(got, forest.predict_labels(trained, d))
    assert len(list(out.iterdir())) == 10


def test_pngs_of_the_same_name_in_two_folders_do_not_overwrite(model, tmp_path):  # noqa: F811
    path, trained = model
    depth = frames(2)
    for folder, d in zip(("cA", "cB"), depth, strict=True):
        (tmp_path / folder).mkdir()
        Image.fromarray(d).save(tmp_path / folder / "frame.png")
    out = tmp_path / "out"
    r = segment(tmp_path / "cA" / "frame.png", tmp_path / "cB", "--model", path, "--out", out,
                "--crf", "none")  # fmt: skip
    assert r.returncode == 0, r.stderr
    for folder, d in zip(("cA", "cB"), depth, strict=True):
        got = np.asarray(Image.open(out / f"{folder}-frame_labels.png"))
        np.testing.assert_array_equal(got, forest.predict_labels(trained, d))
    assert len(list(out.iterdir())) == 4


def test_an_output_name_taken_earlier_in_the_run_is_refused(model, tmp_path):  # noqa: F811
    path, _ = model
    a, b = frames(2)
    Image.fromarray(a).save(tmp_path / "r_000000.png")
    write_recording(tmp_path / "r.mcap", [(wire.depth_key(), 0, b)])
    out = tmp_path / "out"
    r = segment(tmp_path / "r_000000.png", tmp_path / "r.mcap", "--model", path, "--out", out,
                "--crf", "none")  # fmt: skip
    assert r.returncode == 2
    assert "r.mcap" in r.stderr and "r_000000.png" in r.stderr and "Traceback" not in r.stderr
    assert "segmented 1 frames" in r.stdout


def test_segment_into_a_read_only_folder_is_one_line(model, tmp_path):  # noqa: F811
    path, _ = model
    Image.fromarray(frames(1)[0]).save(tmp_path / "f.png")
    out = tmp_path / "ro"
    out.mkdir()
    seg = f"{' '.join(CLI)} segment {tmp_path / 'f.png'} --model {path} --out {out} --crf none"
    r = in_namespace(f"{read_only(out)} && {{ {seg}; echo rc=$?; }}")
    assert "rc=2" in r.stdout, r.stdout + r.stderr
    line = one_error_line(r.stderr, "segment")
    assert f"cannot write {out}/f_labels.png" in line and "Read-only file system" in line
    assert "0 of 1 frames written" in line
    assert list(out.iterdir()) == []


def test_segment_onto_a_full_disk_stops_with_whole_frames_only(model, tmp_path):  # noqa: F811
    path, _ = model
    rng = np.random.default_rng(1)
    src = tmp_path / "in"
    src.mkdir()
    for i in range(12):  # noisy depth: overlays of ~0.5-0.9 MB each, 12 into a 3 MB tmpfs
        d = rng.integers(500, 4000, KINECT_V1.shape, dtype=np.uint16)
        Image.fromarray(d).save(src / f"f{i:02d}.png")
    mnt = tmp_path / "small"
    mnt.mkdir()
    seg = f"{' '.join(CLI)} segment {src} --model {path} --out {mnt} --crf none"
    script = (f"mount -t tmpfs -o size=3m none {mnt} && {{ {seg}; echo rc=$?; "
              f"echo FILES; ls -A {mnt}; }}")  # fmt: skip
    r = in_namespace(script)
    assert "rc=2" in r.stdout, r.stdout + r.stderr
    line = one_error_line(r.stderr, "segment")
    assert "No space left on device" in line and "of 12 frames written to" in line, line
    written = int(line.split(" of 12 frames")[0].rsplit(" ", 1)[1])
    files = r.stdout.split("FILES")[1].split()
    assert 0 < written < 12
    assert sorted(files) == sorted(
        f"f{i:02d}_{kind}.png" for i in range(written) for kind in ("labels", "overlay")
    ), files  # every written frame has both files; no temporaries left


def test_evaluate_json_into_a_read_only_folder_is_one_line(data, tmp_path):
    from topseg.core.forest.train import TrainConfig
    from topseg.core.formats import dataset as D

    ds = D.open_dataset(data)
    cfg = TrainConfig(n_trees=1, max_depth=4, frames_per_tree=4, pixels_per_frame=200,
                      n_candidates=8, n_thresholds=8)  # fmt: skip
    forest.save_model(tmp_path / "m.npz", forest.train_forest(ds.depth, ds.labels, cfg, seed=1), {})
    ro = tmp_path / "ro"
    ro.mkdir()
    ev = (f"{' '.join(CLI)} evaluate --model {tmp_path / 'm.npz'} --data {data} --crf none "
          f"--frames 2 --json {ro / 's.json'}")  # fmt: skip
    r = in_namespace(f"{read_only(ro)} && {{ {ev}; echo rc=$?; }}")
    assert "rc=2" in r.stdout, r.stdout + r.stderr
    line = one_error_line(r.stderr, "evaluate")
    assert f"cannot write {ro / 's.json'}" in line and "Read-only file system" in line
    assert list(ro.iterdir()) == []


def test_train_out_into_a_read_only_folder_is_one_line(data, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    tr = f"{' '.join(CLI)} train --data {data} --out {ro / 'm.npz'} --serial {' '.join(SMALL)}"
    r = in_namespace(f"{read_only(ro)} && {{ {tr}; echo rc=$?; }}")
    assert "rc=2" in r.stdout, r.stdout + r.stderr
    line = one_error_line(r.stderr, "train")
    assert f"cannot write {ro / 'm.npz'}" in line and "Read-only file system" in line
    assert list(ro.iterdir()) == []
