"""Source specs (`replay:PATH`, `freenect[:index]`, `openni2[:uri]`, `oak[:device-id]`,
`synthetic[:...]`): parse one and open the source it names.

A spec is `kind[:arg]`; the kind picks a driver module (lazily imported, so a machine
without depthai can still replay) and the argument is that driver's to interpret.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from topseg.drivers.base import Source, SourceError, SourceOptions

#: kind -> driver module; each has `open(arg: str | None, options: SourceOptions) -> Source`
DRIVERS: dict[str, str] = {
    "replay": "topseg.drivers.replay",
    "freenect": "topseg.drivers.freenect",
    "openni2": "topseg.drivers.openni2",
    "oak": "topseg.drivers.oak",
    "synthetic": "topseg.drivers.synthetic",
    "faulty": "topseg.drivers.faulty",  # a test aid: faulty:fail_after=N,...@INNER-SPEC
}
USAGE = "replay:PATH, freenect[:index], openni2[:uri], oak[:device-id] or synthetic"


@dataclass(frozen=True)
class SourceSpec:
    """A parsed `kind[:arg]`: the driver kind (a key of DRIVERS) and its argument, or None."""

    kind: str
    arg: str | None = None

    def __str__(self) -> str:
        return self.kind if self.arg is None else f"{self.kind}:{self.arg}"


def parse_spec(text: str) -> SourceSpec:
    """'kind[:arg]' -> SourceSpec; SourceError naming the problem and the valid forms."""
    if not isinstance(text, str) or not text.strip():
        raise SourceError(f"empty source spec; use {USAGE}")
    kind, sep, arg = text.strip().partition(":")
    kind = kind.lower()
    if kind not in DRIVERS:
        raise SourceError(f"unknown source kind {kind!r} in {text!r}; use {USAGE}")
    if sep and not arg:
        raise SourceError(f"source spec {text!r} has nothing after ':'")
    if kind == "replay" and not arg:
        raise SourceError("replay needs a path: replay:FILE.mcap, replay:PNG-FOLDER or replay:DUMP")
    return SourceSpec(kind, arg or None)


def open_source(spec: str | SourceSpec, options: SourceOptions | None = None) -> Source:
    """Open the source a spec names (use it as a context manager)."""
    spec = parse_spec(spec) if isinstance(spec, str) else spec
    try:
        module = importlib.import_module(DRIVERS[spec.kind])
    except ImportError as exc:
        raise SourceError(f"the {spec.kind} driver cannot be loaded here: {exc}") from exc
    return module.open(spec.arg, options or SourceOptions())
