"""Strings from the wire or from a file, made safe to print on a terminal or in a log.

A model id, a driver's last error, a Zenoh key or a recording's channel name is whatever
its sender wrote: escape codes that recolour or clear a terminal, a carriage return or a
newline that forges a row of `topseg status` or a log line, a right-to-left override that
reverses what follows, or a megabyte of text. `printable` shows every such character as
an escape (`\\x1b`, `\\r`, `\\n`, `\\u202e`; a backslash as `\\\\`, so that what is shown
reads back unambiguously) and cuts the result to a bounded length.
"""

from __future__ import annotations

from typing import Any

#: The longest text `printable` returns by default, the cut mark included.
MAX_SHOWN = 120
#: What ends a text that was cut.
CUT_MARK = "..."
#: The usual short escapes; other non-printable characters show as \xNN, \uNNNN, \UNNNNNNNN.
_SHORT = {"\\": "\\\\", "\n": "\\n", "\r": "\\r", "\t": "\\t"}


def _escaped(ch: str) -> str:
    """One character as it is shown: itself when printable, else its Python escape."""
    if ch in _SHORT:
        return _SHORT[ch]
    if ch.isprintable():
        return ch
    code = ord(ch)
    if code < 0x100:
        return f"\\x{code:02x}"
    if code < 0x10000:
        return f"\\u{code:04x}"
    return f"\\U{code:08x}"


def printable(value: Any, limit: int = MAX_SHOWN) -> str:
    """`value` (a str, else its str()) with control characters, escape codes and other
    non-printable characters escaped, at most `limit` characters long (a cut text ends
    with '...'; an escape is never cut in two)."""
    text = value if isinstance(value, str) else str(value)
    limit = max(limit, len(CUT_MARK) + 1)
    pieces = [_escaped(ch) for ch in text[: limit + 1]]  # each shows as 1 character or more
    if sum(map(len, pieces)) <= limit:
        return "".join(pieces)
    kept, size = [], 0
    for piece in pieces:
        if size + len(piece) > limit - len(CUT_MARK):
            break
        kept.append(piece)
        size += len(piece)
    return "".join(kept) + CUT_MARK
