"""Bad start-up input: a damaged or wrong-version model, a Zenoh config that does not parse,
a bad camera name, a bad TOML config. The worker and the driver refuse to start with ONE
line on stderr ("topseg <command>: error: ...", the line systemd shows as STATUS=) and exit
status 2: never a traceback, never a half-started service."""

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from netutil import free_port

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "default.npz"


def _model(tmp: Path, damage: str) -> Path:
    """The bundled model, damaged one way."""
    path = tmp / f"{damage}.npz"
    arrays = dict(np.load(MODEL))
    header = json.loads(arrays["header"].tobytes())
    if damage == "flipped-byte":
        blob = bytearray(MODEL.read_bytes())
        blob[len(blob) // 2] ^= 0xFF  # inside an array member: the zip's CRC-32 catches it
        path.write_bytes(bytes(blob))
        return path
    if damage == "truncated":
        path.write_bytes(MODEL.read_bytes()[: MODEL.stat().st_size // 2])
        return path
    if damage == "empty":
        path.write_bytes(b"")
        return path
    if damage == "version-2":
        header["format_version"] = 2
    elif damage == "other-labels":
        header["labels"] = header["labels"][:-1]
    elif damage == "index-out-of-bounds":
        arrays["left"] = arrays["left"].copy()
        arrays["left"][0] = 10**8
    elif damage == "no-posteriors":
        del arrays["posteriors"]
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez(path, **arrays)
    return path


MODEL_DAMAGE = {
    "flipped-byte": "damaged or truncated (Bad CRC-32",
    "truncated": "damaged or truncated",
    "empty": "not a zip archive",
    "version-2": "model format version 2; this topseg reads version 1",
    "other-labels": "different label table",
    "index-out-of-bounds": "inconsistent forest: a child index is out of bounds",
    "no-posteriors": "lacks the arrays ['posteriors']",
}

#: name -> (config text, what the error line says)
ZENOH_CONFIGS = {
    "unclosed": ('{ mode: "peer", listen: {', "expected identifier or string"),
    "bad-mode": ('{ mode: "flying" }', "line 1, column 9: unknown variant `flying`"),
    "bad-endpoint": (
        '{ listen: { endpoints: ["nonsense"] } }',
        "Endpoints must be of the form <protocol>/<address>",
    ),
    "empty": ("", "Empty config file"),
}


def topseg(*args, timeout=90) -> tuple[int, str]:
    """Run `topseg ARGS` at the default verbosity (as under systemd): (status, stderr)."""
    cmd = [sys.executable, "-m", "topseg.services.cli", *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    return proc.returncode, proc.stderr


def assert_one_line(rc: int, err: str, command: str, *says: str) -> None:
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"{len(lines)} lines on stderr:\n{err}"
    assert lines[0].startswith(f"topseg {command}: error: "), err
    for text in says:
        assert text in lines[0], err
    assert ".rs:" not in err  # no Rust source paths from zenoh's messages


@pytest.mark.parametrize("damage", MODEL_DAMAGE)
def test_worker_refuses_a_damaged_or_foreign_model(tmp_path, damage):
    path = _model(tmp_path, damage)
    rc, err = topseg("worker", "--model", path, "--zenoh-port", free_port())
    assert_one_line(rc, err, "worker", str(path), MODEL_DAMAGE[damage])


@pytest.mark.parametrize("command", ["worker", "driver"])
@pytest.mark.parametrize("name", ZENOH_CONFIGS)
def test_a_zenoh_config_that_does_not_parse_is_one_line(tmp_path, command, name):
    text, says = ZENOH_CONFIGS[name]
    config = tmp_path / f"{name}.json5"
    config.write_text(text)
    first = ["--model", MODEL] if command == "worker" else ["--source", "synthetic"]
    rc, err = topseg(command, *first, "--zenoh-config", config)
    assert_one_line(rc, err, command, f"bad Zenoh config {config}: ", says)


@pytest.mark.parametrize(
    "args, says",
    [
        (["worker", "--model", MODEL, "--cameras", "cell 1/cam0"], "cell name 'cell 1'"),
        (["worker", "--model", MODEL, "--cameras", "a/b/c"], "must be CELL/CAMERA"),
        (["worker", "--model", MODEL, "--zenoh-config", "/nonexistent.json5"], "does not exist"),
        (["worker", "--model", "/tmp"], "cannot read model file /tmp"),
        (["worker", "--model", MODEL, "--zenoh-port", "70000"], "not in 1..65535"),
        (["driver", "--source", "synthetic", "--camera", "a/b"], "camera name 'a/b'"),
        (["driver", "--source", "synthetic", "--cell", "**"], "cell name '**'"),
        (["driver", "--source", "bogus:1"], "unknown source kind 'bogus'"),
        (["driver", "--source", "synthetic", "--fps", "-1"], "fps must be in"),
        (["driver", "--source", "replay:/nonexistent.mcap"], "does not exist"),
    ],
    ids=lambda x: "-".join(map(str, x[:1] + x[-2:])) if isinstance(x, list) else None,
)
def test_bad_names_and_options_are_one_line(args, says):
    rc, err = topseg(*args)
    assert_one_line(rc, err, args[0], says)


@pytest.mark.parametrize(
    "command, toml, says",
    [
        ("driver", 'source = "synthetic"\ncamera = "a/b"\n', "camera name 'a/b'"),
        ("driver", 'source = "synthetic"\nbogus = 1\n', ":3: unknown option 'bogus'"),
        ("driver", 'source = "synthetic"\nfps = "fast"\n', ":3: fps: expected a number"),
        ("worker", f'model = "{MODEL}"\ncameras = ["x y/cam0"]\n', "cell name 'x y'"),
        ("worker", 'model = "m.npz"\ncrf = [', "bad TOML"),
    ],
)
def test_a_bad_toml_config_is_one_line(tmp_path, command, toml, says):
    config = tmp_path / "cam.toml"
    config.write_text(f"[{command}]\n{toml}")
    rc, err = topseg(command, "--config", config)
    assert_one_line(rc, err, command, says)


@pytest.mark.slow
def test_a_zenoh_endpoint_in_use_is_one_error_line_after_the_model_loaded(tmp_path):
    """A runtime failure (the config's listen port is taken): the worker logged its model,
    then says in one line why it cannot join Zenoh; the driver says the same."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        config = tmp_path / "held.json5"
        config.write_text(
            '{ mode: "peer", scouting: { multicast: { enabled: false } }, '
            f'listen: {{ endpoints: ["tcp/127.0.0.1:{port}"], exit_on_failure: true }} }}'
        )
        for command, first in (
            ("worker", ["--model", MODEL]),
            ("driver", ["--source", "synthetic"]),
        ):
            rc, err = topseg(command, *first, "--zenoh-config", config)
            assert rc == 2, err
            errors = [line for line in err.splitlines() if "error" in line.lower()]
            assert errors == [err.strip().splitlines()[-1]], err
            assert errors[0].startswith(f"topseg {command}: error: cannot open a Zenoh session: ")
            assert "Address already in use" in errors[0] and "Traceback" not in err
