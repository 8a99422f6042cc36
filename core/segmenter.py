"""One way from a depth frame to labels: the forest's posteriors, then the CRF.

A `Segmenter` holds a loaded forest, its model header and the settings that shape a run
(`SegmenterConfig`: the CRF, the camera mount, the stride). Every caller that labels frames
(the worker, `segment`, `evaluate`, experiments, the demo, training's validation split, the
benches) goes through it, so there is one validation of a frame, one argmax and one way to
time the two stages.

A model trained on heights (header `"input": "height"`) reads each frame through its mount
(`forest.inputs.model_input`: height above the floor, metric offsets, the floor gate), so
frames of any size and intrinsics are labelled once their mount is known; the floor-gated
share is in `Segmentation.floor_share`. A model trained before reads depth as it always did
and is refused frames of another camera (`check_frame`).
`bundled_model_path` finds the model shipped with topseg, used when no `--model` is named.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from topseg.core import labels as L
from topseg.core.errors import TopsegError

if TYPE_CHECKING:
    from topseg.core.camera import Intrinsics, TopViewMount
    from topseg.core.crf import CRFConfig
    from topseg.core.forest.features import FeatureConfig
    from topseg.core.forest.inputs import ModelInput
    from topseg.core.forest.tree import Forest

# The numba modules (camera, forest, crf) are imported where they are used, so that a
# command's `--help` (which reads MODEL_HELP) does not compile or load them.

#: Levels of the forest's adaptive grid by default (`SegmenterConfig.adaptive`): one, the grid
#: twice as coarse first; measured in docs/performance.md
ADAPTIVE_LEVELS = 1
#: A walked pixel stops walking trees once its first two (or more) give one class this
#: average posterior (`SegmenterConfig.early_exit`); measured in docs/performance.md. 0.95
#: (rung 22) walks 4 % more nodes than 0.9 and keeps the grid's accuracy loss against full
#: resolution under issue 15's 0.01 on both held-out sets (0.9 lost 0.0106 on one).
EARLY_EXIT = 0.95
#: After the CRF, blobs labelled head smaller than this on the surface (cm2) take their
#: border's label: a fifth of a whole head seen from above (200-300 cm2), so that a head cut
#: by the image's edge mostly keeps its label. On rendered time-of-flight frames it raised
#: the share of head blobs that are heads from 0.31-0.54 to 0.79-0.92 (docs/results.md).
MIN_HEAD_CM2 = 50.0
#: After the CRF, blobs labelled chair, storage or table smaller than this on the surface
#: (cm2) take their border's label: a fifth of a chair's seat seen from above (~1600 cm2).
#: Measured in docs/crf.md: avg F1 +0.005 / +0.003 on the held-out sets, furniture on a
#: person 1.1-1.4 points lower on rendered time-of-flight frames.
MIN_FURNITURE_CM2 = 300.0
#: After the CRF, blobs labelled plant smaller than this on the surface (cm2) take their
#: border's label: two thirds of the smallest pot seen from above (14 cm across, ~150 cm2).
#: A noisy camera leaves such specks of plant on table tops. Measured in docs/crf.md.
MIN_PLANT_CM2 = 100.0
#: After the CRF, head blobs smaller than this (cm2) whose centre lies within
#: SATELLITE_RADIUS_CM of a larger head blob's take their border's label: an arm or a hand
#: beside a head, as large as a small head (`islands.relabel_islands`). Measured in
#: docs/results.md on rendered time-of-flight frames.
SATELLITE_HEAD_CM2 = 150.0
#: Two people's heads are a shoulder's breadth apart (~40 cm between centres): a smaller head
#: blob closer than this to a larger one is not a second head (`SATELLITE_HEAD_CM2`).
SATELLITE_RADIUS_CM = 40.0
#: head blobs within this many pixels of the image's edge are held to a smaller minimum
#: (`islands`): the border cuts the head of a person walking in or out of view, and the part
#: in view can be smaller than MIN_HEAD_CM2 (2 px: time-of-flight and stereo cameras often
#: leave the outermost pixel without depth)
ISLAND_EDGE_PX = 2
#: the share of `min_head_cm2` a head blob at the image's edge must reach: of 0, 0.2 and 0.4
#: on the walker stand-ins, 0.4 kept the lower of head precision and recall highest on most
#: sets, and the most head precision on the mounts table (docs/results.md)
EDGE_HEAD_SHARE = 0.4
#: Before labelling, holes without depth inside one surface up to this size (cm2) take the
#: surface's depth (`holes.fill_holes`): a time-of-flight camera's holes in dark hair. On
#: rendered walker frames with hair dropout it took the bundled model's head blobs found
#: from 0.23 to 0.90 at 3.3 m (docs/results.md).
FILL_HOLES_CM2 = 100.0
#: Where `deploy/install.sh` puts the bundled model (below its --root).
INSTALLED_MODEL = Path("/opt/topseg/models/default.npz")
#: The bundled model inside a checkout, relative to its root.
CHECKOUT_MODEL = Path("models") / "default.npz"
#: Help text for `--model` of every command that defaults to the bundled model.
MODEL_HELP = (
    "model file from `topseg train` (default: the bundled model, models/default.npz of "
    "the checkout, or /opt/topseg/models/default.npz when installed with deploy/install.sh)"
)


def bundled_model_path() -> Path:
    """The bundled model: the checkout's `models/default.npz`, else the installed copy.

    The installed copy is found beside the venv that runs topseg (`install.sh` puts the venv
    at PREFIX/venv and the model at PREFIX/models/), else at /opt/topseg. A TopsegError
    (one line) when there is none.
    """
    candidates = [
        Path(__file__).resolve().parents[1] / CHECKOUT_MODEL,  # core/ -> the checkout root
        Path(sys.prefix).resolve().parent / CHECKOUT_MODEL,  # PREFIX/venv -> PREFIX/models
        INSTALLED_MODEL,
    ]
    for path in candidates:
        if path.is_file():
            return path
    raise TopsegError(
        f"no bundled model (looked for {', '.join(map(str, dict.fromkeys(candidates)))}); "
        "name one with --model"
    )


def model_camera(header: dict | None) -> Intrinsics:
    """The intrinsics the model was trained for (Kinect v1 when the header does not say)."""
    from topseg.core.camera import KINECT_V1, TopViewMount

    dataset = (header or {}).get("dataset", {})
    attrs = dataset.get("attrs", {}) if isinstance(dataset, dict) else None
    if not isinstance(attrs, dict):
        raise TopsegError("the model's header names an unreadable dataset (not a table)")
    cam = attrs.get("camera")
    if cam is None or cam == {}:
        return KINECT_V1
    try:
        return TopViewMount.from_dict(cam, source="the model's camera").intrinsics
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise TopsegError(f"the model's header names an unreadable camera ({exc})") from None


def _crf_config(mode: str = "realtime") -> CRFConfig:
    """A CRFConfig of `mode` with the default settings."""
    from topseg.core.crf import CRFConfig

    return CRFConfig(mode=mode)


@dataclass(frozen=True)
class SegmenterConfig:
    """How a Segmenter runs: the seam where run settings are added as fields.

    crf           the CRF settings (mode `none` is the forest's argmax)
    check_camera  a model trained before heights: refuse frames that do not come from the
                  model's camera (size, focal length); off where frames of other sizes are
                  expected (the worker's tests). Height models take any camera.
    stride        forest walked at every stride-th pixel of every stride-th row, the rest
                  upsampled by height (1 = every pixel); None: from each frame's mount, the
                  grid `forest.predict.grid_stride` spaces GRID_SPACING_MM apart on the floor
    mount         the camera's mount, for frames labelled without one of their own (a
                  height model needs one or the other)
    adaptive      on a grid (stride > 1), levels of coarser grids walked first: each finer
                  grid is walked only where the coarser one does not settle its pixels
                  (`forest.predict.predict_proba`); 0 walks every grid pixel
    early_exit    a walked pixel stops walking trees once the average of its first two (or
                  more) gives one class at least this posterior; None walks every tree
    min_head_cm2  after the CRF (realtime or exact), blobs labelled head smaller than this
                  on the surface take their border's label (`islands.relabel_islands`);
                  0 keeps them
    min_furniture_cm2  the same for blobs of chair, storage and table
                  (`islands.FURNITURE_ISLANDS`); 0 keeps them
    min_plant_cm2  the same for blobs of plant; 0 keeps them
    satellite_head_cm2  after the CRF, head blobs smaller than this whose centre lies
                  within SATELLITE_RADIUS_CM of a larger head blob's take their
                  border's label; 0 keeps them
    fill_holes_cm2  a height model first fills each hole without depth up to this size
                  that lies inside one surface with that surface's depth
                  (`holes.fill_holes`), so that the hole is labelled with it; 0 fills none
    downsample    a height model labels every downsample-th pixel of every downsample-th
                  row of a frame (`resolution.decimate`: forest, CRF and island rules at
                  that resolution) and brings the labels back to the frame's by depth
                  (`resolution.upsample_labels`); None: from each frame's mount
                  (`resolution.auto_downsample`: half where a labelled pixel then
                  spans at most 14.4 mm of the floor, as for a Kinect v1 at 3.5 m); 1
                  labels every pixel. Models that read depth work at 1
    """

    crf: CRFConfig = field(default_factory=_crf_config)
    check_camera: bool = True
    stride: int | None = None
    mount: TopViewMount | None = None
    adaptive: int = ADAPTIVE_LEVELS
    early_exit: float | None = EARLY_EXIT
    min_head_cm2: float = MIN_HEAD_CM2
    min_furniture_cm2: float = MIN_FURNITURE_CM2
    min_plant_cm2: float = MIN_PLANT_CM2
    satellite_head_cm2: float = SATELLITE_HEAD_CM2
    fill_holes_cm2: float = FILL_HOLES_CM2
    downsample: int | None = None

    def __post_init__(self) -> None:
        from topseg.core.resolution import MAX_DOWNSAMPLE

        if self.stride is not None and (isinstance(self.stride, bool) or self.stride < 1):
            raise TopsegError(f"stride must be >= 1 (or None: from the mount), got {self.stride}")
        if self.downsample is not None and (
            isinstance(self.downsample, bool) or not 1 <= self.downsample <= MAX_DOWNSAMPLE
        ):
            raise TopsegError(
                f"downsample must be 1-{MAX_DOWNSAMPLE} (or None: from the mount), "
                f"got {self.downsample}"
            )
        if isinstance(self.adaptive, bool) or self.adaptive < 0:
            raise TopsegError(f"adaptive must be >= 0 levels, got {self.adaptive}")
        if self.early_exit is not None and not 0.0 < self.early_exit <= 1.0:
            raise TopsegError(f"early_exit must be in (0, 1] (or None), got {self.early_exit}")
        for name in (
            "min_head_cm2",
            "min_furniture_cm2",
            "min_plant_cm2",
            "satellite_head_cm2",
            "fill_holes_cm2",
        ):
            area = getattr(self, name)
            if not (np.isfinite(area) and area >= 0):
                raise TopsegError(f"{name} must be >= 0 cm2, got {area}")


@dataclass(frozen=True)
class Timings:
    """Milliseconds one frame took: forest, CRF, and the two stages together."""

    forest_ms: float
    crf_ms: float
    total_ms: float


@dataclass(frozen=True)
class Segmentation:
    """What `Segmenter.label` returns for one frame.

    labels       (H, W) uint8 class ids, NO_DEPTH (255) where there is no depth (after
                 small holes inside one surface were filled: `filled_holes`)
    proba        (H, W, C) float32 forest posteriors (a property, see there)
    timings      per-stage milliseconds
    floor_share  share of the pixels with depth the floor gate sent to background without
                 the forest (0 for a model that reads depth)
    small_heads  blobs labelled head by the CRF that were too small to be a head and took
                 their border's label (`SegmenterConfig.min_head_cm2`)
    small_furniture  the same for chair, storage and table (`min_furniture_cm2`) and
                 plant (`min_plant_cm2`)
    satellite_heads  head blobs beside a larger head that took their border's label
                 (`SegmenterConfig.satellite_head_cm2`)
    downsample   the factor the frame was labelled at (`SegmenterConfig.downsample`); the
                 labels are the frame's size whatever it is
    filled_holes holes without depth inside one surface that took its depth and a label
                 (`SegmenterConfig.fill_holes_cm2`)
    """

    labels: np.ndarray
    timings: Timings
    floor_share: float
    _posteriors: Callable[[], np.ndarray] = field(repr=False)
    small_heads: int = 0
    small_furniture: int = 0
    satellite_heads: int = 0
    downsample: int = 1
    _forest_labels: Callable[[], np.ndarray] | None = field(default=None, repr=False)
    filled_holes: int = 0

    @property
    def proba(self) -> np.ndarray:
        """(h, w, C) float32 forest posteriors at the working resolution (the frame's size
        divided by `downsample`): the Segmenter's reused buffer, valid until its next call
        (copy it to keep it). On a grid the Segmenter stores only the ones the CRF reads;
        the first read of `proba` stores the rest (~1.5 ms a 640x480 frame)."""
        return self._posteriors()

    def forest_labels(self) -> np.ndarray:
        """(H, W) uint8: the forest's own argmax (no CRF, no island rules) at the frame's
        resolution, NO_DEPTH without depth; like `proba`, only until the next frame."""
        if self._forest_labels is None:
            raise TopsegError("this Segmentation keeps no forest labels")
        return self._forest_labels()


class Segmenter:
    """A loaded forest and its run settings: `label(depth)` -> labels, posteriors, timings.

    Build it from arrays (`Segmenter(forest, header, crf="realtime")`) or from a model file
    (`Segmenter.from_file(path)`, None = the bundled model). The posterior buffer is reused
    across frames of one size, so one Segmenter serves one thread.
    """

    def __init__(
        self,
        forest: Forest,
        header: dict | None = None,
        config: SegmenterConfig | None = None,
        *,
        crf: CRFConfig | str | None = None,
        model_id: str | None = None,
        path: Path | None = None,
    ) -> None:
        config = config or SegmenterConfig()
        if crf is not None:
            crf = _crf_config(crf) if isinstance(crf, str) else crf
            config = replace(config, crf=crf)
        self.forest = forest
        self.header: dict[str, Any] = dict(header or {})
        self.config = config
        self.path = path
        self.model_id = str(
            model_id or self.header.get("model_id") or (path.name if path else "model")
        )
        self.camera = model_camera(self.header)
        self.features = model_features(self.header, forest)
        self.trained_for: dict[str, Any] | None = self.header.get("trained_for")
        self._out: np.ndarray | None = None
        self._summary = None  # crf.argmax.Summary: the CRF's per-pixel view of _out
        self._frame = 0  # counts writes into _out (a Segmentation fills only its own)

    @property
    def reads_height(self) -> bool:
        """Whether the model reads heights above the floor (and so needs a mount)."""
        return self.features is not None

    @classmethod
    def from_file(
        cls,
        path: str | Path | None = None,
        config: SegmenterConfig | None = None,
        *,
        crf: CRFConfig | str | None = None,
    ) -> Segmenter:
        """Load a model file (None: the bundled model). ModelFileError says what is wrong."""
        from topseg.core.forest.model_file import load_model

        path = bundled_model_path() if path is None else Path(path)
        forest, header = load_model(path)
        return cls(forest, header, config, crf=crf, path=path)

    @property
    def crf_config(self) -> CRFConfig:
        """The CRF settings every frame is smoothed with."""
        return self.config.crf

    def crf_for(self, mount: TopViewMount | None) -> CRFConfig:
        """The CRF settings for frames from `mount`: the config's, with the Potts weight
        raised to `noisy_smoothness` for a height model's frames from a noisy camera (those
        `denoise.needs_denoise` smooths)."""
        from topseg.core.denoise import needs_denoise

        crf = self.config.crf
        if (
            self.features is None
            or mount is None
            or crf.noisy_smoothness <= crf.smoothness
            or not needs_denoise(mount)
        ):
            return crf
        return replace(crf, smoothness=crf.noisy_smoothness)

    @property
    def crf_mode(self) -> str:
        """`none`, `exact` or `realtime`."""
        return self.config.crf.mode

    def check_frame(
        self, depth: np.ndarray, intrinsics: Intrinsics | None = None, name: str = "frame"
    ) -> None:
        """The validation of a frame for a model that reads depth: the model's camera size
        and, when the frame says its intrinsics, focal length (its features are offsets
        scaled for that camera). TopsegError naming the frame."""
        expected = self.camera
        shape = np.shape(depth)
        if shape != expected.shape:
            got = f"{shape[1]}x{shape[0]}" if len(shape) == 2 else f"of shape {shape}"
            raise TopsegError(
                f"{name}: frame is {got} but the model was trained for "
                f"{expected.width}x{expected.height}; resample it to that camera first"
            )
        if intrinsics is not None and abs(intrinsics.fx - expected.fx) > 0.01 * expected.fx:
            raise TopsegError(
                f"{name}: focal length {intrinsics.fx:.1f} px differs from the model's "
                f"{expected.fx:.1f} px"
            )

    def frame_mount(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
    ) -> TopViewMount:
        """The mount a height model reads `depth` with: `mount`, else the config's, with the
        frame's own intrinsics when it says them. TopsegError naming the frame when there is
        none or the frame's size is not its camera's."""
        mount = mount if mount is not None else self.config.mount
        if mount is None:
            raise TopsegError(
                f"{name}: the model reads heights above the floor and needs the camera's mount "
                "(calibrate it with `topseg calibrate` and pass --mount)"
            )
        if intrinsics is not None and intrinsics != mount.intrinsics:
            mount = replace(mount, intrinsics=intrinsics)
        shape = np.shape(depth)
        k = mount.intrinsics
        if shape != k.shape:
            got = f"{shape[1]}x{shape[0]}" if len(shape) == 2 else f"of shape {shape}"
            raise TopsegError(
                f"{name}: frame is {got} but its camera's intrinsics are {k.width}x{k.height}"
            )
        return mount

    def model_input(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
    ) -> ModelInput:
        """What the forest reads of `depth` (validated first; see `label`)."""
        from topseg.core.forest.inputs import legacy_input, model_input

        if self.features is None:
            if self.config.check_camera:
                self.check_frame(depth, intrinsics, name)
            return legacy_input(depth)
        try:
            return model_input(
                depth, self.frame_mount(depth, intrinsics, name, mount), self.features
            )
        except ValueError as exc:
            raise TopsegError(f"{name}: {exc}") from None

    def outside_trained_for(self, mount: TopViewMount) -> str | None:
        """Why a camera on `mount` lies outside what the model was trained for (one line),
        or None when it lies inside (or the model does not say)."""
        if self.features is None:
            return _outside_legacy(self.header, mount)
        return _outside(self.trained_for, mount)

    def posteriors(self, depth: np.ndarray, mount: TopViewMount | None = None) -> np.ndarray:
        """The forest stage alone: (H, W, C) float32 posteriors in the reused buffer (the
        frame not checked against a depth model's camera)."""
        from topseg.core.forest.inputs import legacy_input

        if self.features is None:
            return self._predict(legacy_input(depth), self.stride_for(depth))
        return self._predict(
            self.model_input(depth, mount=mount), self.stride_for(depth, mount=mount)
        )

    def stride_for(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
    ) -> int:
        """The forest's stride on this frame: the config's, else from the frame's mount
        (`grid_stride`); 1 for a model that reads depth (it has no mount to measure by)."""
        from topseg.core.forest.predict import grid_stride

        if self.config.stride is not None:
            return self.config.stride
        if self.features is None:
            return 1
        return grid_stride(self.frame_mount(depth, intrinsics, name, mount))

    def downsample_for(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
    ) -> int:
        """The factor this frame is labelled at: the config's, else from the frame's mount
        (`resolution.auto_downsample`); 1 for a model that reads depth (it is tied to its
        camera's pixels)."""
        from topseg.core.resolution import auto_downsample

        if self.features is None:
            return 1
        if self.config.downsample is not None:
            return self.config.downsample
        return auto_downsample(self.frame_mount(depth, intrinsics, name, mount))

    def working_frame(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
    ) -> tuple[np.ndarray, TopViewMount | None, int]:
        """(depth, mount, factor) of the frame as the Segmenter labels it: decimated by
        `downsample_for`'s factor with its mount's optics decimated alike (the frame and
        the mount it would be read with when the factor is 1). TopsegError naming the frame
        when it is no depth frame or has no mount a height model can read it with."""
        from topseg.core.resolution import decimate, decimated_mount

        factor = self.downsample_for(depth, intrinsics, name, mount)
        full = None if self.features is None else self.frame_mount(depth, intrinsics, name, mount)
        if factor == 1:
            return depth, full, 1
        try:
            small = decimate(depth, factor)
        except ValueError as exc:
            raise TopsegError(f"{name}: {exc}") from None
        return small, decimated_mount(full, factor), factor

    def _predict(self, inp: ModelInput, stride: int, lazy: bool = False) -> np.ndarray:
        from topseg.core.crf.argmax import Summary
        from topseg.core.forest.predict import predict_proba

        shape = (*inp.shape, L.NUM_CLASSES)
        if self._out is None or self._out.shape != shape:
            self._out = np.empty(shape, np.float32)
            self._summary = Summary.empty(inp.shape)  # filled with _out, read by the CRF
        self._frame += 1  # a Segmentation's lazy posteriors are this buffer's until now
        return predict_proba(
            self.forest,
            inp,
            out=self._out,
            stride=stride,
            summary=self._summary,
            lazy=lazy,
            adaptive=self.config.adaptive,
            early_exit=self.config.early_exit,
        )

    def smooth(self, proba: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """The CRF stage alone: (H, W) uint8 labels of `proba` under this CRF mode."""
        from topseg.core.crf import segment_crf

        return segment_crf(proba, depth, self.config.crf)

    def label(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
    ) -> Segmentation:
        """Labels, posteriors and timings of one uint16 depth frame, validated first (`name`
        names it in the error). A height model reads it through `mount` (the config's when
        None) with the frame's `intrinsics` when given, at the working resolution
        (`working_frame`); the labels are the frame's size. The forest stage's time
        includes decimating the frame and building the model input, the CRF stage's the
        island rules and bringing the labels back to the frame's resolution."""
        from topseg.core.camera import without_no_reading
        from topseg.core.resolution import upsample_labels

        t0 = time.perf_counter()
        depth = without_no_reading(depth)  # 65535, "no reading": no depth, as in calibration
        depth, intrinsics, mount = self._as_depth(depth, intrinsics, name, mount)
        depth, filled = self._fill_holes(depth, intrinsics, name, mount)
        small, small_mount, factor = self.working_frame(depth, intrinsics, name, mount)
        if factor == 1:
            return replace(self._label(depth, intrinsics, name, mount, t0), filled_holes=filled)
        work = self._label(small, None, name, small_mount, t0)
        t1 = time.perf_counter()
        labels = upsample_labels(depth, work.labels, small, factor)
        ms = 1000.0 * (time.perf_counter() - t1)
        timings = Timings(
            work.timings.forest_ms, work.timings.crf_ms + ms, work.timings.total_ms + ms
        )

        def forest_labels() -> np.ndarray:
            """The forest's argmax on the decimated frame, brought back to the frame's."""
            return upsample_labels(depth, work.forest_labels(), small, factor)

        return replace(
            work,
            labels=labels,
            timings=timings,
            downsample=factor,
            _forest_labels=forest_labels,
            filled_holes=filled,
        )

    def _fill_holes(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None,
        name: str,
        mount: TopViewMount | None,
    ) -> tuple[np.ndarray, int]:
        """(depth with its small holes inside one surface filled, how many): a height model
        with `fill_holes_cm2` > 0 only; others get the frame as given."""
        from topseg.core.holes import fill_holes

        if self.features is None or self.config.fill_holes_cm2 <= 0:
            return depth, 0
        k = self.frame_mount(depth, intrinsics, name, mount).intrinsics
        try:
            return fill_holes(depth, k, self.config.fill_holes_cm2)
        except ValueError as exc:
            raise TopsegError(f"{name}: {exc}") from None

    def _as_depth(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None,
        name: str,
        mount: TopViewMount | None,
    ) -> tuple[np.ndarray, Intrinsics | None, TopViewMount | None]:
        """(depth, intrinsics, mount) as `label` reads them: a radial camera's range frame
        read as depth once (`TopViewMount.z_depth`), with its mount then saying depth, so
        that the forest, the blob rules and the upsampling all see depth; others as given."""
        given = mount if mount is not None else self.config.mount
        if self.features is None or given is None or not given.radial:
            return depth, intrinsics, mount
        full = self.frame_mount(depth, intrinsics, name, mount)
        try:
            z = full.z_depth(depth)
        except ValueError as exc:
            raise TopsegError(f"{name}: {exc}") from None
        return z, None, replace(full, radial=False)

    def _label(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None,
        name: str,
        mount: TopViewMount | None,
        t0: float,
    ) -> Segmentation:
        """`label` at the frame's own resolution, timed from `t0`."""
        from topseg.core.crf import segment_argmax, segment_crf
        from topseg.core.forest.predict import fill_posteriors

        inp = self.model_input(depth, intrinsics, name, mount)
        stride = self.stride_for(depth, intrinsics, name, mount)
        proba = self._predict(inp, stride, lazy=stride > 1)
        t1 = time.perf_counter()
        frame, filled = self._frame, [stride == 1]

        def fill(mask: np.ndarray | None = None) -> np.ndarray:
            """Store the posteriors left out at `mask` (all: the rest), for this frame only."""
            if self._frame != frame:
                raise TopsegError(
                    "Segmentation.proba of an earlier frame: the Segmenter has labelled "
                    "another since (copy proba before the next label)"
                )
            if not filled[0]:
                fill_posteriors(inp, proba, stride, mask)
                filled[0] = mask is None
            return proba

        crf = self.crf_for(mount if mount is not None else self.config.mount)
        labels = segment_crf(proba, depth, crf, self._summary, None if filled[0] else fill)
        heads, furniture, satellites = self._relabel_islands(labels, depth, intrinsics, name, mount)
        t2 = time.perf_counter()
        ms = 1000.0
        return Segmentation(
            labels,
            Timings(ms * (t1 - t0), ms * (t2 - t1), ms * (t2 - t0)),
            inp.floor_share(),
            fill,
            heads,
            furniture,
            satellites,
            _forest_labels=lambda: segment_argmax(fill(), inp.values > 0),
        )

    @property
    def relabels_islands(self) -> bool:
        """Whether `label` relabels head, furniture or plant blobs under `min_head_cm2`,
        `min_furniture_cm2` or `min_plant_cm2`, or satellite heads, after the CRF (never in
        CRF mode none: that is the forest's argmax, as it is)."""
        cfg = self.config
        largest = max(
            cfg.min_head_cm2, cfg.min_furniture_cm2, cfg.min_plant_cm2, cfg.satellite_head_cm2
        )
        return largest > 0 and cfg.crf.mode != "none"

    def _relabel_islands(
        self,
        labels: np.ndarray,
        depth: np.ndarray,
        intrinsics: Intrinsics | None,
        name: str,
        mount: TopViewMount | None,
    ) -> tuple[int, int, int]:
        """The CRF's head, furniture and plant blobs under their minimum areas, and its
        satellite heads, relabelled in place, measured with the frame's intrinsics: how many
        small head blobs, small furniture and plant blobs, and satellite heads."""
        if not self.relabels_islands:
            return 0, 0, 0
        from topseg.core.islands import (
            FURNITURE_COUNTED,
            edge_shares,
            island_areas,
            relabel_islands,
        )

        if self.features is None:
            k = intrinsics if intrinsics is not None else self.camera
        else:
            k = self.frame_mount(depth, intrinsics, name, mount).intrinsics
        cfg = self.config
        areas = island_areas(cfg.min_head_cm2, cfg.min_furniture_cm2, cfg.min_plant_cm2)
        small, satellites = relabel_islands(
            labels, depth, k, areas, cfg.satellite_head_cm2, SATELLITE_RADIUS_CM,
            ISLAND_EDGE_PX, edge_shares(EDGE_HEAD_SHARE),
        )  # fmt: skip
        return int(small[L.HEAD]), int(small[list(FURNITURE_COUNTED)].sum()), satellites

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the kernels on a small frame, before the
        first real one; the frame is not checked against the model's camera.

        The frame goes through twice: writable (a PNG, a synthetic frame) and read-only
        (what `wire.decode_depth` gives the worker). Numba compiles a kernel apart for
        read-only arrays: without the second pass, the model input's and the CRF's edge
        kernels were compiled on a worker's first real frame, and with numba's cache cold
        (after an upgrade) the worker dropped its first 10 frames meanwhile."""
        from topseg.core.camera import KINECT_V1, TopViewMount

        depth = np.full((48, 64), 3000, np.uint16)
        mount = None
        if self.features is not None:
            # a virtual camera at the model's canonical height (a constant of the model, not
            # a mount); a floor strip so that the floor gate's path is compiled too
            mount = TopViewMount(KINECT_V1.scaled_to(64, 48), self.features.canonical_height_mm)
            depth[:] = int(mount.height_mm * 0.6)
            depth[:, :8] = int(mount.height_mm)
            # a band without depth at the image's edge, between the floor and the surface
            # (not a hole `fill_holes` closes), so that the edge-gap fill is compiled too
            # (`forest.edge_gaps`): without it, `make demo` on a clean clone dropped 73 of
            # 300 frames while a worker compiled it on the first frame with such a band
            depth[-3:, :] = 0
        from topseg.core.crf import segment_crf
        from topseg.core.denoise import edge_table, smooth_depth
        from topseg.core.fattening import thin_edges
        from topseg.core.forest.inputs import legacy_input
        from topseg.core.forest.predict import fill_posteriors, predict_proba
        from topseg.core.resolution import decimate, upsample_labels

        read_only = depth.copy()
        read_only.flags.writeable = False
        for frame in (depth, read_only):
            if self.features is None:
                inp = legacy_input(frame)
            else:
                self._fill_holes(frame, None, "warm-up frame", mount)
                inp = self.model_input(frame, mount=mount)
            for stride in (1, 2):  # both paths: every pixel walked, and a lazy grid upsampled
                proba = self._predict(inp, stride, lazy=stride > 1)
                fill = None if stride == 1 else partial(fill_posteriors, inp, proba, stride)
                labels = segment_crf(proba, frame, self.config.crf, self._summary, fill)
                self._relabel_islands(labels, frame, None, "warm-up frame", mount)
            # the kernel variant that clamps probes, which a frame with a surface a few cm
            # from the camera takes (`forest.predict.MAX_PAD`)
            predict_proba(self.forest, inp, max_pad=0)
            if self.features is not None:  # the half-resolution path's own two steps
                small = decimate(frame, 2)
                upsample_labels(frame, labels[::2, ::2], small, 2)
                # the smoothing a noisy camera's frames get (`core.denoise`) and the thinning
                # a stereo camera's get (`core.fattening`), neither this mount's
                smooth_depth(frame, edge_table(mount.sensor, 1.0))
                thin_edges(frame, 1, 100.0)
        if self.config.crf.mode == "realtime":
            from topseg.core.crf import realtime

            realtime.warm_up(L.NUM_CLASSES)  # the solve of a large band, in parallel


def model_features(header: dict | None, forest: Forest | None = None) -> FeatureConfig | None:
    """The FeatureConfig of a model that reads heights (header `"input": "height"`), None for
    one that reads depth. TopsegError when the header says heights but not its features."""
    from topseg.core.forest.features import FeatureConfig
    from topseg.core.forest.inputs import reads_height

    if not reads_height(header):
        return None
    d = (header or {}).get("features")
    if d is None:
        d = (header or {}).get("recipe", {}).get("config", {}).get("features")
    if not isinstance(d, dict):
        raise TopsegError("the model reads heights but its header does not say its features")
    for key in ("off_image", "edge_gaps"):  # written before the field: probes read background
        d = d if key in d else {**d, key: "background"}
    try:
        features = FeatureConfig.from_dict(d, source="the model's feature config")
    except ValueError as exc:
        raise TopsegError(f"the model's header names unreadable features ({exc})") from None
    if forest is not None and features.background_mm != forest.background_mm:
        raise TopsegError("the model's header and forest disagree on background_mm")
    return features


#: slack on the trained height range and tilt before a camera counts as outside them
HEIGHT_SLACK_MM = 100.0
TILT_SLACK_DEG = 1.0


def _outside(trained_for: dict | None, mount: TopViewMount) -> str | None:
    """The reason `mount` lies outside a height model's `trained_for`, or None."""
    if not trained_for:
        return None
    reasons = []
    lo, hi = trained_for.get("height_mm", [None, None])
    h = mount.height_mm
    if lo is not None and hi is not None and not lo - HEIGHT_SLACK_MM <= h <= hi + HEIGHT_SLACK_MM:
        reasons.append(
            f"camera height {h / 1000:.2f} m is outside the {lo / 1000:.2f}-{hi / 1000:.2f} m "
            "the model was trained for"
        )
    max_tilt = trained_for.get("tilt_deg")
    if max_tilt is not None and mount.tilt_deg() > max_tilt + TILT_SLACK_DEG:
        reasons.append(
            f"camera tilt {mount.tilt_deg():.1f} deg exceeds the model's {max_tilt:.1f} deg"
        )
    sensors = trained_for.get("sensors")
    if sensors and mount.sensor not in sensors:
        reasons.append(
            f"sensor {mount.sensor} is not one the model was trained for ({', '.join(sensors)})"
        )
    return "; ".join(reasons) or None


def _outside_legacy(header: dict, mount: TopViewMount) -> str | None:
    """The reason `mount` is not the one mount a depth-reading model was trained for."""
    from topseg.core.camera import TopViewMount

    cam = header.get("dataset", {}).get("attrs", {}).get("camera")
    try:
        trained = TopViewMount.from_dict(cam) if cam else None
    except (KeyError, TypeError, ValueError):
        trained = None
    if trained is None:
        return "the model reads raw depth and does not say the mount it was trained for"
    if (
        abs(mount.height_mm - trained.height_mm) > HEIGHT_SLACK_MM
        or mount.tilt_deg() > TILT_SLACK_DEG
    ):
        return (
            f"the model reads raw depth and was trained for one mount ({trained.height_mm / 1000:.2f} m, "
            f"straight down); this camera is {mount.height_mm / 1000:.2f} m up, tilted "
            f"{mount.tilt_deg():.1f} deg"
        )
    return None
