"""One policy for reading config dataclasses from plain dicts (TOML tables, JSON headers).

    CRFConfig.from_dict(table, source="/etc/topseg/cell1.toml [crf]")

`from_dict(cls, data, source)` builds the dataclass `cls` from `data`: a key that is not a
field of `cls` or a value of the wrong type is a `ConfigError` naming the key and `source`;
a field that `data` leaves out takes its default (so a file that lacks a newer field
still loads), unless the caller lists it in `required`. Nested config dataclasses are read
through their own `from_dict`, with `source` extended by the key (`source.key`). A value
that the dataclass itself rejects (its `__post_init__` raising ValueError or TopsegError)
becomes a ConfigError with the same source. Ints are accepted where a float is declared and
stored as floats; lists where a tuple is declared and stored as tuples.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

from topseg.core.errors import ConfigError, TopsegError

T = TypeVar("T")


def from_dict(
    cls: type[T], data: Any, source: str | None = None, *, required: Iterable[str] = ()
) -> T:
    """`cls(**data)` after checking every key and type; ConfigError naming key and source."""
    where = source or cls.__name__
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a table of settings, got {describe(data)}")
    hints = _hints(cls)
    init = [f.name for f in dataclasses.fields(cls) if f.init]
    for key in data:
        if key not in init:
            raise ConfigError(
                f"{where}: unknown key {key!r}{suggest(str(key), init)}; known: {', '.join(init)}"
            )
    missing = [k for k in required if k not in data]
    if missing:
        raise ConfigError(f"{where}: missing key {missing[0]!r}")
    kw = {
        key: _check(value, hints.get(key, Any), f"{where}.{key}", key, where)
        for key, value in data.items()
    }
    try:
        return cls(**kw)
    except ConfigError:
        raise
    except (TopsegError, ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The resolved annotations of a dataclass (postponed annotations evaluated)."""
    return typing.get_type_hints(cls)


def _check(value: Any, hint: Any, path: str, key: str, where: str) -> Any:
    """`value` checked against `hint` (and converted: int -> float, list -> tuple)."""
    ok, converted = _match(value, hint, path)
    if not ok:
        raise ConfigError(f"{where}: {key} must be {expected(hint)}, got {describe(value)}")
    return converted


def _match(value: Any, hint: Any, path: str) -> tuple[bool, Any]:
    """(does `value` fit `hint`, the value to store)."""
    if hint is Any or hint is object:
        return True, value
    if hint is type(None) or hint is None:
        return value is None, value
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin is typing.Union or origin is types.UnionType:
        for arm in args:
            ok, converted = _match(value, arm, path)
            if ok:
                return True, converted
        return False, value
    if origin is typing.Literal:
        return value in args and not isinstance(value, bool), value
    if hint is bool:
        return isinstance(value, bool), value
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if hint is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        return ok, float(value) if ok else value
    if hint is str:
        return isinstance(value, str), value
    if origin is tuple or hint is tuple:
        return _match_sequence(value, args, path, tuple)
    if origin is list or hint is list:
        return _match_sequence(value, (*args, ...) if args else (), path, list)
    if origin is dict or hint is dict:
        return isinstance(value, Mapping), value
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if isinstance(value, hint):
            return True, value
        if not isinstance(value, Mapping):
            return False, value
        reader = getattr(hint, "from_dict", None)
        if reader is None:
            return True, from_dict(hint, value, path)
        return True, reader(value, source=path)
    if isinstance(hint, type):
        return isinstance(value, hint), value
    return True, value  # an annotation this checker does not know: the dataclass decides


def _match_sequence(value: Any, args: tuple, path: str, kind: type) -> tuple[bool, Any]:
    """A list or tuple whose items fit `args` (fixed length, or `X, ...`)."""
    if not isinstance(value, list | tuple):
        return False, value
    if not args:
        return True, kind(value)
    if len(args) == 2 and args[1] is Ellipsis:
        item_hints = [args[0]] * len(value)
    elif len(args) != len(value):
        return False, value
    else:
        item_hints = list(args)
    items = []
    for item, item_hint in zip(value, item_hints, strict=True):
        ok, converted = _match(item, item_hint, path)
        if not ok:
            return False, value
        items.append(converted)
    return True, kind(items)


def expected(hint: Any) -> str:
    """What a value of type `hint` looks like, in words, for an error message."""
    if hint is type(None) or hint is None:
        return "null"
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin is typing.Union or origin is types.UnionType:
        return " or ".join(expected(a) for a in args)
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    simple = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    if hint in simple:
        return simple[hint]
    if origin is tuple and args and args[-1] is not Ellipsis:
        return f"a list of {len(args)} ({', '.join(expected(a) for a in args)})"
    if origin in (tuple, list) or hint in (tuple, list):
        return "a list"
    if origin is dict or hint is dict:
        return "a table"
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return "a table"
    return getattr(hint, "__name__", str(hint))


def describe(value: Any) -> str:
    """A value's kind and repr, as a config error shows it: `a string ('x')`."""
    names = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}
    names |= {list: "a list", tuple: "a list", dict: "a table", type(None): "null"}
    return f"{names.get(type(value), type(value).__name__)} ({value!r})"


def suggest(name: str, candidates: Iterable[str]) -> str:
    """` (did you mean 'x'?)` for the closest of `candidates`, or ''."""
    close = difflib.get_close_matches(name, list(candidates), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


@dataclasses.dataclass(frozen=True)
class Option:
    """How a setting (a dataclass field) appears on a command line and in a service's TOML
    table: `--<flag>` and the key `<flag>`. The command-line parser is generated from these
    (`services.cli.options`), so a setting is declared once, beside its default.

    kind     float | int | auto_int (`auto` or an int: None is auto) | share_or_off (a share
             in (0, 1] or `off`: None is off) | choice | path (a file name or `off`: None
             is off)
    lo, hi   the bounds a value must lie in (inclusive; None: unbounded)
    choices  the values of a `choice`
    """

    flag: str
    help: str
    metavar: str | None = None
    kind: str = "float"
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] = ()


def setting(default: Any = dataclasses.MISSING, *, factory: Any = None, **option: Any) -> Any:
    """A dataclass field with a default and, when `option` is given, its `Option`."""
    meta = {"option": Option(**option)} if option else {}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def options_of(cls: type) -> list[tuple[str, dataclasses.Field, Option]]:
    """(path, field, option) of every field of a (nested) settings dataclass that has an
    `Option`, in declaration order; `path` is dotted through nested settings (`crf.mode`)."""
    out = []
    for f in dataclasses.fields(cls):
        hint = _hints(cls).get(f.name)
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            out += [(f"{f.name}.{p}", g, o) for p, g, o in options_of(hint)]
        elif "option" in f.metadata:
            out.append((f.name, f, f.metadata["option"]))
    return out


def with_options(config: T, values: Mapping[str, Any]) -> T:
    """`config` (a settings dataclass) with every setting whose option is named in `values`
    (by its flag with `_` for `-`: what argparse calls its dest) set to that value, nested
    settings included; names of no setting are ignored."""
    changes = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            nested = with_options(value, values)
            if nested is not value:
                changes[f.name] = nested
        elif "option" in f.metadata:
            dest = f.metadata["option"].flag.replace("-", "_")
            if dest in values and values[dest] != value:
                changes[f.name] = values[dest]
    return dataclasses.replace(config, **changes) if changes else config
