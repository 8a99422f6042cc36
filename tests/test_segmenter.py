"""The one Segmenter and the one score(): the same labels as the forest + CRF path they replace,
the bundled model, the frame check, and scores against a confusion computed by hand."""

from pathlib import Path

import numpy as np
import pytest
from segmenter_rules import (
    check_context_as_the_segmenter,
    check_people_as_the_segmenter,
    prior_as_the_segmenter,
    relabel_as_the_segmenter,
    vote_as_the_segmenter,
)

from topseg.core import bundled_model, crf, forest, segmenter_config
from topseg.core import labels as L
from topseg.core import segmenter as S
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.forest.model_header import model_camera
from topseg.core.formats import recording, wire
from topseg.core.holes import fill_holes
from topseg.core.islands import FURNITURE_COUNTED
from topseg.core.scoring import score
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.core.segmenter_config import (
    ADAPTIVE_LEVELS,
    EARLY_EXIT,
    GridConfig,
    PostConfig,
    PreConfig,
)

REPO = Path(__file__).resolve().parents[1]
SMALL = KINECT_V1.scaled_to(40, 30)


def demo_frames(n):
    """The first `n` (depth, truth) pairs of the bundled recording."""
    depth, out = {}, []
    for msg in recording.read_messages(REPO / "recordings" / "demo.mcap"):
        if msg.key.endswith("/depth"):
            f = wire.decode_depth(msg.data)
            depth[f.seq] = f.depth
        elif msg.key.endswith("/truth"):
            t = wire.decode_labels(msg.data)
            if t.seq in depth:
                out.append((depth.pop(t.seq), t.labels))
        if len(out) == n:
            return out
    return out


def numpy_argmax(proba, depth):
    """Forest-only labels in plain numpy (numpy's argmax: first maximum on ties)."""
    out = np.argmax(proba, axis=-1).astype(np.uint8)
    out[np.asarray(depth) == 0] = L.NO_DEPTH
    return out


@pytest.fixture(scope="module")
def bundled():
    return Segmenter.from_file(None, crf="realtime")


@pytest.fixture(scope="module")
def legacy():
    """A raw-depth model trained by the code before height inputs (tests/data/legacy_model.npz)."""
    return Segmenter.from_file(REPO / "tests" / "data" / "legacy_model.npz", crf="realtime")


def test_from_file_none_is_the_bundled_model(bundled):
    assert bundled.path == REPO / "models" / "default.npz" == S.bundled_model_path()
    assert bundled.crf_mode == "realtime"
    assert bundled.model_id  # the header's model_id, else the file name
    # the bundled model reads height above the floor and was trained across mounts and sensors
    assert bundled.reads_height
    trained = bundled.trained_for
    assert {"kinect_v1", "kinect_v2", "oak_d", "realsense_d435"} <= set(trained["sensors"])
    assert trained["height_mm"][0] <= 2500 and trained["height_mm"][1] >= 4500
    with pytest.raises(TopsegError, match=r"cam3: .*needs the camera's mount"):
        bundled.label(np.full((480, 640), 3000, np.uint16), name="cam3")


def test_no_bundled_model_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setattr(bundled_model, "CHECKOUT_MODEL", Path("no-such-folder") / "none.npz")
    monkeypatch.setattr(bundled_model, "INSTALLED_MODEL", tmp_path / "none.npz")
    with pytest.raises(TopsegError, match="no bundled model") as err:
        bundled_model.bundled_model_path()
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("mode", ["none", "realtime"])
def test_labels_are_those_of_the_forest_then_crf_path(legacy, mode):
    seg = Segmenter(legacy.forest, legacy.header, crf=mode)
    model, _ = forest.load_model(legacy.path)
    for depth, _ in demo_frames(3):
        got = seg.label(depth, name="demo")
        proba = forest.predict_proba(model, depth)
        if mode == "none":
            expected, small = numpy_argmax(proba, depth), np.zeros(L.NUM_CLASSES)  # as it is
            satellites = 0
        else:
            expected = crf.segment_crf(proba, depth, crf.CRFConfig(mode=mode))
            k = seg.camera
            small, satellites = relabel_as_the_segmenter(expected, depth, k)
        np.testing.assert_array_equal(got.labels, expected)
        assert (
            got.counts["small_heads"] == small[L.HEAD]
            and got.counts["satellite_heads"] == satellites
        )
        assert got.counts["small_furniture"] == small[list(FURNITURE_COUNTED)].sum()
        np.testing.assert_array_equal(got.proba, proba)
        assert got.labels.dtype == np.uint8 and got.proba.dtype == np.float32
        t = got.timings
        assert t.forest_ms > 0 and t.crf_ms >= 0 and t.total_ms >= t.forest_ms


@pytest.mark.parametrize("mode", ["none", "realtime", "exact"])
def test_a_grid_labels_as_the_eager_path_and_fills_its_posteriors_when_read(mode):
    """On a grid the Segmenter stores only the posteriors the CRF reads; labels and the
    posteriors read afterwards are those of the eager forest + CRF path."""
    from topseg.core.forest.inputs import model_input

    k = KINECT_V1.scaled_to(160, 120)
    mount = TopViewMount(k, PAPER_MOUNT.height_mm)
    seg = Segmenter.from_file(
        None, SegmenterConfig(mount=mount, grid=GridConfig(stride=2)), crf=mode
    )
    for depth, _ in demo_frames(2):
        depth = np.ascontiguousarray(depth[::4, ::4])
        got = seg.label(depth)
        depth, filled = fill_holes(depth, k)  # what the Segmenter labels
        assert got.counts["filled_holes"] == filled
        inp = model_input(depth, mount, seg.features)
        proba = forest.predict_proba(
            seg.forest, inp, stride=2, adaptive=ADAPTIVE_LEVELS, early_exit=EARLY_EXIT
        )
        prior_as_the_segmenter(proba, depth, inp, mount, seg.context_prior)
        want = crf.segment_crf(proba, depth, seg.config.crf)
        if mode != "none":
            check_context_as_the_segmenter(want, depth, inp, proba, mount, seg.context_check)
            check_people_as_the_segmenter(want, depth, proba, mount, seg.person_check)
            vote_as_the_segmenter(want, depth, mount, seg.n_classes)
            relabel_as_the_segmenter(want, depth, k)
        np.testing.assert_array_equal(got.labels, want)
        np.testing.assert_array_equal(got.proba, proba)
    stale = seg.label(depth)
    seg.label(depth)
    with pytest.raises(TopsegError, match="earlier frame"):
        stale.proba  # noqa: B018 (the property is what is tested)


def test_the_one_argmax_agrees_with_numpy_on_ties_and_no_depth():
    rng = np.random.default_rng(4)
    for _ in range(20):
        proba = rng.integers(0, 3, size=(17, 23, L.NUM_CLASSES)).astype(np.float32)  # ties
        depth = rng.integers(0, 3, size=(17, 23)).astype(np.uint16)
        got = crf.segment_argmax(proba, depth > 0)
        np.testing.assert_array_equal(got, numpy_argmax(proba, depth))


def test_frames_of_another_camera_are_refused_by_name(legacy):
    """A raw-depth model knows one camera: frames of another are refused, not mislabelled."""
    with pytest.raises(TopsegError, match=r"cam7: frame is 320x240 but .* 640x480"):
        legacy.label(np.zeros((240, 320), np.uint16), name="cam7")
    wide = Intrinsics(640, 480, 400.0, 400.0, 319.5, 239.5)
    with pytest.raises(TopsegError, match=r"f9: focal length 400\.0 px"):
        legacy.label(np.zeros((480, 640), np.uint16), wide, name="f9")
    # the check can be left out; warm_up compiles on a small frame whatever the camera
    loose = Segmenter(legacy.forest, config=SegmenterConfig(check_camera=False))
    assert loose.label(np.full((24, 32), 2000, np.uint16)).labels.shape == (24, 32)
    legacy.warm_up()


def test_model_camera_from_the_header():
    header = {
        "dataset": {"attrs": {"camera": TopViewMount(SMALL, PAPER_MOUNT.height_mm).to_dict()}}
    }
    assert model_camera(header) == SMALL
    assert model_camera({}) == KINECT_V1
    with pytest.raises(TopsegError, match="unreadable camera"):
        model_camera({"dataset": {"attrs": {"camera": {"intrinsics": {}}}}})


def hand_confusion(pairs):
    cm = np.zeros((L.NUM_CLASSES, L.NUM_CLASSES), np.int64)
    for truth, pred in pairs:
        keep = truth != L.NO_DEPTH
        p = np.where(pred[keep] == L.NO_DEPTH, L.BACKGROUND, pred[keep]).astype(np.int64)
        t = truth[keep].astype(np.int64)
        np.add.at(cm, (t, p), 1)
    return cm


def test_score_equals_the_confusion_computed_by_hand():
    rng = np.random.default_rng(1)
    trees = [forest.random_tree(rng, 5, 2, 40 * 2500.0, 300.0) for _ in range(2)]
    model = forest.Forest.from_trees(trees)
    header = {
        "dataset": {"attrs": {"camera": TopViewMount(SMALL, PAPER_MOUNT.height_mm).to_dict()}}
    }
    frames = []
    for _ in range(4):
        depth = rng.integers(1500, 4000, size=SMALL.shape).astype(np.uint16)
        depth[rng.random(SMALL.shape) < 0.1] = 0
        truth = rng.integers(0, L.NUM_CLASSES, size=SMALL.shape).astype(np.uint8)
        truth[rng.random(SMALL.shape) < 0.05] = L.NO_DEPTH
        frames.append((depth, truth))
    config = crf.CRFConfig(mode="realtime", smoothness=2.0)
    result = score(Segmenter(model, header, crf=config), iter(frames), examples=2)

    forest_pred, crf_pred = [], []
    for depth, truth in frames:
        proba = forest.predict_proba(model, depth)
        forest_pred.append((truth, numpy_argmax(proba, depth)))
        labels = crf.segment_crf(proba, depth, config)
        relabel_as_the_segmenter(labels, depth, SMALL)
        crf_pred.append((truth, labels))
    np.testing.assert_array_equal(result.forest.confusion, hand_confusion(forest_pred))
    np.testing.assert_array_equal(result.crf.confusion, hand_confusion(crf_pred))
    assert result.frames == result.forest.frames == 4 and result.crf_mode == "realtime"
    assert len(result.examples) == 2
    np.testing.assert_array_equal(result.examples[1][2], forest_pred[1][1])
    np.testing.assert_array_equal(result.examples[1][3], crf_pred[1][1])
    assert set(result.ms_per_frame()) == {"forest", "crf"}

    none = score(Segmenter(model, header, crf="none"), frames)
    np.testing.assert_array_equal(none.crf.confusion, none.forest.confusion)
    np.testing.assert_array_equal(none.forest.confusion, result.forest.confusion)
    with pytest.raises(TopsegError, match="frame 0"):
        score(Segmenter(model, crf="none"), frames)  # Kinect v1 expected: 640x480


def test_a_model_that_knows_robots_and_objects_labels_them_through_every_stage():
    rng = np.random.default_rng(5)
    trees = [forest.random_tree(rng, 5, 2, 40 * 2500.0, 300.0, L.NUM_CLASSES) for _ in range(2)]
    model = forest.Forest.from_trees(trees)
    header = {
        "dataset": {"attrs": {"camera": TopViewMount(SMALL, PAPER_MOUNT.height_mm).to_dict()}}
    }
    config = crf.CRFConfig(mode="realtime", smoothness=2.0)
    seg = Segmenter(model, header, crf=config)
    assert seg.n_classes == L.NUM_CLASSES
    seg.warm_up()
    depth = rng.integers(1500, 4000, size=SMALL.shape).astype(np.uint16)
    got = seg.label(depth)
    proba = forest.predict_proba(model, depth)
    assert got.proba.shape == (*SMALL.shape, L.NUM_CLASSES)
    np.testing.assert_array_equal(got.forest_labels(), numpy_argmax(proba, depth))
    want = crf.segment_crf(proba, depth, config)
    relabel_as_the_segmenter(want, depth, SMALL)
    np.testing.assert_array_equal(got.labels, want)
    assert {L.ROBOT, L.OBJECT} <= set(np.unique(got.forest_labels()).tolist())
    assert set(L.OPEN_WORLD_IDS) & set(np.unique(got.labels).tolist())


def height_segmenter(**config):
    from topseg.core.forest.inputs import header_fields, trained_for

    rng = np.random.default_rng(3)
    model = forest.Forest.from_trees([forest.random_tree(rng, 5, 2, 40 * 2500.0, 300.0)])
    header = header_fields(forest.FeatureConfig(), trained_for([TopViewMount(SMALL, 3000.0)]))
    return Segmenter(model, header, SegmenterConfig(**config), crf="none")


def test_a_height_model_takes_frames_of_any_camera_with_their_mount():
    from topseg.core.forest.inputs import model_input

    seg = height_segmenter()
    assert seg.reads_height and seg.trained_for["height_mm"] == [3000.0, 3000.0]
    for k in (SMALL, KINECT_V1.scaled_to(64, 40), Intrinsics(51, 42, 36.5, 36.5, 25, 21)):
        mount = TopViewMount(k, 3000.0, 0.0, 4.0)
        depth = np.full(k.shape, 2000, np.uint16)
        # the floor in the first columns: depth of the plane below a tilted camera
        h = mount.height_map_mm(np.full(k.shape, 3000, np.uint16))
        depth[:, :5] = np.round(3000 * 3000 / (3000 - h[:, :5])).astype(np.uint16)
        got = seg.label(depth, name="any", mount=mount)
        want = forest.predict_proba(seg.forest, model_input(depth, mount, seg.features))
        np.testing.assert_array_equal(got.proba, want)
        assert 0 < got.floor_share < 0.5
        assert np.all(got.labels[:, :3] == L.BACKGROUND)
    # the frame's own intrinsics win over the mount's
    other = TopViewMount(KINECT_V1, 3000.0)
    depth = np.full(SMALL.shape, 2000, np.uint16)
    assert seg.label(depth, SMALL, mount=other).labels.shape == SMALL.shape
    with pytest.raises(TopsegError, match=r"cam3: .* needs the camera's mount"):
        seg.label(depth, name="cam3")
    with pytest.raises(
        TopsegError, match="f2: frame is 40x30 but its camera's intrinsics are 640x480"
    ):
        seg.label(depth, name="f2", mount=other)
    # the config's mount, when the frame comes without one
    withmount = height_segmenter(mount=TopViewMount(SMALL, 3000.0))
    assert withmount.label(depth).labels.shape == SMALL.shape
    withmount.warm_up()
    height_segmenter().warm_up()


def test_a_radial_camera_is_labelled_as_its_depth_would_be():
    """A range frame with a radial mount is labelled as the depth frame it stands for: the
    forest, the blob rules and the upsampling all read depth (`Segmenter._as_depth`)."""
    from dataclasses import replace

    from topseg.core.camera import depth_to_range, range_to_depth
    from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

    k = KINECT_V1.scaled_to(160, 120)
    mount = TopViewMount(k, 3300.0, 1.0, -0.5)
    frame = Synthesizer(SynthesisConfig(mode="modeled", seed=4, camera=mount)).render(frame_seed=0)
    ranges = depth_to_range(frame.depth[: k.height, : k.width].astype(np.uint16), k)
    seg = Segmenter.from_file(S.bundled_model_path())
    got = seg.label(ranges, name="tof", mount=replace(mount, radial=True))
    want = seg.label(range_to_depth(ranges, k), mount=mount)
    np.testing.assert_array_equal(got.labels, want.labels)
    assert got.floor_share == want.floor_share > 0.3
    # read as depth, everything off the axis sits too low: the flag is what makes it right
    misread = seg.label(ranges, mount=mount)
    assert misread.floor_share > want.floor_share + 0.05
    assert np.mean(misread.labels != want.labels) > 0.02
    with pytest.raises(TopsegError, match=r"tof: .* 160x120"):
        seg.label(ranges[:60], name="tof", mount=replace(mount, radial=True))


def test_a_height_model_header_must_say_its_features():
    model = forest.Forest.from_trees([forest.random_tree(np.random.default_rng(0), 2, 2, 1e5)])
    with pytest.raises(TopsegError, match="features"):
        Segmenter(model, {"input": "height"})


def test_a_depth_model_says_when_a_mount_is_not_its_own(legacy):
    assert "does not say" in legacy.outside_trained_for(PAPER_MOUNT)  # no camera in its header
    header = {"dataset": {"attrs": {"camera": PAPER_MOUNT.to_dict()}}}
    known = Segmenter(legacy.forest, header)
    assert known.outside_trained_for(PAPER_MOUNT) is None
    assert "raw depth" in known.outside_trained_for(TopViewMount(KINECT_V1, 3300.0))


def test_the_adaptive_grid_is_a_config_field_checked_up_front():
    assert SegmenterConfig().grid.adaptive == ADAPTIVE_LEVELS >= 1
    with pytest.raises(TopsegError, match="adaptive"):
        SegmenterConfig(grid=GridConfig(adaptive=-1))
    k = KINECT_V1.scaled_to(160, 120)
    mount = TopViewMount(k, PAPER_MOUNT.height_mm)
    plain = Segmenter.from_file(
        None, SegmenterConfig(mount=mount, grid=GridConfig(stride=2, adaptive=0))
    )
    adaptive = Segmenter.from_file(
        None, SegmenterConfig(mount=mount, grid=GridConfig(stride=2, adaptive=1))
    )
    depth = np.ascontiguousarray(demo_frames(1)[0][0][::4, ::4])
    got, want = adaptive.label(depth), plain.label(depth)
    assert (got.labels == want.labels).mean() > 0.9  # the same scene ...
    assert not np.array_equal(got.proba, want.proba)  # ... and not the same walk


def test_the_early_exit_is_a_config_field_checked_up_front():
    assert SegmenterConfig().grid.early_exit == EARLY_EXIT
    for bad in (0.0, -0.5, 1.01):
        with pytest.raises(TopsegError, match="early_exit"):
            SegmenterConfig(grid=GridConfig(early_exit=bad))
    k = KINECT_V1.scaled_to(160, 120)
    mount = TopViewMount(k, PAPER_MOUNT.height_mm)
    every = Segmenter.from_file(
        None, SegmenterConfig(mount=mount, grid=GridConfig(stride=2, early_exit=None))
    )
    early = Segmenter.from_file(None, SegmenterConfig(mount=mount, grid=GridConfig(stride=2)))
    depth = np.ascontiguousarray(demo_frames(1)[0][0][::4, ::4])
    got, want = early.label(depth), every.label(depth)
    assert (got.labels == want.labels).mean() > 0.97  # the same scene ...
    assert not np.array_equal(got.proba, want.proba)  # ... from fewer trees at some pixels


def test_warm_up_compiles_what_a_first_large_frame_runs():
    """A worker warms up on a small frame; the lazy grid's fill, the band solved in two
    parts in parallel and the walk with clamped probes must be ready too (loading them on the
    first real frame costs ~40 ms and drops frames at a worker's start)."""
    from topseg.core.crf import realtime
    from topseg.core.forest import predict

    seg = Segmenter.from_file(None, SegmenterConfig(check_camera=False), crf="realtime")
    seg.warm_up()
    k = seg.forest.features_per_node
    clamped, wide = predict._kernel(k, True), predict._kernel(k, False)
    for kernel in (predict._fill, realtime._solve_parts, realtime.band_parts, clamped, wide):
        assert kernel.signatures, kernel


def test_warm_up_compiles_what_a_frame_off_the_wire_runs():
    """Frames decoded from the wire are read-only arrays, for which numba compiles its own
    kernels: after warm_up, labelling one must compile nothing (with a cold cache, that
    compile on a worker's first frames drops about 10 of them), at the frame's resolution or
    at half of it, smoothed or not. In a fresh interpreter: this
    one's kernels may hold those signatures from earlier tests. (The edge-gap fill is among
    them: left to compile on the first frame with a no-depth band at its edge, it costs
    `make demo` on a clean clone 73 of 300 frames.)"""
    import subprocess
    import sys

    script = """
import numba, numpy as np
from topseg.core import crf
from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.crf import energy
from topseg.core.formats import wire
from topseg.core import denoise, islands, resolution
from topseg.core.forest import edge_gaps, inputs, predict
from topseg.core.segmenter import Segmenter, SegmenterConfig

seg = Segmenter.from_file(None, SegmenterConfig(check_camera=False), crf="realtime")
seg.warm_up()
kernels = [
    v
    for module in (
        energy, inputs, edge_gaps, predict, crf.realtime, crf.argmax, islands, resolution, denoise
    )
    for v in vars(module).values()
    if isinstance(v, numba.core.dispatcher.Dispatcher)
]
before = [set(k.signatures) for k in kernels]
depth = np.full((120, 160), 2500, np.uint16)
depth[40:80, 50:110] = 1500  # something standing on the floor
depth[:, :6] = 0  # a band without depth at the image's edge (`edge_gaps`)
mount = TopViewMount(KINECT_V1.scaled_to(160, 120), 3000.0)
frame = wire.decode_depth(wire.encode_depth(wire.DepthFrame(depth, mount.intrinsics, mount=mount)))
assert not frame.depth.flags.writeable
seg.label(frame.depth, frame.intrinsics, mount=frame.mount)
# a Kinect v1 3 m up: labelled at half resolution, the labels brought back
big = np.full((480, 640), 3000, np.uint16)
big[160:320, 200:440] = 1800
mount = TopViewMount(KINECT_V1, 3000.0)
frame = wire.decode_depth(wire.encode_depth(wire.DepthFrame(big, mount.intrinsics, mount=mount)))
assert seg.label(frame.depth, frame.intrinsics, mount=frame.mount).downsample == 2
# a D435 4.5 m up: its frames are smoothed before the forest (`core.denoise`)
from topseg.core.sensors import get_sensor
d435 = get_sensor("realsense_d435").intrinsics
mount = TopViewMount(d435, 4500.0, sensor="realsense_d435")
far = np.full((480, 640), 4500, np.uint16)
far[160:320, 200:440] = 3300
frame = wire.decode_depth(wire.encode_depth(wire.DepthFrame(far, d435, mount=mount)))
assert denoise.needs_denoise(frame.mount)
seg.label(frame.depth, frame.intrinsics, mount=frame.mount)
print([k.py_func.__name__ for k, b in zip(kernels, before) if set(k.signatures) != b])
"""
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=True
    )
    assert out.stdout.strip().splitlines()[-1] == "[]"


@pytest.mark.slow
def test_small_head_and_furniture_blobs_take_their_borders_label_after_the_crf():
    """`min_head_cm2`, `min_furniture_cm2`, `min_plant_cm2`: the CRF's labels, then head,
    furniture and plant blobs under them relabelled with the frame's own focal lengths; 0
    keeps the CRF's labels."""
    assert SegmenterConfig().post.min_head_cm2 == segmenter_config.MIN_HEAD_CM2 > 0
    assert SegmenterConfig().post.min_furniture_cm2 == segmenter_config.MIN_FURNITURE_CM2 > 0
    assert SegmenterConfig().post.min_plant_cm2 == segmenter_config.MIN_PLANT_CM2 > 0
    for name in ("min_head_cm2", "min_furniture_cm2", "min_plant_cm2", "satellite_head_cm2"):
        for bad in (-1.0, float("nan"), float("inf")):
            with pytest.raises(TopsegError, match=name):
                PostConfig(**{name: bad})
    # at the frame's own resolution, where the rule runs on the labels it returns (at half
    # resolution it runs before they are brought back: tested with the downsample below)
    kept = Segmenter.from_file(
        None,
        SegmenterConfig(
            mount=PAPER_MOUNT,
            post=PostConfig(
                min_head_cm2=0, min_furniture_cm2=0, min_plant_cm2=0, satellite_head_cm2=0
            ),
            grid=GridConfig(downsample=1),
        ),
    )
    assert not kept.config.relabels_islands
    cleaned = Segmenter.from_file(
        None, SegmenterConfig(mount=PAPER_MOUNT, grid=GridConfig(downsample=1))
    )
    k = PAPER_MOUNT.intrinsics
    relabelled = np.zeros(L.NUM_CLASSES, np.int64)
    for depth, _ in demo_frames(6):
        raw = kept.label(depth)
        want = raw.labels.copy()
        n, satellites = relabel_as_the_segmenter(want, depth, k)
        got = cleaned.label(depth)
        np.testing.assert_array_equal(got.labels, want)
        assert (
            raw.counts["small_heads"]
            == raw.counts["small_furniture"]
            == raw.counts["satellite_heads"]
            == 0
        )
        assert got.counts["satellite_heads"] == satellites
        assert got.counts["small_heads"] == n[L.HEAD]
        assert got.counts["small_furniture"] == n[list(FURNITURE_COUNTED)].sum()
        relabelled += n
    assert relabelled[L.HEAD] > 0 and relabelled[list(FURNITURE_COUNTED)].sum() > 0


@pytest.mark.slow
def test_a_fine_camera_is_labelled_at_half_resolution_and_brought_back_by_depth(legacy):
    """By default a Kinect v1 3.5 m up (6 mm of floor a pixel) is labelled at half
    resolution: the labels are those of the decimated frame seen through the decimated
    optics, brought back to the frame's size by depth; the forest's own labels likewise."""
    from topseg.core.resolution import decimate, decimated_mount, upsample_labels

    depth = demo_frames(1)[0][0]
    auto = Segmenter.from_file(None, SegmenterConfig(mount=PAPER_MOUNT))
    one = Segmenter.from_file(
        None, SegmenterConfig(mount=PAPER_MOUNT, grid=GridConfig(downsample=1))
    )
    got = auto.label(depth)
    assert got.downsample == 2 and got.labels.shape == depth.shape
    depth, filled = fill_holes(depth, PAPER_MOUNT.intrinsics)  # first, at the frame's size
    assert got.counts["filled_holes"] == filled > 0
    small = decimate(depth, 2)
    unfilled = Segmenter.from_file(
        None,
        SegmenterConfig(
            mount=PAPER_MOUNT, grid=GridConfig(downsample=1), pre=PreConfig(fill_holes_cm2=0.0)
        ),
    )  # the frame's holes were filled at its own size, before decimating
    want = unfilled.label(small, mount=decimated_mount(PAPER_MOUNT, 2))
    np.testing.assert_array_equal(got.labels, upsample_labels(depth, want.labels, small, 2))
    forest_labels = upsample_labels(depth, want.forest_labels(), small, 2)
    np.testing.assert_array_equal(got.forest_labels(), forest_labels)
    assert got.proba.shape == (*small.shape, auto.n_classes)
    np.testing.assert_array_equal(got.proba, want.proba)
    assert got.floor_share == want.floor_share > 0
    t = got.timings
    assert t.forest_ms > 0 and t.crf_ms > 0 and t.total_ms >= t.forest_ms + t.crf_ms - 1e-6
    # every pixel at the frame's own resolution when asked, or when the model reads depth
    assert one.label(depth).downsample == 1 == one.plan(depth).downsample
    assert legacy.plan(depth).downsample == 1
    assert Segmenter(
        legacy.forest, legacy.header, SegmenterConfig(grid=GridConfig(downsample=2))
    ).label(depth).labels.shape == (480, 640)


def test_the_downsample_is_a_config_field_checked_up_front():
    assert SegmenterConfig().grid.downsample is None  # from each frame's mount
    for bad in (0, 5, True, -1):
        with pytest.raises(TopsegError, match="downsample"):
            SegmenterConfig(grid=GridConfig(downsample=bad))
    seg = Segmenter.from_file(None, SegmenterConfig(mount=PAPER_MOUNT))
    with pytest.raises(TopsegError, match=r"f9: .*uint16"):
        seg.label(np.zeros((480, 640), np.float32), name="f9")


@pytest.mark.slow
def test_a_noisy_camera_gets_the_heavier_crf_weight(bundled, legacy):
    """Frames the Segmenter smooths (a D435 at 4.5 m: 85 mm of noise at the floor) are
    smoothed by the CRF with `noisy_smoothness`; a Kinect v1 at 3.5 m keeps `smoothness`,
    and so does every camera when `noisy_smoothness` is not the larger."""
    from topseg.core.crf import CRFConfig
    from topseg.core.denoise import needs_denoise
    from topseg.services.batch.experiment.mounts import cell_mount, render_cell

    noisy, quiet = cell_mount("realsense_d435", 4.5, 3.0), cell_mount("kinect_v1", 3.5, 0.0)
    assert needs_denoise(noisy) and not needs_denoise(quiet)

    def seg(**crf):
        config = SegmenterConfig(crf=CRFConfig(mode="realtime", **crf))
        return Segmenter(bundled.forest, bundled.header, config)

    def crf_for(segmenter, mount):
        """The CRF settings the segmenter's plan gives a frame from `mount`."""
        frame = np.zeros(mount.intrinsics.shape, np.uint16)
        return segmenter.plan(frame, mount=mount).crf

    default = seg()
    assert crf_for(default, noisy).smoothness == crf.energy.NOISY_SMOOTHNESS == 3.0
    assert crf_for(default, quiet) == default.crf_config
    assert crf_for(seg(smoothness=4.0), noisy).smoothness == 4.0  # never below smoothness
    assert crf_for(seg(noisy_smoothness=0.5), noisy).smoothness == 1.0
    assert crf_for(legacy, noisy) == legacy.crf_config  # a depth model has no noise model
    with pytest.raises(TopsegError, match="noisy_smoothness must be in"):
        CRFConfig(noisy_smoothness=-1.0)

    depth, _truth, mount = render_cell(noisy, 1)[0]
    heavy = default.label(depth, mount=mount).labels
    np.testing.assert_array_equal(heavy, seg(smoothness=3.0).label(depth, mount=mount).labels)
    assert np.any(heavy != seg(noisy_smoothness=1.0).label(depth, mount=mount).labels)
    depth, _truth, mount = render_cell(quiet, 1)[0]
    np.testing.assert_array_equal(
        default.label(depth, mount=mount).labels,
        seg(noisy_smoothness=1.0).label(depth, mount=mount).labels,
    )


def test_a_labelled_frame_is_freed_without_the_cycle_collector(bundled):
    """A Segmentation and its frame's working state hold no reference cycle: they go when
    the last reference goes, not frames later when the cycle collector runs (with a cycle,
    60 frames of the demo recording raised the peak memory by 69 MiB)."""
    import gc
    import weakref

    depth, _truth = demo_frames(1)[0]
    gc.collect()
    gc.disable()
    try:
        result = bundled.label(depth, mount=PAPER_MOUNT)
        result.forest_labels()
        frame = weakref.ref(result._frame)
        del result
        assert frame() is None
    finally:
        gc.enable()
