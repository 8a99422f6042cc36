"""Where the viewer logs in Rerun, and the blueprint that lays those entities out.

Entity paths (one place, used by the logging and by the blueprint):

- `world`: the floor frame, z up (`ViewCoordinates.RIGHT_HAND_Z_UP`).
- `world/<cell>/<camera>/camera`: the camera, a `Transform3D` from its mount (the pose of
  the optical frame in the floor frame); without a known mount it has no transform, so the
  camera's optical frame stands in for the floor frame (the scene then hangs upside down).
- `world/<cell>/<camera>/camera/image`: the Pinhole, with `depth` and `labels` below it.
- `world/<cell>/<camera>/points`: the labelled cloud in floor coordinates.
- `<cell>/<camera>/stats/{ms/<stage>,fps,count/<name>}`: scalars over time.
- `<cell>/safety/{state,speed_scale,reaction_ms,min_distance_m}`: a cell's safety state
  (clear 0, warning 1, stop 2) and its numbers as scalars over time; `<cell>/safety/reasons`
  the states and their reasons as a text log.
- `world/<cell>/<camera>/safety/{zones/<zone>,nearest,robot}` with a cell file
  (`--cell`): its zones, the nearest person-robot pair and the robot's capsules, in that
  camera's world frame beside its cloud; without one, `world/<cell>/safety/nearest` in the
  cell frame (the same as the camera's world frame for a camera at the cell's origin).
- `legend`: one coloured, named dot per label (Points2D with class ids), so the label
  table stays visible next to the images.

Each camera's floor frame has its origin below that camera; cameras are not registered to
each other, so two cameras' clouds share the 3-D view without being aligned.
"""

from __future__ import annotations

from collections.abc import Iterable

from topseg.core import labels

WORLD = "world"
LEGEND = "legend"
#: spacing of the 3-D view's floor grid, metres
GRID_SPACING_M = 0.5


def camera_entity(cell: str, camera: str) -> str:
    """The camera's entity: its mount transform lives here."""
    return f"{WORLD}/{cell}/{camera}/camera"


def image_entity(cell: str, camera: str) -> str:
    """The camera's Pinhole; `depth` and `labels` are its children."""
    return f"{camera_entity(cell, camera)}/image"


def points_entity(cell: str, camera: str) -> str:
    """The camera's labelled point cloud, in floor coordinates."""
    return f"{WORLD}/{cell}/{camera}/points"


def safety_entity(cell: str) -> str:
    """The root of a cell's safety scalars and reasons."""
    return f"{cell}/safety"


def safety_shapes_entity(cell: str, camera: str | None = None) -> str:
    """The root of a cell's safety shapes: in a camera's world frame
    (`world/<cell>/<camera>/safety`), or in the cell frame without one."""
    if camera is None:
        return f"{WORLD}/{cell}/safety"
    return f"{WORLD}/{cell}/{camera}/safety"


def stats_entity(cell: str, camera: str) -> str:
    """The root of the camera's worker stats scalars."""
    return f"{cell}/{camera}/stats"


def legend_points():
    """The label legend: one dot per label (and no-depth) in a column, coloured and named."""
    import rerun as rr

    table = (*labels.LABELS, labels.NO_DEPTH_LABEL)
    return rr.Points2D(
        [(0.0, float(row)) for row in range(len(table))],
        radii=0.4,
        class_ids=[lab.id for lab in table],
        labels=[lab.name for lab in table],
        show_labels=True,
    )


def _camera_views(cell: str, camera: str):
    import rerun.blueprint as rrb

    image = image_entity(cell, camera)
    stats = stats_entity(cell, camera)
    return rrb.Vertical(
        rrb.Horizontal(
            rrb.Spatial2DView(
                name=f"{cell}/{camera} depth", origin=image, contents="$origin/depth"
            ),
            rrb.Spatial2DView(
                name=f"{cell}/{camera} labels", origin=image, contents="$origin/labels"
            ),
        ),
        rrb.Horizontal(
            rrb.TimeSeriesView(name=f"{cell}/{camera} ms per stage", origin=f"{stats}/ms"),
            rrb.TimeSeriesView(name=f"{cell}/{camera} fps", origin=stats, contents="$origin/fps"),
        ),
        row_shares=[2, 1],
        name=f"{cell}/{camera}",
    )


def _cell_views(cell: str):
    import rerun.blueprint as rrb

    base = safety_entity(cell)
    return rrb.Vertical(
        rrb.TimeSeriesView(
            name=f"{cell} safety state",
            origin=base,
            contents=["$origin/state", "$origin/speed_scale"],
        ),
        rrb.TimeSeriesView(name=f"{cell} reaction ms", origin=base, contents="$origin/reaction_ms"),
        rrb.TextLogView(name=f"{cell} safety reasons", origin=f"{base}/reasons"),
        name=f"{cell} safety",
    )


def blueprint(cameras: Iterable[tuple[str, str]], cells: Iterable[str] = ()):
    """The viewer's layout for these (cell, camera) pairs and cells with a safety state:
    per camera its depth and labels views over its timing plots, per cell its state, speed
    scale, reaction time and reasons, beside the shared 3-D view of the floor frame (with a
    floor grid) over the label legend."""
    import rerun as rr
    import rerun.blueprint as rrb

    scene = rrb.Vertical(
        rrb.Spatial3DView(
            name="floor frame",
            origin=WORLD,
            line_grid=rrb.LineGrid3D(
                visible=True, spacing=GRID_SPACING_M, plane=rr.components.Plane3D.XY
            ),
        ),
        rrb.Spatial2DView(name="labels", origin=LEGEND),
        row_shares=[4, 1],
    )
    per_camera = [_camera_views(cell, camera) for cell, camera in sorted(set(cameras))]
    per_camera += [_cell_views(cell) for cell in sorted(set(cells))]
    if per_camera:
        content = rrb.Horizontal(rrb.Tabs(*per_camera), scene, column_shares=[3, 2])
    else:
        content = scene
    return rrb.Blueprint(content, rrb.SelectionPanel(state="collapsed"))
