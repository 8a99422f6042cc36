"""Forward kinematics of a parsed URDF in one pass down its tree.

yourdfpy parses the URDF (joints, origins, axes, mimic rules); posing through its scene graph
costs 3-4 ms an arm (`update_cfg` then one `get_transform` per link, each a fresh product
along the path from the root). The same poses come from one walk of the joints from the
root, each link's pose its parent's times the joint's origin and motion: 0.1-0.2 ms an
arm. Mimic joints follow yourdfpy's rule (q = multiplier * q_mimicked + offset; a mimicked
joint that is not actuated reads 0), so the poses are the library's to rounding, which
`tests/test_kinematics.py` checks on every catalogue arm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: joint kinds: no motion, rotation about the axis, translation along it
FIXED, REVOLUTE, PRISMATIC = 0, 1, 2


@dataclass(frozen=True)
class Kinematics:
    """A URDF's tree as flat arrays, joints in an order where every parent link's pose is
    known before its child's: for joint j, `parent[j]` and `child[j]` index `links`,
    `origin[j]` its (4, 4) origin, `axis[j]` its unit axis, `kind[j]` FIXED / REVOLUTE /
    PRISMATIC, and its value `scale[j] * q[source[j]] + offset[j]` of the actuated values q
    (`source[j]` -1: the value is `offset[j]`)."""

    links: tuple[str, ...]
    parent: np.ndarray
    child: np.ndarray
    origin: np.ndarray
    axis: np.ndarray
    kind: np.ndarray
    source: np.ndarray
    scale: np.ndarray
    offset: np.ndarray

    @classmethod
    def of(cls, urdf) -> Kinematics:
        """The kinematics of a yourdfpy URDF (its actuated joints in `actuated_joint_names`
        order are the values `poses` takes)."""
        actuated = {name: i for i, name in enumerate(urdf.actuated_joint_names)}
        links = [urdf.base_link]
        index = {urdf.base_link: 0}
        by_parent: dict[str, list] = {}
        for joint in urdf.robot.joints:
            by_parent.setdefault(joint.parent, []).append(joint)
        rows = []
        todo = [urdf.base_link]
        while todo:
            link = todo.pop()
            for joint in by_parent.get(link, []):
                if joint.child in index:
                    continue
                index[joint.child] = len(links)
                links.append(joint.child)
                todo.append(joint.child)
                rows.append((joint, index[link], index[joint.child]))
        n = len(rows)
        origin = np.tile(np.eye(4), (n, 1, 1))
        axis = np.zeros((n, 3))
        kind = np.zeros(n, np.int64)
        source = np.full(n, -1, np.int64)
        scale = np.ones(n)
        offset = np.zeros(n)
        for j, (joint, _, _) in enumerate(rows):
            if joint.origin is not None:
                origin[j] = joint.origin
            if joint.type in ("revolute", "continuous", "prismatic"):
                kind[j] = PRISMATIC if joint.type == "prismatic" else REVOLUTE
                direction = np.asarray(joint.axis, np.float64).reshape(3)
                norm = float(np.linalg.norm(direction))
                # yourdfpy rotates about the unit axis but translates along the axis as given
                axis[j] = direction / norm if kind[j] == REVOLUTE and norm > 0 else direction
            if joint.mimic is not None:
                source[j] = actuated.get(joint.mimic.joint, -1)
                multiplier, shift = joint.mimic.multiplier, joint.mimic.offset
                scale[j] = (1.0 if multiplier is None else multiplier) if source[j] >= 0 else 0.0
                offset[j] = 0.0 if shift is None else shift
            elif joint.name in actuated:
                source[j] = actuated[joint.name]
        return cls(
            tuple(links),
            np.array([r[1] for r in rows], np.int64),
            np.array([r[2] for r in rows], np.int64),
            origin, axis, kind, source, scale, offset,
        )  # fmt: skip

    def poses(self, q: np.ndarray) -> np.ndarray:
        """(links, 4, 4) every link's pose in the root link's frame at the actuated values
        `q` (radians for rotations, metres for translations)."""
        q = np.asarray(q, np.float64)
        values = np.where(self.source >= 0, q[np.maximum(self.source, 0)], 0.0)
        values = self.scale * values + self.offset
        local = self.origin.copy()
        turning = self.kind == REVOLUTE
        if turning.any():
            local[turning, :3, :3] = local[turning, :3, :3] @ _rotations(
                self.axis[turning], values[turning]
            )
        sliding = self.kind == PRISMATIC
        if sliding.any():
            step = self.axis[sliding] * values[sliding, None]
            local[sliding, :3, 3] += np.einsum("nij,nj->ni", self.origin[sliding, :3, :3], step)
        out = np.empty((len(self.links), 4, 4))
        out[0] = np.eye(4)
        for j in range(len(self.parent)):
            out[self.child[j]] = out[self.parent[j]] @ local[j]
        return out


def _rotations(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations by `angles` about the unit `axes` (Rodrigues' formula)."""
    x, y, z = axes[:, 0], axes[:, 1], axes[:, 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=1).reshape(-1, 3, 3)
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)
