"""`--help` says what a command does in a few lines, where the details are, then its options."""

from __future__ import annotations

import argparse

import pytest
from docsutil import ROOT, broken

from topseg.services.cli import COMMANDS, DETAILS, build_parser, describe

#: the most lines a command's description may take at 80 columns, its Details line included
MAX_DESCRIPTION_LINES = 8


def command_parsers(name: str) -> list[argparse.ArgumentParser]:
    """The parser of `topseg NAME` and those of its subcommands (`bench forest`, ...)."""
    parsers = list(describe.subcommands(build_parser([name])))
    own = next(p for p in parsers if p.prog == f"topseg {name}")
    return [own, *describe.subcommands(own)]


def description_lines(parser: argparse.ArgumentParser) -> list[str]:
    """The description as `--help` prints it, one string a line."""
    formatter = parser._get_formatter()
    formatter.add_text(parser.description)
    return formatter.format_help().strip("\n").splitlines()


@pytest.mark.parametrize("name", COMMANDS)
def test_help_is_a_short_summary_then_details_then_the_options(name, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    for parser in command_parsers(name):
        lines = description_lines(parser)
        text = [line for line in lines if line.strip()]
        assert text, f"{parser.prog} --help says nothing about what it does"
        assert len(lines) <= MAX_DESCRIPTION_LINES, (
            f"{parser.prog} --help opens with {len(lines)} lines of description (at most "
            f"{MAX_DESCRIPTION_LINES}): keep the module docstring's first paragraph short and "
            "put the reasoning in the docs"
        )
        assert text[-1].startswith("Details: docs/"), f"{parser.prog}: no Details line"
        shown = parser.format_help()
        after = shown[shown.index(lines[-1]) + len(lines[-1]) :].lstrip("\n")
        assert after.startswith(("positional arguments:", "options:")), (
            f"{parser.prog} --help: the options do not follow the description"
        )


@pytest.mark.parametrize("name", COMMANDS)
def test_every_command_names_a_page_that_exists(name):
    assert name in DETAILS, f"topseg {name}: add its docs page to cli.DETAILS"
    target = DETAILS[name]
    assert target.startswith("docs/")
    assert broken(target, ROOT / "README.md") is None, broken(target, ROOT / "README.md")


def test_summary_is_the_first_paragraph_on_one_line():
    doc = """First line
    goes on.

    Second paragraph.
    """
    assert describe.summary(doc) == "First line goes on."
    assert describe.description(doc, "PAGE") == "First line goes on.\n\nDetails: PAGE"
    assert describe.summary(None) == ""
