"""The synthesis entry point: reproducible frames by seed, in this process and another, labels
that follow the noise, and configs that survive JSON."""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT
from topseg.core.errors import TopsegError
from topseg.core.synth.density import DensityFunction
from topseg.core.synth.scene import PlacedObject, Scene
from topseg.core.synth.synthesis import (
    POSES,
    ROOMS,
    MountDistribution,
    SynthesisConfig,
    Synthesizer,
)


def _digest(frame) -> str:
    h = hashlib.sha256()
    h.update(frame.depth.tobytes())
    h.update(frame.labels.tobytes())
    h.update(json.dumps(frame.scene, sort_keys=True).encode())
    return h.hexdigest()


@pytest.fixture(scope="module")
def synth():
    with Synthesizer(SynthesisConfig(noise="kinect", seed=3)) as s:
        yield s


def test_frames_have_the_contracted_shapes_and_labels_follow_the_noise(synth):
    f = synth.render(0)
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.uint16
    assert f.labels.shape == (480, 640) and f.labels.dtype == np.uint8
    assert np.array_equal(f.labels == labels.NO_DEPTH, f.depth == 0)
    assert (f.depth == 0).any()  # the kinect model leaves shadows
    present = set(np.unique(f.labels).tolist())
    assert present <= {*range(labels.NUM_CLASSES), labels.NO_DEPTH}
    assert present & set(labels.HUMAN_IDS)
    scene = Scene.from_dict(json.loads(json.dumps(f.scene)))
    assert math.isfinite(DensityFunction().log_density(scene))
    assert f.seed == 0 and set(f.timings_ms) == {"sample", "build", "raycast", "noise"}


def test_the_same_seed_gives_the_same_frame_and_others_differ(synth):
    a, b = synth.render(11), synth.render(12)
    assert _digest(synth.render(11)) == _digest(a)
    assert _digest(a) != _digest(b)
    with Synthesizer(SynthesisConfig(noise="kinect", seed=4), warm=False) as other:
        assert _digest(other.render(11)) != _digest(a)  # the config's seed matters too
    for bad in (-1, 1.5, "3", True):
        with pytest.raises(TopsegError, match="frame_seed"):
            synth.render(bad)


def test_a_warm_synthesizer_never_creates_bodies_while_rendering(synth):
    b = synth.builder
    furniture_keys, humans = set(b._furniture), set(b._humans)
    assert len(furniture_keys) == 8 * 4 * 21 and len(humans) == 31  # kinds x variants x heights
    for i in range(30):
        synth.render(1000 + i)
    assert set(b._furniture) == furniture_keys and set(b._humans) == humans  # copies aside


def test_the_same_seed_gives_the_same_frame_in_another_process(synth):
    """The other process does not warm its pools: frames cannot depend on what is pooled."""
    code = (
        "import hashlib, json, sys;"
        "from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer;"
        "s = Synthesizer(SynthesisConfig(noise='kinect', seed=3), warm=False);"
        "f = s.render(7);"
        "h = hashlib.sha256(); h.update(f.depth.tobytes()); h.update(f.labels.tobytes());"
        "h.update(json.dumps(f.scene, sort_keys=True).encode()); print(h.hexdigest())"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip().splitlines()[-1] == _digest(synth.render(7))


def test_a_known_table_appears_where_and_as_deep_as_it_should():
    table = PlacedObject(0, "table_rect", 0, 0.75, 0.5, -0.4, 0.0, 0.0)
    scene = Scene("modeled", "industrial_workspace", (-2.3, -1.8), (2.3, 1.8), 0.3, 0.3, [table])
    with Synthesizer(SynthesisConfig(noise="none"), warm=False) as s:
        f = s.render_scene(scene)
    k = PAPER_MOUNT.intrinsics
    z = 3.5 - 0.75
    u = round(0.5 / z * k.fx + k.cx)
    v = round(0.4 / z * k.fy + k.cy)  # world y = -0.4 is below the image centre
    assert f.labels[v, u] == labels.TABLE and f.depth[v, u] == 2750
    m = f.labels == labels.TABLE
    top = m & (f.depth == 2750)
    # its top is 1.2 m x 0.7 m at 2.75 m: (1.2 * fx / z) x (0.7 * fy / z) pixels
    assert top.sum() == pytest.approx((1.2 * k.fx / z) * (0.7 * k.fy / z), rel=0.03)
    assert np.all(f.depth[~m] == 3500) and np.all(f.labels[~m] == labels.BACKGROUND)


def test_non_modeled_frames_hold_one_item():
    with Synthesizer(
        SynthesisConfig(mode="non-modeled", noise="gaussian:15", room="office"), warm=False
    ) as s:
        for i in range(4):
            sc = s.render(i).scene
            assert len(sc["objects"]) + (sc["human"] is not None) == 1 and not sc["relations"]
            assert sc["room"] == "office"


def test_config_round_trips_and_validates():
    c = SynthesisConfig(
        mode="non-modeled", noise="gaussian:30", room="lab_corridor", theta_max=0.1, seed=9
    )
    assert c.density.theta_max_ho == c.density.theta_max_oo == 0.1
    back = SynthesisConfig.from_dict(json.loads(json.dumps(c.to_dict())))
    assert back.to_dict() == c.to_dict()
    assert SynthesisConfig(noise=" Kinect ").noise == "kinect"
    for kw, msg in (
        ({"mode": "half"}, "mode"),
        ({"noise": "pink"}, "unknown noise"),
        ({"room": "attic"}, "room"),
        ({"theta_max": 2.0}, "theta_max"),
        ({"seed": -1}, "seed"),
    ):
        with pytest.raises(TopsegError, match=msg):
            SynthesisConfig(**kw)
    with pytest.raises(TopsegError, match="unknown key"):
        SynthesisConfig.from_dict({"modes": "modeled"})
    assert len(ROOMS) >= 4 and "sitting" in POSES and "walking" in POSES


def test_a_closed_synthesizer_refuses_to_render():
    s = Synthesizer(SynthesisConfig(noise="none"), warm=False)
    s.close()
    s.close()  # twice is fine
    with pytest.raises(TopsegError, match="closed"):
        s.render(0)


def test_bench_reports_each_stage():
    import argparse

    from topseg.services.batch.bench import synthesis as bench_synthesis

    args = argparse.Namespace(
        frames=3, warmup=1, mode="non-modeled", noise="gaussian:15", threads=0
    )
    out = bench_synthesis.measure(args)
    for stage in ("sample", "build", "raycast", "noise"):
        assert out[f"{stage}_ms_p50"] > 0
    assert out["frames"] == 3 and out["frames_per_s"] > 0 and out["noise"] == "gaussian:15"
    with pytest.raises(TopsegError, match="frames"):
        bench_synthesis.measure(
            argparse.Namespace(frames=0, warmup=0, mode="modeled", noise="none", threads=0)
        )


@pytest.mark.slow
def test_memory_stays_flat_over_thousands_of_frames():
    """Bodies are pooled: once the pools hold every furniture variant and height drawn, more
    frames allocate nothing in pybullet."""
    import resource

    with Synthesizer(SynthesisConfig(noise="kinect")) as s:
        for i in range(1500):
            s.render(i)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        bodies = s.builder.n_bodies
        for i in range(1500, 3000):
            s.render(i)
        after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    assert after - before < 40  # MiB; the remaining growth is the last few pool entries
    assert s.builder.n_bodies - bodies < 0.2 * bodies


def test_drawn_mounts_span_their_ranges_and_travel_with_each_frame():
    config = SynthesisConfig(
        mounts=MountDistribution(), noise="none", room="industrial_workspace", seed=2
    )
    assert SynthesisConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    seen = set()
    with Synthesizer(config, warm=False) as s:
        for i in range(10):
            f = s.render(i)
            m = f.mount
            assert m == s.mount_for(i)  # a pure function of the frame's seed
            assert f.scene["mount"] == m.to_dict()
            assert f.depth.shape == f.labels.shape == m.intrinsics.shape
            assert 2400 <= m.height_mm <= 4500 and abs(m.pitch_deg) <= 10 and abs(m.roll_deg) <= 10
            seen.add(m.sensor)
            # no walls in this room: every background pixel is floor, at height ~0
            h = m.height_map_mm(f.depth)
            floor = f.labels == labels.BACKGROUND
            assert floor.mean() > 0.3 and np.nanmax(np.abs(h[floor])) < 1.0
            people = np.isin(f.labels, labels.HUMAN_IDS)
            if people.any():
                assert np.nanmax(h[people]) < 2000  # heights are heights, whatever the mount
        again = s.render(3)
        assert np.array_equal(again.depth, s.render(3).depth)
    assert len(seen) >= 3
    summary = config.mount_summary()
    assert summary["height_mm"] == [2400.0, 4500.0] and summary["tilt_deg"] > 10
    assert [512, 424] in summary["resolutions"] and [640, 400] in summary["resolutions"]


def test_sensor_noise_follows_each_frames_sensor():
    for name in ("kinect_v1", "kinect_v2", "oak_d", "realsense_d435"):
        config = SynthesisConfig(mounts=MountDistribution(sensors=(name,)), noise="sensor")
        with Synthesizer(config, warm=False) as s:
            f = s.render(0)
            assert f.mount.sensor == name
            assert s.noise_for(f.mount).spec.split(":")[0] in ("kinect", "tof", "stereo")
            assert np.array_equal(f.labels == labels.NO_DEPTH, f.depth == 0)
    with pytest.raises(TopsegError, match="unknown sensor"):
        MountDistribution(sensors=("kinect_v3",))


def test_time_of_flight_frames_lose_depth_on_heads_only():
    """The renderer's labels reach the noise model: dark hair drops out in patches, and no
    other pixel changes (the same seed, with and without hair dropout)."""
    frames = {}
    for dropout in (0.0, 0.5):
        config = SynthesisConfig(noise=f"tof:dark_dropout={dropout},speckle=0", seed=4)
        with Synthesizer(config, warm=False) as s:
            frames[dropout] = [s.render(i) for i in range(4)]
    for clear, hairy in zip(frames[0.0], frames[0.5], strict=True):
        head = clear.labels == labels.HEAD
        changed = clear.depth != hairy.depth
        assert not changed[~head].any()
        if head.sum() > 200:
            assert np.mean(hairy.depth[head] == 0) == pytest.approx(0.5, abs=0.2)
    assert sum((f.labels == labels.HEAD).sum() > 200 for f in frames[0.0]) >= 2


def test_a_fixed_mount_keeps_the_papers_frames():
    """mounts=None draws no mount: the frame is at the paper's mount, its scene drawn from the
    frame's scene stream, which the mount's third stream leaves untouched."""
    with Synthesizer(SynthesisConfig(noise="gaussian:15", seed=5), warm=False) as s:
        f = s.render(7)
        scene_rng, _ = s.rngs(7)
        assert Scene.from_dict(f.scene).to_dict() == f.scene
        assert s.density.sample(scene_rng).to_dict() == f.scene
    assert f.mount == PAPER_MOUNT and f.depth.shape == PAPER_MOUNT.intrinsics.shape
