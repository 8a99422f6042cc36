"""What the forest reads: a frame's depth turned into probe values, offset scales and a floor gate.

The forest never reads raw depth. For a frame with depth D (mm) seen from mount M, a model
trained on heights (header `"input": "height"`) reads

- probe values `V = clip(round(C - h), 1, background_mm - 1)` (uint16; 0 where D == 0), with
  `h = M.height_map_mm(D)` each pixel's height above the floor and C the model's
  `canonical_height_mm`: the depth a virtual camera C mm above the floor, looking straight
  down, would read. Probe differences are then height differences and an "absolute" feature
  reads height above the floor, whatever the real camera's height and tilt;
- offset scales `S = (fx / reference_focal_px) / D` (float32, 1/mm): a feature's offset u
  (pixel*mm at the reference focal length) moves a probe by round(u * S(s)) pixels, so the
  offsets span the same metric distance on any sensor, at any resolution and any range;
- a floor gate: pixels with depth whose height is below `floor_margin_mm(D, sensor, s)` (a
  few sigma of the sensor's depth noise at that range, times the mount's measured
  `noise_scale` s, within [`MIN_FLOOR_MARGIN_MM`, `MAX_FLOOR_MARGIN_MM`]) are
  background without walking the forest. They stay probe targets (the floor is context);
- a probe image: V with each no-depth region that touches the image's edge filled from the
  surface beside it, when the model's features say so (`FeatureConfig.edge_gaps`,
  `edge_gaps.fill_edge_gaps`); those pixels still get no label.

Before any of this, a stereo camera's fattened edges are thinned by the width its noise
model expects (`core.fattening`), and a frame from a camera whose depth noise at the floor is
large (stereo cameras at range) is smoothed by an edge-preserving filter (`core.denoise`).

Models whose header has no `"input"` read the legacy input they were trained on: V = D,
S = float32(1) / float32(D), no gate.
`model_input` and `legacy_input` are the only two builders; training and inference both call
them (`input_for` picks by header).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numba
import numpy as np

from topseg.core.camera import TopViewMount, check_depth
from topseg.core.denoise import denoise
from topseg.core.fattening import unfatten
from topseg.core.forest.edge_gaps import fill_edge_gaps
from topseg.core.forest.feature_config import FeatureConfig
from topseg.core.sensors import depth_sigma_mm

if TYPE_CHECKING:
    from topseg.core.camera import TopViewMount

#: the header value of models that read heights (`model_input`)
HEIGHT_INPUT = "height"
#: the floor gate's smallest margin (mm): below this height a pixel is floor on any sensor
MIN_FLOOR_MARGIN_MM = 40.0
#: the floor gate's largest margin (mm): a noisy stereo camera far away (3 sigma is 250 mm
#: for a D435 at 4.5 m) must not gate away feet, low plants and seat cushions
MAX_FLOOR_MARGIN_MM = 150.0
#: sigmas of the sensor's depth noise the floor gate allows
FLOOR_SIGMAS = 3.0


@dataclass(frozen=True)
class ModelInput:
    """What the forest reads of one frame.

    values  (H, W) uint16 probe values (virtual depth in mm, see the module); 0: no depth
    scale   (H, W) float32 offset scale per pixel (1/mm); 0 where there is no depth
    floor   (H, W) bool: pixels the floor gate sends to background without the forest
    probes  (H, W) uint16 image the feature probes read, when it differs from `values`:
            no-depth regions touching the image's edge filled from the surface beside
            them (`FeatureConfig.edge_gaps`, `edge_gaps.fill_edge_gaps`); None: `values`.
            Which pixels are labelled still follows `values`.
    """

    values: np.ndarray
    scale: np.ndarray
    floor: np.ndarray
    probes: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the frame."""
        return self.values.shape

    @property
    def probe_values(self) -> np.ndarray:
        """The image feature probes read: `probes`, or `values` when there is none."""
        return self.values if self.probes is None else self.probes

    def above_floor(self) -> np.ndarray:
        """(H, W) bool: the pixels with depth that the floor gate did not take (the ones the
        forest labels)."""
        return (self.values > 0) & ~self.floor

    def floor_share(self) -> float:
        """Share of the pixels with depth that the floor gate skipped (0 with no depth)."""
        n = int(np.count_nonzero(self.values))
        return float(np.count_nonzero(self.floor)) / n if n else 0.0


def floor_margin_mm(
    depth_mm: np.ndarray, sensor: str = "kinect_v1", noise_scale: float = 1.0
) -> np.ndarray:
    """Height (mm) below which a pixel at this depth is floor: FLOOR_SIGMAS sigma of the
    sensor's depth noise at that range, times `noise_scale` (the camera's measured noise over
    the model's, `TopViewMount.noise_scale`), within [MIN_FLOOR_MARGIN_MM,
    MAX_FLOOR_MARGIN_MM]; float32."""
    sigma = depth_sigma_mm(depth_mm, sensor)
    margin = np.float32(FLOOR_SIGMAS * noise_scale) * sigma
    return np.clip(margin, np.float32(MIN_FLOOR_MARGIN_MM), np.float32(MAX_FLOOR_MARGIN_MM))


@functools.lru_cache(maxsize=16)
def _margin_table(sensor: str, noise_scale: float) -> np.ndarray:
    """`floor_margin_mm` of every uint16 depth, for one sensor and noise scale (a frame is one
    lookup)."""
    table = floor_margin_mm(np.arange(65536, dtype=np.float32), sensor, noise_scale)
    table.flags.writeable = False
    return table


def model_input(
    depth: np.ndarray, mount: TopViewMount, features: FeatureConfig, for_training: bool = False
) -> ModelInput:
    """The input of a height model (see the module) for a uint16 depth frame from `mount`, as
    training reads it: a radial camera's range read as depth first (`TopViewMount.z_depth`),
    a stereo camera's fattened edges thinned (`core.fattening`), frames from a noisy camera
    smoothed (`core.denoise`; `for_training`: with a training frame's passes), then
    `height_input`. The Segmenter runs the same steps as stages (`core.stages`). The frame
    must have the mount's intrinsics' shape; ValueError otherwise.
    """
    depth = _checked(depth, mount)
    depth = denoise(unfatten(mount.z_depth(depth), mount), mount, for_training)
    return height_input(depth, mount, features)


def _checked(depth: np.ndarray, mount: TopViewMount) -> np.ndarray:
    """`depth` as a C-contiguous uint16 frame of the mount's size; ValueError otherwise."""
    depth = check_depth(depth, "model input")
    k = mount.intrinsics
    if depth.shape != k.shape:
        raise ValueError(
            f"frame is {depth.shape[1]}x{depth.shape[0]} but its mount's camera is "
            f"{k.width}x{k.height}"
        )
    return depth


def height_input(depth: np.ndarray, mount: TopViewMount, features: FeatureConfig) -> ModelInput:
    """Probe values, offset scales and the floor gate (see the module) of a depth frame from
    `mount` that is already pre-processed; the probe image with edge gaps filled when the
    features say so. ValueError when the frame is not the mount's size."""
    depth = _checked(depth, mount)
    k = mount.intrinsics
    values = np.empty(depth.shape, np.uint16)
    scale = np.empty(depth.shape, np.float32)
    floor = np.empty(depth.shape, np.bool_)
    _height_input(
        depth,
        mount.height_rays(),
        np.float32(mount.height_mm),
        np.float32(features.canonical_height_mm),
        np.float32(int(features.background_mm) - 1),
        np.float32(k.fx / features.reference_focal_px),
        _margin_table(mount.sensor, float(mount.noise_scale)),
        values,
        scale,
        floor,
    )
    probes = fill_edge_gaps(values)[0] if features.edge_gaps == "nearest" else None
    return ModelInput(values, scale, floor, None if probes is values else probes)


@numba.njit(cache=True, parallel=True)
def _height_input(depth, ray, height, canonical, top, focal_ratio, margin, values, scale, floor):
    """`model_input`'s three images in one pass over the frame, in float32 as
    `TopViewMount.height_map_mm` computes heights (h = depth * ray + height; `ray` is
    `TopViewMount.height_rays`): values clip(floor(canonical - h + 0.5), 1, top), scale
    focal_ratio / depth, floor h < margin[depth]; zeros and False without depth."""
    for r in numba.prange(depth.shape[0]):
        for c in range(depth.shape[1]):
            d = depth[r, c]
            if d == 0:
                values[r, c] = 0
                scale[r, c] = np.float32(0.0)
                floor[r, c] = False
                continue
            z = np.float32(d)
            h = z * ray[r, c] + height
            v = np.floor((canonical - h) + np.float32(0.5))
            values[r, c] = np.uint16(min(max(v, np.float32(1.0)), top))
            scale[r, c] = focal_ratio / z
            floor[r, c] = h < margin[d]


def legacy_input(depth: np.ndarray) -> ModelInput:
    """The input of a depth model (no heights): V = D, S = float32(1) / float32(D) (as the
    kernels computed it from depth), 0 where D == 0, and no floor gate."""
    depth = check_depth(depth, "model input")
    d = depth.astype(np.float32)
    with np.errstate(divide="ignore"):
        scale = np.float32(1.0) / d
    scale[depth == 0] = 0.0
    return ModelInput(depth, scale, np.zeros(depth.shape, bool))


def reads_height(header: dict[str, Any] | None) -> bool:
    """Whether a model header says the model reads heights (`model_input`), not depth."""
    return (header or {}).get("input") == HEIGHT_INPUT


def as_input(x: np.ndarray | ModelInput) -> ModelInput:
    """A ModelInput as is; a depth frame as its legacy input (for callers of depth kernels)."""
    return x if isinstance(x, ModelInput) else legacy_input(x)


def check_input(x: ModelInput, user: str = "forest") -> ModelInput:
    """`x` with C-contiguous uint16 values (and probes), float32 scale and bool floor of one
    shape."""
    values = check_depth(x.values, user)
    scale = np.ascontiguousarray(x.scale, np.float32)
    floor = np.ascontiguousarray(x.floor, np.bool_)
    probes = None if x.probes is None else check_depth(x.probes, user)
    if scale.shape != values.shape or floor.shape != values.shape:
        raise ValueError(
            f"{user}: values {values.shape}, scale {scale.shape} and floor {floor.shape} differ"
        )
    if probes is not None and probes.shape != values.shape:
        raise ValueError(f"{user}: probes {probes.shape} and values {values.shape} differ")
    return ModelInput(values, scale, floor, probes)


def header_fields(features: FeatureConfig, trained_for: dict | None = None) -> dict[str, Any]:
    """What a height model's header says about its input: `input`, `features` and, when
    known, `trained_for` (the mounts and sensors of its training frames)."""
    out: dict[str, Any] = {"input": HEIGHT_INPUT, "features": features.to_dict()}
    if trained_for is not None:
        out["trained_for"] = trained_for
    return out


def trained_for(mounts: list[TopViewMount]) -> dict[str, Any]:
    """The range a set of training mounts covers: `height_mm` [lo, hi], `tilt_deg` (max),
    `sensors` and `resolutions` ([w, h], sorted)."""
    if not mounts:
        raise ValueError("no mounts to describe")
    heights = [float(m.height_mm) for m in mounts]
    tilts = [float(m.tilt_deg()) if hasattr(m, "tilt_deg") else 0.0 for m in mounts]
    return {
        "height_mm": [round(min(heights), 1), round(max(heights), 1)],
        "tilt_deg": round(max(tilts), 2),
        "sensors": sorted({getattr(m, "sensor", "kinect_v1") for m in mounts}),
        "resolutions": [
            list(r) for r in sorted({(m.intrinsics.width, m.intrinsics.height) for m in mounts})
        ],
    }


def dataset_mount(ds: Any, k: int) -> TopViewMount:
    """The mount of the k-th frame of a dataset: `ds.mount(k)` where the dataset stores one
    per frame, else its `camera` attribute (datasets without per-frame mounts)."""
    per_frame = getattr(ds, "mount", None)
    if callable(per_frame):
        return per_frame(k)
    return TopViewMount.from_dict(ds.attrs["camera"], source="the dataset's camera")
