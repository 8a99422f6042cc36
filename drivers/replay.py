"""Replay recorded depth: `replay:PATH` where PATH is

- an MCAP recording (`FILE.mcap`, or `FILE.mcap#KEY` to pick one depth channel), ROS 2 or
  msgpack (`core/formats/recording.py` reads both): its depth channel (the first one unless
  named), with ground truth from the same camera's `truth` channel when it has one (paired
  by `seq`), and its companion messages: joint states (`topseg/<cell>/robot/<name>/joints`)
  and safety truth (`topseg/<cell>/safety/separation`, `core/formats/cell_truth.py`), each
  handed on with the depth frame it follows in the file (one read before the first depth
  frame, with the first), its stamp as far from the frame's as recorded; messages that
  fail to decode are skipped and counted;
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
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from topseg.core.camera import KINECT_V1, Intrinsics, TopViewMount
from topseg.core.formats import cell_truth, recording, wire
from topseg.core.formats.wire import MAX_SIDE, DepthFrame, LabelFrame, WireError
from topseg.drivers import fakenect_dump
from topseg.drivers.base import Pacer, Source, SourceError, SourceFrame, SourceOptions

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0
#: companion messages held per frame (memory bound: a robot's joint states at 1 kHz with
#: frames at 10 fps are 100)
MAX_COMPANIONS = 256


@dataclass(frozen=True)
class Companion:
    """A recorded message handed on with a depth frame: its key, its bytes, and how far
    (ns) its stamp lies from the frame's recorded stamp."""

    key: str
    data: bytes
    offset_ns: int


#: PIL modes of a 16-bit single-channel image.
DEPTH_PNG_MODES = ("I;16", "I;16B", "I;16L", "I")


@dataclass
class ReplayFrame:
    """One recorded frame: a name for the files made from it, depth (uint16 mm), the camera
    when the file says it (None for a PNG), the recorded time in seconds (None without
    timing), the truth labels when recorded, the recorded `seq` (None for a PNG), the
    camera's mount when the recorded message carried one (None otherwise) and the recorded
    depth key (None for a PNG)."""

    name: str
    depth: np.ndarray
    intrinsics: Intrinsics | None
    media_s: float | None = None
    truth: np.ndarray | None = None
    seq: int | None = None
    mount: TopViewMount | None = None
    key: str | None = None
    stamp_ns: int | None = None
    companions: list[Companion] = field(default_factory=list)


# -- readers: the one place recorded depth is read and validated (the replay driver and
#    `topseg segment` both read through them)


def read_depth_png(path: Path) -> np.ndarray:
    """A 16-bit single-channel PNG as uint16 mm; a SourceError naming the file otherwise."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            if max(img.size) > MAX_SIDE:  # before load(): a lying header must not allocate
                raise SourceError(f"{path}: a {img.width}x{img.height} image is no depth frame")
            img.load()
            if img.mode not in DEPTH_PNG_MODES:
                raise SourceError(
                    f"{path}: a depth PNG must be 16-bit greyscale (mm), this one is {img.mode}"
                )
            depth = np.asarray(img)
    except (
        UnidentifiedImageError,
        OSError,
        SyntaxError,
        ValueError,
        Image.DecompressionBombError,
    ) as exc:
        raise SourceError(f"{path}: not a readable PNG ({exc})") from None
    if depth.ndim != 2 or depth.size == 0 or depth.min() < 0 or depth.max() > 65535:
        raise SourceError(f"{path}: depth must be one channel of 0..65535 mm")
    return depth.astype(np.uint16)


def png_files(folder: Path) -> list[Path]:
    """The PNGs of a folder in name order (the order they are replayed and segmented)."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() == ".png")


def png_intrinsics(width: int, height: int) -> Intrinsics:
    """The optics assumed for a PNG, which does not say: Kinect v1 scaled to its size."""
    return KINECT_V1 if (width, height) == (640, 480) else KINECT_V1.scaled_to(width, height)


def png_frames(paths: list[Path]) -> Iterator[ReplayFrame]:
    """Frames of 16-bit PNGs (named by file stem, no intrinsics, no timing)."""
    for p in paths:
        yield ReplayFrame(p.stem, read_depth_png(p), None)


#: cameras whose truth a recording may hold before its first depth frame (memory bound)
MAX_EARLY_CAMERAS = 16
#: truth frames held per camera until their depth frame comes (memory bound)
MAX_TRUTHS_HELD = 16
#: depth frames of a channel with truth held until their truth comes: a recorder receives
#: the two keys in no set order, and on a loaded machine a truth can come after the next
#: depth frame or two (memory bound: 8 VGA frames are 5 MB)
MAX_FRAMES_AWAITING_TRUTH = 8


class RecordingFrames:
    """The frames of one depth channel of an MCAP recording (the first one unless `key`
    names it), with the same camera's truth paired by `seq` when it has one.

    Messages that do not decode are skipped, logged and counted in `rejected`; other
    cameras' depth channels seen are in `others` (channels whose key no camera could have,
    `wire.depth_key_problem`, are never read). Frames are named `STEM_SEQ` (seq 6 digits), or
    `STEM_TAG_SEQ` with a `tag` (the camera, when a recording holds several); a seq seen
    before in this channel (a driver restarted within the recording) gets `-N` for its Nth
    occurrence, so no two frames share a name. Iterating again reads the file again.

    With `companions`, the joint states and safety truth the file holds come with the frame
    they follow (`ReplayFrame.companions`); a frame is then handed on once the next depth
    frame (or the end) is read, so that all of its companions are there.
    """

    def __init__(
        self, path: Path, key: str | None = None, tag: str | None = None, companions: bool = False
    ) -> None:
        self.path = path
        self.key = key
        self.tag = tag
        self.companions = companions
        self.depth_key: str | None = key
        self.rejected = 0
        self.dropped_companions = 0
        self.others: set[str] = set()
        self._bad: set[str] = set()  # depth channels whose key no camera could have

    def __iter__(self) -> Iterator[ReplayFrame]:
        depth_key = self.key
        truth_key = None if depth_key is None else _truth_of(depth_key)
        pending: deque[ReplayFrame] = deque()  # in depth order, awaiting their truth
        truths: OrderedDict[int, np.ndarray] = OrderedDict()
        early: dict[str, OrderedDict[int, np.ndarray]] = {}  # truths before any depth
        seen: dict[int, int] = {}  # seq -> how often it came (a restart repeats seqs)
        has_truth = False  # whether this channel's camera has sent any truth
        stem = self.path.stem if self.tag is None else f"{self.path.stem}_{self.tag}"

        def pair(item: ReplayFrame) -> None:
            truth = truths.pop(item.seq, None)
            if truth is not None and truth.shape != item.depth.shape:
                self._reject(
                    truth_key, WireError(f"truth {truth.shape} != depth {item.depth.shape}")
                )
                truth = None
            item.truth = truth

        def ready() -> Iterator[ReplayFrame]:
            """The frames that wait no longer: those at the front with their truth, and
            the oldest beyond the window (one frame until the channel shows any truth);
            with companions, never the newest (its companions may follow)."""
            window = MAX_FRAMES_AWAITING_TRUTH if has_truth else 1
            keep = 1 if self.companions else 0
            while len(pending) > keep and (pending[0].truth is not None or len(pending) > window):
                yield pending.popleft()

        early_companions: list[Companion] = []  # before the first depth frame
        info = recording.RecordingInfo()  # counts the ROS 2 messages that do not decode
        counted = 0
        for msg in recording.read_messages(self.path, info=info):
            self.rejected += info.rejected - counted
            counted = info.rejected
            if self.companions and cell_truth.companion_kind(msg.key) is not None:
                self._keep_companion(pending[-1] if pending else None, early_companions, msg)
                continue
            kind = msg.key.rsplit("/", 1)[-1]
            if depth_key is None and kind == "depth" and wire.depth_key_problem(msg.key):
                self._other(msg.key, depth_key)  # no camera's key: never read
                continue
            if depth_key is None and kind == "depth":
                depth_key, truth_key = msg.key, _truth_of(msg.key)
                self.depth_key = depth_key
                truths = early.pop(truth_key, truths)
                has_truth = bool(truths)
                early.clear()
            if depth_key is None and kind == "truth":
                # a truth written before the first depth frame (Zenoh does not order the
                # keys): kept by camera until the channel to read is known
                self._keep_truth(early.setdefault(msg.key, OrderedDict()), msg)
                while len(early) > MAX_EARLY_CAMERAS:
                    early.pop(next(iter(early)))
                continue
            if msg.key == depth_key:
                try:
                    frame = wire.decode_depth(msg.data)
                except WireError as exc:
                    self._reject(msg.key, exc)
                    continue
                n = seen[frame.seq] = seen.get(frame.seq, 0) + 1
                name = f"{stem}_{frame.seq:06d}" + (f"-{n}" if n > 1 else "")
                item = ReplayFrame(
                    name,
                    frame.depth,
                    frame.intrinsics,
                    msg.log_time_ns / 1e9,
                    seq=frame.seq,
                    mount=frame.mount,
                    key=depth_key,
                    stamp_ns=frame.stamp_ns,
                )
                for c in early_companions:  # their offsets were kept as stamps
                    item.companions.append(Companion(c.key, c.data, c.offset_ns - frame.stamp_ns))
                early_companions.clear()
                pair(item)  # its truth may have come first
                pending.append(item)
                yield from ready()
            elif msg.key == truth_key:
                seq = self._keep_truth(truths, msg)
                has_truth = has_truth or seq is not None
                waiting = next((f for f in pending if f.seq == seq and f.truth is None), None)
                if waiting is not None:
                    pair(waiting)
                yield from ready()
            elif kind == "depth":
                self._other(msg.key, depth_key)
        self.rejected += info.rejected - counted
        while pending:
            yield pending.popleft()
        if depth_key is None:
            raise SourceError(f"{self.path} holds no depth channel")

    def _keep_companion(self, frame: ReplayFrame | None, early: list[Companion], msg) -> None:
        """Attach a companion message to `frame` (the newest depth frame read), or keep it
        in `early` (by its stamp) before the first; at most MAX_COMPANIONS a frame, the
        rest dropped and counted; one that does not decode is rejected."""
        try:
            stamp = cell_truth.stamp_of(msg.data)
        except WireError as exc:
            self._reject(msg.key, exc)
            return
        held = early if frame is None else frame.companions
        if len(held) >= MAX_COMPANIONS:
            self.dropped_companions += 1
            return
        offset = stamp if frame is None else stamp - (frame.stamp_ns or 0)
        held.append(Companion(msg.key, bytes(msg.data), offset))

    def _keep_truth(self, truths: OrderedDict[int, np.ndarray], msg) -> int | None:
        """Decode truth message `msg` into `truths` (seq -> labels, the newest
        MAX_TRUTHS_HELD kept): its seq, or None when it does not decode (rejected)."""
        try:
            truth = wire.decode_labels(msg.data)
        except WireError as exc:
            self._reject(msg.key, exc)
            return None
        truths[truth.seq] = truth.labels
        while len(truths) > MAX_TRUTHS_HELD:
            truths.popitem(last=False)
        return truth.seq

    def _other(self, key: str, reading: str | None) -> None:
        """Note (once) a depth channel this reader does not read: a camera's in `others`; one
        whose key no camera could have is logged, escaped, by a reader that picks its
        channel itself (a replay; `input_frames` says so for a reader given its key)."""
        problem = wire.depth_key_problem(key)
        if problem is not None:
            if self.key is None and key not in self._bad and len(self._bad) < MAX_EARLY_CAMERAS:
                self._bad.add(key)
                log.warning("%s: a depth channel not read: %s", self.path, problem)
            return
        if key in self.others or len(self.others) >= MAX_EARLY_CAMERAS:
            return
        self.others.add(key)
        log.info("%s: also holds %s; reading %s only", self.path, key, reading)

    def _reject(self, key: str | None, exc: Exception) -> None:
        self.rejected += 1
        log.warning("%s: skipped a damaged message on %s: %s", self.path, wire.shown_key(key), exc)


def _truth_of(depth_key: str) -> str:
    return depth_key.rsplit("/", 1)[0] + "/truth"


def depth_channels(path: Path) -> dict[str, int]:
    """{depth key: messages on it} of a recording, in the order the channels first appear."""
    counts: dict[str, int] = {}
    for msg in recording.read_messages(path):
        if msg.key.rsplit("/", 1)[-1] == "depth":
            counts[msg.key] = counts.get(msg.key, 0) + 1
    return counts


def camera_channels(channels: dict[str, int]) -> tuple[dict[str, int], dict[str, str]]:
    """`depth_channels` split into the channels of cameras (keys a live camera could publish
    on: `wire.depth_key_problem`, the checks keys on the wire get) and the others, {key:
    why, in one line with the key escaped}: those are not read."""
    good: dict[str, int] = {}
    bad: dict[str, str] = {}
    for key, count in channels.items():
        problem = wire.depth_key_problem(key)
        if problem is None:
            good[key] = count
        else:
            bad[key] = problem
    return good, bad


def camera_tag(depth_key: str) -> str:
    """`topseg/<cell>/<camera>/depth` -> `<cell>-<camera>` (for file names)."""
    parts = depth_key.split("/")
    return "-".join(parts[1:-1]) if len(parts) >= 4 else depth_key.replace("/", "-")


def input_frames(
    path: Path,
    on_recording: Callable[[RecordingFrames], None] | None = None,
    on_bad_channel: Callable[[Path, str], None] | None = None,
) -> Iterator[ReplayFrame]:
    """Every frame a file or folder holds, named for output files: a 16-bit PNG, a folder of
    them, or an MCAP recording (every camera's depth channel in turn; with more than one,
    names carry `<cell>-<camera>`). SourceError when `path` is none of these or holds no
    frame. `on_recording` is handed the reader of each channel once it has been read (to
    report what it skipped); a channel whose key no camera could have (`camera_channels`) is
    not read, and `on_bad_channel` is handed the file and why (else it is logged)."""
    if path.is_dir():
        pngs = png_files(path)
        if not pngs:
            raise SourceError(f"{path}: no .png files in this folder")
        yield from png_frames(pngs)
    elif path.suffix.lower() == ".png":
        yield from png_frames([path])
    elif path.suffix.lower() == ".mcap":
        channels, bad = camera_channels(depth_channels(path))
        for why in bad.values():
            if on_bad_channel is not None:
                on_bad_channel(path, why)
            else:
                log.warning("%s: a depth channel not read: %s", path, why)
        if not channels and not bad:
            raise SourceError(f"{path} holds no depth channel")
        count = 0
        for key in channels:
            reader = RecordingFrames(path, key, camera_tag(key) if len(channels) > 1 else None)
            for frame in reader:
                count += 1
                yield frame
            if on_recording is not None:
                on_recording(reader)
        if not count and channels:
            raise SourceError(f"{path}: no readable depth frame in this recording")
    elif not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    else:
        raise SourceError(f"{path}: expected a .png, a folder of PNGs or an .mcap recording")


class ReplaySource(Source):
    """A recording, PNG folder or fakenect dump played as a depth source (see the module)."""

    def __init__(self, path: Path, kind: str, options: SourceOptions, key: str | None = None):
        self.path = path
        self.kind = kind
        self.key = key
        self.options = options
        self.finite = not options.loop
        self.description = f"replay:{path}" + (f"#{key}" if key else "")
        self.nominal_fps = options.fps or (DEFAULT_FPS if kind == "png" else None)
        self._rejected_before = 0  # by the readers of earlier passes
        self._reader: RecordingFrames | None = None
        self._pngs: list[Path] = []
        if kind == "png":
            self._pngs = png_files(path)
        elif kind == "fakenect":
            self.intrinsics = KINECT_V1

    @property
    def rejected(self) -> int:
        """Messages skipped because they did not decode, over every pass so far."""
        return self._rejected_before + (self._reader.rejected if self._reader else 0)

    def _items(self) -> Iterator[ReplayFrame]:
        if self.kind == "mcap":
            if self._reader is not None:
                self._rejected_before += self._reader.rejected
            self._reader = RecordingFrames(self.path, self.key, companions=True)
            yield from self._reader
        elif self.kind == "png":
            for item in png_frames(self._pngs):
                h, w = item.depth.shape
                item.intrinsics = png_intrinsics(w, h)
                yield item
        else:
            for i, f in enumerate(fakenect_dump.read_dump(self.path)):
                yield ReplayFrame(str(i), fakenect_dump.raw_to_mm(f.raw), KINECT_V1, f.host_s)

    # -- playing

    def frames(self) -> Iterator[SourceFrame]:
        """The frames paced as recorded (or at `fps`), restamped and numbered on, looping
        when asked; SourceError when a pass holds no frame."""
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
                self.intrinsics, self.mount = item.intrinsics, item.mount
                depth = DepthFrame(item.depth, item.intrinsics, seq, stamp, "", item.mount)
                truth = None if item.truth is None else LabelFrame(item.truth, seq, stamp, "")
                yield SourceFrame(depth, truth, tuple(item.companions))
                seq += 1
                count += 1
            if count == 0:
                raise SourceError(f"{self.description} holds no depth frames")
            if not self.options.loop:
                return
            estimate_fps = False
            period = 1.0 / (self.nominal_fps or DEFAULT_FPS)
            offset += last + period


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
