"""docs/reference/cli.md is what docs/reference/make_cli.py writes from the real parsers."""

from __future__ import annotations

import importlib.util

from docsutil import ROOT

SCRIPT = ROOT / "docs" / "reference" / "make_cli.py"


def load_generator():
    """docs/reference/make_cli.py as a module (docs/ is not a package)."""
    spec = importlib.util.spec_from_file_location("make_cli", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_committed_cli_reference_is_what_the_parsers_say(monkeypatch):
    make_cli = load_generator()
    monkeypatch.setenv("COLUMNS", make_cli.COLUMNS)
    for name in make_cli.ENVIRONMENT:
        monkeypatch.delenv(name, raising=False)
    assert make_cli.OUT.read_text() == make_cli.render(), (
        "docs/reference/cli.md is out of date with the command-line parsers: "
        "regenerate it with `make docs` (.venv/bin/python docs/reference/make_cli.py)"
    )


def test_the_reference_lists_every_command():
    from topseg.services.cli import COMMANDS

    text = (ROOT / "docs" / "reference" / "cli.md").read_text()
    for name in COMMANDS:
        assert f"\n## topseg {name}\n" in text
