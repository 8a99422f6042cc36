"""Argparse options: `type=` helpers that refuse a bad number up front (finite, in range,
positive), and the Segmenter's settings as options generated from `SegmenterConfig`.

`topseg`'s subcommand parsers turn the ArgumentTypeError into one line naming the option
(`cli.OneLineParser`), e.g. `topseg driver: error: argument --fps: must be in [0.1, 1000],
got 1e-300`, exit 2: never a crash or a day-long sleep later.

Every setting of the Segmenter (`SegmenterConfig`) and of training (`TrainConfig`) is declared
once, on its field (`core.config.setting`: flag, bounds, help); `add_setting_arguments` makes
the options (and so the services' TOML keys, `config_file`), `settings_from_args` reads them
back and `setting_argv` writes a configuration as the flags that give it.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from dataclasses import MISSING, replace
from typing import Any, TypeVar

from topseg.core.config import Option, options_of, with_options
from topseg.core.errors import TopsegError
from topseg.core.formats import wire
from topseg.core.segmenter_config import SegmenterConfig


def _fmt(x: float) -> str:
    """A bound as the operator typed it: 1000, not 1000.0."""
    return f"{x:g}"


def finite(lo: float = -math.inf, hi: float = math.inf) -> Callable[[str], float]:
    """A `type=` for a finite float in [lo, hi] (NaN and inf always refused)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be in [{_fmt(lo)}, {_fmt(hi)}], got {text}")
        return value

    parse.__name__ = "number"
    return parse


def int_range(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """A `type=` for an integer >= lo (and <= hi when given)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < lo or (hi is not None and value > hi):
            bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return value

    parse.__name__ = "integer"
    return parse


#: a `type=` for an integer >= 1
positive_int = int_range(1)
#: a `type=` for an integer >= 0
non_negative_int = int_range(0)


def early_exit(text: str) -> float | None:
    """A `type=` for the forest's `--early-exit`: `off` (None: every tree) or a posterior in
    (0, 1]."""
    if text == "off":
        return None
    value = finite()(text)
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1] or off, got {text}")
    return value


early_exit.__name__ = "early exit"


def path_or_off(text: str) -> str | None:
    """A `type=` for a file setting: `off` (None: none) or a file name, taken as written."""
    if text == "off":
        return None
    if not text:
        raise argparse.ArgumentTypeError("expected a file name or off, got ''")
    return text


path_or_off.__name__ = "path"


T = TypeVar("T")

#: the groups of `SegmenterConfig` a command can take as options, in order
SEGMENTER_GROUPS = ("pre", "grid", "crf", "post", "background")


def auto_int(lo: int, hi: int | None) -> Callable[[str], int | None]:
    """A `type=` for `auto` (None) or an integer in [lo, hi]."""
    number = int_range(lo, hi)

    def parse(text: str) -> int | None:
        return None if text == "auto" else number(text)

    parse.__name__ = "auto or integer"
    return parse


def _parser(option: Option) -> dict[str, Any]:
    """The `add_argument` keywords that parse and check an option of its kind."""
    lo = -math.inf if option.lo is None else option.lo
    hi = math.inf if option.hi is None else option.hi
    if option.kind == "choice":
        return {"choices": option.choices}
    if option.kind == "float":
        return {"type": finite(lo, hi)}
    int_hi = None if option.hi is None else int(option.hi)
    if option.kind == "int":
        return {"type": int_range(int(option.lo or 0), int_hi)}
    if option.kind == "auto_int":
        return {"type": auto_int(int(option.lo or 0), int_hi)}
    if option.kind == "share_or_off":
        return {"type": early_exit}
    if option.kind == "path":
        return {"type": path_or_off}
    raise ValueError(f"unknown option kind {option.kind!r}")


def _dest(option: Option) -> str:
    return option.flag.replace("-", "_")


def add_setting_arguments(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    groups: Sequence[str] | None = None,
) -> None:
    """Every setting of the settings dataclass `cls` (of its nested `groups` only, when
    given) as an option, generated from the fields' `Option`s; `settings_from_args` reads
    them back."""
    for path, f, option in options_of(cls):
        if groups is None or path.split(".")[0] in groups:
            default = f.default_factory() if f.default is MISSING else f.default
            parser.add_argument(
                f"--{option.flag}",
                dest=_dest(option),
                default=default,
                metavar=option.metavar or {"int": "N", "float": "X"}.get(option.kind),
                help=option.help,
                **_parser(option),
            )


def settings_from_args(args: argparse.Namespace, base: T) -> T:
    """`base` (a settings dataclass) with every setting `args` has an option for."""
    return with_options(base, vars(args))


def add_segmenter_arguments(
    parser: argparse.ArgumentParser, groups: Sequence[str] = SEGMENTER_GROUPS
) -> None:
    """The Segmenter's settings of `groups` as options (`--crf`, `--stride`, ...)."""
    add_setting_arguments(parser, SegmenterConfig, groups)


def segmenter_config(
    args: argparse.Namespace, base: SegmenterConfig | None = None, **fixed: Any
) -> SegmenterConfig:
    """`base` (the defaults when None) with every Segmenter option `args` has, and `fixed`
    fields (`mount`, `check_camera`) set."""
    return replace(settings_from_args(args, base or SegmenterConfig()), **fixed)


def _text(value: Any, option: Option) -> str:
    if value is None:
        return "off" if option.kind in ("share_or_off", "path") else "auto"
    return str(value)


def setting_argv(config: Any, groups: Sequence[str] | None = None) -> list[str]:
    """The command-line options that give `config`'s settings (of its nested `groups` only,
    when given): for a command started by another, such as the worker of `run_pipeline`."""
    argv = []
    for path, _, option in options_of(type(config)):
        *group, name = path.split(".")
        if groups is None or (group[:1] and group[0] in groups):
            owner = getattr(config, group[0]) if group else config
            argv += [f"--{option.flag}", _text(getattr(owner, name), option)]
    return argv


def parse_camera(text: str) -> tuple[str, str]:
    """A `--cameras` entry 'cell/camera' -> (cell, camera); TopsegError naming a bad one."""
    parts = text.split("/")
    if len(parts) != 2:
        raise TopsegError(f"--cameras entry {text!r} must be CELL/CAMERA")
    try:
        wire.camera_prefix(*parts)
    except wire.WireError as exc:
        raise TopsegError(f"--cameras entry {text!r}: {exc}") from None
    return parts[0], parts[1]
