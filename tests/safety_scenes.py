"""Rendered frames of a small cell for the safety tests: a floor, the cell's robot posed at
given joints, and people as boxes and balls labelled with body parts, seen by a ceiling
camera at a placement. The labels are the ray caster's exact ones."""

from __future__ import annotations

import numpy as np

from topseg.core import labels
from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.formats.wire import DepthFrame, LabelFrame
from topseg.core.safety.cell import CameraPlacement
from topseg.core.safety.robot import CellRobot, _to_camera_world
from topseg.core.synth.geometry import BOX, CAPSULE, SPHERE
from topseg.core.synth.render import Primitives, Triangles, raycast

MOUNT = TopViewMount(KINECT_V1.scaled_to(320, 240), height_mm=3000.0)


def _prims(kinds, sizes, centres, label_ids, rots=None) -> Primitives:
    n = len(kinds)
    rot = np.repeat(np.eye(3)[None], n, axis=0) if rots is None else np.asarray(rots, float)
    return Primitives(
        np.asarray(kinds, np.int32),
        np.asarray(sizes, np.float64).reshape(n, 3),
        np.asarray(centres, np.float64).reshape(n, 3),
        rot.reshape(n, 3, 3),
        np.asarray(label_ids, np.uint8),
    )


def _z_to(direction: np.ndarray) -> np.ndarray:
    """A rotation taking local z to `direction` (unit)."""
    z = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def person(x: float, y: float, height: float = 1.75, hand_at: tuple | None = None) -> Primitives:
    """A standing person at (x, y) (cell frame): legs, body, head as boxes and a ball; with
    `hand_at` (x, y, z) a hand ball there on an arm (a capsule) from the shoulder."""
    top = height - 0.12
    kinds = [BOX, BOX, SPHERE]
    sizes = [(0.15, 0.1, 0.45), (0.2, 0.12, 0.3), (0.1, 0, 0)]
    centres = [(x, y, 0.45), (x, y, 1.2), (x, y, top)]
    ids = [labels.LEGS, labels.BODY, labels.HEAD]
    rots = [np.eye(3)] * 3
    if hand_at is not None:
        hand = np.asarray(hand_at, float)
        shoulder = np.array([x, y, 1.4])
        arm = hand - shoulder
        kinds += [SPHERE, CAPSULE]
        sizes += [(0.05, 0, 0), (0.045, np.linalg.norm(arm) / 2, 0)]
        centres += [tuple(hand), tuple((hand + shoulder) / 2)]
        ids += [labels.HAND, labels.LOWER_ARM]
        rots += [np.eye(3), _z_to(arm)]
    return _prims(kinds, sizes, centres, ids, rots)


def floor() -> Primitives:
    """The floor: a wide thin box under z = 0, background."""
    return _prims([BOX], [(20.0, 20.0, 0.05)], [(0.0, 0.0, -0.05)], [labels.BACKGROUND])


def render(
    placement: CameraPlacement,
    robot: CellRobot | None = None,
    joints: dict | None = None,
    people: list[Primitives] = (),
    mount: TopViewMount = MOUNT,
    seq: int = 0,
    stamp_ns: int = 0,
    name: str = "cam0",
) -> tuple[DepthFrame, LabelFrame]:
    """One camera's depth (with its mount) and exact labels of the cell."""
    prims = [floor(), *people]
    tris = Triangles.empty()
    if robot is not None:
        rp, tris = robot.geometry(joints or {})
        prims.append(rp)
    world, tris = _to_camera_world(Primitives.concat(prims), tris, placement)
    depth, lab = raycast(world, mount, tris)
    return (
        DepthFrame(depth, mount.intrinsics, seq, stamp_ns, name, mount),
        LabelFrame(lab, seq, stamp_ns, name),
    )
