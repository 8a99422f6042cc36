"""Label depth offline: 16-bit PNGs (mm), folders of them or MCAP recordings in; for each
frame NAME, `NAME_labels.png` (label ids, 255 = no depth) and `NAME_overlay.png` out. Each
frame is labelled through its camera's mount: `--mount FILE`, else the one a recording
carries, else one estimated from the frames and printed. A damaged input is skipped with one
line (exit 2); Ctrl-C stops after the frame at hand (exit 130).

For each input frame NAME it writes `NAME_labels.png` (8-bit label ids, 255 = no depth) and
`NAME_overlay.png` (depth in grey with the label colours blended on top), both or neither
(temporaries, then renames). NAME is the PNG's stem (`<folder>-<stem>` when stems collide
among the inputs) or `<recording stem>_<seq>` for each depth channel of a recording
(`<stem>_<cell>-<camera>_<seq>` when it holds several cameras; `-N` on a seq seen again, as
after a driver restart). An output name already written in this run is refused with one line.
A write that fails stops the run: one line naming the path, how many frames were written,
exit 2. Ctrl-C (or SIGTERM) finishes the frame at hand and stops there: the summary and one
line saying how many frames were written, exit 130. The end prints how many frames of each
camera went where.

A model that reads heights above the floor (every model trained since mounts were drawn)
labels each frame through its camera's mount: `--mount FILE` (from `topseg calibrate`) when
given, else the mount a recording's messages carry, else one estimated from the input's own
frames (up to `ESTIMATE_FRAMES` spread over each camera: a folder of PNGs is one, and so is
each depth channel of a recording) and printed. PNGs say no intrinsics: the mount file's are used, else
those of the supported sensor of that frame size. A depth model (one that reads raw depth)
takes only frames of its own camera (size and focal length) and needs no mount.

A damaged input (an unreadable or non-16-bit PNG, a frame of another camera, a file that is
not a recording, frames whose floor cannot be found, a recording channel whose key no camera
could have: the checks keys on the wire get) is skipped with one line on stderr and the
others are still segmented; the exit status is then 2. A mount not estimated from the
frames (`--mount`, or the one a recording carries) is checked against each camera's first
frame with depth enough to tell (`core.calibration.check_floor`): one that disagrees (its
floor is not where the depth shows it) labels none of that camera's frames, says so in one
line and the exit status is 2: calibrate again, or `--estimate-mount` (or no `--mount`)
estimates the mount from the frames instead. Readings of 65535 ("no reading") are no depth. A recording cut short or with
damaged messages gives what it holds. The end prints the share of pixels the floor gate sent
to background without the forest, and how many head and furniture blobs were too small to
be what they were labelled (`--min-head-cm2`, `--min-furniture-cm2`, `--min-plant-cm2`) and how many head blobs
lay beside a larger head (`--satellite-head-cm2`), and took their border's label.

`--background FILE` (from `topseg calibrate --background`) gates the static cell's recorded
background: pixels within its noise go to background without the forest. The end then says
how many pixels matched it and how many frames read more than `--background-mismatch` of it
farther than recorded (a fixture or the camera moved since it was recorded: record it
again). Frames of another camera than the background's are skipped with one line (exit 2).
"""

from __future__ import annotations

import argparse
import io
import logging
import sys
import threading
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

from topseg.core.atomic import atomic_write, atomic_write_all
from topseg.core.bundled_model import MODEL_HELP
from topseg.core.calibration import check_floor, estimate_mount
from topseg.core.camera import range_text, without_no_reading
from topseg.core.denoise import smoothing_text
from topseg.core.errors import TopsegError
from topseg.core.fattening import thinning_text
from topseg.core.labels import BACKGROUND, NO_DEPTH, colorize
from topseg.core.segmenter import Segmenter
from topseg.core.sensors import NAMES, get_sensor, sensor_of_frames
from topseg.drivers.replay import (
    RecordingFrames,
    camera_channels,
    depth_channels,
    input_frames,
    png_files,
    read_depth_png,
)
from topseg.services.cli.options import (
    add_segmenter_arguments,
    segmenter_config,
)
from topseg.services.runtime.lifecycle import stop_between_steps

log = logging.getLogger("topseg.segment")

#: frames (at most) a mount is estimated from, spread over an input
ESTIMATE_FRAMES = 30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Inputs, --model (default: the bundled model), --out, --crf and --smoothness."""
    parser.add_argument(
        "inputs", nargs="+", type=Path, metavar="INPUT", help="PNG files, folders of PNGs, .mcap"
    )
    parser.add_argument("--model", type=Path, default=None, help=MODEL_HELP)
    parser.add_argument(
        "--out", required=True, type=Path, help="folder for the label PNGs and overlays"
    )
    add_segmenter_arguments(parser)
    mounts = parser.add_mutually_exclusive_group()
    mounts.add_argument(
        "--mount",
        type=Path,
        default=None,
        help="mount file from `topseg calibrate` (default: the frames' own, else estimated "
        "from each input's frames); checked against each camera's frames",
    )
    mounts.add_argument(
        "--estimate-mount",
        action="store_true",
        help="estimate each camera's mount from its frames even when a recording carries "
        "one (for a recording whose mount disagrees with its frames)",
    )
    parser.add_argument(
        "--sensor",
        choices=NAMES,
        default=None,
        help="with no --mount: the sensor the frames come from, whose noise model the "
        "estimated mount takes and, for PNGs (which say no optics), whose optics (default: "
        "the supported sensor of the frames' size, kinect_v1 for 640x480)",
    )


def overlay(depth, labels):
    """Depth in grey (near = bright) with label colours blended on the foreground."""
    valid = depth > 0
    grey = np.zeros(depth.shape, np.float32)
    if valid.any():
        lo, hi = np.percentile(depth[valid], [1, 99])
        grey = np.clip((hi - depth.astype(np.float32)) / max(hi - lo, 1.0), 0, 1)
    base = np.repeat((grey * 200 + 30)[..., None], 3, axis=2)
    colours = colorize(labels).astype(np.float32)
    fg = ((labels != BACKGROUND) & (labels != NO_DEPTH))[..., None]
    out = np.where(fg, 0.35 * base + 0.65 * colours, base)
    out[~valid] = 0
    return out.astype(np.uint8)


def save_png(path: Path, array) -> None:
    """Atomic PNG write."""
    from PIL import Image

    with atomic_write(path) as f:
        Image.fromarray(array).save(f, format="PNG")


def run(args: argparse.Namespace) -> int:
    """Segment every input; a damaged one is skipped with one line, and exit 2 at the end."""
    segmenter = Segmenter.from_file(args.model, segmenter_config(args))
    given = None
    if args.mount is not None and segmenter.reads_height:
        from topseg.core.calibration import read_mount_file
        from topseg.services.live.worker_mount import mount_text

        given = read_mount_file(args.mount)
        print(f"mount from {args.mount}: {mount_text(given)}")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TopsegError(f"cannot create {args.out}: {exc.strerror}") from None
    inputs = [(arg, _expand(arg)) for arg in args.inputs]
    all_sources = [s for _, sources in inputs for s in sources]
    run_ = _Run(segmenter, args.out, given, _png_names(all_sources), _count_frames(all_sources))
    run_.estimate_all = getattr(args, "estimate_mount", False)
    run_.given_path = args.mount
    skipped = 0
    try:
        with stop_between_steps() as run_.stop:  # Ctrl-C: stop after the frame at hand
            skipped = _segment_all(run_, inputs, given, args.sensor)
    except _Interrupted:
        run_.summary()
        print(
            f"topseg segment: interrupted; {run_.count} of {run_.total} frames written to "
            f"{args.out} (each with its overlay)",
            file=sys.stderr,
        )
        return 130
    except _WriteFailed as exc:
        run_.summary()
        raise TopsegError(
            f"cannot write {exc.path}: {exc.reason}; {run_.count} of {run_.total} frames "
            f"written to {args.out} (each with its overlay)"
        ) from None
    run_.summary()
    if segmenter.reads_height and run_.count:
        print(
            f"floor skipped: {100 * run_.floor_share / run_.count:.1f} % of the pixels with "
            "depth went to background without the forest"
        )
    if segmenter.reads_height and segmenter.config.pre.fill_holes_cm2 > 0 and run_.count:
        print(
            f"holes filled: {run_.counts['filled_holes']} holes without depth inside one surface (under "
            f"{segmenter.config.pre.fill_holes_cm2:g} cm2) took that surface's depth and label in "
            f"{run_.count} frames"
        )
    if segmenter.background is not None and run_.count:
        print(background_summary(segmenter, run_))
    if segmenter.config.relabels_islands and run_.count:
        cfg = segmenter.config
        print(
            f"blobs relabelled as too small: {run_.counts['small_heads']} head (under "
            f"{cfg.post.min_head_cm2:g} cm2), {run_.counts['small_furniture']} furniture (under "
            f"{cfg.post.min_furniture_cm2:g} cm2, plants {cfg.post.min_plant_cm2:g}); head blobs beside a larger head: "
            f"{run_.counts['satellite_heads']} (under {cfg.post.satellite_head_cm2:g} cm2) in {run_.count} "
            "frames"
        )
    if run_.refused:
        raise TopsegError(
            f"{run_.refused} frames not written: their output names were taken (see above)"
        )
    if run_.bad_channels:
        raise TopsegError(
            f"{run_.bad_channels} recording channels not read: their keys are no camera's "
            "(see above)"
        )
    if run_.mount_refused:
        raise TopsegError(
            f"{run_.mount_refused} frames not labelled: their mount disagrees with their depth "
            "(see above)"
        )
    if skipped:
        raise TopsegError(
            f"{skipped} of {len(all_sources)} inputs could not be segmented (see above)"
        )
    return 0


def background_summary(segmenter: Segmenter, run_: _Run) -> str:
    """What the recorded background did over the run, and whether frames saw it gone."""
    cfg = segmenter.config.background
    line = (
        f"background {cfg.path} ({segmenter.background_id[:12]}): "
        f"{run_.counts['background_px']} pixels matched it and went to background without "
        f"the forest in {run_.count} frames"
    )
    if run_.background_mismatched:
        line += (
            f"; {run_.background_mismatched} frames read over {100 * cfg.mismatch_share:g} % "
            "of it farther than recorded: a fixture or the camera moved since it was recorded "
            "(record it again: topseg calibrate --background)"
        )
    return line


def _segment_all(run_: _Run, inputs: list, given, sensor: str | None = None) -> int:
    """Segment every input (`run`'s loop), mounts estimated with `sensor`'s model (None:
    from the frames' size) where none is given; how many inputs were skipped."""
    skipped = 0
    segmenter = run_.segmenter
    for arg, sources in inputs:
        try:
            estimates: dict = {}
            if segmenter.reads_height and given is None:
                estimates = _estimates(arg, sources, sensor, run_.estimate_all)
            for key, est in estimates.items():
                if isinstance(est, TopsegError):  # this camera: no mount, not segmented
                    skipped += 1
                    camera = "" if key is None else f" {key}"
                    print(f"topseg segment: skipped {arg}{camera}: {est}", file=sys.stderr)
            for source in sources:
                try:
                    run_.segment(arg, source, estimates)
                except _WriteFailed:
                    raise
                except TopsegError as exc:  # this input is damaged: say so, go on
                    skipped += 1
                    print(f"topseg segment: skipped {exc}", file=sys.stderr)
        except _WriteFailed:
            raise
        except TopsegError as exc:  # no mount for this input: none of it is segmented
            skipped += len(sources)
            print(f"topseg segment: skipped {arg}: {exc}", file=sys.stderr)
    return skipped


class _Interrupted(Exception):
    """Ctrl-C (or SIGTERM) came: the run stops before its next frame."""


class _WriteFailed(Exception):
    """An output file could not be written (the run stops there)."""

    def __init__(self, path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = path, reason


class _Run:
    """One `segment` run: the Segmenter, where labels go, the mount given, the counts."""

    def __init__(self, segmenter, out: Path, given, names: dict, total: int) -> None:
        self.segmenter, self.out, self.given = segmenter, out, given
        self.names, self.total = names, total
        self.count = 0
        self.refused = 0
        self.mount_refused = 0  # frames whose given or carried mount disagreed with them
        self.estimate_all = False  # --estimate-mount: a recording's own mounts not used
        self.given_path = None  # the mount file `given` was read from
        self.bad_channels = 0  # recording channels whose key no camera could have
        self.verdicts: dict = {}  # (camera, mount) -> whether it agrees with its frames
        self.floor_share = 0.0
        self.counts = dict.fromkeys(segmenter.counter_names, 0)  # every stage's counters
        self.background_mismatched = 0  # frames that saw too much of the background gone
        self._warned: set = set()
        self.written: dict[str, str] = {}  # output name -> the input it was written from
        self.where: dict[str, list] = {}  # camera -> [frames, first name, last name]
        self.stop = threading.Event()  # set by Ctrl-C: stop before the next frame

    def segment(self, arg: Path, source: Path, estimates: dict) -> None:
        """Label every frame of one source and write its PNGs (both of a frame or neither)."""
        frames = input_frames(source, _report_skipped, self._bad_channel)
        for frame in frames:
            if self.stop.is_set():
                raise _Interrupted
            what = f"{source}" if frame.key is None else f"{source} {frame.key} seq {frame.seq}"
            camera = f"{arg}" if frame.key is None else f"{source} {frame.key}"
            mount = None
            if self.segmenter.reads_height:
                carried = None if self.estimate_all else frame.mount
                mount = self.given or carried or estimates.get(frame.key)
                if isinstance(mount, TopsegError):
                    continue  # said once for the camera
                if mount is None:
                    mount = _png_mount(frame)
                if mount is not estimates.get(frame.key) and not self._agrees(camera, frame, mount):
                    self.mount_refused += 1
                    continue  # said once for the camera and mount
                self._warn_outside(mount, frame.name)
            name = self.names.get(source, frame.name)
            if name in self.written:
                self.refused += 1
                print(
                    f"topseg segment: error: {what} not written: {name}_labels.png was written "
                    f"from {self.written[name]} in this run",
                    file=sys.stderr,
                )
                continue
            result = self.segmenter.label(frame.depth, frame.intrinsics, frame.name, mount)
            shown = without_no_reading(frame.depth)  # 65535, "no reading": black, no label
            files = {
                self.out / f"{name}_labels.png": _png_bytes(result.labels),
                self.out / f"{name}_overlay.png": _png_bytes(overlay(shown, result.labels)),
            }
            try:
                atomic_write_all(files)
            except OSError as exc:
                raise _WriteFailed(exc.filename or self.out, exc.strerror or str(exc)) from None
            self.written[name] = what
            entry = self.where.setdefault(camera, [0, name, name])
            entry[0] += 1
            entry[2] = name
            self.count += 1
            self.floor_share += result.floor_share
            limit = self.segmenter.config.background.mismatch_share
            self.background_mismatched += result.background_missing_share > limit
            for name, n in result.counts.items():
                self.counts[name] = self.counts.get(name, 0) + n

    def _bad_channel(self, path: Path, why: str) -> None:
        """One line for a recording channel whose key no camera could have; not read."""
        self.bad_channels += 1
        print(f"topseg segment: skipped a channel of {path}: {why}", file=sys.stderr)

    def _agrees(self, camera: str, frame, mount) -> bool:
        """Whether a mount not estimated from these frames (--mount, or the recording's own)
        agrees with the camera's depth (`core.calibration.check_floor`), judged on its first
        frame with depth enough to tell; when not, one line says so and why, and none of the
        camera's frames is labelled with it (a floor that is not there erases people)."""
        verdict = self.verdicts.get((camera, mount))
        if verdict is not None:
            return verdict
        checked = mount
        if frame.intrinsics is not None and frame.intrinsics != mount.intrinsics:
            checked = replace(mount, intrinsics=frame.intrinsics)  # as the Segmenter reads it
        try:
            result = check_floor(frame.depth, checked)
        except ValueError:  # not the mount's frame size: the Segmenter says so itself
            return True
        if result.agrees is None:
            return True  # too little depth to tell: judged on the next frame
        self.verdicts[(camera, mount)] = result.agrees
        if not result.agrees:
            whose = f"mount file {self.given_path}" if self.given else "the recording's mount"
            hint = (
                "calibrate the camera again (topseg calibrate) and give --mount, or leave out "
                "--mount to estimate it from the frames"
                if self.given
                else "give --estimate-mount to estimate it from the frames, or --mount FILE"
            )
            print(
                f"topseg segment: error: {camera}: {whose} disagrees with its frames: "
                f"{result.reason()}; its frames are not labelled ({hint})",
                file=sys.stderr,
            )
        return result.agrees

    def summary(self) -> None:
        """How many frames went where, per camera (a folder of PNGs is one camera)."""
        print(f"segmented {self.count} frames into {self.out}")
        for camera, (n, first, last) in self.where.items():
            names = first if n == 1 else f"{first} .. {last}"
            print(f"  {camera}: {n} frame{'s' if n != 1 else ''} -> {names}")

    def _warn_outside(self, mount, name: str) -> None:
        """One warning per mount that lies outside what the model was trained for."""
        if mount is None or mount in self._warned:
            return
        self._warned.add(mount)
        reason = self.segmenter.outside_trained_for(mount)
        if reason:
            print(f"topseg segment: warning: {name}: {reason}", file=sys.stderr)


def _png_bytes(array) -> bytes:
    """An array encoded as PNG."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def _png_names(sources: list[Path]) -> dict[Path, str]:
    """Output names of the PNG inputs whose stems collide: `<parent folder>-<stem>`."""
    pngs = [p for p in sources if p.suffix.lower() == ".png"]
    stems = Counter(p.stem for p in pngs)
    return {p: f"{p.resolve().parent.name}-{p.stem}" for p in pngs if stems[p.stem] > 1}


def _count_frames(sources: list[Path]) -> int:
    """Frames the inputs hold, as far as a quick look tells (a PNG is one; a recording's
    depth messages)."""
    total = 0
    for source in sources:
        if source.suffix.lower() == ".mcap":
            try:
                total += sum(camera_channels(depth_channels(source))[0].values())
            except TopsegError:
                pass
        elif source.suffix.lower() == ".png":
            total += 1
    return total


def _png_mount(frame):
    """No mount for a frame that says none: a one-line error."""
    raise TopsegError(f"{frame.name}: no camera mount for this frame (give --mount)")


def _spread(items: list, n: int) -> list:
    """At most `n` of `items`, evenly spread from first to last."""
    if len(items) <= n:
        return list(items)

    return [items[int(i)] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


def _recording_sample(frames) -> tuple[list, object, bool]:
    """(up to ESTIMATE_FRAMES depth frames spread over one camera's frames, their intrinsics,
    whether every frame carries its own mount)."""
    kept: list = []
    step, seen, intrinsics, all_mounted = 1, 0, None, True
    for frame in frames:
        all_mounted &= frame.mount is not None
        if seen % step == 0:
            kept.append(frame.depth)
            intrinsics = intrinsics or frame.intrinsics
            if len(kept) >= 2 * ESTIMATE_FRAMES:  # keep every other, take half as many
                kept, step = kept[::2], step * 2
        seen += 1
    return _spread(kept, ESTIMATE_FRAMES), intrinsics, all_mounted


def _estimates(
    arg: Path, sources: list[Path], sensor: str | None = None, force: bool = False
) -> dict:
    """{depth key (None for PNGs): the mount estimated from that camera's frames (printed),
    None when its frames all carry their own (and not `force`), or the TopsegError saying
    why there is none}. A folder of PNGs is one camera; each camera's depth channel of a
    recording is one. TopsegError when an input cannot be read at all."""
    if all(p.suffix.lower() == ".png" for p in sources):
        frames = [read_depth_png(p) for p in _spread(sources, ESTIMATE_FRAMES)]
        return {None: _estimate(str(arg), frames, None, False, sensor)}
    out: dict = {}
    for source in sources:
        if source.suffix.lower() != ".mcap":
            next(iter(input_frames(source)))  # says what is wrong with it
            continue
        channels, _ = camera_channels(depth_channels(source))  # the others: said when read
        for key in channels:
            label = f"{arg}" if len(channels) == 1 else f"{arg} {key}"
            frames, intrinsics, all_mounted = _recording_sample(RecordingFrames(source, key))
            try:
                out[key] = _estimate(label, frames, intrinsics, all_mounted and not force, sensor)
            except TopsegError as exc:
                out[key] = exc
    return out


def _estimate(label: str, frames: list, intrinsics, all_mounted: bool, name: str | None = None):
    """The mount estimated from one camera's frames (printed) with sensor `name`'s model
    (None: the sensor of the frames' size), or None when its frames all carry their own.
    TopsegError (one line) when it cannot be estimated."""
    if all_mounted and frames:
        return None
    if not frames:
        raise TopsegError("no frames to estimate the camera's mount from")
    shape = frames[0].shape
    frames = [f for f in frames if f.shape == shape]
    if intrinsics is None:
        sensor = sensor_of_frames(shape, name)
        if sensor is None:
            raise TopsegError(
                f"{shape[1]}x{shape[0]} frames that say no intrinsics and match no supported "
                "sensor; calibrate the camera and give --mount"
            )
        intrinsics = sensor.intrinsics
    else:  # a recording says its optics; the sensor names the noise model
        sensor = get_sensor(name) if name else sensor_of_frames(shape)
    estimate = estimate_mount(frames, intrinsics, sensor.name if sensor else "unknown")
    mount = estimate.mount
    if sensor is not None and mount.sensor != sensor.name:
        mount = replace(mount, sensor=sensor.name)

    print(
        f"{label}: estimated mount: height {mount.height_mm / 1000:.2f} m, pitch "
        f"{mount.pitch_deg:.1f} deg, roll {mount.roll_deg:.1f} deg, floor inliers "
        f"{100 * estimate.inlier_share:.0f} % ({len(frames)} frames), floor noise "
        f"{estimate.residual_mm:.1f} mm (x{mount.noise_scale:.2f} the {mount.sensor} model)"
        f"{range_text(mount)}{thinning_text(mount)}{smoothing_text(mount)}"
    )
    return mount


def _report_skipped(reader) -> None:
    """One line for what a recording held but was not segmented."""
    if reader.rejected:
        log.warning("%s: %d damaged messages skipped", reader.path, reader.rejected)
    if reader.others:
        from topseg.core.formats.wire import shown_key

        log.warning(
            "%s: segmented %s only; also holds %s",
            reader.path,
            shown_key(reader.depth_key),
            ", ".join(sorted(shown_key(key) for key in reader.others)),
        )


def _expand(path: Path) -> list[Path]:
    """A folder of PNGs -> its PNGs (each one an input of its own); anything else as is."""
    if path.is_dir():
        return png_files(path) or [path]  # an empty folder: input_frames says so
    return [path]
