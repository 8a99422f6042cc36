"""How a forest's features are drawn and read (`FeatureConfig`), apart from the kernels that
read them (`features`), so that the model input (`inputs`) can name it."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from topseg.core.config import from_dict, setting

#: what `FeatureConfig.off_image` and `FeatureConfig.edge_gaps` may say
OFF_IMAGE_READS = ("nearest", "background")


@dataclass(frozen=True)
class FeatureConfig:
    """The feature pool drawn per tree.

    n_features: PC, the pool size (paper: 300).
    patch_px: side of the square patch the offsets stay within at the reference depth
        (paper: 64, so |u|, |v| <= 32 px per axis).
    reference_depth_mm: depth at which `patch_px` is measured; ~2500 mm is the height of a
        person's shoulders and table tops in a 3.5 m top view.
    background_mm: what a probe off the image or on no depth reads; larger than any depth.
    absolute_fraction: share of the pool whose v offset points off every image, so that
        f(s) = p(s + u/d(s)) - background_mm: the probe's depth against a fixed value, i.e.
        its height above the floor for a fixed top-view mount. Not in the paper (0 keeps
        its pure depth differences, which cannot tell a table's flat interior from the
        floor); 0.2 lifts procedural-scene pixel accuracy from ~0.86 to ~0.97
        (tests/test_forest_learn.py). It gives up depth invariance for those features; a
        height model (`inputs.model_input`) reads height above the floor there instead.
    canonical_height_mm: C, a height model's normalisation constant (not a mount): probes
        read C - height, the depth a virtual camera C mm above the floor, looking straight
        down, would see (`inputs.model_input`).
    reference_focal_px: the focal length (px) the offsets are defined at: on a camera of
        focal length fx an offset moves a probe fx / reference_focal_px as far (the default
        is Kinect v1's, so on a Kinect v1 offsets are not scaled).
    off_image: what a probe outside the image reads: "nearest", the pixel on the image's
        edge nearest to it, or "background", `background_mm` (what a model whose
        header lacks the key reads, `model_header.model_features`). On the
        time-of-flight walker stand-ins (2.4-3.6 m), two-tree models trained alike found
        heads at the image's edge with precision 0.82-0.94 reading "nearest" against
        0.52-0.75 reading "background" (docs/results.md).
    edge_gaps: what a probe on a no-depth region touching the image's edge reads (a
        time-of-flight camera's ring outside its valid circle, a stereo camera's invalid
        band, a resampled frame's empty border): "nearest", the surface nearest to it
        (`edge_gaps.fill_edge_gaps`, as if the region were off the image), or
        "background", `background_mm` like any pixel without depth (what a model whose
        header lacks the key reads).
    """

    @property
    def nearest_off_image(self) -> bool:
        """Whether a probe outside the image reads the nearest edge pixel (the kernels' flag)."""
        return self.off_image == "nearest"

    n_features: int = setting(
        300, flag="features", kind="int", lo=1, hi=1_000_000, help="feature pool per tree (PC)"
    )
    patch_px: int = 64
    reference_depth_mm: float = 2500.0
    background_mm: int = 10000
    absolute_fraction: float = setting(
        0.0,
        flag="absolute-fraction",
        lo=0.0,
        hi=1.0,
        help="share of the pool comparing a probe with a fixed depth (not in the paper; 0)",
    )
    canonical_height_mm: float = 4000.0
    reference_focal_px: float = 570.3
    off_image: str = setting(
        "nearest",
        flag="off-image",
        kind="choice",
        choices=OFF_IMAGE_READS,
        help="what a probe off the image reads: the nearest pixel on the image's edge "
        "(default; a person cut by the edge reads as going on), or the background constant",
    )
    edge_gaps: str = setting(
        "nearest",
        flag="edge-gaps",
        kind="choice",
        choices=OFF_IMAGE_READS,
        help="what a probe on a no-depth region touching the image's edge reads (a "
        "time-of-flight camera's ring, a stereo camera's invalid band): the surface nearest "
        "to it (default; as if off the image), or the background constant",
    )

    def __post_init__(self) -> None:
        for name in ("off_image", "edge_gaps"):
            if getattr(self, name) not in OFF_IMAGE_READS:
                raise ValueError(
                    f"{name} must be one of {', '.join(OFF_IMAGE_READS)}, "
                    f"got {getattr(self, name)!r}"
                )
        for name in ("reference_depth_mm", "absolute_fraction", "canonical_height_mm"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be a finite number, got {getattr(self, name)}")
        if not np.isfinite(self.reference_focal_px):
            raise ValueError(f"reference_focal_px must be > 0, got {self.reference_focal_px}")
        if not 1 <= self.n_features <= 1_000_000:
            raise ValueError(f"n_features must be in [1, 1000000], got {self.n_features}")
        if not 2 <= self.patch_px <= 4096:
            raise ValueError(f"patch_px must be in [2, 4096], got {self.patch_px}")
        if self.n_features < 1:
            raise ValueError(f"n_features must be >= 1, got {self.n_features}")
        if self.patch_px < 2:
            raise ValueError(f"patch_px must be >= 2, got {self.patch_px}")
        if self.reference_depth_mm <= 0:
            raise ValueError(f"reference_depth_mm must be > 0, got {self.reference_depth_mm}")
        if not 0.0 <= self.absolute_fraction <= 1.0:
            raise ValueError(f"absolute_fraction must be in [0, 1], got {self.absolute_fraction}")
        if not 0 < self.canonical_height_mm < self.background_mm:
            raise ValueError(
                f"canonical_height_mm must be in (0, background_mm), got {self.canonical_height_mm}"
            )
        if self.reference_focal_px <= 0:
            raise ValueError(f"reference_focal_px must be > 0, got {self.reference_focal_px}")
        if not 0 < self.background_mm <= 16000:
            # clamped probes differ by at most background_mm, which must fit in int16
            raise ValueError(f"background_mm must be in (0, 16000], got {self.background_mm}")

    @property
    def max_offset(self) -> float:
        """Largest |offset| component, pixel*mm."""
        return self.patch_px / 2 * self.reference_depth_mm

    def to_dict(self) -> dict:
        """The config as a plain dict (`from_dict` reads it back)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "feature config") -> FeatureConfig:
        """The config in `d` (`to_dict`'s form); a key missing takes its default, an unknown or
        mistyped one is a ConfigError naming it."""
        return from_dict(cls, d, source)
