"""The robot's base pose in the cell frame, fitted to a camera's depth frames.

A tape measure puts the robot's base a few cm off; the safety service's separation and the
robot's own pixels need it closer. Given depth frames of one camera of the cell, each paired
with the robot's joint state at the frame's time (`FramePairer`: the state nearest in stamp,
no more than `MAX_PAIR_GAP_MS` away), `fit_base_pose` finds the base's x, y, z and yaw that
make the robot rendered at those joint states (`core/synth/render.py`, through the camera's
mount and placement) match the measured depth, starting from the cell file's base.

The residual, per frame, over a crop of the image around the robot as the cell file places
it (large crops read at every 2nd, 3rd ... pixel, so that a fit takes seconds): where the
rendered robot and the measured depth agree within 6 cm, their difference; everything else
costs a fixed 3 cm (`_residual`), plus, for the robot drawn over the floor, the distance to
the nearest measured surface above the floor (which pulls it there from ~10 cm off). So a
person's arm in front of a link, a hole or a fixture beside the robot costs the same
wherever the robot is and drags nothing. The residuals go through the soft_l1 robust loss.

The rendering is not differentiable and its cost moves in pixel steps.
`scipy.optimize.least_squares` (forward differences of 5 mm and 0.5 degree) stalled on that
5 cm and 6 degrees from a rendered truth, its Jacobian made of pixels flipping at the
outline; `scipy.optimize.minimize`'s Nelder-Mead, which compares costs and needs no
Jacobian, finds it within a millimetre, restarted while it still moves (it can shrink
early).

The fit reports the residual over the robot's pixels at the fitted pose (median, 90th
percentile, the share within 2 cm) and refuses (`RobotCalibrationError`, one line) when the
robot is not in view, or the fit moved far or left a residual too large to trust.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.optimize import minimize

from topseg.core.camera import TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.safety.robot import base_quat
from topseg.core.synth.render import Primitives, Triangles, raycast_m

#: a depth frame and a joint state further apart than this are not a pair (ms)
MAX_PAIR_GAP_MS = 20.0
#: joint states kept while their depth frames are on the way (1 s at 250 Hz)
KEEP_STATES = 256
#: depth frames kept while their joint states are on the way
KEEP_FRAMES = 8


class RobotCalibrationError(TopsegError):
    """The base pose cannot be fitted: the robot not in view, no usable joint states, or a
    fit whose residual is too large to trust."""


# --- pairing depth frames with joint states --------------------------------------------------


@dataclass(frozen=True)
class Pairing:
    """What pairing did with the frames it settled: the frames paired, those with no joint
    state within the gap (and the smallest gap among them, ns, None when no state was
    there at all)."""

    paired: int = 0
    unpaired: int = 0
    nearest_unpaired_ns: int | None = None


def nearest_state(stamp_ns: int, states, max_gap_ns: int):
    """The state of `states` (each with `stamp_ns`) nearest to `stamp_ns`, and its distance
    in ns; (None, distance or None) when none lies within `max_gap_ns`."""
    best, gap = None, None
    for state in states:
        d = abs(int(state.stamp_ns) - int(stamp_ns))
        if gap is None or d < gap:
            best, gap = state, d
    if gap is None or gap > max_gap_ns:
        return None, gap
    return best, gap


class FramePairer:
    """Pairs depth frames with the joint state nearest in stamp, as frames and states come
    (live, or from a recording in file order). A frame is settled once a state newer than
    it by more than the gap has come (no nearer one can follow in stamp order) or at
    `finish`; memory is bounded (`KEEP_STATES` states, `KEEP_FRAMES` frames waiting)."""

    def __init__(self, wanted: int, max_gap_ms: float = MAX_PAIR_GAP_MS) -> None:
        self.wanted = int(wanted)
        self.max_gap_ns = int(max_gap_ms * 1e6)
        self.states: deque = deque(maxlen=KEEP_STATES)
        self.waiting: deque = deque()
        self.pairs: list[tuple[object, object]] = []
        self.frames = 0
        self.state_count = 0
        self.unpaired = 0
        self.nearest_unpaired_ns: int | None = None

    @property
    def done(self) -> bool:
        """Whether `wanted` pairs are made."""
        return len(self.pairs) >= self.wanted

    def add_state(self, state) -> None:
        """Take a joint state (with `stamp_ns`) and settle the frames it decides."""
        self.states.append(state)
        self.state_count += 1
        self._settle(final=False)

    def add_frame(self, frame) -> None:
        """Take a depth frame (with `stamp_ns`); the oldest waiting one is settled (paired
        or not) when more than `KEEP_FRAMES` wait."""
        if self.done:
            return
        self.frames += 1
        self.waiting.append(frame)
        self._settle(final=False)
        while len(self.waiting) > KEEP_FRAMES:
            self._pair(self.waiting.popleft())

    def finish(self) -> None:
        """No more messages: settle every waiting frame."""
        self._settle(final=True)

    def _settle(self, final: bool) -> None:
        """Pair the waiting frames no later state can come nearer to (all with `final`)."""
        newest = max((int(s.stamp_ns) for s in self.states), default=None)
        keep: deque = deque()
        for frame in self.waiting:
            if final or (newest is not None and newest > int(frame.stamp_ns) + self.max_gap_ns):
                self._pair(frame)
            else:
                keep.append(frame)
        self.waiting = keep

    def _pair(self, frame) -> None:
        """Pair `frame` with its nearest state, or count it unpaired."""
        if self.done:
            return
        state, gap = nearest_state(frame.stamp_ns, self.states, self.max_gap_ns)
        if state is not None:
            self.pairs.append((frame, state))
            return
        self.unpaired += 1
        if gap is not None and (self.nearest_unpaired_ns is None or gap < self.nearest_unpaired_ns):
            self.nearest_unpaired_ns = gap

    def shortfall(self, depth_what: str, joints_what: str) -> str:
        """Why fewer than `wanted` pairs were made, in a line (for a refusal)."""
        if not self.frames:
            return f"no depth frames on {depth_what}"
        if not self.state_count:
            return f"no joint states on {joints_what}: is the robot's driver publishing?"
        if self.nearest_unpaired_ns is not None:
            return (
                f"the joint states are stale: {len(self.pairs)} of {self.frames} depth frames "
                f"had one within {self.max_gap_ns / 1e6:g} ms (the nearest of the others "
                f"{self.nearest_unpaired_ns / 1e6:.0f} ms away: are the clocks in sync?)"
            )
        return f"only {len(self.pairs)} of {self.wanted} depth frames had a joint state"


# --- the fit ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class BasePose:
    """The robot's base in the cell frame: position (m) and yaw about z (degrees)."""

    xyz_m: tuple[float, float, float]
    yaw_deg: float

    def as_vector(self) -> np.ndarray:
        """(4,) x, y, z (m), yaw (degrees)."""
        return np.array([*self.xyz_m, self.yaw_deg], np.float64)

    @classmethod
    def of_vector(cls, v) -> BasePose:
        """The pose of (x, y, z, yaw) (`as_vector`'s inverse)."""
        return cls((float(v[0]), float(v[1]), float(v[2])), float(v[3]))


@dataclass(frozen=True)
class RobotView:
    """One depth frame of the camera with the robot's joint state at its time: `depth_mm`
    (H, W) uint16 as the camera sends it, `mount` the camera's, `joints` {name: position}."""

    depth_mm: np.ndarray
    mount: TopViewMount
    joints: dict[str, float]


@dataclass(frozen=True)
class RobotFitConfig:
    """The fit's settings."""

    step_m: float = 0.005  # the unit of x, y, z in the search
    step_deg: float = 0.5  # the unit of the yaw in the search
    simplex_steps: float = 4.0  # the first simplex: this many units along each axis
    tolerance_steps: float = 0.4  # done when the simplex is within this many units
    restarts: int = 3  # Nelder-Mead may shrink early: restarted while it still moves
    f_scale_mm: float = 20.0  # residuals beyond this count less and less (soft_l1's scale)
    # a rendered robot pixel and the measured depth further apart than this do not match:
    # something in front of the robot, or the robot drawn where it is not
    occlusion_mm: float = 60.0
    # what a pixel that does not match costs (as a residual, mm; `_residual`)
    mismatch_mm: float = 30.0
    above_floor_mm: float = 50.0  # a measured surface this high over the floor may be robot
    crop_margin_m: float = 0.25  # the crop reaches this far around the robot at the start
    max_pixels: int = 12000  # per frame: larger crops are read at every k-th pixel
    min_robot_pixels: int = 30  # fewer of the robot's pixels in a frame: the frame is left out
    min_seen_share: float = 0.1  # a surface above the floor under fewer of them: not in view
    max_evaluations: int = 400  # of the cost, at most (each renders every frame once)
    max_change_m: float = 0.3  # a fit farther from the start than this is refused
    max_change_deg: float = 20.0  # as is one turned farther than this
    within_mm: float = 20.0  # the share of robot pixels within this is reported
    max_median_mm: float = 15.0  # a fitted residual beyond this is refused
    min_within_share: float = 0.6  # fewer robot pixels within `within_mm`: refused


@dataclass(frozen=True)
class RobotFit:
    """A fitted base pose, the start it came from, and the residual over the robot's pixels
    (measured minus rendered at the fitted pose, where the camera measured depth)."""

    start: BasePose
    pose: BasePose
    median_mm: float
    p90_mm: float
    within_share: float
    within_mm: float
    robot_pixels: int
    frames: int
    evaluations: int

    def change(self) -> np.ndarray:
        """(4,) fitted minus start: dx, dy, dz (m), dyaw (degrees)."""
        return self.pose.as_vector() - self.start.as_vector()

    def summary(self) -> str:
        """Lines for a person: the pose, the change, the residual."""
        x, y, z = self.pose.xyz_m
        dx, dy, dz, dyaw = self.change()
        return "\n".join(
            [
                f"base       x {x:+.3f}  y {y:+.3f}  z {z:+.3f} m  yaw {self.pose.yaw_deg:+.2f} deg",
                f"change     x {1000 * dx:+.0f}  y {1000 * dy:+.0f}  z {1000 * dz:+.0f} mm  "
                f"yaw {dyaw:+.2f} deg from the cell file's",
                f"residual   median {self.median_mm:.1f} mm, p90 {self.p90_mm:.1f} mm over "
                f"{self.robot_pixels} robot pixels; {100 * self.within_share:.0f} % within "
                f"{self.within_mm / 10:g} cm",
                f"frames     {self.frames} ({self.evaluations} fit evaluations)",
            ]
        )


@dataclass
class _Crop:
    """One view read for the fit: its cropped (and strided) mount, measured depth, floor
    depth and above-floor mask, and the robot at its joints with its base at the origin."""

    mount: TopViewMount
    measured_mm: np.ndarray  # float64, NaN without depth
    floor_mm: np.ndarray  # float64, the floor's depth on each pixel's ray (inf: no floor)
    above_floor: np.ndarray  # bool
    to_above_mm: np.ndarray  # distance to the nearest pixel above the floor (mm at the robot)
    pixel_mm: float  # how wide a pixel of the crop is at the robot's depth (mm)
    prims: Primitives
    tris: Triangles
    rendered_pixels: int  # of the robot at the start pose
    seen_pixels: int  # of those, where a surface above the floor was measured


def fit_base_pose(
    robot, placement, views: list[RobotView], config: RobotFitConfig | None = None
) -> RobotFit:
    """The base pose of `robot` (a `CellRobot`, its spec's base the start) that best explains
    `views` of the camera at `placement` (a `CameraPlacement`); RobotCalibrationError when
    the robot is not in view or the fit's residual is too large."""
    config = config or RobotFitConfig()
    if not views:
        raise RobotCalibrationError("no depth frames to fit the robot's base to")
    start = BasePose(tuple(float(v) for v in robot.spec.base_xyz_m), float(robot.spec.base_yaw_deg))
    crops = [_crop(robot, placement, view, start, config) for view in views]
    crops = _check_in_view(crops, placement, config)
    steps = np.array([config.step_m, config.step_m, config.step_m, config.step_deg])
    x0 = start.as_vector()

    def cost(units: np.ndarray) -> float:
        pose = x0 + units * steps
        r = np.concatenate([_residual(c, pose, placement, config) for c in crops])
        return float(np.sum(soft_l1(r / config.f_scale_mm)))

    units, evaluations = np.zeros(4), 0
    for _ in range(config.restarts + 1):  # a fresh simplex where the last one shrank
        simplex = units + np.vstack([np.zeros(4), config.simplex_steps * np.eye(4)])
        result = minimize(
            cost,
            units,
            method="Nelder-Mead",
            options={
                "initial_simplex": simplex,
                "xatol": config.tolerance_steps,
                "fatol": np.inf,  # stop on the pose's precision alone
                "maxfev": config.max_evaluations,
            },
        )
        evaluations += int(result.nfev)
        moved = np.abs(result.x - units).max()
        units = result.x
        if moved <= config.tolerance_steps:
            break
    pose = BasePose.of_vector(x0 + units * steps)
    errors = np.concatenate([_robot_errors(c, pose.as_vector(), placement) for c in crops])
    fit = _report(start, pose, errors, len(crops), evaluations, config)
    _check_fit(fit, config)
    return fit


def soft_l1(z: np.ndarray) -> np.ndarray:
    """The soft_l1 robust loss of scaled residuals: 2 (sqrt(1 + z^2) - 1), quadratic
    within 1, linear beyond (as `scipy.optimize.least_squares` defines it)."""
    return 2.0 * (np.sqrt(1.0 + np.square(z)) - 1.0)


def _report(start, pose, errors, frames, evaluations, config) -> RobotFit:
    """The RobotFit of `errors` (mm, |measured - rendered| over the robot's pixels)."""
    if not len(errors):
        raise RobotCalibrationError(
            "the fit did not converge: it moved the robot out of the camera's view (are the "
            "joint states the robot's, and the base within ~10 cm of the cell file's?)"
        )
    return RobotFit(
        start=start,
        pose=pose,
        median_mm=float(np.median(errors)),
        p90_mm=float(np.percentile(errors, 90)),
        within_share=float(np.mean(errors <= config.within_mm)),
        within_mm=config.within_mm,
        robot_pixels=len(errors),
        frames=frames,
        evaluations=evaluations,
    )


def _check_fit(fit: RobotFit, config: RobotFitConfig) -> None:
    """RobotCalibrationError when the residual is too large to trust the pose."""
    dx, dy, dz, dyaw = fit.change()
    if math.hypot(dx, dy, dz) > config.max_change_m or abs(dyaw) > config.max_change_deg:
        raise RobotCalibrationError(
            f"the fit did not converge: it moved the base {math.hypot(dx, dy, dz):.2f} m and "
            f"{dyaw:+.0f} deg from the cell file's (at most {config.max_change_m:g} m and "
            f"{config.max_change_deg:g} deg): measure the base again, then calibrate"
        )
    if fit.median_mm > config.max_median_mm or fit.within_share < config.min_within_share:
        raise RobotCalibrationError(
            f"the fit did not converge: the residual is too large (median {fit.median_mm:.0f} mm, "
            f"{100 * fit.within_share:.0f} % of {fit.robot_pixels} robot pixels within "
            f"{config.within_mm / 10:g} cm; at most {config.max_median_mm:g} mm and at least "
            f"{100 * config.min_within_share:.0f} % needed): is the base more than ~10 cm or "
            "the joint states off, or the robot mostly hidden?"
        )


def _crop(robot, placement, view: RobotView, start: BasePose, config) -> _Crop | None:
    """The view cropped around the robot at the start pose (strided to `max_pixels`); None
    when the robot at the start pose covers fewer than `min_robot_pixels` of it."""
    mount = view.mount
    depth = np.asarray(view.depth_mm)
    if depth.shape != mount.intrinsics.shape:
        raise RobotCalibrationError(
            f"a depth frame of {depth.shape[1]}x{depth.shape[0]} does not match its camera "
            f"({mount.intrinsics.width}x{mount.intrinsics.height})"
        )
    flip = base_quat(0.0, bool(robot.spec.upside_down))
    prims, tris = robot.model.link_geometry(robot.check_joints(view.joints), np.zeros(3), flip)
    plain = replace(mount, radial=False)
    floor = _floor_mm(mount)
    posed_prims, posed_tris = _posed(prims, tris, start.as_vector(), placement)
    whole = raycast_m(posed_prims, plain, posed_tris)[0] * 1000.0
    hit = whole < floor  # parts below the floor are not seen
    if hit.sum() < config.min_robot_pixels:
        return None
    box = _grown_box(hit, whole, mount, config.crop_margin_m)
    stride = max(1, math.ceil(math.sqrt(_area(box) / config.max_pixels)))
    sub = _sub_mount(plain, box, stride)
    (v0, v1), (u0, u1) = box
    pick = (slice(v0, v1, stride), slice(u0, u1, stride))
    z = mount.z_depth(depth)[pick].astype(np.float64)
    measured = np.where(z > 0, z, np.nan)
    above = np.nan_to_num(mount.height_map_mm(depth)[pick], nan=0.0) > config.above_floor_mm
    pixel_mm = float(np.median(whole[hit])) / sub.intrinsics.fx
    to_above = _distance_mm(~above, pixel_mm, 1000.0 * config.crop_margin_m)
    seen = int((above & hit[pick]).sum())
    return _Crop(
        sub, measured, floor[pick], above, to_above, pixel_mm, prims, tris,
        int(hit[pick].sum()), seen,
    )  # fmt: skip


def _floor_mm(mount: TopViewMount) -> np.ndarray:
    """(H, W) float64 depth (mm) of the floor on each pixel's ray; inf where the ray misses
    the floor (above the horizon)."""
    rays = mount.height_rays().astype(np.float64)
    with np.errstate(divide="ignore"):
        return np.where(rays < 0, -mount.height_mm / rays, np.inf)


def _check_in_view(crops: list[_Crop | None], placement, config) -> list[_Crop]:
    """The crops the robot is in; RobotCalibrationError when it is in none, or the camera
    sees almost nothing above the floor where the cell file puts it (the robot elsewhere,
    or the camera's placement wrong)."""
    kept = [c for c in crops if c is not None]
    if not kept:
        raise RobotCalibrationError(
            f"the robot is not in view: at the cell file's base it covers fewer than "
            f"{config.min_robot_pixels} pixels of camera {placement.name!r} in every frame; "
            "check the base and the camera's placement in the cell file"
        )
    rendered = sum(c.rendered_pixels for c in kept)
    seen = sum(c.seen_pixels for c in kept)
    if seen < config.min_seen_share * rendered:
        raise RobotCalibrationError(
            f"the robot is not in view: camera {placement.name!r} sees a surface above the "
            f"floor on {100 * seen / rendered:.0f} % of the pixels where the cell file puts the "
            f"robot (at least {100 * config.min_seen_share:.0f} % needed); is it there, and "
            "are its base and the camera's placement in the cell file right to within ~10 cm?"
        )
    return kept


def _grown_box(hit, depth_m, mount, margin_m) -> tuple[tuple[int, int], tuple[int, int]]:
    """((v0, v1), (u0, u1)): the box of `hit` grown by `margin_m` at its nearest depth."""
    vs, us = np.nonzero(hit)
    z = float(depth_m[hit].min())
    k = mount.intrinsics
    du, dv = math.ceil(margin_m * k.fx / z), math.ceil(margin_m * k.fy / z)
    v0, v1 = max(0, vs.min() - dv), min(k.height, vs.max() + 1 + dv)
    u0, u1 = max(0, us.min() - du), min(k.width, us.max() + 1 + du)
    return (int(v0), int(v1)), (int(u0), int(u1))


def _area(box) -> int:
    """Pixels in a box."""
    (v0, v1), (u0, u1) = box
    return (v1 - v0) * (u1 - u0)


def _sub_mount(mount: TopViewMount, box, stride: int) -> TopViewMount:
    """The mount of the pixels `[v0:v1:stride, u0:u1:stride]`: pixel (i, j) of it is pixel
    (v0 + stride i, u0 + stride j) of `mount`, the optics shifted and scaled to match."""
    (v0, v1), (u0, u1) = box
    k = mount.intrinsics
    k2 = replace(
        k,
        width=len(range(u0, u1, stride)),
        height=len(range(v0, v1, stride)),
        fx=k.fx / stride,
        fy=k.fy / stride,
        cx=(k.cx - u0) / stride,
        cy=(k.cy - v0) / stride,
    )
    return replace(mount, intrinsics=k2)


def _posed(prims: Primitives, tris: Triangles, pose: np.ndarray, placement):
    """The robot's shapes (base at the origin) with its base at `pose` (x, y, z, yaw deg),
    in the camera's world frame."""
    c, s = math.cos(math.radians(pose[3])), math.sin(math.radians(pose[3]))
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    m = placement.rotation().T @ rz
    t = (np.asarray(pose[:3], np.float64) - placement.offset()) @ placement.rotation()
    moved = Primitives(prims.kind, prims.size, prims.center @ m.T + t, m @ prims.rot, prims.label)
    return moved, Triangles(tris.vertices @ m.T + t, tris.label)


def _rendered_mm(crop: _Crop, pose: np.ndarray, placement) -> np.ndarray:
    """The robot's depth (mm, float64, inf where it is not or is below the floor) on the
    crop at `pose`."""
    prims, tris = _posed(crop.prims, crop.tris, pose, placement)
    depth_mm = raycast_m(prims, crop.mount, tris)[0] * 1000.0
    return np.where(depth_mm < crop.floor_mm, depth_mm, np.inf)  # not seen below the floor


def _residual(crop: _Crop, pose: np.ndarray, placement, config) -> np.ndarray:
    """The crop's residuals at `pose` (mm), one per pixel, by what the pixel shows:

    - the rendered robot within `occlusion_mm` of the measured depth: their difference;
    - something measured nearer than the rendered robot (a person's arm over a link):
      `mismatch_mm`, whatever the pose, so that it pulls the robot nowhere;
    - something measured farther (the floor beside a link): `mismatch_mm` plus the distance
      to the nearest measured surface above the floor, which pulls the robot towards it;
    - a measured surface above the floor the robot does not cover: its distance to the
      rendered robot, at most `mismatch_mm` (the robot cannot leave its pixels for free,
      and covering a person gains it nothing);
    - no depth measured, or floor without robot: 0.
    """
    robot = _rendered_mm(crop, pose, placement)
    on_robot = np.isfinite(robot)
    measured = np.isfinite(crop.measured_mm)
    diff = np.where(on_robot & measured, robot - np.nan_to_num(crop.measured_mm), 0.0)
    k = config.mismatch_mm
    near = np.abs(diff) <= config.occlusion_mm
    out = np.where(near, diff, np.where(diff > 0, k, k + crop.to_above_mm))
    uncovered = crop.above_floor & ~on_robot
    to_robot = _distance_mm(~on_robot, crop.pixel_mm, k)
    out = np.where(on_robot & measured, out, np.where(uncovered, to_robot, 0.0))
    return out.ravel()


def _distance_mm(outside: np.ndarray, pixel_mm: float, cap_mm: float) -> np.ndarray:
    """For each pixel, the distance (mm, `pixel_mm` a pixel, at most `cap_mm`) to the
    nearest pixel that is not `outside`; `cap_mm` everywhere when every pixel is."""
    if outside.all():
        return np.full(outside.shape, cap_mm)
    return np.minimum(ndimage.distance_transform_edt(outside) * pixel_mm, cap_mm)


def _robot_errors(crop: _Crop, pose: np.ndarray, placement) -> np.ndarray:
    """|measured - rendered| (mm) over the robot's pixels at `pose` where depth was measured."""
    robot = _rendered_mm(crop, pose, placement)
    use = np.isfinite(robot) & np.isfinite(crop.measured_mm)
    return np.abs(robot[use] - crop.measured_mm[use])
