"""Bad option values are refused up front with one line naming the option and exit 2 (never
a traceback, a crash later, or a sleep for days): `train`'s numbers, `driver --fps` and
`--frame-timeout`, `record --duration`, `status --timeout`, `evaluate --frames 0`,
`router --listen garbage`, numbers of `bench`, `demo` and `datagen`, and a PNG whose header
claims 60000x60000 in the replay driver."""

import struct
import subprocess
import sys
import zlib

import pytest
from netutil import free_port


def topseg(*args, timeout=90) -> tuple[int, str]:
    """Run `topseg ARGS`: (status, stderr)."""
    cmd = [sys.executable, "-m", "topseg.services.cli", *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    return proc.returncode, proc.stderr


def assert_one_line(rc, err, command, *says):
    """Exit 2, one `topseg COMMAND: error:` line saying `says`, no traceback or Rust path."""
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"topseg {command}: error: "), err
    for text in says:
        assert text in lines[0], err
    assert ".rs:" not in err


TRAIN = [
    ("--depth", "100000"),
    ("--validation", "1.0"),
    ("--validation", "nan"),
    ("--frames-per-tree", "0"),
    ("--features", "0"),
    ("--absolute-fraction", "2"),
    ("--absolute-fraction", "nan"),
    ("--trees", "0"),
    ("--responses", "0"),
    ("--thresholds", "-1"),
    ("--pixels-per-frame", "0"),
    ("--seed", "-1"),
    ("--max-validation-frames", "-1"),
    ("--workers", "0"),
]


@pytest.mark.parametrize(("option", "value"), TRAIN)
def test_train_refuses_a_bad_number(tmp_path, option, value):
    rc, err = topseg(
        "train", "--data", tmp_path / "none", "--out", tmp_path / "m.npz", option, value
    )
    assert_one_line(rc, err, "train", option)


OTHERS = [
    ("driver", "--fps", "1e-300"),
    ("driver", "--fps", "1e-6"),
    ("driver", "--fps", "nan"),
    ("driver", "--frame-timeout", "nan"),
    ("driver", "--frame-timeout", "inf"),
    ("record", "--duration", "nan"),
    ("status", "--timeout", "inf"),
    ("evaluate", "--frames", "0"),
    ("evaluate", "--smoothness", "nan"),
    ("evaluate", "--smoothness", "-1"),
    ("worker", "--mount-check", "nan"),
    ("worker", "--smoothness", "inf"),
]


@pytest.mark.parametrize(("command", "option", "value"), OTHERS)
def test_commands_refuse_a_bad_number(tmp_path, command, option, value):
    extra = {
        "driver": ["--source", "synthetic"],
        "record": ["--out", tmp_path / "r.mcap"],
        "evaluate": ["--data", tmp_path / "none"],
    }.get(command, [])
    rc, err = topseg(command, *extra, option, value, "--zenoh-port", free_port())
    assert_one_line(rc, err, command, option)


BENCH_DEMO_DATAGEN = [
    ("bench", "crf", "--frames", "0"),
    ("bench", "crf", "--smoothness", "nan"),
    ("bench", "forest", "--depth", "100"),
    ("bench", "datagen", "--chunk", "0"),
    ("bench", "pipeline", "--fps", "1e-300"),
    ("bench", "train", "--scale", "inf"),
    ("bench", "transport", "--fps", "-1"),
    ("bench", "synthesis", "--warmup", "-1"),
    ("bench", "calibrate", "--mounts", "0"),
    ("demo", None, "--fps", "nan"),
    ("demo", None, "--trees", "0"),
    ("datagen", None, "--frames", "0"),
    ("datagen", None, "--workers", "-2"),
    ("datagen", "preview", "--count", "0"),
]


@pytest.mark.parametrize(("command", "sub", "option", "value"), BENCH_DEMO_DATAGEN)
def test_bench_demo_and_datagen_refuse_a_bad_number(tmp_path, command, sub, option, value):
    extra = {"datagen": ["--out", tmp_path / "ds.zarr"], "preview": [tmp_path / "ds.zarr"]}
    args = [command, *([sub] if sub else []), *extra.get(sub or command, []), option, value]
    rc, err = topseg(*args)
    assert_one_line(rc, err, command, option)


def test_router_refuses_a_garbage_endpoint():
    rc, err = topseg("router", "--listen", "garbage", "--zenoh-port", free_port())
    assert_one_line(rc, err, "router", "--listen garbage", "Endpoints must be of the form")


def test_replay_driver_refuses_a_huge_png_header(tmp_path):
    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", 60000, 60000, 16, 0, 0, 0, 0)
    (tmp_path / "big.png").write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(b"\0" * 10))
        + chunk(b"IEND", b"")
    )
    rc, err = topseg("driver", "--source", f"replay:{tmp_path}", "--zenoh-port", free_port())
    err = "\n".join(line for line in err.splitlines() if " INFO " not in line)
    assert_one_line(rc, err, "driver", "big.png")
