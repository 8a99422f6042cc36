"""The static cell's background: pixels whose depth matches the recorded background within its
noise join the floor gate, so the forest never walks them and the CRF keeps them background
(`core.background`).

The frame's working depth (holes filled, decimated; never thinned or smoothed, as the
background was recorded) is compared with the background sampled to the working grid, which
is resolved once per camera and grid and kept. A pixel nearer than the background (a person
where it was floor or a table) stays foreground; one farther than it by more than the
tolerance saw something static go and is counted as missing (`background_missing_px`).

The plan says what to do (`FramePlan.background`): `gate`, `measure` (count only: the worker
while the background no longer matches) or `off`. Frames of another camera than the
background's are refused with one line naming the file.
"""

from __future__ import annotations

from topseg.core.background import (
    BackgroundModel,
    GateGrid,
    check_camera,
    gate_background,
    gate_grid,
)
from topseg.core.stages.base import Stage, StageModel
from topseg.core.stages.plan import FramePlan, FrameState

#: the grids kept at most (one per camera size and working resolution seen)
MAX_GRIDS = 8


class BackgroundStage(Stage):
    """The recorded background joins the floor gate (see the module)."""

    name = "background"
    counters = ("background_px", "background_missing_px")

    def __init__(self, model: StageModel) -> None:
        super().__init__(model)
        self.background: BackgroundModel | None = model.background
        self._grids: dict[tuple, GateGrid] = {}

    def run(self, frame: FrameState) -> None:
        """Count what matches the background and what went missing; gate the matches."""
        bg, plan = self.background, frame.plan
        if bg is None or plan.background == "off":
            frame.counts.update(background_px=0, background_missing_px=0)
            return
        grid = self.grid(plan)
        inp = frame.inp
        apply = plan.background == "gate"
        if apply:
            frame.floor_share = inp.floor_share()  # the floor gate's own, before it widens
        matched, missing = gate_background(frame.depth, inp.values, grid, inp.floor, apply)
        frame.counts.update(background_px=matched if apply else 0, background_missing_px=missing)
        frame.background_valid_px = grid.valid_px

    def grid(self, plan: FramePlan) -> GateGrid:
        """The background on this frame's working grid (resolved once per camera and grid);
        TopsegError when the frame's camera is not the background's."""
        camera = plan.mount.intrinsics if plan.mount is not None else plan.island_intrinsics
        radial = plan.range_mount is not None
        key = (camera, plan.downsample, radial)
        grid = self._grids.get(key)
        if grid is None:
            cfg = self.model.config.background
            check_camera(self.background, camera, cfg.path or f"of id {self.background.id[:12]}")
            grid = gate_grid(self.background, plan.downsample, cfg.sigmas, cfg.margin_mm, radial)
            if len(self._grids) >= MAX_GRIDS:
                self._grids.clear()
            self._grids[key] = grid
        return grid
