"""Write docs/reference/cli.md, the command-line reference, from topseg's real parsers.

    make docs            # or: .venv/bin/python docs/reference/make_cli.py

Every command and subcommand gets its usage, its summary and its options exactly as
`--help` prints them at 100 columns; `tests/test_docs_cli.py` fails when the committed file
differs from what this script writes, so the reference cannot drift from the code.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

OUT = Path(__file__).resolve().parent / "cli.md"
#: the width the reference is formatted at, whatever the terminal
COLUMNS = "100"
#: environment variables that would put a machine's own defaults into the help text
ENVIRONMENT = ("TOPSEG_CONFIG", "TOPSEG_ZENOH_CONFIG", "TOPSEG_ZENOH_PORT", "ROS_DOMAIN_ID")

HEADER = """\
# Command-line reference

Generated from the parsers by `make docs` (`docs/reference/make_cli.py`); do not edit by
hand. Every command also takes `--config FILE`, a TOML file whose `[<command>]` table gives
defaults for its long options ([configuration.md](configuration.md)), and the global options
`-v` / `-q` before the command. The pages behind each command's `Details:` line explain what
the options are for.

"""


def command_parsers() -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of `topseg` itself, every command and its subcommands."""
    from topseg.services.cli import COMMANDS, build_parser, describe

    top = build_parser([])
    found = [("topseg", top.description or "", top)]
    for name, (_module, help_text) in COMMANDS.items():
        parser = next(
            p
            for p in describe.subcommands(build_parser([name]))
            if p.prog.endswith(f"topseg {name}")
        )
        found.append((parser.prog, help_text, parser))
        found += [(p.prog, "", p) for p in describe.subcommands(parser)]
    return found


def anchor(prog: str) -> str:
    """The GitHub anchor of a `## prog` heading."""
    return prog.replace(" ", "-")


def render() -> str:
    """The whole reference as Markdown (formatted at COLUMNS columns, see `main`)."""
    parsers = command_parsers()
    lines = [HEADER.rstrip(), "", "| command | what it does |", "|---|---|"]
    for prog, help_text, _ in parsers[1:]:
        if help_text:
            lines.append(f"| [`{prog}`](#{anchor(prog)}) | {help_text} |")
    lines.append("")
    for prog, _, parser in parsers:
        lines += [f"## {prog}", "", "```text", parser.format_help().rstrip(), "```", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Write OUT (or print it with `--stdout`), formatted the same on every machine."""
    os.environ["COLUMNS"] = COLUMNS
    for name in ENVIRONMENT:
        os.environ.pop(name, None)
    text = render()
    if "--stdout" in (argv or []):
        sys.stdout.write(text)
    else:
        OUT.write_text(text)
        print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
