"""Scene description -> pybullet bodies, kept alive between frames, and their primitives.

Creating pybullet shapes costs ~1 ms a body and leaks memory that `removeBody` does not give
back (about 100 kB a frame here), so the builder never removes a body. It pools them: one
humanoid per height on the 1 cm grid (loaded with `globalScaling` the first time that height
is drawn), one body per furniture (kind, variant, height), wall slabs (one per direction and
copy, each `rooms.WALL_HALF_LENGTH_M` long either way, moved to where the scene's room and
mount put its walls) and the floor. Building a scene moves the bodies it needs into place (poses reset, joints set) and
parks the rest far below the floor, out of every camera's view.

`primitives()` reads the active bodies' geometry back from pybullet (shape data cached per
body, link world poses per frame) as flat arrays for `topseg.core.synth.render`.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass

import numpy as np

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, TopViewMount
from topseg.core.synth import furniture, humanoid, rooms
from topseg.core.synth.geometry import (
    BOX,
    CAPSULE,
    CYLINDER,
    MAX_PARTS,
    SPHERE,
    Part,
    quat_to_matrix,
    yaw_quat,
)
from topseg.core.synth.render import Primitives
from topseg.core.synth.scene import Scene

PARK_Z = -100.0  # parked bodies wait here, below the floor and far beyond the camera's range


def park_position(uid: int) -> list[float]:
    """Where body `uid` waits: below the floor, 5 m from every other parked body (bodies that
    overlap cost pybullet broadphase work on every reset)."""
    return [5.0 * (uid % 64), 5.0 * (uid // 64), PARK_Z]


FLOOR_HALF_M = 10.0


@contextlib.contextmanager
def quiet_stdio():
    """Silence C-level stdout/stderr (pybullet's URDF importer warns on every load)."""
    fds = []
    try:
        for fd in (1, 2):
            fds.append((fd, os.dup(fd)))
        null = os.open(os.devnull, os.O_WRONLY)
        for fd, _ in fds:
            os.dup2(null, fd)
        os.close(null)
        yield
    finally:
        for fd, saved in fds:
            os.dup2(saved, fd)
            os.close(saved)


@dataclass
class Body:
    """A pooled pybullet body and its shapes, in the frames pybullet reports them.

    Per shape: link index (-1 = base), kind, size (geometry.Part convention), local position
    and rotation relative to that link's frame, label.
    """

    uid: int
    multilink: bool
    link: np.ndarray
    kind: np.ndarray
    size: np.ndarray
    local_pos: np.ndarray
    local_rot: np.ndarray
    label: np.ndarray


_GEOM_TO_KIND = {}


def _geom_kinds(p) -> dict[int, int]:
    if not _GEOM_TO_KIND:
        _GEOM_TO_KIND.update(
            {
                p.GEOM_SPHERE: SPHERE,
                p.GEOM_CAPSULE: CAPSULE,
                p.GEOM_BOX: BOX,
                p.GEOM_CYLINDER: CYLINDER,
            }
        )
    return _GEOM_TO_KIND


def read_shapes(client: int, uid: int, label_of_link) -> Body:
    """A body's visual shapes as pybullet reports them (getVisualShapeData)."""
    import pybullet as p

    kinds = _geom_kinds(p)
    rows = p.getVisualShapeData(uid, physicsClientId=client)
    link, kind, size, lpos, lrot, lab = [], [], [], [], [], []
    for row in rows:
        geom, dims = row[2], row[3]
        if geom not in kinds:
            raise ValueError(
                f"body {uid}: shape type {geom} is not a sphere, capsule, box or cylinder"
            )
        k = kinds[geom]
        if k == SPHERE:
            s = (dims[0], 0.0, 0.0)
        elif k == BOX:  # pybullet reports full extents
            s = (dims[0] / 2, dims[1] / 2, dims[2] / 2)
        else:  # (length, radius)
            s = (dims[1], dims[0] / 2, 0.0)
        link.append(row[1])
        kind.append(k)
        size.append(s)
        lpos.append(row[5])
        lrot.append(quat_to_matrix(row[6]))
        lab.append(label_of_link(row[1]))
    return Body(
        uid,
        p.getNumJoints(uid, physicsClientId=client) > 0,
        np.array(link, np.int64),
        np.array(kind, np.int32),
        np.array(size, np.float64).reshape(-1, 3),
        np.array(lpos, np.float64).reshape(-1, 3),
        np.array(lrot, np.float64).reshape(-1, 3, 3),
        np.array(lab, np.uint8),
    )


def _create_compound(client: int, parts, label: int) -> Body:
    """One static body whose base carries all `parts` (geometry.Part) as visual shapes."""
    import pybullet as p

    if len(parts) > MAX_PARTS:
        raise ValueError(
            f"an item has at most {MAX_PARTS} parts (pybullet's limit), got {len(parts)}"
        )
    types, half, radii, lengths, pos, orn = [], [], [], [], [], []
    geom = {
        SPHERE: p.GEOM_SPHERE,
        CAPSULE: p.GEOM_CAPSULE,
        BOX: p.GEOM_BOX,
        CYLINDER: p.GEOM_CYLINDER,
    }
    for part in parts:
        types.append(geom[part.kind])
        half.append(list(part.size) if part.kind == BOX else [0.0, 0.0, 0.0])
        radii.append(part.size[0] if part.kind != BOX else 0.0)
        lengths.append(2 * part.size[1] if part.kind in (CAPSULE, CYLINDER) else 0.0)
        pos.append(list(part.pos))
        orn.append(list(part.quat))
    vis = p.createVisualShapeArray(
        shapeTypes=types, halfExtents=half, radii=radii, lengths=lengths,
        visualFramePositions=pos, visualFrameOrientations=orn, physicsClientId=client,
    )  # fmt: skip
    uid = p.createMultiBody(
        baseMass=0, baseVisualShapeIndex=vis, basePosition=[0, 0, PARK_Z], physicsClientId=client
    )
    p.resetBasePositionAndOrientation(uid, park_position(uid), [0, 0, 0, 1], physicsClientId=client)
    return read_shapes(client, uid, lambda _link: label)


def _grid(lo: float, hi: float, step: float) -> list[float]:
    """The heights of the grid step that lie in [lo, hi]."""
    return [
        k * step for k in range(int(np.ceil(lo / step - 1e-9)), int(np.floor(hi / step + 1e-9)) + 1)
    ]


class SceneBuilder:
    """Owns the pooled bodies of one pybullet client and poses them for each scene."""

    def __init__(self, client: int, mount: TopViewMount = PAPER_MOUNT) -> None:
        """`mount` places the walls of scenes that record no mount of their own."""

        self.client = client
        self.mount = mount
        self._urdf = humanoid.urdf_path()  # pybullet_data's humanoid, proportions fixed
        self._furniture: dict[tuple[str, int, float], list[Body]] = {}
        self._humans: dict[tuple[float, int], Body] = {}
        self._walls: dict[tuple[str, int], Body] = {}
        self._labels: dict[tuple[int, int], int] = {}
        self.floor = self._make_floor()
        self.active: list[Body] = [self.floor]

    # --- pools ---------------------------------------------------------------------------

    def _remember(self, body: Body) -> Body:
        for li, lab in zip(body.link.tolist(), body.label.tolist(), strict=True):
            self._labels[(body.uid, li)] = lab
        return body

    def _make_floor(self) -> Body:
        import pybullet as p

        body = _create_compound(
            self.client,
            [Part(BOX, (FLOOR_HALF_M, FLOOR_HALF_M, 0.05), (0.0, 0.0, -0.05))],
            labels.BACKGROUND,
        )
        p.resetBasePositionAndOrientation(
            body.uid, [0, 0, 0], [0, 0, 0, 1], physicsClientId=self.client
        )
        return self._remember(body)

    def _wall_body(self, half: tuple, copy: int) -> Body:
        """A pooled wall slab with half extents `half` (long along x or y), centred on its base."""
        key = ("x" if half[0] >= half[1] else "y", copy)
        if key not in self._walls:
            body = _create_compound(self.client, [Part(BOX, tuple(half), (0.0, 0.0, 0.0))],
                                    labels.BACKGROUND)  # fmt: skip
            self._walls[key] = self._remember(body)
        return self._walls[key]

    def _walls_of(self, room: str, mount: TopViewMount) -> list[tuple[Body, tuple]]:
        """The room's walls under `mount`: (pooled slab, centre) pairs."""
        out, copies = [], {}
        for centre, half in rooms.get(room).wall_boxes(mount):
            axis = "x" if half[0] >= half[1] else "y"
            n = copies.get(axis, 0)
            copies[axis] = n + 1
            out.append((self._wall_body(tuple(half), n), tuple(centre)))
        return out

    def _furniture_body(self, kind: str, variant: int, height: float, copy: int) -> Body:
        key = (kind, variant, furniture.quantize_height(height))
        pool = self._furniture.setdefault(key, [])
        while len(pool) <= copy:
            m = furniture.model(*key)
            pool.append(self._remember(_create_compound(self.client, m.parts, m.label)))
        return pool[copy]

    def _human_body(self, height: float, copy: int = 0) -> Body:
        import pybullet as p

        key = (humanoid.quantize_height(height), copy)
        if key not in self._humans:
            with quiet_stdio():
                uid = p.loadURDF(
                    self._urdf, [0, 0, 2 * PARK_Z], globalScaling=humanoid.scale_for_height(key[0]),
                    useFixedBase=True, flags=p.URDF_MAINTAIN_LINK_ORDER, physicsClientId=self.client,
                )  # fmt: skip
            names = [
                p.getJointInfo(uid, j, physicsClientId=self.client)[12].decode()
                for j in range(p.getNumJoints(uid, physicsClientId=self.client))
            ]
            # nothing is simulated: without collision filtering, every reset of a humanoid
            # updates broadphase pairs with the others parked beside it (~0.1 ms a call)
            for link in range(-1, len(names)):
                p.setCollisionFilterGroupMask(uid, link, 0, 0, physicsClientId=self.client)
            p.resetBasePositionAndOrientation(
                uid, park_position(uid), [0, 0, 0, 1], physicsClientId=self.client
            )
            self._humans[key] = self._remember(
                read_shapes(
                    self.client,
                    uid,
                    lambda li: (
                        humanoid.LINK_LABELS.get(names[li], labels.BACKGROUND)
                        if li >= 0
                        else labels.BACKGROUND
                    ),
                )
            )
        return self._humans[key]

    def warm(self, object_heights: dict, human_heights: tuple[float, float]) -> None:
        """Create one body per furniture (kind, variant, height) and one humanoid per height in
        these ranges (metres, per class), so frames never wait for pybullet to create shapes
        (~1.5 s for the paper's ranges). A class with no range here gets its bodies when first
        drawn."""
        for kind, cls in furniture.CLASS_OF_KIND.items():
            if cls not in object_heights:
                continue
            lo, hi = object_heights[cls]
            for variant in range(furniture.N_VARIANTS):
                for h in _grid(lo, hi, furniture.HEIGHT_STEP_M):
                    self._furniture_body(kind, variant, h, 0)
        for h in _grid(*human_heights, humanoid.HEIGHT_STEP_M):
            self._human_body(h)

    @property
    def n_bodies(self) -> int:
        """pybullet bodies made so far (floor, furniture and humanoid pools, walls)."""
        return (
            1 + sum(len(v) for v in self._furniture.values()) + len(self._humans) + len(self._walls)
        )

    # --- building ------------------------------------------------------------------------

    def label_of(self, uid: int, link: int) -> int:
        """Label of a body's link, for pybullet's segmentation mask."""
        return self._labels.get((uid, link), labels.BACKGROUND)

    def build(self, scene: Scene) -> list[Body]:
        """Pose the bodies `scene` needs, park the rest; returns the active bodies."""
        import pybullet as p

        c = self.client
        wanted: list[Body] = [self.floor]
        copies: dict[tuple, int] = {}
        placements = []
        for wall, centre in self._walls_of(scene.room, scene.mount or self.mount):
            wanted.append(wall)
            placements.append((wall, centre, (0.0, 0.0, 0.0, 1.0)))
        for o in scene.objects:
            key = (o.kind, o.variant, furniture.quantize_height(o.height))
            n = copies.get(key, 0)
            copies[key] = n + 1
            body = self._furniture_body(o.kind, o.variant, o.height, n)
            placements.append((body, (o.x, o.y, o.z), yaw_quat(o.yaw)))
            wanted.append(body)
        for h in scene.humans:
            key = humanoid.quantize_height(h.height)
            n = copies.get(key, 0)
            copies[key] = n + 1
            body = self._human_body(h.height, n)
            wanted.append(body)
            placements.append((body, h.base_pos, h.base_quat))
            model = humanoid.load_model()
            for i, link in enumerate(model.links):
                if link.joint_type == "spherical":
                    p.resetJointStateMultiDof(
                        body.uid, i, h.pose.joints[link.name], physicsClientId=c
                    )
                elif link.joint_type == "revolute":
                    p.resetJointState(body.uid, i, h.pose.joints[link.name][0], physicsClientId=c)
        keep = {b.uid for b in wanted}
        for b in self.active:
            if b.uid not in keep:
                p.resetBasePositionAndOrientation(
                    b.uid, park_position(b.uid), [0, 0, 0, 1], physicsClientId=c
                )
        for body, pos, quat in placements:
            p.resetBasePositionAndOrientation(body.uid, list(pos), list(quat), physicsClientId=c)
        self.active = wanted
        return wanted

    def primitives(self, bodies: list[Body] | None = None) -> Primitives:
        """World-frame primitives of the active bodies, read from pybullet."""
        import pybullet as p

        c = self.client
        out = []
        for b in self.active if bodies is None else bodies:
            if b.multilink:
                states = p.getLinkStates(
                    b.uid,
                    sorted(set(b.link.tolist())),
                    computeForwardKinematics=1,
                    physicsClientId=c,
                )
                frames = {}
                for li, st in zip(sorted(set(b.link.tolist())), states, strict=True):
                    frames[li] = (np.asarray(st[4]), quat_to_matrix(st[5]))
                pos = np.array([frames[li][0] for li in b.link.tolist()])
                rot = np.array([frames[li][1] for li in b.link.tolist()])
            else:
                bp, bq = p.getBasePositionAndOrientation(b.uid, physicsClientId=c)
                pos = np.broadcast_to(np.asarray(bp), (len(b.link), 3))
                rot = np.broadcast_to(quat_to_matrix(bq), (len(b.link), 3, 3))
            center = pos + np.einsum("nij,nj->ni", rot, b.local_pos)
            world_rot = np.einsum("nij,njk->nik", rot, b.local_rot)
            out.append(Primitives(b.kind, b.size, center, world_rot, b.label))
        return Primitives.concat(out)
