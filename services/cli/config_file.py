"""Option defaults from a TOML file: `topseg <command> --config FILE` (or `$TOPSEG_CONFIG`).

The file's `[<command>]` table holds that command's long options (without the dashes;
`zenoh-port` or `zenoh_port`), and a shared `[zenoh]` table holds `zenoh-config` and
`zenoh-port` for every service; the command's own table wins over `[zenoh]`, and the
command line wins over both. Flags take `true`/`false`, options with several values a list.
Tables of the other commands are ignored, so one file can serve a camera's driver and its
worker (`/etc/topseg/<instance>.toml` under systemd, see `deploy/`):

    [zenoh]
    zenoh-config = "/etc/topseg/zenoh/peer.json5"

    [driver]
    source = "freenect:0"
    cell = "cell1"
    camera = "kinect"

Bad TOML, unknown tables or keys, and values of the wrong type stop the command with one
line naming the file and line (ConfigError: exit 2). Paths are taken as written: use
absolute ones (a service runs in `/`).
"""

from __future__ import annotations

import argparse
import os
import re
import tomllib
from collections.abc import Iterable, Sequence
from typing import Any

from topseg.core.config import describe, suggest
from topseg.core.errors import ConfigError

CONFIG_ENV = "TOPSEG_CONFIG"
#: Tables any command may read, and the options they may hold.
SHARED_TABLES = {"zenoh": ("zenoh-config", "zenoh-port")}


def add_arguments(
    parser: argparse.ArgumentParser,
    command: str,
    argv: Sequence[str],
    commands: Iterable[str] = (),
) -> None:
    """Add `--config FILE` to a command's parser and apply the file's defaults, if one is named."""
    parser.add_argument(
        "--config",
        metavar="FILE",
        default=os.environ.get(CONFIG_ENV) or None,
        help=f"TOML file whose [{command}] table (and [zenoh]) gives defaults for these "
        f"options; the command line wins (default ${CONFIG_ENV})",
    )
    path = config_arg(argv) or os.environ.get(CONFIG_ENV) or None
    if path:
        apply(parser, command, path, commands)


def config_arg(argv: Sequence[str]) -> str | None:
    """The value of `--config` in a command line, if any (the last one wins)."""
    found = None
    for i, arg in enumerate(argv):
        if arg == "--":
            break
        if arg == "--config" and i + 1 < len(argv):
            found = argv[i + 1]
        elif arg.startswith("--config="):
            found = arg.split("=", 1)[1]
    return found


def load(path: str) -> tuple[dict[str, Any], str]:
    """(parsed TOML, its text); ConfigError with file:line for a missing or bad file."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except FileNotFoundError:
        raise ConfigError(f"config {path} does not exist") from None
    except OSError as exc:
        raise ConfigError(f"cannot read config {path}: {exc.strerror}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        return tomllib.loads(text), text
    except tomllib.TOMLDecodeError as exc:
        message = str(exc)
        m = re.search(r"\(at line (\d+), column (\d+)\)", message)
        if m:
            message = message[: m.start()].strip()
            raise ConfigError(f"{path}:{m[1]}:{m[2]}: bad TOML: {message}") from None
        raise ConfigError(f"{path}: bad TOML: {message}") from None


def options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """A parser's long options by name without dashes (help and --config left out)."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._VersionAction):
            continue
        for opt in action.option_strings:
            if opt.startswith("--") and opt != "--config":
                found[opt[2:]] = action
    return found


def apply(
    parser: argparse.ArgumentParser, command: str, path: str, commands: Iterable[str] = ()
) -> dict[str, Any]:
    """Set the parser's defaults from the file's tables; returns {dest: value} applied."""
    data, text = load(path)
    known = options(parser)
    others = set(commands) - {command}
    chosen: list[tuple[str, str, Any]] = []  # (table, key, value); later entries win
    for table, body in data.items():
        if not isinstance(body, dict):
            raise ConfigError(
                f"{where(path, text, None, table)}: {table!r} must be inside a table "
                f"such as [{command}]"
            )
        if table in others:
            continue
        if table in SHARED_TABLES:
            allowed = SHARED_TABLES[table]
            for key, value in body.items():
                name = key.replace("_", "-")
                if name not in allowed:
                    raise ConfigError(
                        f"{where(path, text, table, key)}: unknown key {key!r} in [{table}] "
                        f"(it takes {', '.join(allowed)})"
                    )
                if name in known:  # a command without Zenoh options ignores [zenoh]
                    chosen.insert(0, (table, key, value))
            continue
        if table != command:
            tables = sorted({command, *others, *SHARED_TABLES})
            raise ConfigError(
                f"{where(path, text, table, None)}: unknown table [{table}]"
                f"{suggest(table, tables)} (tables: {', '.join(tables)})"
            )
        chosen.extend((table, key, value) for key, value in body.items())

    applied: dict[str, Any] = {}
    for table, key, value in chosen:
        name = key.replace("_", "-")
        action = known.get(name)
        if action is None:
            raise ConfigError(
                f"{where(path, text, table, key)}: unknown option {key!r} in [{table}]"
                f"{suggest(name, known)} (see topseg {command} --help)"
            )
        try:
            applied[action.dest] = convert(action, value)
        except ValueError as exc:
            raise ConfigError(f"{where(path, text, table, key)}: {key}: {exc}") from None
        action.required = False  # the file gave it
    parser.set_defaults(**applied)
    return applied


def convert(action: argparse.Action, value: Any) -> Any:
    """A TOML value as the option's default; ValueError saying what was expected."""
    if action.nargs == 0:  # a flag: store_true, store_false, store_const
        if not isinstance(value, bool):
            raise ValueError(f"expected true or false, got {describe(value)}")
        return action.const if value else action.default
    many = action.nargs in ("+", "*") or (isinstance(action.nargs, int) and action.nargs > 1)
    if isinstance(action, argparse._AppendAction):
        many = True
    if many:
        if not isinstance(value, list):
            value = [value] if action.nargs in ("+", "*") else value
        if not isinstance(value, list):
            raise ValueError(f"expected a list, got {describe(value)}")
        if action.nargs == "+" and not value:
            raise ValueError("expected at least one value")
        return [scalar(action, v) for v in value]
    return scalar(action, value)


def scalar(action: argparse.Action, value: Any) -> Any:
    """One TOML value as the option's type (and among its choices); ValueError otherwise."""
    kind = action.type
    if isinstance(value, dict | list):
        raise ValueError(f"expected one value, got {describe(value)}")
    if isinstance(value, bool):
        raise ValueError(f"expected {expected(kind)}, got {describe(value)}")
    if kind is int:
        if not isinstance(value, int):
            raise ValueError(f"expected an integer, got {describe(value)}")
    elif kind is float:
        if not isinstance(value, int | float):
            raise ValueError(f"expected a number, got {describe(value)}")
        value = float(value)
    elif kind is None or kind is str:
        if not isinstance(value, str):
            raise ValueError(f"expected a string, got {describe(value)}")
    else:
        # a `options` number or integer: the TOML value must be one, before its range check
        numeric = getattr(kind, "__name__", "")
        if numeric == "number" and not isinstance(value, int | float):
            raise ValueError(f"expected a number, got {describe(value)}")
        if numeric == "integer" and not isinstance(value, int):
            raise ValueError(f"expected an integer, got {describe(value)}")
        try:
            value = kind(value if isinstance(value, str) else str(value))
        except argparse.ArgumentTypeError as exc:  # a `options` check: its own words
            raise ValueError(str(exc)) from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"invalid value {value!r} ({exc})") from None
    if action.choices is not None and value not in action.choices:
        choices = ", ".join(repr(c) for c in action.choices)
        raise ValueError(f"{value!r} is not one of {choices}")
    return value


def expected(kind) -> str:
    """An option type in words, for an error message."""
    return {int: "an integer", float: "a number"}.get(kind, "a string")


def where(path: str, text: str, table: str | None, key: str | None) -> str:
    """'FILE:LINE' of a table header or of a key inside it (best effort), else 'FILE'."""
    current = None
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        header = re.fullmatch(r"\[\s*([^\[\]]+?)\s*\]\s*(#.*)?", stripped)
        if header:
            current = header[1].strip("\"'")
            if key is None and current == table:
                return f"{path}:{number}"
            continue
        if key is not None and current == table:
            m = re.match(r"""["']?([^"'=\s]+)["']?\s*=""", stripped)
            if m and m[1] == key:
                return f"{path}:{number}"
    return path
