"""Post-processing: blobs too small to be what they are labelled take their border's label
(`core.islands`), then the labels come back to the frame's resolution by depth
(`core.resolution.upsample_labels`)."""

from __future__ import annotations

from topseg.core import labels as L
from topseg.core.islands import (
    EDGE_HEAD_SHARE,
    FURNITURE_COUNTED,
    ISLAND_EDGE_PX,
    SATELLITE_RADIUS_CM,
    edge_shares,
    island_areas,
    relabel_islands,
)
from topseg.core.resolution import upsample_labels
from topseg.core.stages.base import CRFS_SHARE, Stage
from topseg.core.stages.plan import FrameState


class PostStage(Stage):
    """Island rules (not in CRF mode none), then labels at the frame's resolution."""

    name = "post"
    counters = ("small_heads", "small_furniture", "satellite_heads")
    share = CRFS_SHARE

    def run(self, frame: FrameState) -> None:
        """Relabel small blobs in place, count them, bring the labels to full resolution."""
        heads, furniture, satellites = self._relabel_islands(frame)
        frame.counts.update(
            small_heads=heads, small_furniture=furniture, satellite_heads=satellites
        )
        factor = frame.plan.downsample
        if factor == 1:
            return
        small, full, working = frame.depth, frame.full_depth, frame.working_forest_labels
        frame.labels = upsample_labels(full, frame.labels, small, factor)
        frame.working_forest_labels = lambda: upsample_labels(full, working(), small, factor)

    def _relabel_islands(self, frame: FrameState) -> tuple[int, int, int]:
        """(small head blobs, small furniture and plant blobs, satellite heads) relabelled."""
        if not self.model.config.relabels_islands:
            return 0, 0, 0
        cfg = self.model.config.post
        areas = island_areas(cfg.min_head_cm2, cfg.min_furniture_cm2, cfg.min_plant_cm2)
        small, satellites = relabel_islands(
            frame.labels, frame.depth, frame.plan.island_intrinsics, areas,
            cfg.satellite_head_cm2, SATELLITE_RADIUS_CM, ISLAND_EDGE_PX,
            edge_shares(EDGE_HEAD_SHARE),
        )  # fmt: skip
        return int(small[L.HEAD]), int(small[list(FURNITURE_COUNTED)].sum()), satellites
