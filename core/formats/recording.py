"""MCAP recordings of the wire: one channel per key expression, the exact message bytes.

A recording is an MCAP file (DESIGN section 4): each Zenoh key expression it saw is one
channel (topic = the key, message encoding `msgpack`, no schema), and each message's data is
the very bytes that crossed the wire; ground truth rides on its own `.../truth` channel.
Log time is when the recorder received the message.

`RecordingWriter` writes to a temporary file beside the target and renames it into place on
`close()`, so a finished recording appears whole or not at all. If the disk fills (or any
write fails) it stops, renames what it has into place and raises `RecordingError`: the
messages in complete chunks stay readable. `read_messages` reads files front to back and so
also reads such cut-short files (and ones left by a crash) up to their last complete chunk.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import tempfile
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from topseg.core.errors import TopsegError

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "msgpack"
#: Small chunks bound what a crash or a full disk can take with it (about two depth frames).
CHUNK_SIZE = 1 << 20


class RecordingError(TopsegError):
    """A recording could not be written or read."""


@dataclass(frozen=True)
class RecordedMessage:
    """One message as recorded: its key, the exact wire bytes, log and publish ns, sequence."""

    key: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int


@dataclass
class RecordingInfo:
    """What a recording holds: messages per key, time span, and whether it was cut short."""

    counts: dict[str, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    truncated: bool = False
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def keys(self) -> list[str]:
        """The key expressions seen, sorted (one channel each)."""
        return sorted(self.counts)


class RecordingWriter:
    """Write wire messages to `path` (an .mcap file), atomically.

    Use as a context manager or call `close()`; `write()` raises `RecordingError` when the
    disk is full, after saving what was written.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        metadata: dict[str, str] | None = None,
        compression: str = "zstd",
        chunk_size: int = CHUNK_SIZE,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        from topseg import __version__

        self.path = Path(path)
        if self.path.is_dir():
            raise RecordingError(f"{self.path} is a directory, not a recording file name")
        if not self.path.parent.is_dir():
            raise RecordingError(f"cannot record to {self.path}: {self.path.parent} does not exist")
        try:
            compress = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}.get(
                compression, CompressionType.NONE
            )
            fd, tmp = tempfile.mkstemp(
                dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".partial"
            )
            self._tmp = Path(tmp)
            mask = os.umask(0)
            os.umask(mask)
            os.fchmod(fd, 0o666 & ~mask)  # mkstemp's 0600 would lock other users out
            self._file = os.fdopen(fd, "wb")
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=compress)
            self._writer.start(profile="", library=f"topseg {__version__}")
            info = {"topseg_version": __version__, "created_ns": str(time.time_ns())}
            self._writer.add_metadata("topseg", {**info, **(metadata or {})})
        except OSError as exc:
            raise RecordingError(f"cannot record to {self.path}: {exc}") from exc
        self._channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self.messages = 0
        self._closed = False

    def write(
        self,
        key: str,
        data: bytes,
        log_time_ns: int | None = None,
        publish_time_ns: int | None = None,
    ) -> None:
        """Append one message on the channel for `key` (created on first use)."""
        if self._closed:
            raise RecordingError(f"recording {self.path} is already closed")
        if not isinstance(key, str) or not key:
            raise RecordingError(f"a recording key must be a non-empty string, got {key!r}")
        now = time.time_ns() if log_time_ns is None else int(log_time_ns)
        try:
            channel = self._channels.get(key)
            if channel is None:
                channel = self._writer.register_channel(key, MESSAGE_ENCODING, 0)
                self._channels[key] = channel
                self._sequence[key] = 0
            seq = self._sequence[key]
            self._writer.add_message(
                channel,
                log_time=now,
                data=bytes(data),
                publish_time=now if publish_time_ns is None else int(publish_time_ns),
                sequence=seq % 2**32,
            )
        except OSError as exc:
            self._salvage()
            raise RecordingError(
                f"writing {self.path} failed after {self.messages} messages ({exc}); "
                "what was written before is kept there and stays readable"
            ) from exc
        self._sequence[key] = seq + 1
        self.messages += 1

    def close(self) -> Path:
        """Finish the file (index and summary), flush it to disk and move it into place."""
        if self._closed:
            return self.path
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._tmp, self.path)
        except OSError as exc:
            self._salvage()
            raise RecordingError(
                f"finishing {self.path} failed ({exc}); it keeps the messages written before"
            ) from exc
        self._closed = True
        return self.path

    def discard(self) -> None:
        """Drop an unfinished recording: nothing appears at `path`."""
        if not self._closed:
            self._closed = True
            try:
                self._file.close()
            except OSError:
                pass
            self._tmp.unlink(missing_ok=True)

    def _salvage(self) -> None:
        """After a failed write: keep the bytes that reached the file, under the final name."""
        self._closed = True
        try:
            self._file.close()
        except OSError:
            pass  # the buffered tail could not be written either; the prefix on disk stays
        try:
            os.replace(self._tmp, self.path)
        except OSError:
            log.error("could not move %s to %s", self._tmp, self.path)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._closed:
            self.close()


def _stream_records(path: Path, info: RecordingInfo) -> Iterator[object]:
    """Records of an MCAP file front to back, stopping quietly where a cut-short file ends."""
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    try:
        f = open(path, "rb")
    except OSError as exc:
        raise RecordingError(f"cannot read recording {path}: {exc}") from exc
    with f:
        try:
            reader = StreamReader(f, validate_crcs=True)
            yield from reader.records
        except (McapError, struct.error, EOFError, ValueError) as exc:
            if f.tell() <= 8:
                raise RecordingError(f"{path} is not an MCAP recording ({exc})") from None
            info.truncated = True
            log.warning("%s ends early (%s): read what it holds", path, type(exc).__name__)
        except Exception as exc:  # decompression of a torn chunk fails in its library's terms
            if type(exc).__module__.split(".")[0] not in ("zstandard", "lz4", "_zstd"):
                raise
            info.truncated = True
            log.warning("%s ends in a damaged chunk (%s): read what it holds", path, exc)


def read_messages(
    path: str | os.PathLike,
    keys: Iterable[str] | None = None,
    info: RecordingInfo | None = None,
) -> Iterator[RecordedMessage]:
    """Messages of a recording in file order (= the order they were recorded).

    `keys` keeps only those channels. Pass a `RecordingInfo` to learn whether the file
    was cut short (`info.truncated`).
    """
    from mcap.records import Channel, Message, Metadata

    wanted = None if keys is None else set(keys)
    info = RecordingInfo() if info is None else info
    topics: dict[int, str] = {}
    for record in _stream_records(Path(path), info):
        if isinstance(record, Channel):
            if record.message_encoding != MESSAGE_ENCODING:
                log.warning(
                    "%s: channel %s is %s, not msgpack: skipped",
                    path,
                    record.topic,
                    record.message_encoding,
                )
                continue
            topics[record.id] = record.topic
        elif isinstance(record, Metadata):
            info.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Message):
            key = topics.get(record.channel_id)
            if key is None or (wanted is not None and key not in wanted):
                continue
            info.counts[key] = info.counts.get(key, 0) + 1
            if info.start_ns is None:
                info.start_ns = record.log_time
            info.end_ns = record.log_time
            yield RecordedMessage(
                key, bytes(record.data), record.log_time, record.publish_time, record.sequence
            )


def inspect(path: str | os.PathLike) -> RecordingInfo:
    """Read a whole recording and say what it holds."""
    info = RecordingInfo()
    for _ in read_messages(path, info=info):
        pass
    return info


def info_json(info: RecordingInfo) -> str:
    """`inspect`'s answer as indented JSON (counts per key, time span, truncated, metadata)."""
    return json.dumps(
        {
            "keys": info.counts,
            "start_ns": info.start_ns,
            "end_ns": info.end_ns,
            "truncated": info.truncated,
            "metadata": info.metadata,
        },
        indent=2,
    )
