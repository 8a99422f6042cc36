"""Room templates: the floor the density function places items on, and the walls around it.

The paper generated its scenes in four rooms of an industrial workspace and an office. Each
template here is a floor rectangle matched to what the ceiling camera sees (`view_rect`: the
bounding rectangle of the floor the image covers, about 3.9 m x 2.9 m at 3.5 m for a Kinect v1
looking straight down; shifted and stretched when the camera is tilted): items stand with
their centre on it and may reach a margin beyond it, so the frame edge can cut them. Walls
stand on the sides the room has them, and the template has its taste in furniture: how often
each class and each object-object relation appears.

World frame (camera.TopViewMount): x, y on the floor, z up, origin below the camera centre.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from topseg.core.camera import PAPER_MOUNT, TopViewMount

WALL_HEIGHT_M = 2.5
WALL_THICKNESS_M = 0.15
#: how far the floor reaches beyond what the camera sees, so items can be cut by the frame
MARGIN_M = 0.3
#: a wall's inset is at most this share of the view across it (small views at low ceilings)
MAX_INSET_SHARE = 0.125
#: half length of every wall: longer than any view, so one pooled wall body fits every mount
WALL_HALF_LENGTH_M = 10.0


def view_rect(mount: TopViewMount) -> tuple[tuple[float, float], tuple[float, float]]:
    """(lo, hi) world corners (m) of the bounding rectangle of the floor the image shows.

    The four image corners' rays meet the floor plane z = 0; straight down this is the
    centred width x depth of `floor_extent_m`, tilted it is a trapezoid's bounding box.
    """
    k = mount.intrinsics
    u = np.array([-0.5, k.width - 0.5, k.width - 0.5, -0.5])
    v = np.array([-0.5, -0.5, k.height - 0.5, k.height - 0.5])
    ray_c = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(4)], axis=1)
    rot = np.asarray(mount.rotation_world_to_camera(), np.float64)
    centre = np.asarray(mount.centre_world_m(), np.float64)
    ray_w = ray_c @ rot  # R^T d for each row
    if np.any(ray_w[:, 2] >= -1e-6):
        raise ValueError("the camera sees past the horizon: too much tilt for a top view")
    t = -centre[2] / ray_w[:, 2]
    xy = centre[:2] + t[:, None] * ray_w[:, :2]
    lo, hi = xy.min(0), xy.max(0)
    return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))


@dataclass(frozen=True)
class RoomTemplate:
    """A room: `walls` names the sides that have one ("north" is +y, "east" is +x).

    `inset` is how far inside the camera's view each wall stands (metres, at most
    MAX_INSET_SHARE of the view across it), so the camera sees it. `floor()` is where items'
    centres go (the view, up to the walls); `bounds()` is what their footprints must stay in
    (up to the walls, `MARGIN_M` beyond the view elsewhere).
    """

    name: str
    description: str
    walls: tuple[str, ...] = ()
    inset: dict = field(default_factory=dict)
    class_weights: dict = field(default_factory=dict)
    oo_relation_weights: dict = field(default_factory=dict)
    n_objects: tuple[int, int] = (2, 6)

    def _edges(
        self, mount: TopViewMount, margin: float
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        (x0, y0), (x1, y1) = view_rect(mount)
        w, d = x1 - x0, y1 - y0
        # outward distance of each side's view edge from the origin, and the view across it
        half = {"east": (x1, w), "west": (-x0, w), "north": (y1, d), "south": (-y0, d)}
        edge = {}
        for side, (h, across) in half.items():
            if side in self.walls:  # the wall's inner face
                inset = min(self.inset.get(side, 0.4), MAX_INSET_SHARE * across)
                edge[side] = h - inset - WALL_THICKNESS_M / 2
            else:
                edge[side] = h + margin
        return (-edge["west"], -edge["south"]), (edge["east"], edge["north"])

    def floor(
        self, mount: TopViewMount = PAPER_MOUNT
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """(lo, hi) corners of where items' centres go: the camera's view, inside the walls."""
        return self._edges(mount, 0.0)

    def bounds(
        self, mount: TopViewMount = PAPER_MOUNT
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """(lo, hi) corners footprints stay within: the walls, or MARGIN_M beyond the view."""
        return self._edges(mount, MARGIN_M)

    def wall_boxes(self, mount: TopViewMount = PAPER_MOUNT) -> list[tuple[tuple, tuple]]:
        """Each wall as (centre xyz, half extents xyz), WALL_HALF_LENGTH_M long either way."""
        (x0, y0), (x1, y1) = self.bounds(mount)
        t = WALL_THICKNESS_M / 2
        hz = WALL_HEIGHT_M / 2
        span_x = span_y = WALL_HALF_LENGTH_M
        boxes = []
        for side in self.walls:
            if side == "north":
                boxes.append(((0.0, y1 + t, hz), (span_x, t, hz)))
            elif side == "south":
                boxes.append(((0.0, y0 - t, hz), (span_x, t, hz)))
            elif side == "east":
                boxes.append(((x1 + t, 0.0, hz), (t, span_y, hz)))
            elif side == "west":
                boxes.append(((x0 - t, 0.0, hz), (t, span_y, hz)))
        return boxes

    def to_dict(self, mount: TopViewMount = PAPER_MOUNT) -> dict:
        """Name, walls, and the floor and bounds corners (m) under `mount`, as JSON-able lists."""
        lo, hi = self.floor(mount)
        blo, bhi = self.bounds(mount)
        return {
            "name": self.name,
            "walls": list(self.walls),
            "floor_lo": list(lo),
            "floor_hi": list(hi),
            "bounds_lo": list(blo),
            "bounds_hi": list(bhi),
        }


_ALL_OO = {
    "tables_joined": 1.0,
    "storage_under_table": 1.0,
    "chair_under_table": 1.0,
    "plant_on_table": 1.0,
    "free": 1.0,
}

TEMPLATES: dict[str, RoomTemplate] = {
    t.name: t
    for t in (
        RoomTemplate(
            "industrial_workspace",
            "open shop floor around a robot cell: workbenches, shelving, a stool or two",
            walls=(),
            class_weights={"table": 3.0, "storage": 3.0, "chair": 2.0, "plant": 0.5},
            oo_relation_weights={
                **_ALL_OO,
                "tables_joined": 2.0,
                "storage_under_table": 2.0,
                "plant_on_table": 0.3,
            },
            n_objects=(2, 6),
        ),
        RoomTemplate(
            "office",
            "office against one wall: desks, office chairs, plants, wardrobes",
            walls=("north",),
            inset={"north": 0.35},
            class_weights={"table": 2.0, "chair": 3.0, "plant": 2.0, "storage": 1.5},
            oo_relation_weights={**_ALL_OO, "chair_under_table": 2.0, "plant_on_table": 2.0},
            n_objects=(2, 6),
        ),
        RoomTemplate(
            "meeting_room",
            "corner of a meeting room: joined tables with chairs around, a plant on the table",
            walls=("north", "west"),
            inset={"north": 0.3, "west": 0.45},
            class_weights={"table": 2.0, "chair": 4.0, "plant": 1.5, "storage": 0.5},
            oo_relation_weights={**_ALL_OO, "tables_joined": 2.5, "chair_under_table": 3.0},
            n_objects=(3, 7),
        ),
        RoomTemplate(
            "lab_corridor",
            "lab bay between two walls: shelves and benches along the walls",
            walls=("north", "south"),
            inset={"north": 0.3, "south": 0.3},
            class_weights={"storage": 3.0, "table": 2.0, "chair": 1.5, "plant": 1.0},
            oo_relation_weights={**_ALL_OO, "storage_under_table": 2.0},
            n_objects=(2, 5),
        ),
    )
}

ROOMS: tuple[str, ...] = tuple(TEMPLATES)


def get(name: str) -> RoomTemplate:
    """The template called `name`; KeyError naming the known rooms otherwise."""
    try:
        return TEMPLATES[name]
    except KeyError:
        raise KeyError(f"unknown room {name!r}; known: {', '.join(ROOMS)}") from None
