"""The Foxglove layout file: the app's import format, with the viewer's topics."""

import json
from pathlib import Path

from topseg.services.live import foxglove_layout
from topseg.services.live.viewer_foxglove import topic

LAYOUT_FILE = Path(__file__).parents[1] / "docs" / "foxglove" / "topseg-layout.json"


def leaves(node) -> list[str]:
    """The panel ids of a mosaic layout tree."""
    if isinstance(node, str):
        return [node]
    assert node["direction"] in ("row", "column") and 0 < node["splitPercentage"] < 100
    return leaves(node["first"]) + leaves(node["second"])


def test_the_committed_file_is_the_generated_layout_of_the_default_camera():
    assert json.loads(LAYOUT_FILE.read_text()) == foxglove_layout.layout(), (
        "regenerate: python -m topseg.services.live.foxglove_layout > docs/foxglove/topseg-layout.json"
    )


def test_every_panel_is_placed_once_and_reads_the_cameras_topics():
    layout = foxglove_layout.layout("c2", "top")
    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
    assert {name.split("!")[0] for name in layout["configById"]} == {"Image", "3D", "Plot"}
    assert foxglove_layout.layout_topics(layout) == {
        topic("c2", "top", stream)
        for stream in ("depth", "labels_color", "camera_info", "points", "stats")
    } | {"/topseg/c2/safety", "/topseg/c2/safety/scene"}
    safety = layout["configById"]["Plot!safety"]
    assert [p["value"] for p in safety["paths"]] == [
        "/topseg/c2/safety.speed_scale",
        "/topseg/c2/safety.level",
    ]
    plot = layout["configById"]["Plot!timings"]
    assert [p["value"] for p in plot["paths"]] == [
        f"{topic('c2', 'top', 'stats')}.timings_ms.{stage}"
        for stage in ("forest", "crf", "total", "latency")
    ]
    scene = layout["configById"]["3D!floor"]
    assert scene["followTf"] == "c2_top_floor"  # the floor below that camera
    assert scene["topics"][topic("c2", "top", "points")]["colorMode"] == "rgba-fields"
    assert scene["layers"]["grid"]["layerId"] == "foxglove.Grid"
