"""The `topseg` command: every subcommand (and bench) has working --help; errors are one line."""

import atexit
import os
import subprocess
import sys

import pytest

from topseg.services import cli as cli_module
from topseg.services.batch.bench import BENCHES
from topseg.services.cli import COMMANDS, LIVE_SERVICES, console, main


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert "usage: topseg " + command in capsys.readouterr().out


@pytest.mark.parametrize("stage", sorted(BENCHES))
def test_every_bench_has_help(stage, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", stage, "--help"])
    assert exc.value.code == 0
    assert "--json" in capsys.readouterr().out


def test_top_level_help_lists_commands_and_version_runs():
    out = subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for command in COMMANDS:
        assert command in out
    v = subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "--version"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert v.startswith("topseg ")


@pytest.mark.parametrize("given, expected", [(None, "PASSIVE"), ("active", "active")])
def test_openmp_threads_sleep_between_kernels_unless_the_environment_says(given, expected):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    code = (
        "import contextlib, io, os\n"
        "from topseg.services import cli\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "    cli.main(['--version'])\n"
        "print(os.environ['OMP_WAIT_POLICY'])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.stdout.strip().splitlines()[-1] == expected, out.stderr


@pytest.mark.parametrize(
    "command, ends_at_once", [("viewer", True), ("safety", True), ("datagen", False)]
)
def test_a_live_service_ends_its_process_at_once_after_its_exit_handlers(
    monkeypatch, command, ends_at_once
):
    """A live service's process ends by os._exit once its exit handlers ran (no teardown to
    stop Rust threads in); any other command exits as usual."""
    ran, ended = [], []
    monkeypatch.setattr(sys, "argv", ["topseg", "-q", command, "--anything"])
    monkeypatch.setattr(cli_module, "main", lambda argv: 3 if argv[1] == command else 99)
    monkeypatch.setattr(cli_module.os, "_exit", ended.append)
    atexit.register(ran.append, "handler")
    try:
        if ends_at_once:
            console()
            assert ended == [3] and ran == ["handler"]
        else:
            with pytest.raises(SystemExit) as exit_:
                console()
            assert exit_.value.code == 3 and ended == [] and ran == []
    finally:
        atexit.unregister(ran.append)
    assert LIVE_SERVICES <= set(COMMANDS)
