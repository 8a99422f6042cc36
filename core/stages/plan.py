"""A frame's plan (everything decided about it before any stage runs) and its working state."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from topseg.core.camera import Intrinsics, TopViewMount
    from topseg.core.crf import CRFConfig, Summary
    from topseg.core.forest.inputs import ModelInput


@dataclass(frozen=True)
class FramePlan:
    """How one frame is labelled, resolved once from (depth, intrinsics, mount, settings) by
    the model's input adapter (`readers`); the stages only carry it out.

    name           names the frame in errors
    range_mount    the mount of a camera that measures range along each ray, whose frame is
                   read as depth first (`TopViewMount.z_depth`); None: the frame is depth
    mount          the frame's mount at its own resolution, reading depth; None for a model
                   that reads raw depth
    fill_holes_cm2 holes without depth inside one surface up to this area are filled (0: none)
    downsample     the frame is labelled at every downsample-th pixel of every downsample-th row
    work_mount     `mount` at the working resolution (None with `mount`)
    thinning       (radius px, jump mm) of a stereo camera's edge thinning; radius 0: none
    smoothing      passes of the edge-preserving smoothing (0: none)
    stride         the forest walks every stride-th pixel of every stride-th row
    crf            the CRF settings, its Potts weight chosen for the camera's noise
    island_intrinsics  the optics blob areas are measured with, at the working resolution
    background     what the background stage does with the Segmenter's recorded background:
                   `off` (nothing), `measure` (count what matches it and what went missing)
                   or `gate` (count, and send the pixels that match it to background)
    """

    name: str
    range_mount: TopViewMount | None
    mount: TopViewMount | None
    fill_holes_cm2: float
    downsample: int
    work_mount: TopViewMount | None
    thinning: tuple[int, float]
    smoothing: int
    stride: int
    crf: CRFConfig
    island_intrinsics: Intrinsics
    background: str = "off"


@dataclass
class FrameState:
    """One frame on its way through the stages; each stage reads what earlier ones left.

    depth          the frame as given; after `pre`, at the working resolution (holes filled):
                   what the CRF and the island rules read
    full_depth     after `pre`: the frame at its own resolution, holes filled (what labels
                   are brought back to)
    forest_depth   after `pre`: `depth` thinned and smoothed, what the model input is built from
    inp            after `model_input`: what the forest reads
    proba          after `forest`: the posteriors buffer; on a grid (`lazy`) only the ones the
                   CRF reads are stored, `fill(mask)` stores more (None: all)
    summary        after `forest`: the posteriors' argmax and top two, for the CRF
    labels         after `crf`: labels at the working resolution; after `post`, the frame's
    counts         every stage's counters for this frame
    floor_share    set by a stage that widens the floor gate (`background`): the floor gate's
                   own share before it did; None: `inp.floor_share()`
    background_valid_px  after `background`: the background's pixels on the working grid
                   (0 without one)
    heights_mm     the working frame's heights above the floor, once a stage asked for them
                   (`heights`)
    """

    plan: FramePlan
    depth: np.ndarray
    full_depth: np.ndarray | None = None
    forest_depth: np.ndarray | None = None
    inp: ModelInput | None = None
    proba: np.ndarray | None = None
    summary: Summary | None = None
    lazy: bool = False
    fill: Callable[[np.ndarray | None], np.ndarray] | None = None
    labels: np.ndarray | None = None
    working_forest_labels: Callable[[], np.ndarray] | None = None
    counts: dict[str, int] = field(default_factory=dict)
    floor_share: float | None = None
    background_valid_px: int = 0
    heights_mm: np.ndarray | None = None

    def heights(self) -> np.ndarray:
        """(h, w) float32 height above the floor (mm) of each working pixel (NaN without
        depth), computed once for the stages after the CRF (which leave `depth` as it is)."""
        if self.heights_mm is None:
            self.heights_mm = self.plan.work_mount.height_map_mm(self.depth)
        return self.heights_mm

    def posteriors(self) -> np.ndarray:
        """Every posterior of this frame, the ones a grid left out stored first."""
        return self.fill(None)
