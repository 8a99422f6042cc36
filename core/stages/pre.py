"""Pre-processing: "no reading" (65535) read as no depth, range read as depth, small holes
filled, decimation, edge thinning and smoothing, as the frame's plan says. The CRF and the island rules read the working depth;
the model input is built from the thinned and smoothed copy."""

from __future__ import annotations

from topseg.core.camera import check_depth, without_no_reading
from topseg.core.denoise import edge_table, smooth_depth
from topseg.core.fattening import thin_edges
from topseg.core.holes import fill_holes
from topseg.core.resolution import decimate
from topseg.core.stages.base import Stage
from topseg.core.stages.plan import FrameState


class PreStage(Stage):
    """No reading, range to depth, holes, decimation, thinning, smoothing (`FramePlan`)."""

    name = "pre"
    counters = ("filled_holes",)

    def run(self, frame: FrameState) -> None:
        """Leave `full_depth`, the working `depth` and `forest_depth` on the frame."""
        plan = frame.plan
        depth = without_no_reading(frame.depth)  # as calibration reads it: never floor
        if plan.range_mount is not None:
            depth = plan.range_mount.z_depth(depth)
        filled = 0
        if plan.mount is not None and plan.fill_holes_cm2 > 0:
            depth, filled = fill_holes(depth, plan.mount.intrinsics, plan.fill_holes_cm2)
        frame.counts["filled_holes"] = filled
        frame.full_depth = depth
        if plan.downsample > 1:
            depth = decimate(depth, plan.downsample)
        frame.depth = depth
        radius, jump_mm = plan.thinning
        if radius > 0 or plan.smoothing > 0:
            depth = check_depth(depth, "model input")
        if radius > 0:
            depth = thin_edges(depth, radius, jump_mm)
        if plan.smoothing > 0:
            mount = plan.work_mount
            edges = edge_table(mount.sensor, float(mount.noise_scale))
            depth = smooth_depth(depth, edges, iterations=plan.smoothing)
        frame.forest_depth = depth
