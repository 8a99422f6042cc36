"""Where the camera hangs: fit the floor plane in a few depth frames and turn it into a mount.

    estimate = estimate_mount(frames, intrinsics, sensor="kinect_v1")
    estimate.mount        # TopViewMount: height above the floor, pitch, roll, intrinsics
    estimate.residual_mm  # RMS distance of the floor inliers from the fitted plane
    estimate.mount.noise_scale  # that residual over the sensor model's noise at those depths

Pure: arrays in, results out (the mount file lives in `core/formats/mount_file.py`).

The fit works in inverse depth. A floor point on pixel ray r = ((u - cx)/fx, (v - cy)/fy, 1)
at depth z satisfies n . (z r) + d = 0, so 1/z = a u' + b v' + c exactly: a plane is a
linear model of the ray coordinates, and structured-light and stereo noise, whose depth
error grows as z^2, is about constant in 1/z. Per frame, scikit-learn's `RANSACRegressor`
finds the plane on a seeded subsample of the valid pixels with a noise-aware inlier test
(a depth residual below k sigma(z), sigma growing as z^2); then all frames' points are
pooled and the plane is refitted by least squares on its inliers.

The floor is the *farthest* large plane (a big table top is a plane too, and nearer): a
candidate plane with many valid points well beyond it (below the floor) is rejected during
the RANSAC search, so the search settles on the plane nothing lies under.

`CalibrationError` says in one line why no mount came out: no depth in the frames, no plane
covering enough of the view (also when per-frame floors disagree although the frames
themselves agree: a still camera that sees too little floor), frames that disagree (the
camera moved), a tilt beyond what the model supports, or a mount no camera can have.
"""

from __future__ import annotations

import datetime as dt
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from topseg.core import sensors
from topseg.core.camera import (
    NOISE_SCALE_RANGE,
    Intrinsics,
    TopViewMount,
    check_depth,
    check_mount,
    range_to_depth,
)
from topseg.core.denoise import MIN_SIGMA_MM, floor_sigma_mm, needs_denoise
from topseg.core.errors import TopsegError
from topseg.core.fattening import thinning_line
from topseg.core.sensors import depth_sigma_mm

#: frames `_fits_as_range` tries reading as range when no floor fits them as depth
RADIAL_TRIES = 5


class CalibrationError(TopsegError):
    """No trustworthy mount in these frames; the message says why in one line."""


@dataclass(frozen=True)
class CalibrationConfig:
    """How the floor is found and when the result is refused.

    points_per_frame: valid pixels drawn (seeded) from each frame for the fit.
    seed: the subsample's and RANSAC's random seed (the same frames give the same mount).
    min_threshold_mm, k_sigma, noise_mm_per_m2: the inlier test; a point is on the plane
        when its depth is within max(min_threshold_mm, k_sigma * sigma(z)) of the plane's,
        sigma(z) the sensor's depth noise (`core.sensors`), or, for a sensor not known
        there, noise_mm_per_m2 * z_m^2 (Kinect v1 like: 1.4 mm per m^2, after Khoshelham
        & Elberink 2012).
    beyond_factor, max_beyond_share: a candidate floor is rejected when more than this
        share of the valid points lies beyond it (farther, i.e. below it) by more than
        beyond_factor inlier thresholds: it is a table top, not the floor.
    max_candidate_tilt_deg: planes steeper than this are walls, never floor candidates.
    min_inlier_share: the floor must hold at least this share of the valid pixels over all
        frames used; one frame's floor at least half of it (a crowd may pass in some).
    max_tilt_deg: the largest tilt accepted (the model is trained up to 10 deg; a margin).
    max_height_spread_mm, max_angle_spread_deg: how far per-frame floors may disagree.
    min_valid_points: a frame with fewer valid pixels is skipped.
    max_trials: RANSAC iterations per frame at most.
    max_depth_mm: readings farther than this are left out of the fit, as if they had no
        depth: no top-view camera hangs that high, and some cameras send 65535 for "no
        reading", which would otherwise look like a plane below the floor.
    min_hidden_floor_share: a flat surface below the plane found, showing in at least this
        share of the valid pixels, is the floor mostly hidden (a table over most of the
        view): refused.
    """

    points_per_frame: int = 3000
    seed: int = 0
    min_threshold_mm: float = 15.0
    noise_mm_per_m2: float = 1.4
    k_sigma: float = 3.0
    beyond_factor: float = 2.0
    max_beyond_share: float = 0.08
    max_candidate_tilt_deg: float = 45.0
    min_inlier_share: float = 0.3
    max_tilt_deg: float = 15.0
    max_height_spread_mm: float = 50.0
    max_angle_spread_deg: float = 1.0
    min_valid_points: int = 500
    max_trials: int = 200
    max_depth_mm: float = 20000.0
    min_hidden_floor_share: float = 0.02

    def __post_init__(self) -> None:
        if self.points_per_frame < 10 or self.max_trials < 1 or self.min_valid_points < 3:
            raise ValueError("points_per_frame >= 10, min_valid_points >= 3, max_trials >= 1")
        if not 0 < self.min_inlier_share <= 1 or not 0 <= self.max_beyond_share < 1:
            raise ValueError("min_inlier_share must be in (0, 1], max_beyond_share in [0, 1)")
        if min(self.min_threshold_mm, self.k_sigma, self.beyond_factor) <= 0:
            raise ValueError("inlier thresholds must be positive")

    def threshold(self, sensor: str) -> Threshold:
        """The inlier threshold for frames of `sensor` (its noise, or Kinect-like if unknown)."""
        return Threshold.of(sensor, self)


class Threshold:
    """The inlier threshold (mm of depth) as a function of depth: k sigma(z), at least a floor.

    sigma(z) is tabulated once (every 50 mm to 12 m) from the sensor's noise model, so
    calling it on thousands of points costs one `np.interp`.
    """

    GRID_MM = np.arange(0.0, 12001.0, 50.0)

    def __init__(self, table_mm: np.ndarray, description: str) -> None:
        self.table_mm = table_mm
        self.description = description

    @classmethod
    def of(cls, sensor: str, cfg: CalibrationConfig) -> Threshold:
        """The threshold for `sensor` under `cfg`."""
        z_m = cls.GRID_MM / 1000.0
        try:
            sigma = np.asarray(sensors.get_sensor(sensor).sigma_mm(z_m), np.float64)
            what = f"{cfg.k_sigma:g} sigma of {sensor} noise"
        except TopsegError:
            sigma = cfg.noise_mm_per_m2 * z_m * z_m
            what = f"{cfg.k_sigma:g} x {cfg.noise_mm_per_m2:g} mm/m^2 z^2"
        table = np.maximum(cfg.min_threshold_mm, cfg.k_sigma * sigma)
        return cls(table, f"max({cfg.min_threshold_mm:g} mm, {what})")

    def __call__(self, z_mm: np.ndarray) -> np.ndarray:
        """The threshold (mm) at each depth in `z_mm`."""
        return np.interp(np.asarray(z_mm, np.float64), self.GRID_MM, self.table_mm)


@dataclass(frozen=True)
class MountEstimate:
    """A mount fitted from frames, with how well the floor fitted and how the frames agreed.

    residual_mm: RMS distance of the floor inliers from the plane.
    inlier_share: share of the valid pixels on the floor.
    frames_used / frames_given: frames that gave a floor / frames passed in.
    height_spread_mm, angle_spread_deg: largest difference between one frame's floor and
        the consensus (height, normal angle).
    made_at: when the estimate was made, UTC ISO 8601.
    """

    mount: TopViewMount
    residual_mm: float
    inlier_share: float
    frames_used: int
    frames_given: int
    height_spread_mm: float
    angle_spread_deg: float
    made_at: str

    def fit_dict(self) -> dict:
        """The fit's figures as a plain dict (the mount file's `fit` section)."""
        return {
            "residual_mm": round(float(self.residual_mm), 3),
            "inlier_share": round(float(self.inlier_share), 4),
            "frames_used": int(self.frames_used),
            "frames_given": int(self.frames_given),
            "height_spread_mm": round(float(self.height_spread_mm), 3),
            "angle_spread_deg": round(float(self.angle_spread_deg), 4),
            "made_at": self.made_at,
        }

    def summary(self) -> str:
        """Human lines: height, pitch, roll, tilt, residual, inlier share, camera, sensor, and
        whether its frames are thinned (`core.fattening`) and smoothed before the forest."""
        m, k = self.mount, self.mount.intrinsics
        return "\n".join(
            [
                f"height     {m.height_mm:8.1f} mm above the floor",
                f"pitch      {m.pitch_deg:+8.2f} deg",
                f"roll       {m.roll_deg:+8.2f} deg",
                f"tilt       {m.tilt_deg():8.2f} deg from straight down",
                f"residual   {self.residual_mm:8.1f} mm RMS "
                f"(x{m.noise_scale:.2f} the {m.sensor} noise model: the floor gate's scale)",
                f"floor      {100 * self.inlier_share:8.1f} % of the valid pixels",
                f"frames     {self.frames_used} of {self.frames_given} "
                f"(spread {self.height_spread_mm:.1f} mm, {self.angle_spread_deg:.2f} deg)",
                f"camera     {k.width}x{k.height} fx {k.fx:.1f} fy {k.fy:.1f} "
                f"cx {k.cx:.1f} cy {k.cy:.1f}",
                f"sensor     {m.sensor}",
                "depth      "
                + (
                    "range along each pixel's ray (radial distance): read as depth along "
                    "the optical axis"
                    if m.radial
                    else "along the optical axis"
                ),
                thinning_line(m),
                _smoothing_line(m),
            ]
        )


def _smoothing_line(m: TopViewMount) -> str:
    """Whether frames from this mount are smoothed before the forest (`core.denoise`)."""
    sigma = floor_sigma_mm(m)
    if needs_denoise(m):
        return f"smoothing  on: noise {sigma:.0f} mm at the floor (>= {MIN_SIGMA_MM:g} mm)"
    return f"smoothing  off: noise {sigma:.0f} mm at the floor (< {MIN_SIGMA_MM:g} mm)"


# ---------------------------------------------------------------------------- the points


@dataclass(frozen=True)
class _Points:
    """Sampled valid pixels of one frame: ray coordinates (N, 2), depth mm and 1000/depth."""

    rays: np.ndarray  # (N, 2) float64: ((u - cx) / fx, (v - cy) / fy)
    z_mm: np.ndarray  # (N,) float64
    w: np.ndarray  # (N,) float64: 1000 / z_mm (inverse depth, 1/m)
    valid: int  # valid pixels in the frame


def _sample(
    depth: np.ndarray, k: Intrinsics, n: int, rng: np.random.Generator, max_mm: float
) -> _Points:
    """Up to `n` valid pixels of `depth` (depth, and at most `max_mm`), drawn without
    replacement."""
    valid = (depth > 0) & (depth <= max_mm)
    flat = np.flatnonzero(valid)
    count = flat.size
    if flat.size > n:
        flat = np.sort(rng.choice(flat, n, replace=False))
    v, u = np.divmod(flat, depth.shape[1])
    z = depth.ravel()[flat].astype(np.float64)
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy], axis=1)
    return _Points(rays, z, 1000.0 / z if z.size else z, int(count))


def _design(rays: np.ndarray) -> np.ndarray:
    """[u', v', 1] per point."""
    return np.column_stack([rays, np.ones(len(rays))])


def _plane_depth(coef: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Depth (mm) at which each ray meets the plane 1/z = a u' + b v' + c; inf if never."""
    w = _design(rays) @ coef
    with np.errstate(divide="ignore"):
        return np.where(w > 0, 1000.0 / np.where(w > 0, w, 1.0), np.inf)


def _tilt_of(coef: np.ndarray) -> float:
    """Degrees between the plane's normal (a, b, c) and the optical axis."""
    return math.degrees(math.acos(min(1.0, abs(coef[2]) / float(np.linalg.norm(coef)))))


def _beyond_share(coef: np.ndarray, pts: _Points, thr_mm: np.ndarray, factor: float) -> float:
    """Share of the points farther than the plane by more than `factor` thresholds."""
    z_plane = _plane_depth(coef, pts.rays)
    beyond = pts.z_mm - z_plane > factor * thr_mm
    return float(np.count_nonzero(beyond)) / max(1, len(pts.z_mm))


def _inliers(coef: np.ndarray, pts: _Points, thr: Threshold) -> np.ndarray:
    """Points whose depth is within the noise threshold of the plane's."""
    return np.abs(pts.z_mm - _plane_depth(coef, pts.rays)) <= thr(pts.z_mm)


def _ransac_plane(
    pts: _Points, cfg: CalibrationConfig, thr: Threshold, seed: int
) -> np.ndarray | None:
    """(a, b, c) of the farthest large plane in one frame's points, or None if none."""
    from sklearn.linear_model import LinearRegression, RANSACRegressor

    def loss(w_true: np.ndarray, w_pred: np.ndarray) -> np.ndarray:
        z_true = 1000.0 / w_true
        with np.errstate(divide="ignore"):
            z_pred = np.where(w_pred > 0, 1000.0 / np.where(w_pred > 0, w_pred, 1.0), np.inf)
        return np.abs(z_true - z_pred) / thr(z_true)

    def is_model_valid(model, _x, _y) -> bool:
        coef = np.array([*model.coef_, model.intercept_], np.float64)
        if not coef[2] > 0 or _tilt_of(coef) > cfg.max_candidate_tilt_deg:
            return False
        share = _beyond_share(coef, pts, thr_all, cfg.beyond_factor)
        return share <= cfg.max_beyond_share

    thr_all = thr(pts.z_mm)
    ransac = RANSACRegressor(
        LinearRegression(),
        min_samples=3,
        residual_threshold=1.0,
        loss=loss,
        is_model_valid=is_model_valid,
        max_trials=cfg.max_trials,
        stop_probability=0.999,
        random_state=seed,
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "max_trials reached": handled below as no plane
            ransac.fit(pts.rays, pts.w)
    except ValueError:  # no candidate plane was valid, or none had inliers
        return None
    est = ransac.estimator_
    coef = np.array([*est.coef_, est.intercept_], np.float64)
    if not coef[2] > 0:
        return None
    return _refine(coef, [pts], thr)


def _refine(coef: np.ndarray, points: Sequence[_Points], thr: Threshold) -> np.ndarray:
    """Least squares on the plane's inliers over all `points`, three rounds."""
    rays = np.concatenate([p.rays for p in points])
    w = np.concatenate([p.w for p in points])
    pooled = _Points(rays, np.concatenate([p.z_mm for p in points]), w, 0)
    for _ in range(3):
        inl = _inliers(coef, pooled, thr)
        if np.count_nonzero(inl) < 3:
            break
        coef = np.linalg.lstsq(_design(rays[inl]), w[inl], rcond=None)[0]
    return coef


def _plane_to_mount(coef: np.ndarray, k: Intrinsics, sensor: str) -> TopViewMount:
    """The mount of the floor 1/z = a u' + b v' + c: n = (a, b, c), n . X - 1000 = 0 (mm)."""
    return TopViewMount.from_floor_plane(coef, -1000.0, k, sensor)


def _angle_deg(n1: np.ndarray, n2: np.ndarray) -> float:
    """Angle in degrees between two unit vectors."""
    return math.degrees(math.acos(float(np.clip(np.dot(n1, n2), -1.0, 1.0))))


def _check_enough(found: int, frames: int, frame_share: float) -> None:
    """CalibrationError unless a floor was found in at least half the frames."""
    if found * 2 < frames:
        raise CalibrationError(
            f"no plane covers enough of the view: a floor holding {frame_share:.0%} of the "
            f"valid pixels was found in only {found} of {frames} frames; "
            f"clear the floor under the camera or aim it at the floor"
        )


def _as_range(pts: _Points) -> _Points:
    """`pts` with each value read as range along its pixel's ray, turned into depth along
    the optical axis: z = r / |(u', v', 1)|."""
    z = pts.z_mm / np.sqrt(1.0 + np.einsum("ij,ij->i", pts.rays, pts.rays))
    return _Points(pts.rays, z, 1000.0 / z if z.size else z, pts.valid)


def _fits_as_range(
    samples: Sequence[_Points], cfg: CalibrationConfig, thr: Threshold, frame_share: float
) -> bool:
    """Whether a floor fits at least half of (up to RADIAL_TRIES of) these frames when each
    value is read as range along its pixel's ray: a radial-distance camera, whose floor is a
    bowl as depth (22 % deeper in a Kinect v1 view's corners)."""
    tried = list(samples)[:RADIAL_TRIES]
    found = 0
    for i, pts in enumerate(tried):
        z = _as_range(pts)
        coef = _ransac_plane(z, cfg, thr, cfg.seed + i)
        found += coef is not None and _inliers(coef, z, thr).mean() >= frame_share
    return found > 0 and found * 2 >= len(tried)


# ---------------------------------------------------------------------------- the estimate


def estimate_mount(
    frames: Sequence[np.ndarray],
    intrinsics: Intrinsics,
    sensor: str = "unknown",
    config: CalibrationConfig | None = None,
) -> MountEstimate:
    """The mount of the camera that took `frames` ((H, W) uint16 mm, one camera, still).

    When no floor fits the frames as depth but one fits them read as range along each
    pixel's ray (a radial-distance camera), the mount is fitted to them as such and says so
    (`TopViewMount.radial`). Raises CalibrationError (one line) when the frames hold no
    depth, no plane covers `min_inlier_share` of the view, per-frame floors disagree, or the
    tilt is too large.
    """
    return _estimate(frames, intrinsics, sensor, config or CalibrationConfig(), try_range=True)


def _estimate(
    frames: Sequence[np.ndarray],
    intrinsics: Intrinsics,
    sensor: str,
    cfg: CalibrationConfig,
    try_range: bool,
) -> MountEstimate:
    """`estimate_mount`; with `try_range` False, frames are only ever read as depth."""
    frames = [check_depth(f, "calibration") for f in frames]
    if not frames:
        raise CalibrationError("no frames to calibrate from")
    for f in frames:
        if f.shape != intrinsics.shape:
            raise CalibrationError(
                f"a frame of {f.shape[1]}x{f.shape[0]} does not match the camera's "
                f"{intrinsics.width}x{intrinsics.height}"
            )
    thr = cfg.threshold(sensor)
    rng = np.random.default_rng(cfg.seed)
    samples = [_sample(f, intrinsics, cfg.points_per_frame, rng, cfg.max_depth_mm) for f in frames]
    with_depth = [s for s in samples if s.valid >= cfg.min_valid_points]
    if not with_depth:
        best = max(s.valid for s in samples)
        raise CalibrationError(
            f"the source gives no depth: the best of {len(frames)} frames has {best} valid "
            f"pixels, at least {cfg.min_valid_points} needed"
        )

    planes, used, shares = [], [], []
    frame_share = cfg.min_inlier_share / 2
    for i, pts in enumerate(with_depth):
        coef = _ransac_plane(pts, cfg, thr, cfg.seed + i)
        share = _inliers(coef, pts, thr).mean() if coef is not None else 0.0
        if share >= frame_share:
            planes.append(coef)
            used.append(pts)
            shares.append(share)
    if (
        len(planes) * 2 < len(with_depth)
        and try_range
        and _fits_as_range(with_depth, cfg, thr, frame_share)
    ):
        z_frames = [range_to_depth(f, intrinsics) for f in frames]
        estimate = _estimate(z_frames, intrinsics, sensor, cfg, try_range=False)
        return replace(estimate, mount=replace(estimate.mount, radial=True))
    _check_enough(len(planes), len(with_depth), frame_share)

    # The consensus: the plane of a frame with a clear floor nearest the others. A frame
    # with little floor in view (a crowd, a big table) that disagrees with it found some
    # other plane and is dropped; frames with a clear floor that disagree mean the camera
    # moved, and are refused below.
    mounts = [_plane_to_mount(c, intrinsics, sensor) for c in planes]
    heights = np.array([m.height_mm for m in mounts])
    normals = np.array([m.up_normal_camera() for m in mounts])
    strong = [i for i, sh in enumerate(shares) if sh >= cfg.min_inlier_share] or list(
        range(len(planes))
    )
    median_n = np.median(normals[strong], axis=0)
    median_h = float(np.median(heights[strong]))
    centre = min(
        strong,
        key=lambda i: abs(heights[i] - median_h) + 1000.0 * np.linalg.norm(normals[i] - median_n),
    )

    def agrees(i: int) -> bool:
        return (
            abs(heights[i] - heights[centre]) <= cfg.max_height_spread_mm
            and _angle_deg(normals[i], normals[centre]) <= cfg.max_angle_spread_deg
        )

    keep = [i for i in range(len(planes)) if i in strong or agrees(i)]
    _check_enough(len(keep), len(with_depth), frame_share)
    seed_plane = planes[centre]
    planes, used = [planes[i] for i in keep], [used[i] for i in keep]
    heights, normals = heights[keep], normals[keep]
    coef = _refine(seed_plane, used, thr)
    mount = _plane_to_mount(coef, intrinsics, sensor)

    height_spread = float(np.max(np.abs(heights - mount.height_mm)))
    n = mount.up_normal_camera()
    angle_spread = max(_angle_deg(n, m) for m in normals)
    if height_spread > cfg.max_height_spread_mm or angle_spread > cfg.max_angle_spread_deg:
        spread = (
            f"{height_spread:.0f} mm in height and {angle_spread:.2f} deg in angle across "
            f"{len(planes)} frames (at most {cfg.max_height_spread_mm:g} mm, "
            f"{cfg.max_angle_spread_deg:g} deg)"
        )
        if frames_still(frames, thr, cfg.max_depth_mm):
            raise CalibrationError(
                f"no one floor fits these frames: the planes found in them differ by {spread}, "
                "yet the frames themselves agree (the camera is still): too little floor is "
                "in view (a large surface nearer than the floor, a table, covers most of it); "
                "clear the floor under the camera or aim it at more floor"
            )
        raise CalibrationError(
            f"the frames disagree: the floor found in them differs by {spread}, and so do the "
            "frames (the camera moved); hold the camera still and calibrate again"
        )
    if mount.tilt_deg() > cfg.max_tilt_deg:
        raise CalibrationError(
            f"the camera is tilted {mount.tilt_deg():.1f} deg from straight down (pitch "
            f"{mount.pitch_deg:+.1f}, roll {mount.roll_deg:+.1f}); at most "
            f"{cfg.max_tilt_deg:g} deg is supported: point it straight down"
        )

    pooled = _Points(
        np.concatenate([p.rays for p in used]),
        np.concatenate([p.z_mm for p in used]),
        np.concatenate([p.w for p in used]),
        0,
    )
    inl = _inliers(coef, pooled, thr)
    share = float(inl.mean())
    if share < cfg.min_inlier_share:
        raise CalibrationError(
            f"no plane covers enough of the view: the floor holds {share:.0%} of the valid "
            f"pixels, at least {cfg.min_inlier_share:.0%} needed; clear the floor under the camera"
        )
    _check_nothing_flat_below(coef, pooled, thr, cfg, mount)
    x_mm = pooled.z_mm[inl, None] * _design(pooled.rays[inl])
    residual = float(np.sqrt(np.mean((mount.height_mm + x_mm @ n) ** 2)))
    mount = replace(mount, noise_scale=noise_scale(residual, pooled.z_mm[inl], sensor))
    try:
        check_mount(mount)  # what a mount file or the wire would refuse is no estimate
    except ValueError as exc:
        raise CalibrationError(f"the floor found gives no camera's mount: {exc}") from None
    return MountEstimate(
        mount=mount,
        residual_mm=residual,
        inlier_share=share,
        frames_used=len(planes),
        frames_given=len(frames),
        height_spread_mm=height_spread,
        angle_spread_deg=angle_spread,
        made_at=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    )


def _check_nothing_flat_below(
    coef: np.ndarray, pooled: _Points, thr: Threshold, cfg: CalibrationConfig, mount
) -> None:
    """CalibrationError when a flat surface shows below the plane found, in more than
    `min_hidden_floor_share` of the view (but less than the `max_beyond_share` that vetoes a
    candidate): the floor, mostly hidden, and the plane a table top over most of the view.
    Stray readings beyond the floor (reflections) are not flat."""
    beyond = pooled.z_mm - _plane_depth(coef, pooled.rays) > cfg.beyond_factor * thr(pooled.z_mm)
    share = float(np.mean(beyond)) if beyond.size else 0.0
    if share < cfg.min_hidden_floor_share:
        return
    x_mm = pooled.z_mm[beyond, None] * _design(pooled.rays[beyond])
    heights = mount.height_mm + x_mm @ mount.up_normal_camera()
    q1, median, q3 = np.percentile(heights, [25, 50, 75])
    if q3 - q1 > 2 * float(np.median(thr(pooled.z_mm[beyond]))):
        return
    raise CalibrationError(
        f"a flat surface {-median:.0f} mm below the plane found shows in {share:.0%} of the "
        f"view: that is the floor, mostly hidden (a table over most of the view?); clear "
        "the floor under the camera or aim it at more floor"
    )


def frames_still(
    frames: Sequence[np.ndarray], thr: Threshold, max_mm: float, max_changed: float = 0.5
) -> bool:
    """Whether `frames` show one still view: in each, at most `max_changed` of the pixels
    with depth (in it and the first frame, a sampled grid) differ from the first frame's by
    more than the noise threshold. A camera that moved changes nearly every pixel; people
    walking by, some."""
    first = np.asarray(frames[0])[::4, ::4].astype(np.float64)
    for frame in frames[1:]:
        other = np.asarray(frame)[::4, ::4].astype(np.float64)
        both = (first > 0) & (other > 0) & (first <= max_mm) & (other <= max_mm)
        if not both.any():
            continue
        a, b = first[both], other[both]
        if np.mean(np.abs(a - b) > thr(a)) > max_changed:
            return False
    return True


def floor_mask(
    depth: np.ndarray, mount: TopViewMount, config: CalibrationConfig | None = None
) -> np.ndarray:
    """(H, W) bool: pixels whose point lies on the mount's floor, within the inlier threshold.

    The test is on depth along the pixel's ray, as in the fit: a point at height h sits
    h / |n . r| mm of depth off the floor, with r = ((u - cx)/fx, (v - cy)/fy, 1). A radial
    camera's frame is read as depth first.
    """
    cfg = config or CalibrationConfig()
    depth = mount.z_depth(check_depth(depth, "floor_mask"))
    mount = replace(mount, radial=False)
    h = mount.height_map_mm(depth)
    n_dot_r = mount.height_map_mm(np.ones_like(depth)) - np.float32(mount.height_mm)
    with np.errstate(invalid="ignore", divide="ignore"):
        along_ray = np.abs(h) / np.abs(n_dot_r)
    return (depth > 0) & (along_ray <= cfg.threshold(mount.sensor)(depth))


@dataclass(frozen=True)
class FloorCheckConfig:
    """When a mount's floor and a frame's depth disagree (`check_floor`).

    step: every step-th row and column is looked at (a frame is a few thousand points).
    min_tolerance_mm, noise_sigmas: a pixel is off the mount's floor by more than the
        tolerance max(min_tolerance_mm, noise_sigmas x the sensor's depth noise at the
        frame's median depth x the mount's noise_scale).
    max_below_share: more than this share of the pixels with depth farther below the
        mount's floor than the tolerance: the floor lies lower (the mount hangs the camera
        too low, or tilts it wrongly). Nothing stands below the floor; a few bad readings
        (reflections) may.
    low_percentile: the frame's lowest surface is this percentile of its heights; above the
        tolerance, the floor lies higher (the mount hangs the camera too high). Some floor
        shows in every view, even under a crowd or a big table.
    min_valid_points: fewer sampled pixels with depth tell nothing (a check without verdict).
    max_depth_mm: farther readings are no depth, as in the fit (`CalibrationConfig`).
    """

    step: int = 4
    min_tolerance_mm: float = 100.0
    noise_sigmas: float = 5.0
    max_below_share: float = 0.2
    low_percentile: float = 1.0
    min_valid_points: int = 200
    max_depth_mm: float = 20000.0


@dataclass(frozen=True)
class FloorCheck:
    """How a mount's floor agrees with the depth one frame sees (`check_floor`).

    valid: sampled pixels with depth. below_share: share of them farther below the mount's
    floor than `tolerance_mm`. lowest_mm: the height of the frame's lowest surface under the
    mount (about 0 when they agree). offset_mm: where the frame's floor lies against the
    mount's, about (negative: lower). agrees: None when too few pixels have depth to tell.
    """

    mount_height_mm: float
    valid: int
    below_share: float
    lowest_mm: float
    offset_mm: float
    tolerance_mm: float
    agrees: bool | None

    def reason(self) -> str:
        """Why the mount and the frame disagree, in one line ('' when they do not)."""
        if self.agrees is not False:
            return ""
        seen = self.mount_height_mm - self.offset_mm
        if self.offset_mm < 0:
            why = (
                f"{100 * self.below_share:.0f} % of the pixels with depth lie more than "
                f"{self.tolerance_mm:.0f} mm below its floor"
            )
        else:
            why = (
                f"nothing in view comes within {self.tolerance_mm:.0f} mm of its floor: the "
                f"lowest surface is {self.lowest_mm:.0f} mm above it"
            )
        return (
            f"the mount puts the camera {self.mount_height_mm / 1000:.2f} m above the floor, "
            f"the depth about {seen / 1000:.2f} m ({why})"
        )


def check_floor(
    depth: np.ndarray, mount: TopViewMount, config: FloorCheckConfig | None = None
) -> FloorCheck:
    """Whether `mount`'s floor agrees with what `depth` (one frame of its camera) sees: pure
    and cheap (a sampled grid of pixels), for every consumer of a mount it did not estimate
    from these frames (a mount file, a mount on the wire or in a recording). A mount that
    hangs the camera too low leaves much of the view below its floor; one that hangs it too
    high leaves nothing near its floor. Frames with 0, 65535 or beyond-range readings count
    those as no depth. ValueError when the frame is not of the mount's camera's size."""
    from topseg.core.forest.inputs import depth_sigma_mm

    cfg = config or FloorCheckConfig()
    depth = np.asarray(depth)
    if depth.shape != mount.intrinsics.shape:
        raise ValueError(
            f"a {depth.shape[1] if depth.ndim == 2 else '?'}x{depth.shape[0]} frame does not "
            f"match the mount's {mount.intrinsics.width}x{mount.intrinsics.height} camera"
        )
    step = max(1, int(cfg.step))
    z = mount.z_depth(depth)[::step, ::step].astype(np.float32)
    rays = mount.height_rays()[::step, ::step]
    ok = (z > 0) & (z <= cfg.max_depth_mm)
    z = z[ok]
    heights = z * rays[ok] + np.float32(mount.height_mm)
    valid = int(z.size)
    if valid < cfg.min_valid_points:
        return FloorCheck(float(mount.height_mm), valid, 0.0, 0.0, 0.0, 0.0, None)
    sigma = float(depth_sigma_mm(np.float32(np.median(z)), mount.sensor))
    tolerance = max(cfg.min_tolerance_mm, cfg.noise_sigmas * sigma * float(mount.noise_scale))
    below = heights < -tolerance
    below_share = float(np.count_nonzero(below)) / valid
    lowest = float(np.percentile(heights, cfg.low_percentile))
    if below_share > cfg.max_below_share:
        agrees, offset = False, float(np.median(heights[below]))
    else:
        agrees, offset = lowest <= tolerance, lowest
    return FloorCheck(float(mount.height_mm), valid, below_share, lowest, offset, tolerance, agrees)


def noise_scale(residual_mm: float, floor_depth_mm: np.ndarray, sensor: str) -> float:
    """The floor's measured noise (`residual_mm`, RMS) over the sensor model's RMS noise at the
    floor points' depths, to 2 decimals, within `NOISE_SCALE_RANGE`: 1 on a camera that
    matches its model, below 1 on a quieter one (a time-of-flight camera taken for a Kinect v1).
    """
    sigma = depth_sigma_mm(np.asarray(floor_depth_mm, np.float32), sensor).astype(np.float64)
    model = math.sqrt(float(np.mean(sigma * sigma))) if sigma.size else 0.0
    if not (model > 0 and math.isfinite(residual_mm)):
        return 1.0
    lo, hi = NOISE_SCALE_RANGE
    return round(min(max(residual_mm / model, lo), hi), 2)


def mount_difference(a: TopViewMount, b: TopViewMount) -> tuple[float, float]:
    """(height difference mm, angle between floor normals deg): how far a camera moved."""
    return (
        abs(a.height_mm - b.height_mm),
        _angle_deg(a.up_normal_camera(), b.up_normal_camera()),
    )


from topseg.core.formats.mount_file import (  # noqa: E402  (re-exported for callers' ease)
    read_mount_file,
    write_mount_file,
)

__all__ = [
    "CalibrationConfig",
    "CalibrationError",
    "FloorCheck",
    "FloorCheckConfig",
    "MountEstimate",
    "check_floor",
    "estimate_mount",
    "floor_mask",
    "mount_difference",
    "read_mount_file",
    "write_mount_file",
]
