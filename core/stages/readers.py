"""Input adapters: how a model reads a frame, and so how a frame's plan is resolved.

A model trained on heights above the floor (`HeightReader`) reads every frame through its
camera's mount: range read as depth, holes filled, a working resolution and a grid stride
from the mount, stereo edges thinned and noisy frames smoothed, and a stronger CRF for a
noisy camera. A model trained on raw depth (`DepthReader`) reads raw depth at its own
camera's resolution and nothing else. The Segmenter holds one adapter and never asks which.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from topseg.core.camera import KINECT_V1, Intrinsics, TopViewMount
from topseg.core.denoise import needs_denoise, passes
from topseg.core.errors import TopsegError
from topseg.core.fattening import thinning_of
from topseg.core.forest.inputs import ModelInput, height_input, legacy_input
from topseg.core.forest.predict import grid_stride
from topseg.core.resolution import auto_downsample, decimated_mount
from topseg.core.segmenter_config import SegmenterConfig
from topseg.core.stages.plan import FramePlan

if TYPE_CHECKING:
    from topseg.core.crf import CRFConfig
    from topseg.core.forest.features import FeatureConfig

#: slack on the trained height range and tilt before a camera counts as outside them
HEIGHT_SLACK_MM = 100.0
TILT_SLACK_DEG = 1.0


class ModelReader(Protocol):
    """What the Segmenter asks of a model's input adapter."""

    reads_height: bool

    def plan(
        self,
        depth: np.ndarray,
        intrinsics: Intrinsics | None,
        mount: TopViewMount | None,
        name: str,
        config: SegmenterConfig,
    ) -> FramePlan:
        """The frame's plan; TopsegError naming the frame when it cannot be read."""
        ...

    def model_input(self, depth: np.ndarray, plan: FramePlan) -> ModelInput:
        """What the forest reads of the (pre-processed) frame."""
        ...

    def outside_trained_for(self, mount: TopViewMount) -> str | None:
        """Why a camera on `mount` lies outside what the model was trained for, or None."""
        ...

    def warm_up_mount(self) -> TopViewMount | None:
        """A small frame's mount for compiling the kernels (None: frames need none)."""
        ...


def noisy_crf(crf: CRFConfig, mount: TopViewMount) -> CRFConfig:
    """`crf` with its Potts weight raised to `noisy_smoothness` for frames from a noisy camera
    (those `denoise.needs_denoise` smooths), else `crf` itself."""
    if crf.noisy_smoothness <= crf.smoothness or not needs_denoise(mount):
        return crf
    return replace(crf, smoothness=crf.noisy_smoothness)


class HeightReader:
    """The adapter of a model that reads heights above the floor (header `"input": "height"`)."""

    reads_height = True

    def __init__(self, features: FeatureConfig, trained_for: dict[str, Any] | None) -> None:
        self.features = features
        self.trained_for = trained_for

    def frame_mount(
        self,
        shape: tuple[int, ...],
        intrinsics: Intrinsics | None,
        mount: TopViewMount | None,
        name: str,
        config: SegmenterConfig,
    ) -> TopViewMount:
        """The mount the frame is read with: `mount`, else the config's, with the frame's own
        intrinsics when it says them. TopsegError naming the frame when there is none or the
        frame's size is not its camera's."""
        mount = mount if mount is not None else config.mount
        if mount is None:
            raise TopsegError(
                f"{name}: the model reads heights above the floor and needs the camera's mount "
                "(calibrate it with `topseg calibrate` and pass --mount)"
            )
        if intrinsics is not None and intrinsics != mount.intrinsics:
            mount = replace(mount, intrinsics=intrinsics)
        k = mount.intrinsics
        if shape != k.shape:
            got = f"{shape[1]}x{shape[0]}" if len(shape) == 2 else f"of shape {shape}"
            raise TopsegError(
                f"{name}: frame is {got} but its camera's intrinsics are {k.width}x{k.height}"
            )
        return mount

    def plan(self, depth, intrinsics, mount, name, config) -> FramePlan:
        """The plan of a frame read through its mount (see the module)."""
        given = self.frame_mount(np.shape(depth), intrinsics, mount, name, config)
        full = replace(given, radial=False) if given.radial else given
        grid = config.grid
        factor = grid.downsample if grid.downsample is not None else auto_downsample(full)
        work = full if factor == 1 else decimated_mount(full, factor)
        return FramePlan(
            name=name,
            range_mount=given if given.radial else None,
            mount=full,
            fill_holes_cm2=config.pre.fill_holes_cm2,
            downsample=factor,
            work_mount=work,
            thinning=thinning_of(work),
            smoothing=passes(work),
            stride=grid.stride if grid.stride is not None else grid_stride(work),
            crf=noisy_crf(config.crf, work),
            island_intrinsics=work.intrinsics,
        )

    def model_input(self, depth: np.ndarray, plan: FramePlan) -> ModelInput:
        """Heights, offset scales and the floor gate of the frame (`forest.inputs`)."""
        return height_input(depth, plan.work_mount, self.features)

    def outside_trained_for(self, mount: TopViewMount) -> str | None:
        """The reason `mount` lies outside the model's `trained_for`, or None."""
        if not self.trained_for:
            return None
        reasons = []
        lo, hi = self.trained_for.get("height_mm", [None, None])
        h = mount.height_mm
        if (
            lo is not None
            and hi is not None
            and not (lo - HEIGHT_SLACK_MM <= h <= hi + HEIGHT_SLACK_MM)
        ):
            reasons.append(
                f"camera height {h / 1000:.2f} m is outside the {lo / 1000:.2f}-"
                f"{hi / 1000:.2f} m the model was trained for"
            )
        max_tilt = self.trained_for.get("tilt_deg")
        if max_tilt is not None and mount.tilt_deg() > max_tilt + TILT_SLACK_DEG:
            reasons.append(
                f"camera tilt {mount.tilt_deg():.1f} deg exceeds the model's {max_tilt:.1f} deg"
            )
        sensors = self.trained_for.get("sensors")
        if sensors and mount.sensor not in sensors:
            reasons.append(
                f"sensor {mount.sensor} is not one the model was trained for ({', '.join(sensors)})"
            )
        return "; ".join(reasons) or None

    def warm_up_mount(self) -> TopViewMount:
        """A 64x48 virtual camera at the model's canonical height (a constant of the model)."""
        return TopViewMount(KINECT_V1.scaled_to(64, 48), self.features.canonical_height_mm)


class DepthReader:
    """The adapter of a model that reads raw depth: its own camera only."""

    reads_height = False

    def __init__(self, camera: Intrinsics, header: dict[str, Any]) -> None:
        self.camera = camera
        self.header = header

    def check_frame(
        self, depth: np.ndarray, intrinsics: Intrinsics | None = None, name: str = "frame"
    ) -> None:
        """The model's camera size and, when the frame says its intrinsics, focal length (its
        features are offsets scaled for that camera). TopsegError naming the frame."""
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

    def plan(self, depth, intrinsics, mount, name, config) -> FramePlan:
        """The plan of a raw-depth frame: its own resolution, no pre-processing; the frame
        checked against the model's camera unless `config.check_camera` is off."""
        if config.check_camera:
            self.check_frame(depth, intrinsics, name)
        return FramePlan(
            name=name,
            range_mount=None,
            mount=None,
            fill_holes_cm2=0.0,
            downsample=1,
            work_mount=None,
            thinning=(0, 0.0),
            smoothing=0,
            stride=config.grid.stride if config.grid.stride is not None else 1,
            crf=config.crf,
            island_intrinsics=intrinsics if intrinsics is not None else self.camera,
        )

    def model_input(self, depth: np.ndarray, plan: FramePlan) -> ModelInput:
        """V = D, S = 1 / D, no floor gate (`forest.inputs.legacy_input`)."""
        return legacy_input(depth)

    def outside_trained_for(self, mount: TopViewMount) -> str | None:
        """The reason `mount` is not the one mount the model was trained for, or None."""
        cam = self.header.get("dataset", {}).get("attrs", {}).get("camera")
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
                f"the model reads raw depth and was trained for one mount "
                f"({trained.height_mm / 1000:.2f} m, straight down); this camera is "
                f"{mount.height_mm / 1000:.2f} m up, tilted {mount.tilt_deg():.1f} deg"
            )
        return None

    def warm_up_mount(self) -> None:
        """None: a raw-depth model needs no mount."""
        return None
