"""Room templates: the floor the density function places items on, and the walls around it.

The paper generated its scenes in four rooms of an industrial workspace and an office. Each
template here is a floor rectangle matched to what the ceiling camera sees (about
3.9 m x 2.9 m at 3.5 m for Kinect v1): items stand with their centre on it and may reach a
margin beyond it, so the frame edge can cut them. Walls stand on the sides the room has them,
and the template has its taste in furniture: how often each class and each object-object
relation appears.

World frame (camera.TopViewMount): x, y on the floor, z up, origin below the camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from topseg.core.camera import TOP_VIEW, TopViewMount

WALL_HEIGHT_M = 2.5
WALL_THICKNESS_M = 0.15
#: how far the floor reaches beyond what the camera sees, so items can be cut by the frame
MARGIN_M = 0.3


@dataclass(frozen=True)
class RoomTemplate:
    """A room: `walls` names the sides that have one ("north" is +y, "east" is +x).

    `inset` is how far inside the camera's view each wall stands (metres), so the camera sees
    it. `floor()` is where items' centres go (the view, up to the walls); `bounds()` is what
    their footprints must stay in (up to the walls, `MARGIN_M` beyond the view elsewhere).
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
        w, d = mount.floor_extent_m()
        half = {"east": w / 2, "west": w / 2, "north": d / 2, "south": d / 2}
        edge = {}
        for side, h in half.items():
            if side in self.walls:  # the wall's inner face
                edge[side] = h - self.inset.get(side, 0.4) - WALL_THICKNESS_M / 2
            else:
                edge[side] = h + margin
        return (-edge["west"], -edge["south"]), (edge["east"], edge["north"])

    def floor(
        self, mount: TopViewMount = TOP_VIEW
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """(lo, hi) corners of where items' centres go: the camera's view, inside the walls."""
        return self._edges(mount, 0.0)

    def bounds(
        self, mount: TopViewMount = TOP_VIEW
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """(lo, hi) corners footprints stay within: the walls, or MARGIN_M beyond the view."""
        return self._edges(mount, MARGIN_M)

    def wall_boxes(self, mount: TopViewMount = TOP_VIEW) -> list[tuple[tuple, tuple]]:
        """Each wall as (centre xyz, half extents xyz), long enough to fill the view."""
        (x0, y0), (x1, y1) = self.bounds(mount)
        w, d = mount.floor_extent_m()
        t = WALL_THICKNESS_M / 2
        hz = WALL_HEIGHT_M / 2
        span_x = w / 2 + 2 * MARGIN_M + 1.0
        span_y = d / 2 + 2 * MARGIN_M + 1.0
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

    def to_dict(self, mount: TopViewMount = TOP_VIEW) -> dict:
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
