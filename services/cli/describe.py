"""What `--help` says about a command: a short summary, the page with the details, its options.

A command module's docstring opens with a summary paragraph of a few lines; the rest of the
docstring is for developers. `--help` shows the summary, one `Details: docs/...` line and
then the options, so the reasoning lives in the docs and the options stay in view.
"""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Iterator


def summary(doc: str | None) -> str:
    """The first paragraph of a docstring, its lines joined (argparse wraps it again)."""
    if not doc:
        return ""
    first = inspect.cleandoc(doc).split("\n\n", 1)[0]
    return " ".join(first.split())


def description(doc: str | None, details: str | None = None) -> str:
    """A parser's description: the docstring's summary, then `Details: PAGE` on its own."""
    text = summary(doc)
    return f"{text}\n\nDetails: {details}" if details else text


class ParagraphFormatter(argparse.HelpFormatter):
    """argparse's formatter, but the description's paragraphs (split by a blank line) stay
    apart, so the `Details:` line is not run into the summary."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        fill = super()._fill_text
        return "\n\n".join(fill(p, width, indent) for p in text.split("\n\n") if p.strip())


def subcommands(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """The parsers of a parser's subcommands, each followed by its own, depth first."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):  # aliases share a parser
                yield child
                yield from subcommands(child)
