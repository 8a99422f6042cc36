"""`topseg bench forest` end to end: a small random forest on procedural frames (fast), and the
default (the bundled model on rendered frames) in `make test-all`."""

from __future__ import annotations

import json

import pytest

from topseg.services.cli import main

#: the default's node visits: the Kinect v1 at 3.5 m is labelled at half resolution, where
#: the grid ~25 mm apart on the floor is every other pixel
GRID_VISITS = "node_visits_per_frame_stride2_downsample2"


def _figures(capsys, *args: str) -> dict:
    assert main(["-q", "bench", "forest", "--json", "--repeats", "1", *args]) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_random_forest_on_procedural_frames_at_two_strides(capsys):
    figures = _figures(
        capsys, "--forest", "random", "--trees", "2", "--depth", "8", "--frames", "2",
        "--frames-from", "procedural", "--stride", "2",
    )  # fmt: skip
    assert figures["trees"] == 2 and figures["depth"] == 8
    assert figures["adaptive_levels"] == 1  # the default; random posteriors settle no pixel
    assert "procedural" in figures["frames"]
    # every walked pixel of a full random tree walks all 8 levels; stride 2 walks ~1/4 of them
    assert figures["mean_levels_walked"] == 8.0
    full, grid = figures["node_visits_per_frame_stride1"], figures["node_visits_per_frame_stride2"]
    assert 0.2 < grid / full < 0.3
    assert (
        figures["forest_ms_per_frame_stride1"] > 0 and "avg_f1_forest_only_stride1" not in figures
    )


@pytest.mark.slow
def test_default_times_the_bundled_model_on_rendered_frames(capsys):
    figures = _figures(capsys, "--frames", "2")
    assert figures["forest"].startswith("bundled model")
    assert "rendered modeled scenes" in figures["frames"]
    assert figures[GRID_VISITS] < figures["node_visits_per_frame_stride1"] / 10
    assert 0 < figures["avg_f1_forest_only_stride2_downsample2"] <= 1
    # the adaptive grid (default) walks fewer grid pixels than the whole grid (--adaptive 0)
    plain = _figures(capsys, "--frames", "2", "--adaptive", "0")
    assert figures[GRID_VISITS] < 0.9 * plain[GRID_VISITS]
    assert figures["node_visits_per_frame_stride1"] == plain["node_visits_per_frame_stride1"]
    # the early exit (default) walks fewer trees at the grid pixels than --early-exit off
    every = _figures(capsys, "--frames", "2", "--early-exit", "off")
    assert figures[GRID_VISITS] < 0.9 * every[GRID_VISITS]
    assert figures["node_visits_per_frame_stride1"] == every["node_visits_per_frame_stride1"]


def test_frames_from_the_users_camera():
    """`--sensor` and `--height` put the bench's camera where the user's is: its sensor's
    resolution and noise, its height; the default stays the paper's Kinect v1 at 3.5 m."""
    import argparse

    from topseg.core.camera import PAPER_MOUNT
    from topseg.services.batch.bench import frames

    parser = argparse.ArgumentParser()
    frames.add_arguments(parser)
    assert frames.bench_mount(parser.parse_args([])) is PAPER_MOUNT
    mount = frames.bench_mount(parser.parse_args(["--sensor", "oak_d", "--height", "4.5"]))
    assert (mount.sensor, mount.height_mm, mount.intrinsics.shape) == ("oak_d", 4500.0, (400, 640))
    assert frames.bench_mount(parser.parse_args(["--height", "2.8"])).sensor == "kinect_v1"
    with pytest.raises(SystemExit):
        parser.parse_args(["--height", "0.5"])
    pairs, what = frames.bench_frames(frames.RENDERED, 1, 0, mount)
    assert pairs[0][0].shape == (400, 640) and "oak_d at 4.50 m" in what
