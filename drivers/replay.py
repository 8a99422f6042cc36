"""Replay recorded depth: `replay:PATH` where PATH is

- an MCAP recording (`FILE.mcap`, or `FILE.mcap#KEY` to pick one depth channel): its depth
  channel (the first one unless named), with ground truth from the same camera's `truth`
  channel when it has one (paired by `seq`); messages that fail to decode are skipped
  and counted;
- a folder of 16-bit PNGs in millimetres, played in name order at `fps` (default 30), with
  Kinect v1 optics scaled to the image size;
- a libfreenect fakenect dump (a folder with INDEX.txt), read directly (no libfreenect).

Real time (the default) keeps the recorded spacing between frames (or 1/fps); otherwise
frames come as fast as they are consumed. `loop` starts again at the end, one frame period
later. Frames are stamped with the time they are handed on and numbered on across loops.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topseg.core.camera import KINECT_V1, Intrinsics
from topseg.core.formats import recording, wire
from topseg.core.formats.wire import DepthFrame, LabelFrame, WireError
from topseg.drivers import fakenect_dump
from topseg.drivers.base import Pacer, Source, SourceError, SourceFrame, SourceOptions

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0


@dataclass
class _Item:
    media_s: float | None  # recorded time, seconds; None when the source has no timing
    depth: np.ndarray
    intrinsics: Intrinsics
    truth: np.ndarray | None = None


class ReplaySource(Source):
    def __init__(self, path: Path, kind: str, options: SourceOptions, key: str | None = None):
        self.path = path
        self.kind = kind
        self.key = key
        self.options = options
        self.finite = not options.loop
        self.description = f"replay:{path}" + (f"#{key}" if key else "")
        self.nominal_fps = options.fps or (DEFAULT_FPS if kind == "png" else None)
        self.rejected = 0
        self._pngs: list[Path] = []
        if kind == "png":
            self._pngs = sorted(p for p in path.iterdir() if p.suffix.lower() == ".png")
        elif kind == "fakenect":
            self.intrinsics = KINECT_V1

    # -- readers

    def _items(self) -> Iterator[_Item]:
        if self.kind == "mcap":
            yield from self._mcap_items()
        elif self.kind == "png":
            yield from self._png_items()
        else:
            for f in fakenect_dump.read_dump(self.path):
                yield _Item(f.host_s, fakenect_dump.raw_to_mm(f.raw), KINECT_V1)

    def _png_items(self) -> Iterator[_Item]:
        from PIL import Image, UnidentifiedImageError

        for p in self._pngs:
            try:
                with Image.open(p) as img:
                    mode = img.mode
                    depth = np.array(img)
            except (OSError, UnidentifiedImageError) as exc:
                raise SourceError(f"cannot read {p}: {exc}") from exc
            if depth.ndim != 2 or mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise SourceError(f"{p} is a {mode} image; replay needs 16-bit grey PNGs in mm")
            if depth.dtype != np.uint16:
                if depth.min() < 0 or depth.max() > 65535:
                    raise SourceError(f"{p} holds values outside 0..65535 mm")
                depth = depth.astype(np.uint16)
            h, w = depth.shape
            k = KINECT_V1 if (w, h) == (640, 480) else KINECT_V1.scaled_to(w, h)
            yield _Item(None, depth, k)

    def _mcap_items(self) -> Iterator[_Item]:
        depth_key = self.key
        truth_key = None if depth_key is None else _truth_of(depth_key)
        held: _Item | None = None
        held_seq = -1
        truths: OrderedDict[int, np.ndarray] = OrderedDict()
        others: set[str] = set()

        def emit(item: _Item, seq: int) -> _Item:
            truth = truths.pop(seq, None)
            if truth is not None and truth.shape != item.depth.shape:
                self._reject(
                    truth_key, WireError(f"truth {truth.shape} != depth {item.depth.shape}")
                )
                truth = None
            item.truth = truth
            return item

        for msg in recording.read_messages(self.path):
            kind = msg.key.rsplit("/", 1)[-1]
            if depth_key is None and kind == "depth":
                depth_key, truth_key = msg.key, _truth_of(msg.key)
            if msg.key == depth_key:
                try:
                    frame = wire.decode_depth(msg.data)
                except WireError as exc:
                    self._reject(msg.key, exc)
                    continue
                if held is not None:
                    yield emit(held, held_seq)
                held = _Item(msg.log_time_ns / 1e9, frame.depth, frame.intrinsics)
                held_seq = frame.seq
            elif msg.key == truth_key:
                try:
                    truth = wire.decode_labels(msg.data)
                except WireError as exc:
                    self._reject(msg.key, exc)
                    continue
                truths[truth.seq] = truth.labels
                while len(truths) > 16:
                    truths.popitem(last=False)
                if held is not None and truth.seq == held_seq:
                    yield emit(held, held_seq)
                    held = None
            elif kind == "depth" and msg.key not in others:
                others.add(msg.key)
                log.info("%s: also holds %s; replaying %s only", self.path, msg.key, depth_key)
        if held is not None:
            yield emit(held, held_seq)
        if depth_key is None:
            raise SourceError(f"{self.path} holds no depth channel")

    def _reject(self, key: str, exc: Exception) -> None:
        self.rejected += 1
        log.warning("%s: skipped a bad message on %s: %s", self.path, key, exc)

    # -- playing

    def frames(self) -> Iterator[SourceFrame]:
        pacer = Pacer(self.options.realtime)
        estimate_fps = self.nominal_fps is None  # recorded timing: measure it on the first pass
        seq = 0
        offset = 0.0  # media time where this pass starts
        while True:
            first = last = None
            count = 0
            for item in self._items():
                if self.options.fps or item.media_s is None:
                    t = count / (self.options.fps or DEFAULT_FPS)
                else:
                    first = item.media_s if first is None else first
                    t = item.media_s - first
                    if estimate_fps and t > 0:
                        self.nominal_fps = count / t
                last = t
                pacer.wait(offset + t)
                stamp = time.time_ns()
                self.intrinsics = item.intrinsics
                depth = DepthFrame(item.depth, item.intrinsics, seq, stamp, "")
                truth = None if item.truth is None else LabelFrame(item.truth, seq, stamp, "")
                yield SourceFrame(depth, truth)
                seq += 1
                count += 1
            if count == 0:
                raise SourceError(f"{self.description} holds no depth frames")
            if not self.options.loop:
                return
            estimate_fps = False
            period = 1.0 / (self.nominal_fps or DEFAULT_FPS)
            offset += last + period


def _truth_of(depth_key: str) -> str:
    return depth_key.rsplit("/", 1)[0] + "/truth"


def open(arg: str | None, options: SourceOptions) -> ReplaySource:
    """`replay:PATH` -> a ReplaySource, after checking what PATH is."""
    if not arg:
        raise SourceError("replay needs a path: replay:FILE.mcap, replay:PNG-FOLDER or replay:DUMP")
    path, key = Path(arg), None
    if not path.exists() and "#" in arg:
        base, _, key = arg.rpartition("#")
        path = Path(base)
        try:
            if wire.parse_key(key).kind != "depth":
                raise WireError("not a depth key")
        except WireError:
            raise SourceError(
                f"{key!r} in {arg!r} is not a depth key (topseg/<cell>/<camera>/depth)"
            ) from None
    if not path.exists():
        raise SourceError(f"replay: {path} does not exist")
    if path.is_file():
        with path.open("rb") as f:
            magic = f.read(8)
        if magic != b"\x89MCAP0\r\n":
            raise SourceError(f"replay: {path} is not an MCAP recording")
        return ReplaySource(path, "mcap", options, key)
    if key is not None:
        raise SourceError(f"replay: a #KEY only applies to MCAP files, and {path} is a folder")
    if fakenect_dump.is_dump(path):
        return ReplaySource(path, "fakenect", options)
    if any(p.suffix.lower() == ".png" for p in path.iterdir()):
        return ReplaySource(path, "png", options)
    raise SourceError(f"replay: {path} holds no .png files and no fakenect INDEX.txt")
