import os
import stat

import pytest

from topseg.core.atomic import atomic_write


def test_replaces_whole_file_with_open_permissions(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"old")
    old = os.umask(0o022)
    try:
        with atomic_write(p) as f:
            f.write(b"new contents")
    finally:
        os.umask(old)
    assert p.read_bytes() == b"new contents"
    assert stat.S_IMODE(p.stat().st_mode) == 0o644  # not mkstemp's 0600
    assert [q.name for q in tmp_path.iterdir()] == ["f.bin"]


def test_an_error_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_write(p) as f:
        f.write(b"half")
        raise RuntimeError("disk full")
    assert p.read_bytes() == b"old"
    assert [q.name for q in tmp_path.iterdir()] == ["f.bin"]
