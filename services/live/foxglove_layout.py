"""The Foxglove layout of one camera's viewer topics (`docs/foxglove/topseg-layout.json`).

Panel configurations come from the Foxglove SDK's layout classes (`foxglove.layouts`:
`ImageConfig`, `ThreeDeeConfig`, ...). They are wrapped in the layout file the Foxglove app
imports ("Layouts > Import from file..."): `configById` (panel id `<type>!<name>` -> its
config), `layout` (a mosaic tree: `first`, `second`, `direction`, `splitPercentage`),
`globalVariables`, `userNodes`, `playbackConfig`. The SDK's own `Layout.to_json()` format is
read by its notebook and playground viewers, not (yet) by the app, hence the wrapper.

    python -m topseg.services.live.foxglove_layout [--cell C] [--camera K] > layout.json
"""

from __future__ import annotations

import argparse
import json

from topseg.core.formats import ros2_messages, wire
from topseg.services.live.viewer_foxglove import safety_topic, topic

#: depth shown from black (0 mm) to white (this many mm) in the depth panel
DEPTH_DISPLAY_MAX_MM = 5000


def _config(part) -> dict:
    """A foxglove.layouts config object as the plain dict the app stores."""
    return json.loads(part.to_json())


#: the worker's stages plotted over time, from its stats messages (ms)
PLOTTED_STAGES = ("forest", "crf", "total", "latency")


def layout(cell: str = wire.DEFAULT_CELL, camera: str = wire.DEFAULT_CAMERA) -> dict:
    """The layout of a camera: depth and label-colour images over the labelled 3-D cloud in
    the floor frame (with a grid, the cell's safety zones and nearest pair) beside plots of
    the worker's ms per stage and the cell's speed scale and state."""
    import foxglove.layouts as fl

    calibration = topic(cell, camera, "camera_info")
    depth = fl.ImageConfig(
        image_mode=fl.ImageModeConfig(
            image_topic=topic(cell, camera, "depth"),
            calibration_topic=calibration,
            min_value=0,
            max_value=DEPTH_DISPLAY_MAX_MM,
        )
    )
    label_colours = fl.ImageConfig(
        image_mode=fl.ImageModeConfig(
            image_topic=topic(cell, camera, "labels_color"), calibration_topic=calibration
        )
    )
    scene = fl.ThreeDeeConfig(
        follow_tf=ros2_messages.floor_frame(cell, camera),
        topics={
            topic(cell, camera, "points"): fl.BaseRendererPointCloudTopicSettings(
                visible=True, color_mode="rgba-fields", point_size=3
            ),
            safety_topic(cell, "scene"): fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        },
        layers={"grid": fl.BaseRendererGridLayerSettings()},
    )
    stats = topic(cell, camera, "stats")
    timings = fl.PlotConfig(
        paths=[
            fl.PlotSeries(value=f"{stats}.timings_ms.{stage}", label=f"{stage} ms", enabled=True)
            for stage in PLOTTED_STAGES
        ],
        y_axis_label="ms",
        show_legend=True,
    )
    state = safety_topic(cell)
    safety = fl.PlotConfig(
        paths=[
            fl.PlotSeries(value=f"{state}.speed_scale", label="speed scale", enabled=True),
            fl.PlotSeries(value=f"{state}.level", label="state (0 clear, 2 stop)", enabled=True),
        ],
        show_legend=True,
    )
    panels = {
        "Image!depth": depth,
        "Image!labels": label_colours,
        "3D!floor": scene,
        "Plot!timings": timings,
        "Plot!safety": safety,
    }
    return {
        "configById": {name: _config(config) for name, config in panels.items()},
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {
            "direction": "column",
            "splitPercentage": 40,
            "first": {
                "direction": "row",
                "splitPercentage": 50,
                "first": "Image!depth",
                "second": "Image!labels",
            },
            "second": {
                "direction": "row",
                "splitPercentage": 65,
                "first": "3D!floor",
                "second": {
                    "direction": "column",
                    "splitPercentage": 50,
                    "first": "Plot!timings",
                    "second": "Plot!safety",
                },
            },
        },
    }


def layout_topics(data: dict) -> set[str]:
    """The topics a layout's panels read (image, calibration, 3-D and plotted topics; a plot
    path is `<topic>.<field>...`, and topic names hold no dots)."""
    found = set()
    for config in data["configById"].values():
        mode = config.get("imageMode", {})
        found.update(mode[key] for key in ("imageTopic", "calibrationTopic") if key in mode)
        found.update(config.get("topics", {}))
        found.update(series["value"].split(".", 1)[0] for series in config.get("paths", []))
    return found


def main(argv: list[str] | None = None) -> int:
    """Print the layout of one camera as JSON."""
    parser = argparse.ArgumentParser(prog="python -m topseg.services.live.foxglove_layout")
    parser.add_argument("--cell", default=wire.DEFAULT_CELL)
    parser.add_argument("--camera", default=wire.DEFAULT_CAMERA)
    args = parser.parse_args(argv)
    print(json.dumps(layout(args.cell, args.camera), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
