"""One way from a depth frame to labels: a plan, then the stages (`core.stages`).

A `Segmenter` holds a loaded forest, its model header, the model's input adapter
(`stages.readers`: heights through the camera's mount, or a depth model's raw depth) and the
settings that shape a run (`SegmenterConfig`). Every caller that labels frames (the worker,
`segment`, `evaluate`, experiments, the demo, training's validation split, the benches) goes
through `Segmenter.label`, which resolves the frame's `FramePlan` once and runs the stages:
pre-processing, model input, the static cell's background, forest, CRF, post-processing.
Each stage is timed and counts what it changed; `Segmentation` carries both, by name.
A background file in the settings (`BackgroundConfig.path`) is loaded once, with the model.
`bundled_model_path` finds the model shipped with topseg, used when no `--model` is named.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from topseg.core.background import (
    BackgroundModel,
    check_camera,
    load_background,
    warm_up_gate,
)
from topseg.core.bundled_model import bundled_model_path
from topseg.core.camera import Intrinsics, TopViewMount
from topseg.core.context_check import ContextCheck, warm_up_context
from topseg.core.context_prior import ContextPrior
from topseg.core.crf import CRFConfig, realtime, segment_crf
from topseg.core.denoise import edge_table, smooth_depth
from topseg.core.errors import TopsegError
from topseg.core.fattening import thin_edges
from topseg.core.forest.model_file import ModelFileError, load_model
from topseg.core.forest.model_header import model_camera, model_features
from topseg.core.forest.predict import predict_proba
from topseg.core.forest.tree import Forest
from topseg.core.person_check import PersonCheck, warm_up_check
from topseg.core.segmenter_config import SegmenterConfig, crf_config
from topseg.core.stages import (
    FramePlan,
    FrameState,
    StageModel,
    build_stages,
    counter_names,
    run_stages,
)
from topseg.core.stages.base import CRFS_SHARE
from topseg.core.stages.readers import DepthReader, HeightReader, ModelReader
from topseg.core.surfaces import voting_table, warm_up_surfaces


@dataclass(frozen=True)
class Timings:
    """Milliseconds one frame took, by stage (`stages_ms`: the plan, then each stage in
    order), and the two headline figures: the forest's share (plan, pre-processing, model
    input, forest) and the CRF's (CRF and post-processing)."""

    forest_ms: float
    crf_ms: float
    total_ms: float
    stages_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Segmentation:
    """What `Segmenter.label` returns for one frame.

    labels       (H, W) uint8 class ids, NO_DEPTH (255) where there is no depth (after
                 small holes inside one surface were filled: counts["filled_holes"])
    proba        (h, w, C) float32 forest posteriors, after the context prior (a property)
    timings      per-stage milliseconds
    floor_share  share of the pixels with depth the floor gate sent to background without
                 the forest (0 for a model that reads depth)
    counts       every stage's counters for this frame, by name (`Segmenter.counter_names`):
                 filled_holes (holes filled before labelling), background_px (pixels that
                 matched the recorded background and went to background without the forest),
                 background_missing_px (pixels farther than the background: something
                 static went), small_heads / small_furniture (blobs too small to be a head /
                 a piece of furniture or a plant, relabelled), satellite_heads (head blobs
                 beside a larger head, relabelled)
    downsample   the factor the frame was labelled at; the labels are the frame's size
    """

    labels: np.ndarray
    timings: Timings
    floor_share: float
    counts: dict[str, int]
    downsample: int
    _frame: FrameState = field(repr=False)

    @property
    def proba(self) -> np.ndarray:
        """(h, w, C) float32 forest posteriors at the working resolution (the frame's size
        divided by `downsample`), moved by the model's context prior when it has one: the
        Segmenter's reused buffer, valid until its next call (copy it to keep it). On a grid
        the Segmenter stores only the ones the CRF reads; the first read of `proba` stores
        the rest (~1.5 ms a 640x480 frame)."""
        return self._frame.posteriors()

    @property
    def background_missing_share(self) -> float:
        """Share of the recorded background's pixels (on the working grid) that this frame
        saw farther than the background; 0 without a background."""
        valid = self._frame.background_valid_px
        return self.counts.get("background_missing_px", 0) / valid if valid else 0.0

    @property
    def background_gated(self) -> bool:
        """Whether the recorded background gated this frame (False without one, or when
        the caller asked it only to be measured)."""
        return self._frame.plan.background == "gate"

    def forest_labels(self) -> np.ndarray:
        """(H, W) uint8: the forest's own argmax (no CRF, no island rules) at the frame's
        resolution, NO_DEPTH without depth; like `proba`, only until the next frame."""
        return self._frame.working_forest_labels()


class Segmenter:
    """A loaded forest and its run settings: `label(depth)` -> labels, posteriors, timings.

    Build it from arrays (`Segmenter(forest, header, crf="realtime")`) or from a model file
    (`Segmenter.from_file(path)`, None = the bundled model). The posterior buffer is reused
    across frames of one size, so one Segmenter serves one thread. `background` (else the
    file `config.background.path` names, loaded here) is the static cell's recorded
    background; a `BackgroundFileError` says what is wrong with it (and, when the config
    has a mount, that it is another camera's).
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
        background: BackgroundModel | None = None,
    ) -> None:
        config = config or SegmenterConfig()
        if crf is not None:
            crf = crf_config(crf) if isinstance(crf, str) else crf
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
        self.reader: ModelReader
        if self.features is not None:
            self.reader = HeightReader(self.features, self.trained_for)
        else:
            self.reader = DepthReader(self.camera, self.header)
        self.background = background or self._load_background(config)
        self.person_check = self._check(PersonCheck, self.header, path)
        self.context_check = self._check(ContextCheck, self.header, path)
        self.context_prior = self._check(ContextPrior, self.header, path)
        model = StageModel(forest, self.reader, config, self.background, self.person_check,
                           self.context_check, self.context_prior)  # fmt: skip
        self.stages = build_stages(model)
        # the stages whose time is the CRF's headline share; the rest (and the plan) the forest's
        self._crf_share = {stage.name for stage in self.stages if stage.share == CRFS_SHARE}

    @staticmethod
    def _check(kind, header: dict[str, Any], path: Path | None):
        """The check of `kind` (PersonCheck, ContextCheck or ContextPrior) the model header
        carries (None: none); ModelFileError naming the model when it is malformed."""
        try:
            return kind.from_header(header)
        except TopsegError as exc:
            raise ModelFileError(f"{path or 'model'}: {exc}") from None

    @staticmethod
    def _load_background(config: SegmenterConfig) -> BackgroundModel | None:
        """The background file the config names (checked against its mount's camera when it
        has one), or None."""
        path = config.background.path
        if path is None:
            return None
        background = load_background(path)
        if config.mount is not None:
            check_camera(background, config.mount.intrinsics, path)
        return background

    @property
    def background_id(self) -> str | None:
        """The sha256 id of the recorded background in use (None: none)."""
        return None if self.background is None else self.background.id

    @property
    def reads_height(self) -> bool:
        """Whether the model reads heights above the floor (and so needs a mount)."""
        return self.reader.reads_height

    @property
    def n_classes(self) -> int:
        """The number of classes the model knows (label ids 0..n_classes-1)."""
        return self.forest.n_classes

    @property
    def counter_names(self) -> tuple[str, ...]:
        """The names of every counter a Segmentation's `counts` holds."""
        return counter_names(self.stages)

    @property
    def stage_names(self) -> tuple[str, ...]:
        """The stages a frame goes through, in order."""
        return tuple(stage.name for stage in self.stages)

    @classmethod
    def from_file(
        cls,
        path: str | Path | None = None,
        config: SegmenterConfig | None = None,
        *,
        crf: CRFConfig | str | None = None,
    ) -> Segmenter:
        """Load a model file (None: the bundled model). ModelFileError says what is wrong."""
        path = bundled_model_path() if path is None else Path(path)
        forest, header = load_model(path)
        return cls(forest, header, config, crf=crf, path=path)

    def with_background(self, background: BackgroundModel) -> Segmenter:
        """The same model and settings, gated by `background` (a static cell recorded for
        one camera): a new Segmenter, this one unchanged."""
        return Segmenter(
            self.forest, self.header, self.config, model_id=self.model_id, path=self.path,
            background=background,
        )  # fmt: skip

    @property
    def crf_config(self) -> CRFConfig:
        """The CRF settings every frame is smoothed with (before a noisy camera's weight)."""
        return self.config.crf

    @property
    def crf_mode(self) -> str:
        """`none`, `exact` or `realtime`."""
        return self.config.crf.mode

    def outside_trained_for(self, mount: TopViewMount) -> str | None:
        """Why a camera on `mount` lies outside what the model was trained for (one line),
        or None when it lies inside (or the model does not say)."""
        return self.reader.outside_trained_for(mount)

    def plan(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
        gate_background: bool = True,
    ) -> FramePlan:
        """The frame's plan: `mount` (the config's when None) with the frame's `intrinsics`
        when given, for a height model; TopsegError naming the frame when it cannot be read.
        With a recorded background the plan gates with it (`gate_background`) or only
        measures it."""
        plan = self.reader.plan(depth, intrinsics, mount, name, self.config)
        if self.background is None:
            return plan
        return replace(plan, background="gate" if gate_background else "measure")

    def run(self, frame: FrameState, upto: str | None = None) -> dict[str, float]:
        """Run the stages over `frame` (up to and with the stage named `upto`); the
        milliseconds each took. A ValueError of a stage is a TopsegError naming the frame."""
        stages = self.stages
        if upto is not None:
            stages = stages[: self.stage_names.index(upto) + 1]
        try:
            return run_stages(stages, frame)
        except ValueError as exc:
            raise TopsegError(f"{frame.plan.name}: {exc}") from None

    def label(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None = None,
        name: str = "frame",
        mount: TopViewMount | None = None,
        gate_background: bool = True,
    ) -> Segmentation:
        """Labels, posteriors and timings of one uint16 depth frame: its plan (`plan`), then
        every stage. The labels are the frame's size whatever the working resolution.
        `gate_background` False only measures the recorded background (the worker, while it
        no longer matches the frames)."""
        t0 = time.perf_counter()
        frame = FrameState(self.plan(depth, intrinsics, name, mount, gate_background), depth)
        stages_ms = {"plan": 1000.0 * (time.perf_counter() - t0)}
        stages_ms.update(self.run(frame))
        crf_ms = sum(ms for s, ms in stages_ms.items() if s in self._crf_share)
        forest_ms = sum(stages_ms.values()) - crf_ms
        return Segmentation(
            frame.labels,
            Timings(forest_ms, crf_ms, forest_ms + crf_ms, stages_ms),
            frame.inp.floor_share() if frame.floor_share is None else frame.floor_share,
            dict(frame.counts),
            frame.plan.downsample,
            frame,
        )

    def prepare(
        self, depth: np.ndarray, mount: TopViewMount | None = None, name: str = "frame"
    ) -> FrameState:
        """The frame planned, pre-processed and read into its model input (the stages
        before the forest), for the benches: `depth` is then the working frame."""
        frame = FrameState(self.plan(depth, None, name, mount), depth)
        self.run(frame, upto="model_input")
        return frame

    def posteriors(self, depth: np.ndarray, mount: TopViewMount | None = None) -> np.ndarray:
        """The stages up to the forest alone: (h, w, C) float32 posteriors of every pixel at
        the working resolution, in the reused buffer."""
        frame = FrameState(self.plan(depth, None, "frame", mount), depth)
        self.run(frame, upto="forest")
        return frame.posteriors()

    def smooth(self, proba: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """The CRF alone: (H, W) uint8 labels of `proba` under this CRF mode."""
        return segment_crf(proba, depth, self.config.crf)

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the kernels on a small frame, before the
        first real one; the frame is not checked against the model's camera.

        The frame goes through twice: writable (a PNG, a synthetic frame) and read-only
        (what `wire.decode_depth` gives the worker), since numba compiles a kernel apart
        for read-only arrays. Each pass labels it on every pixel and on a lazy grid, at the
        frame's resolution and at half, so that every stage's kernels are compiled."""
        mount = self.reader.warm_up_mount()
        depth = np.full((48, 64), 3000, np.uint16)
        if mount is not None:
            depth[:] = int(mount.height_mm * 0.6)
            depth[:, :8] = int(mount.height_mm)  # a floor strip: the floor gate's path
            # a band without depth at the image's edge, between the floor and the surface
            # (not a hole `fill_holes` closes): the edge-gap fill (`forest.edge_gaps`)
            depth[-3:, :] = 0
        read_only = depth.copy()
        read_only.flags.writeable = False
        factors = (1, 2) if mount is not None else (1,)
        for frame_depth in (depth, read_only):
            for factor in factors:
                for stride in (1, 2):  # every pixel walked, and a lazy grid upsampled
                    grid = replace(self.config.grid, stride=stride, downsample=factor)
                    warm = replace(self.config, grid=grid, check_camera=False)
                    plan = self.reader.plan(frame_depth, None, mount, "warm-up frame", warm)
                    frame = FrameState(plan, frame_depth)
                    self.run(frame)
                    frame.working_forest_labels()
            # the kernel variant that clamps probes, which a frame with a surface a few cm
            # from the camera takes (`forest.predict.MAX_PAD`)
            predict_proba(self.forest, frame.inp, max_pad=0)
            if mount is not None:
                # the smoothing a noisy camera's frames get and the thinning a stereo
                # camera's get, neither this mount's
                smooth_depth(frame_depth, edge_table(mount.sensor, 1.0))
                thin_edges(frame_depth, 1, 100.0)
        if self.config.crf.mode == "realtime":
            realtime.warm_up(self.n_classes)  # the solve of a large band, in parallel
        if self.background is not None:
            warm_up_gate(depth)
        if self.person_check is not None:
            warm_up_check(depth, self.person_check)
        if self.context_check is not None:
            warm_up_context(depth, self.context_check)
        if voting_table(self.n_classes).any():
            warm_up_surfaces(depth.shape)
