"""services/viewer_layout: the Rerun blueprint and entity paths of the viewer, built in memory."""

import numpy as np

from topseg.core import labels
from topseg.services.live import viewer_layout as vl


def views(part) -> list:
    """Every view of a blueprint container, depth first."""
    if hasattr(part, "kind") and hasattr(part, "contents"):
        return [v for child in part.contents for v in views(child)]
    return [part]


def test_every_camera_gets_depth_labels_and_timing_views_beside_the_shared_floor_view():
    bp = vl.blueprint([("c1", "cam1"), ("c1", "cam0"), ("c1", "cam0")])
    found = {(type(v).__name__, str(v.name)): v for v in views(bp.root_container)}
    for cam in ("cam0", "cam1"):
        image = vl.image_entity("c1", cam)
        assert image == f"world/c1/{cam}/camera/image"
        depth = found["Spatial2DView", f"c1/{cam} depth"]
        assert str(depth.origin) == image and depth.contents == "$origin/depth"
        label_view = found["Spatial2DView", f"c1/{cam} labels"]
        assert str(label_view.origin) == image and label_view.contents == "$origin/labels"
        ms = found["TimeSeriesView", f"c1/{cam} ms per stage"]
        assert str(ms.origin) == f"{vl.stats_entity('c1', cam)}/ms"
        assert ("TimeSeriesView", f"c1/{cam} fps") in found
    scene = found["Spatial3DView", "floor frame"]
    assert str(scene.origin) == vl.WORLD and "LineGrid3D" in scene.properties
    assert str(found["Spatial2DView", "labels"].origin) == vl.LEGEND
    assert len(found) == 2 * 4 + 2  # cam0 listed twice is laid out once


def test_without_cameras_the_layout_is_the_floor_view_and_the_legend():
    found = [(type(v).__name__, str(v.name)) for v in views(vl.blueprint([]).root_container)]
    assert found == [("Spatial3DView", "floor frame"), ("Spatial2DView", "labels")]


def test_points_live_in_the_floor_frame_beside_the_camera_they_come_from():
    assert vl.points_entity("c", "k").startswith(f"{vl.WORLD}/c/k/")
    assert vl.image_entity("c", "k").startswith(vl.camera_entity("c", "k") + "/")
    assert not vl.stats_entity("c", "k").startswith(vl.WORLD)  # not spatial


def test_the_legend_shows_every_label_with_its_id_and_name():
    legend = vl.legend_points()
    table = (*labels.LABELS, labels.NO_DEPTH_LABEL)
    ids = legend.class_ids.as_arrow_array().to_numpy(zero_copy_only=False)
    np.testing.assert_array_equal(ids, [lab.id for lab in table])
    names = legend.labels.as_arrow_array().to_pylist()
    assert names == [lab.name for lab in table]
    assert names[-3:] == ["robot", "object", "no-depth"]
