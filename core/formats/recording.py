"""MCAP recordings: the file, its atomic writing, and reading both forms of recording.

A recording is an MCAP file (DESIGN section 4) in one of two forms:
- ROS 2 (what `topseg record` writes by default, `ros2_recording.py`): profile `ros2`,
  CDR messages on ROS 2 topics, readable by ROS 2 tools;
- msgpack (`RecordingWriter.write`, `topseg record --format msgpack`): each Zenoh key
  expression is one channel (topic = the key, message encoding `msgpack`, no schema), and
  each message's data is the very bytes that crossed the wire.
Either way ground truth rides on its own `truth` channel and log time is when the
recorder received the message. `read_messages` yields wire messages from both forms (it
rebuilds them from ROS 2 messages), so no reader has to care which form it reads.

`RecordingWriter` writes to a temporary file beside the target and renames it into place on
`close()`, so a finished recording appears whole or not at all. If the disk fills (or any
write fails) it stops, renames what it has into place and raises `RecordingError`: the
messages in complete chunks stay readable. `read_messages` reads files front to back and so
also reads such cut-short files (and ones left by a crash) up to their last complete chunk.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import struct
import tempfile
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from topseg import __version__
from topseg.core.errors import TopsegError
from topseg.core.formats.wire import WireError, shown_key

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
    """What a recording holds: wire messages per key, time span, whether it was cut short."""

    counts: dict[str, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    truncated: bool = False
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    #: ROS 2 messages skipped because they did not decode (msgpack ones are the reader's)
    rejected: int = 0
    #: the MCAP header's profile: "ros2" for ROS 2 recordings, "" for msgpack ones
    profile: str = ""

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
        profile: str = "",
    ) -> None:
        from mcap.writer import CompressionType, Writer

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
            self._writer.start(profile=profile, library=f"topseg {__version__}")
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
        """Append one message on the msgpack channel for `key` (created on first use)."""
        if not isinstance(key, str) or not key:
            raise RecordingError(f"a recording key must be a non-empty string, got {key!r}")
        channel = self._channels.get(key)
        if channel is None:
            channel = self._channels[key] = self.add_channel(key, MESSAGE_ENCODING)
            self._sequence[key] = 0
        seq = self._sequence[key]
        self.write_to(channel, data, log_time_ns, publish_time_ns, seq)
        self._sequence[key] = seq + 1

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Register a schema record; its id for `add_channel`."""
        with self._guard():
            return self._writer.register_schema(name, encoding, data)

    def add_channel(
        self,
        topic: str,
        message_encoding: str,
        schema_id: int = 0,
        metadata: dict[str, str] | None = None,
    ) -> int:
        """Register a channel (schema 0: none); its id for `write_to`."""
        with self._guard():
            return self._writer.register_channel(topic, message_encoding, schema_id, metadata or {})

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (string keys and values) to the file."""
        with self._guard():
            self._writer.add_metadata(name, data)

    def write_to(
        self,
        channel: int,
        data: bytes,
        log_time_ns: int | None = None,
        publish_time_ns: int | None = None,
        sequence: int = 0,
    ) -> None:
        """Append one message to a channel of `add_channel`; log time defaults to now,
        publish time to the log time, `sequence` is kept modulo 2**32."""
        now = time.time_ns() if log_time_ns is None else int(log_time_ns)
        with self._guard():
            self._writer.add_message(
                channel,
                log_time=now,
                data=bytes(data),
                publish_time=now if publish_time_ns is None else int(publish_time_ns),
                sequence=int(sequence) % 2**32,
            )
        self.messages += 1

    def check_in_place(self) -> None:
        """RecordingError when the file being written is gone (its folder, or the temporary
        file itself, was deleted): what was recorded into it is lost, and saying so beats
        claiming it was kept."""
        if self._closed:
            return
        try:
            gone = os.fstat(self._file.fileno()).st_nlink == 0
        except OSError:
            gone = True
        if gone:
            self.discard()
            raise RecordingError(
                f"{self.path.parent} (or the recording's temporary file in it) was deleted while "
                f"recording {self.path.name}: the {self.messages} messages recorded are lost"
            )

    @contextlib.contextmanager
    def _guard(self) -> Iterator[None]:
        """Refuse writes after close; on a failed write keep what reached the disk."""
        if self._closed:
            raise RecordingError(f"recording {self.path} is already closed")
        try:
            yield
        except OSError as exc:
            self.check_in_place()  # a deleted folder: nothing was kept, say so
            self._salvage()
            raise RecordingError(
                f"writing {self.path} failed after {self.messages} messages ({exc}); "
                "what was written before is kept there and stays readable"
            ) from exc

    def close(self) -> Path:
        """Finish the file (index and summary), flush it to disk and move it into place."""
        if self._closed:
            return self.path
        self.check_in_place()
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
    """Wire messages of a recording in file order (= the order they were recorded).

    Reads both forms: msgpack channels give their bytes as recorded; ROS 2 (`cdr`) channels
    give wire messages rebuilt from them (`ros2_recording.Ros2Channels`), and the ones that
    do not decode are skipped and counted in `info.rejected`. `keys` keeps only those
    channels. Pass a `RecordingInfo` to learn whether the file was cut short
    (`info.truncated`), its profile and metadata.
    """
    from mcap.records import Channel, Header, Message, Metadata, Schema

    wanted = None if keys is None else set(keys)
    info = RecordingInfo() if info is None else info
    topics: dict[int, str] = {}
    schemas: dict[int, str] = {}
    ros = None
    for record in _stream_records(Path(path), info):
        if isinstance(record, Message):
            key = topics.get(record.channel_id)
            data = record.data
            if key is None:
                if ros is None or record.channel_id not in ros:
                    continue
                key = ros.key(record.channel_id)
                if key is not None and wanted is not None and key not in wanted:
                    continue
                try:
                    data = ros.message(record.channel_id, record.data, record.sequence)
                except WireError as exc:
                    info.rejected += 1
                    log.warning(
                        "%s: skipped a damaged message on %s: %s", path, shown_key(key), exc
                    )
                    continue
            if key is None or data is None or (wanted is not None and key not in wanted):
                continue
            info.counts[key] = info.counts.get(key, 0) + 1
            if info.start_ns is None:
                info.start_ns = record.log_time
            info.end_ns = record.log_time
            yield RecordedMessage(
                key, bytes(data), record.log_time, record.publish_time, record.sequence
            )
        elif isinstance(record, Channel):
            if record.message_encoding == MESSAGE_ENCODING:
                topics[record.id] = record.topic
            elif record.message_encoding == "cdr":
                if ros is None:
                    from topseg.core.formats.ros2_recording import Ros2Channels

                    ros = Ros2Channels(path)
                ros.add(record.id, record.topic, schemas.get(record.schema_id))
            else:
                log.warning(
                    "%s: channel %s is %s, neither msgpack nor cdr: skipped",
                    path,
                    record.topic,
                    record.message_encoding,
                )
        elif isinstance(record, Schema):
            schemas[record.id] = record.name
        elif isinstance(record, Metadata):
            info.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Header):
            info.profile = record.profile


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
            "rejected": info.rejected,
            "profile": info.profile,
            "metadata": info.metadata,
        },
        indent=2,
    )
