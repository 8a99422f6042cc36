"""Model files that are intact (every zip member's CRC-32 is right) but say nonsense: a
background of 1e20 mm, a camera that is a string or has no size, a header nested 200k deep,
an array header claiming 40 TiB, posteriors that are all zero or 3e38, a header whose depth
or leaf count disagrees with the arrays. Each is built with the real writer (`save_model`),
then one member is rewritten (with a valid checksum); the loader refuses it with one
ModelFileError naming the file, and `topseg segment`/`evaluate`/`worker` exit 2 with one line."""

import io
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from netutil import free_port

from topseg.core.camera import PAPER_MOUNT
from topseg.core.forest import Forest, ModelFileError, load_model, random_tree, save_model


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A small valid model with a camera in its header."""
    rng = np.random.default_rng(0)
    forest = Forest.from_trees([random_tree(rng, d, 2, 80000.0) for d in (4, 5)])
    path = tmp_path_factory.mktemp("good") / "good.npz"
    save_model(path, forest, {"dataset": {"attrs": {"camera": PAPER_MOUNT.to_dict()}}})
    load_model(path)  # the undamaged model loads
    return path


def npy(array: np.ndarray) -> bytes:
    """`array` as the bytes of a `.npy` member."""
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def rewrite(src, dst, member: str, change) -> None:
    """Copy the model zip, passing `member`'s bytes through change(bytes) -> bytes; the new
    zip's checksums are all valid."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            data = zin.read(info.filename)
            if info.filename == f"{member}.npy":
                data = change(data)
            zout.writestr(info.filename, data)


def header_change(edit):
    """A change that edits the JSON header dict in place (or returns raw JSON text)."""

    def change(data: bytes) -> bytes:
        header = json.loads(np.load(io.BytesIO(data)).tobytes())
        out = edit(header)
        text = out if isinstance(out, str) else json.dumps(header)
        return npy(np.frombuffer(text.encode(), np.uint8))

    return change


def array_change(edit):
    """A change that edits an array (a writable copy) in place."""

    def change(data: bytes) -> bytes:
        arr = np.load(io.BytesIO(data)).copy()
        out = edit(arr)
        return npy(arr if out is None else out)

    return change


def _camera(value):
    return lambda h: h["dataset"]["attrs"].__setitem__("camera", value)


def _intrinsics(**kw):
    def edit(h):
        h["dataset"]["attrs"]["camera"]["intrinsics"].update(kw)

    return edit


def _forest(**kw):
    return lambda h: h["forest"].update(kw)


def _huge_shape(data: bytes) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f4", "fortran_order": False, "shape": (2 * 10**12, 5)}
    )
    return buf.getvalue() + b"\0" * 64


#: name -> (member, change, what the error says)
DAMAGE = {
    "background-1e20": ("header", header_change(_forest(background_mm=10**20)), "background_mm"),
    "background-float": ("header", header_change(_forest(background_mm=1e20)), "forest"),
    "background-zero": ("header", header_change(_forest(background_mm=0)), "background_mm"),
    "background-negative": ("header", header_change(_forest(background_mm=-5)), "background_mm"),
    "camera-string": ("header", header_change(_camera("kinect")), "camera"),
    "camera-no-intrinsics": (
        "header",
        header_change(_camera({"height_mm": 3500.0})),
        "intrinsics",
    ),
    "camera-width-0": ("header", header_change(_intrinsics(width=0)), "camera size"),
    "camera-fx-0": ("header", header_change(_intrinsics(fx=0.0)), "focal length"),
    "dataset-string": (
        "header",
        header_change(lambda h: h.__setitem__("dataset", "x")),
        "dataset",
    ),
    "nested-200k": (
        "header",
        header_change(
            lambda h: json.dumps(h)[:-1] + ', "x": ' + "[" * 200_000 + "]" * 200_000 + "}"
        ),
        "nests more than",
    ),
    "shape-40TiB": ("posteriors", _huge_shape, "claims"),
    "posteriors-zero": (
        "posteriors",
        array_change(lambda a: a.__setitem__(slice(None), 0)),
        "all zeros",
    ),
    "posteriors-3e38": (
        "posteriors",
        array_change(lambda a: a.__setitem__(slice(None), 3e38)),
        "class probabilities",
    ),
    "posteriors-nan": (
        "posteriors",
        array_change(lambda a: a.__setitem__((0, 0), np.nan)),
        "class probabilities",
    ),
    "header-depth": ("header", header_change(_forest(max_depth=19)), "max_depth"),
    "header-leaves": ("header", header_change(_forest(n_leaves=7)), "n_leaves"),
    "header-features": (
        "header",
        header_change(_forest(features_per_node=3)),
        "features_per_node",
    ),
    "child-out-of-range": (
        "left",
        array_change(lambda a: a.__setitem__(0, 10**6)),
        "child index",
    ),
    "threshold-dtype": ("threshold", array_change(lambda a: a.astype(np.float64)), "dtype"),
}


def damaged(good, tmp_path, name):
    """The good model with damage `name`."""
    member, change, _ = DAMAGE[name]
    path = tmp_path / f"{name}.npz"
    rewrite(good, path, member, change)
    with zipfile.ZipFile(path) as zf:
        assert zf.testzip() is None  # every checksum is valid
    return path


@pytest.mark.parametrize("name", DAMAGE)
def test_loader_refuses_nonsense_in_one_line(good, tmp_path, name):
    path = damaged(good, tmp_path, name)
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    message = str(info.value)
    assert str(path) in message and DAMAGE[name][2] in message, message
    assert "\n" not in message and len(message) < 400, message


def topseg(*args, timeout=120) -> tuple[int, str]:
    """Run `topseg ARGS`: (status, stderr)."""
    cmd = [sys.executable, "-m", "topseg.services.cli", *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    return proc.returncode, proc.stderr


def assert_one_line(rc, err, command, *says):
    """Exit 2 and one `topseg COMMAND: error:` line on stderr saying `says`."""
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"topseg {command}: error: "), err
    for text in says:
        assert text in lines[0], err


@pytest.mark.parametrize("name", DAMAGE)
def test_segment_exits_2_with_one_line(good, tmp_path, name):
    path = damaged(good, tmp_path, name)
    rc, err = topseg("segment", tmp_path / "none.png", "--model", path, "--out", tmp_path / "o")
    assert_one_line(rc, err, "segment", str(path), DAMAGE[name][2])


@pytest.mark.parametrize("name", ["background-1e20", "camera-string", "shape-40TiB"])
def test_worker_and_evaluate_exit_2_with_one_line(good, tmp_path, name):
    path = damaged(good, tmp_path, name)
    rc, err = topseg("worker", "--model", path, "--zenoh-port", free_port())
    assert_one_line(rc, err, "worker", str(path))
    rc, err = topseg("evaluate", "--model", path, "--data", tmp_path / "none.zarr")
    assert_one_line(rc, err, "evaluate", str(path))
