"""The `topseg` command: every subcommand (and bench) has working --help; errors are one line."""

import subprocess
import sys

import pytest

from topseg.services.bench import BENCHES
from topseg.services.cli import COMMANDS, main


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
