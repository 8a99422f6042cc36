"""Depth sources behind one interface: replay, freenect, openni2, oak, synthetic.

`open_source(spec, options)` opens one; see `base.py` for the interface and `spec.py` for
the spec syntax.
"""

from topseg.drivers.base import (
    Reconnecting,
    Source,
    SourceError,
    SourceFrame,
    SourceOptions,
    SourceUnavailable,
)
from topseg.drivers.spec import SourceSpec, open_source, parse_spec

__all__ = [
    "Reconnecting",
    "Source",
    "SourceError",
    "SourceFrame",
    "SourceOptions",
    "SourceSpec",
    "SourceUnavailable",
    "open_source",
    "parse_spec",
]
