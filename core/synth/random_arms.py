"""Random robot arms, drawn from a seed and written as URDF, for arms nobody modelled.

`random_arm_urdf(seed)` is the URDF text (boxes, cylinders and spheres, no mesh files) of a
plausible fixed-base arm; the same seed gives the same text. Three styles:

- cobot (0.4 of arms): rounded links (a cylinder with a sphere at each end), a cylindrical
  housing at each pitch joint, sometimes the upper arm set beside the shoulder; reach 0.4-1.4 m;
- industrial (0.4): a box-like shoulder housing, often a counterweight behind it, box links,
  a motor housing behind the elbow, sometimes a parallelogram rod along the upper arm;
  reach 0.7-2.5 m;
- SCARA (0.2): a column, two horizontal arms turning about vertical axes and a quill that
  slides down (prismatic) and turns; reach 0.4-1.2 m.

A cobot or industrial arm has 4-7 revolute joints: base yaw, shoulder, elbow and wrist pitch,
then the flange's roll (5), a wrist roll (6) and an upper-arm roll (7), each within realistic
limits. Upper arm and forearm are 0.1-1.3 m long, links 0.03-0.25 m in radius, the base a
cylinder or a box 0.1-0.6 m wide and high. The end effector is a two-finger gripper, a vacuum
cup plate, a welding torch, a screwdriver spindle, a camera box or none, sometimes behind a
tool changer; some arms carry a cable dress along upper arm and forearm. Every link has
collision geometry; the tool link `TOOL_LINK` is the effector's tip, its x axis the approach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: the arm styles and how often each is drawn
STYLES = ("cobot", "industrial", "scara")
STYLE_WEIGHTS = (0.4, 0.4, 0.2)
#: the end effectors, drawn uniformly
EFFECTORS = ("gripper", "vacuum", "torch", "screwdriver", "camera", "none")
#: the horizontal reach (m) each style is drawn from, log-uniform
REACH_M = {"cobot": (0.4, 1.4), "industrial": (0.7, 2.5), "scara": (0.4, 1.2)}
#: upper arm and forearm lengths, link radii, base width and height (m)
LINK_LENGTH_M = (0.1, 1.3)
LINK_RADIUS_M = (0.03, 0.25)
BASE_SIZE_M = (0.1, 0.6)
#: how often an arm carries a cable dress or a tool changer
CABLE_SHARE = 0.35
TOOL_CHANGER_SHARE = 0.25
#: the tool link's name
TOOL_LINK = "tool0"

_Y = (0.0, 1.0, 0.0)
_Z = (0.0, 0.0, 1.0)
_X = (1.0, 0.0, 0.0)


def _num(v: float) -> str:
    return f"{float(v):.6g}"


def _vec(v) -> str:
    return " ".join(_num(x) for x in v)


def _along(p, q) -> tuple[float, tuple[float, float, float], tuple[float, float, float]]:
    """Length, midpoint and URDF rpy turning local z onto the segment p -> q."""
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    d = q - p
    length = float(np.linalg.norm(d))
    u = d / length
    pitch = math.acos(max(-1.0, min(1.0, float(u[2]))))
    yaw = math.atan2(float(u[1]), float(u[0])) if pitch > 1e-9 else 0.0
    return length, tuple((p + q) / 2), (0.0, pitch, yaw)


@dataclass
class _Link:
    """One URDF link: its collision shapes as (geometry XML, xyz, rpy)."""

    name: str
    shapes: list = field(default_factory=list)
    shift: tuple = (0.0, 0.0, 0.0)  # added to every shape's position (the tool link's)

    def box(self, size, xyz, rpy=(0.0, 0.0, 0.0)) -> None:
        """A box of full `size` centred at `xyz`."""
        self.shapes.append((f'<box size="{_vec(size)}"/>', xyz, rpy))

    def cylinder(self, radius: float, length: float, xyz, rpy=(0.0, 0.0, 0.0)) -> None:
        """A cylinder along its local z, centred at `xyz`."""
        self.shapes.append(
            (f'<cylinder radius="{_num(radius)}" length="{_num(length)}"/>', xyz, rpy)
        )

    def sphere(self, radius: float, xyz) -> None:
        """A sphere centred at `xyz`."""
        self.shapes.append((f'<sphere radius="{_num(radius)}"/>', xyz, (0.0, 0.0, 0.0)))

    def rod(self, p, q, radius: float, rounded: bool = False) -> None:
        """A cylinder from p to q; rounded: a sphere at each end too (a capsule)."""
        length, mid, rpy = _along(p, q)
        self.cylinder(radius, length, mid, rpy)
        if rounded:
            self.sphere(radius, p)
            self.sphere(radius, q)

    def bar(self, p, q, width: float, depth: float) -> None:
        """A box from p to q, `width` x `depth` across."""
        length, mid, rpy = _along(p, q)
        self.box((depth, width, length), mid, rpy)

    def housing(self, radius: float, length: float, xyz, axis) -> None:
        """A joint housing: a cylinder along `axis` (x, y or z) centred at `xyz`."""
        rpy = {_X: (0.0, math.pi / 2, 0.0), _Y: (math.pi / 2, 0.0, 0.0), _Z: (0.0, 0.0, 0.0)}
        self.cylinder(radius, length, xyz, rpy[tuple(axis)])

    def xml(self) -> str:
        """The link's URDF element."""
        parts = []
        for geometry, xyz, rpy in self.shapes:
            at = np.asarray(xyz, np.float64) + self.shift
            origin = f'<origin xyz="{_vec(at)}" rpy="{_vec(rpy)}"/>'
            parts.append(f"    <collision>{origin}<geometry>{geometry}</geometry></collision>")
        return f'  <link name="{self.name}">\n' + "\n".join(parts) + "\n  </link>"


@dataclass
class _Arm:
    """Links and joints of an arm being drawn, in order from the base."""

    name: str
    links: list = field(default_factory=list)
    joints: list = field(default_factory=list)

    def link(self, name: str) -> _Link:
        """A new link."""
        link = _Link(name)
        self.links.append(link)
        return link

    def joint(self, name, kind, parent, child, xyz, axis=_Z, limits=None, rpy=(0, 0, 0)):
        """A joint from `parent` to `child` at `xyz` in the parent's frame."""
        text = (
            f'  <joint name="{name}" type="{kind}">\n'
            f'    <parent link="{parent}"/><child link="{child}"/>\n'
            f'    <origin xyz="{_vec(xyz)}" rpy="{_vec(rpy)}"/>'
        )
        if kind != "fixed":
            lo, hi = limits
            text += (
                f'\n    <axis xyz="{_vec(axis)}"/>\n'
                f'    <limit lower="{_num(lo)}" upper="{_num(hi)}" effort="100" velocity="2"/>'
            )
        self.joints.append(text + "\n  </joint>")

    def urdf(self) -> str:
        """The URDF text."""
        body = [link.xml() for link in self.links] + self.joints
        return (
            f'<?xml version="1.0"?>\n<robot name="{self.name}">\n'
            + "\n".join(body)
            + "\n</robot>\n"
        )


def _clip(v: float, bounds: tuple[float, float]) -> float:
    return float(min(max(v, bounds[0]), bounds[1]))


def _log_uniform(rng, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _symmetric(rng, lo: float, hi: float) -> tuple[float, float]:
    """Limits +-U(lo, hi)."""
    v = float(rng.uniform(lo, hi))
    return -v, v


def random_arm_urdf(seed: int) -> str:
    """The URDF text of a random arm drawn from `seed` (an int >= 0); the same seed gives the
    same text."""
    if int(seed) < 0:
        raise ValueError(f"random arm seed must be >= 0, got {seed}")
    rng = np.random.default_rng(int(seed))
    style = STYLES[int(rng.choice(len(STYLES), p=STYLE_WEIGHTS))]
    reach = _log_uniform(rng, *REACH_M[style])
    arm = _Arm(f"random_{style}_{int(seed)}")
    build = _scara if style == "scara" else _serial
    flange, face, rpy, flange_r = build(rng, arm, style, reach)
    _effector(rng, arm, flange, face, rpy, flange_r)
    return arm.urdf()


# --- the base ------------------------------------------------------------------------------


def _base(rng, arm: _Arm, reach: float, height_share: tuple[float, float]) -> float:
    """The base link (a cylinder or a box standing on z = 0); returns its height."""
    width = _clip(reach * rng.uniform(0.18, 0.32), BASE_SIZE_M)
    height = _clip(reach * rng.uniform(*height_share), BASE_SIZE_M)
    base = arm.link("base_link")
    if rng.random() < 0.5:
        base.cylinder(width / 2, height, (0.0, 0.0, height / 2))
    else:
        depth = _clip(width * rng.uniform(0.8, 1.0), BASE_SIZE_M)
        base.box((width, depth, height), (0.0, 0.0, height / 2))
        if rng.random() < 0.5:  # a foot plate
            plate = 0.02 + 0.04 * width
            base.box((width * 1.3, width * 1.3, plate), (0.0, 0.0, plate / 2))
    return height


# --- cobot and industrial arms --------------------------------------------------------------


def _serial(rng, arm: _Arm, style: str, reach: float):
    """Base, turret, upper arm, forearm and wrist of a 4-7 joint arm; returns the flange link,
    its face's position and rpy there, and its radius."""
    cobot = style == "cobot"
    n = int(rng.integers(4, 8))
    r_up = _clip(reach * rng.uniform(0.05, 0.09), LINK_RADIUS_M)
    r_fore = _clip(r_up * rng.uniform(0.65, 0.85), LINK_RADIUS_M)
    r_wrist = _clip(r_fore * rng.uniform(0.65, 0.9), LINK_RADIUS_M)
    wrist_len = max(reach * rng.uniform(0.06, 0.12), 1.5 * r_wrist)
    up_len = _clip(reach * rng.uniform(0.38, 0.52), LINK_LENGTH_M)
    fore_len = _clip(reach - up_len - wrist_len, LINK_LENGTH_M)
    shoulder_h = reach * rng.uniform(0.12, 0.3)
    base_h = _base(rng, arm, reach, (0.05, 0.2))
    cable = rng.random() < CABLE_SHARE
    r_cable = max(0.006, r_up * rng.uniform(0.12, 0.22))

    arm.joint("base_yaw", "revolute", "base_link", "turret", (0, 0, base_h), _Z,
              _symmetric(rng, 2.6, math.pi))  # fmt: skip
    side = (
        r_up * rng.uniform(1.1, 2.0) * rng.choice((-1.0, 1.0))
        if cobot and rng.random() < 0.5
        else 0.0
    )
    reach_out = 0.0 if cobot else reach * rng.uniform(0.04, 0.14)
    _turret(rng, arm.link("turret"), cobot, r_up, shoulder_h, reach_out)
    arm.joint("shoulder", "revolute", "turret", "upper_arm", (reach_out, side, shoulder_h), _Y,
              (-rng.uniform(1.3, 2.0), rng.uniform(1.3, 2.3)))  # fmt: skip

    upper = arm.link("upper_arm")
    elbow_parent, elbow_at = "upper_arm", up_len
    if n == 7:  # an upper-arm roll splits the upper arm
        split = up_len * rng.uniform(0.4, 0.6)
        _limb(upper, cobot, r_up, (0, 0, 0), (0, 0, split))
        arm.joint("upper_arm_roll", "revolute", "upper_arm", "upper_arm_2", (0, 0, split), _Z,
                  _symmetric(rng, 2.6, math.pi))  # fmt: skip
        lower = arm.link("upper_arm_2")
        _limb(lower, cobot, r_up * 0.95, (0, 0, 0), (0, 0, up_len - split))
        elbow_parent, elbow_at, top = "upper_arm_2", up_len - split, lower
    else:
        _limb(upper, cobot, r_up, (0, 0, 0), (0, 0, up_len))
        top = upper
    if cobot:
        upper.housing(r_up * 1.1, r_up * 2.2, (0, 0, 0), _Y)
    elif n < 7 and rng.random() < 0.5:  # a parallelogram rod behind the upper arm
        back = -r_up * rng.uniform(1.8, 2.6)
        upper.bar((back, 0, 0), (back, 0, up_len), r_up * 0.5, r_up * 0.4)
        upper.bar((back, 0, up_len), (0, 0, up_len), r_up * 0.5, r_up * 0.4)
    if cable:
        top.rod((-(r_up + r_cable), 0, 0.1 * elbow_at), (-(r_up + r_cable), 0, elbow_at), r_cable)

    elbow_side = -side * rng.uniform(0.6, 1.0)
    arm.joint("elbow", "revolute", elbow_parent, "forearm", (0, elbow_side, elbow_at), _Y,
              (-rng.uniform(2.0, 2.7), rng.uniform(1.2, 2.7)))  # fmt: skip
    rise = 0.0 if cobot else reach * rng.uniform(0.0, 0.06)
    forearm = arm.link("forearm")
    _elbow(rng, forearm, cobot, r_up, r_fore, rise)
    wrist_parent, wrist_at, forearm_len = "forearm", fore_len, fore_len
    if n >= 6:  # a wrist roll splits the forearm
        split = fore_len * rng.uniform(0.3, 0.6)
        _limb(forearm, cobot, r_fore, (0, 0, rise), (split, 0, rise))
        arm.joint("wrist_roll", "revolute", "forearm", "forearm_2", (split, 0, rise), _X,
                  _symmetric(rng, 3.0, math.pi))  # fmt: skip
        fore2 = arm.link("forearm_2")
        _limb(fore2, cobot, r_fore * 0.9, (0, 0, 0), (fore_len - split, 0, 0))
        wrist_parent, wrist_at, forearm_len = "forearm_2", fore_len - split, split
        cable_z = rise + r_fore + r_cable
        rise = 0.0
    else:
        _limb(forearm, cobot, r_fore, (0, 0, rise), (fore_len, 0, rise))
        cable_z = rise + r_fore + r_cable
    if cable:
        forearm.rod((0.0, 0, cable_z), (0.9 * forearm_len, 0, cable_z), r_cable)

    arm.joint("wrist_pitch", "revolute", wrist_parent, "wrist", (wrist_at, 0, rise), _Y,
              _symmetric(rng, 1.7, 2.2))  # fmt: skip
    wrist = arm.link("wrist")
    wrist.housing(r_wrist * 1.05, r_wrist * 2.2, (0, 0, 0), _Y)
    _limb(wrist, cobot, r_wrist * 0.9, (0, 0, 0), (wrist_len, 0, 0))
    flange_r = _clip(r_wrist * rng.uniform(0.6, 0.9), (0.02, 0.12))
    thick = max(0.01, flange_r * 0.3)
    if n >= 5:
        arm.joint("flange_roll", "revolute", "wrist", "flange", (wrist_len, 0, 0), _X,
                  _symmetric(rng, 3.0, 2 * math.pi))  # fmt: skip
    else:
        arm.joint("flange_fixed", "fixed", "wrist", "flange", (wrist_len, 0, 0))
    flange = arm.link("flange")
    flange.housing(flange_r, thick, (thick / 2, 0, 0), _X)
    return "flange", (thick, 0.0, 0.0), (0.0, 0.0, 0.0), flange_r


def _limb(link: _Link, cobot: bool, radius: float, p, q) -> None:
    """A link's body from p to q: rounded for a cobot, a box-like cross-section otherwise."""
    if cobot:
        link.rod(p, q, radius, rounded=True)
    else:
        link.bar(p, q, 2 * radius, 1.6 * radius)


def _turret(rng, turret: _Link, cobot: bool, r: float, height: float, reach_out: float) -> None:
    """The link the base yaw turns: a round column for a cobot; a box shoulder housing, often
    with a counterweight behind it, for an industrial arm."""
    if cobot:
        turret.rod((0, 0, 0), (0, 0, height), r * 1.1)
        turret.housing(r * 1.15, r * 2.4, (0, 0, height), _Y)
        return
    turret.cylinder(r * 1.6, min(height, r), (0, 0, min(height, r) / 2))
    turret.box((reach_out + 2.4 * r, 2.6 * r, height + r), (reach_out / 2, 0, (height + r) / 2))
    if rng.random() < 0.6:
        size = r * rng.uniform(0.9, 1.5)
        turret.box((size, 1.8 * r, size * 1.2), (-(1.2 * r + size / 2), 0, height * 0.8))


def _elbow(rng, forearm: _Link, cobot: bool, r_up: float, r_fore: float, rise: float) -> None:
    """The elbow end of the forearm: a cobot's joint housing; an industrial arm's housing
    with the motors (the counterweight) behind it."""
    if cobot:
        forearm.housing(r_up * 1.05, r_up * 2.1, (0, 0, 0), _Y)
        return
    back = r_up * rng.uniform(1.5, 3.0)
    forearm.box((back + 1.8 * r_up, 2.2 * r_up, rise + 2.0 * r_up),
                ((r_up * 0.9 - back) / 2, 0, rise / 2))  # fmt: skip


# --- SCARA -----------------------------------------------------------------------------------


def _scara(rng, arm: _Arm, style: str, reach: float):
    """Column, two horizontal arms, a quill that slides down and turns; returns the flange
    link, its face's position and rpy there (the tool points down), and its radius."""
    base_h = _base(rng, arm, reach, (0.5, 0.9))
    len1 = _clip(reach * rng.uniform(0.5, 0.6), LINK_LENGTH_M)
    len2 = _clip(reach - len1, LINK_LENGTH_M)
    r1 = _clip(reach * rng.uniform(0.07, 0.11), LINK_RADIUS_M)
    r2 = _clip(r1 * rng.uniform(0.7, 0.9), LINK_RADIUS_M)
    t1, t2 = r1 * rng.uniform(0.9, 1.4), r2 * rng.uniform(0.9, 1.4)
    stroke = _clip(base_h * rng.uniform(0.2, 0.4), (0.05, 0.3))
    r_quill = max(0.01, r2 * 0.25)

    arm.joint("j1", "revolute", "base_link", "arm_1", (0, 0, base_h), _Z, _symmetric(rng, 1.8, 2.6))
    link1 = arm.link("arm_1")
    _stadium(link1, len1, r1, t1)
    arm.joint("j2", "revolute", "arm_1", "arm_2", (len1, 0, t1), _Z, _symmetric(rng, 2.0, 2.6))
    link2 = arm.link("arm_2")
    _stadium(link2, len2, r2, t2)
    housing_h = t2 * rng.uniform(1.0, 2.5)
    link2.cylinder(r2 * 0.9, housing_h, (len2, 0, t2 + housing_h / 2))
    below = t1 + rng.uniform(0.03, 0.08)
    arm.joint("quill_z", "prismatic", "arm_2", "quill", (len2, 0, 0), (0, 0, -1), (0.0, stroke))
    quill = arm.link("quill")
    top = t2 + housing_h + stroke
    quill.rod((0, 0, -below), (0, 0, top), r_quill)
    arm.joint("quill_roll", "revolute", "quill", "flange", (0, 0, -below), _Z,
              _symmetric(rng, 3.0, 2 * math.pi))  # fmt: skip
    flange_r = _clip(r_quill * rng.uniform(1.5, 2.5), (0.02, 0.12))
    thick = max(0.01, flange_r * 0.3)
    arm.link("flange").cylinder(flange_r, thick, (0, 0, -thick / 2))
    return "flange", (0.0, 0.0, -thick), (0.0, math.pi / 2, 0.0), flange_r


def _stadium(link: _Link, length: float, radius: float, thick: float) -> None:
    """A flat arm from the origin along x: a box with a round end at each joint."""
    z = thick / 2
    link.box((length, 2 * radius, thick), (length / 2, 0, z))
    link.cylinder(radius, thick, (0, 0, z))
    link.cylinder(radius, thick, (length, 0, z))


# --- end effectors ---------------------------------------------------------------------------


def _effector(rng, arm: _Arm, flange: str, face, rpy, r: float) -> None:
    """The tool link: an end effector (maybe behind a tool changer) from the flange's face to
    its tip, the link's origin at the tip, its x axis pointing out of the flange (each
    builder draws from the flange's face, x0 along x, and returns the tip)."""
    tool = arm.link(TOOL_LINK)
    start = 0.0
    if rng.random() < TOOL_CHANGER_SHARE:  # a tool changer between flange and effector
        start = r * rng.uniform(0.4, 0.8)
        tool.housing(r * 1.1, start, (start / 2, 0, 0), _X)
        tool.box((start * 0.8, r * 0.6, r * 0.5), (start / 2, 0, r * 1.1 + r * 0.25))
    kind = EFFECTORS[int(rng.integers(len(EFFECTORS)))]
    tip = np.asarray(_EFFECTOR_BUILDERS[kind](rng, tool, start, r), np.float64)
    tool.shift = tuple(-tip)
    at = np.asarray(face, np.float64) + _rpy_matrix(rpy) @ tip
    arm.joint("tool_fixed", "fixed", flange, TOOL_LINK, tuple(at), rpy=rpy)


def _rpy_matrix(rpy) -> np.ndarray:
    """URDF's rotation for rpy: Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = (
        math.cos(r),
        math.sin(r),
        math.cos(p),
        math.sin(p),
        math.cos(y),
        math.sin(y),
    )
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def _gripper(rng, tool: _Link, x0: float, r: float) -> float:
    """A palm and two parallel fingers; returns its tip."""
    palm, width = r * rng.uniform(0.8, 1.5), r * rng.uniform(2.2, 3.5)
    depth = r * rng.uniform(1.2, 2.0)
    tool.box((palm, width, depth), (x0 + palm / 2, 0, 0))
    finger, thick = r * rng.uniform(1.2, 3.0), r * rng.uniform(0.25, 0.45)
    gap = width * rng.uniform(0.3, 0.85) / 2
    for y in (-gap, gap):
        tool.box((finger, thick, depth * 0.8), (x0 + palm + finger / 2, y, 0))
    return (x0 + palm + finger, 0.0, 0.0)


def _vacuum(rng, tool: _Link, x0: float, r: float) -> float:
    """A stem, a plate and one to four suction cups; returns its tip."""
    stem = r * rng.uniform(0.5, 1.5)
    tool.housing(r * 0.6, stem, (x0 + stem / 2, 0, 0), _X)
    plate, span = r * 0.25, r * rng.uniform(2.0, 6.0)
    tool.box((plate, span, span * rng.uniform(0.5, 1.0)), (x0 + stem + plate / 2, 0, 0))
    cups, cup = int(rng.integers(1, 5)), r * rng.uniform(0.3, 0.6)
    offsets = [(0.0, 0.0)] if cups == 1 else [
        (span * 0.3 * math.cos(a), span * 0.2 * math.sin(a))
        for a in np.linspace(0, 2 * math.pi, cups, endpoint=False) + math.pi / 4
    ]  # fmt: skip
    length = cup * 1.2
    for y, z in offsets:
        tool.housing(cup if cups > 1 else r, length, (x0 + stem + plate + length / 2, y, z), _X)
    return (x0 + stem + plate + length, 0.0, 0.0)


def _torch(rng, tool: _Link, x0: float, r: float) -> float:
    """A welding torch: a body, a neck bent down and a nozzle; returns its tip."""
    body = r * rng.uniform(1.5, 3.0)
    tool.housing(r * 0.8, body, (x0 + body / 2, 0, 0), _X)
    bend, neck = math.radians(rng.uniform(20, 45)), r * rng.uniform(2.0, 4.0)
    start = np.array([x0 + body, 0.0, 0.0])
    end = start + neck * np.array([math.cos(bend), 0.0, -math.sin(bend)])
    tool.rod(start, end, r * 0.35, rounded=True)
    tool.rod(end - 0.25 * (end - start), end, r * 0.45)
    return tuple(end)


def _screwdriver(rng, tool: _Link, x0: float, r: float) -> float:
    """A motor beside a thin spindle on a bracket; returns its tip."""
    bracket = r * rng.uniform(0.3, 0.6)
    tool.box((bracket, r * 1.6, r * 3.2), (x0 + bracket / 2, 0, r * 0.8))
    motor, spindle = r * rng.uniform(2.0, 4.0), r * rng.uniform(2.0, 4.0)
    tool.housing(r * 0.7, motor, (x0 + bracket + motor / 2, 0, r * 1.6), _X)
    tool.housing(r * 0.2, spindle, (x0 + bracket + spindle / 2, 0, 0), _X)
    return (x0 + bracket + spindle, 0.0, 0.0)


def _camera(rng, tool: _Link, x0: float, r: float) -> float:
    """A bracket carrying a camera box with its lens beside the flange; returns its tip."""
    bracket = r * rng.uniform(0.3, 0.6)
    tool.housing(r, bracket, (x0 + bracket / 2, 0, 0), _X)
    size = np.array([r * 1.2, r * rng.uniform(2.0, 3.5), r * 1.2])
    centre = (x0 + bracket + size[0] / 2, 0, r + size[2] / 2)
    tool.box(size, centre)
    tool.housing(r * 0.4, r * 0.4, (x0 + bracket + size[0] + r * 0.2, 0, centre[2]), _X)
    return (x0 + bracket, 0.0, 0.0)


def _bare(rng, tool: _Link, x0: float, r: float) -> float:
    """No effector: the flange's pilot boss only; returns its tip."""
    boss = max(0.005, r * 0.15)
    tool.housing(r * 0.5, boss, (x0 + boss / 2, 0, 0), _X)
    return (x0 + boss, 0.0, 0.0)


_EFFECTOR_BUILDERS = {
    "gripper": _gripper,
    "vacuum": _vacuum,
    "torch": _torch,
    "screwdriver": _screwdriver,
    "camera": _camera,
    "none": _bare,
}
