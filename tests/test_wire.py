"""The wire format: exact round trips, and every kind of bad message -> WireError, nothing else."""

from dataclasses import replace

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from topseg.core import labels
from topseg.core.camera import KINECT_V1, Intrinsics
from topseg.core.formats import wire
from topseg.core.formats.wire import DepthFrame, LabelFrame, WireError

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
VALID_IDS = [lab.id for lab in labels.LABELS] + [labels.NO_DEPTH]


def small_depth(rng, h=6, w=9):
    k = KINECT_V1.scaled_to(w, h)
    return DepthFrame(rng.integers(0, 65536, (h, w), dtype=np.uint16), k, 7, 123456789, "cam0")


def small_labels(rng, h=6, w=9):
    img = rng.choice(np.array(VALID_IDS, np.uint8), size=(h, w))
    return LabelFrame(img, 7, 123456789, "cam0")


def assert_same_depth(a: DepthFrame, b: DepthFrame):
    np.testing.assert_array_equal(a.depth, b.depth)
    assert a.depth.dtype == b.depth.dtype == np.uint16
    assert (a.seq, a.stamp_ns, a.frame_id) == (b.seq, b.stamp_ns, b.frame_id)
    assert a.intrinsics == b.intrinsics


# ----------------------------------------------------------------------------- round trips


def test_full_size_depth_round_trip_and_layout():
    rng = np.random.default_rng(1)
    depth = rng.integers(0, 8000, KINECT_V1.shape, dtype=np.uint16)
    frame = DepthFrame(
        depth, KINECT_V1, seq=2**40, stamp_ns=1_700_000_000_123_456_789, frame_id="c"
    )
    data = wire.encode_depth(frame)
    back = wire.decode_depth(data)
    assert_same_depth(frame, back)
    # the raw layout is the documented one: little-endian, row-major
    msg = msgpack.unpackb(data)
    assert msg["data"] == depth.astype("<u2").tobytes()
    assert (msg["width"], msg["height"], msg["encoding"], msg["v"]) == (640, 480, "16UC1", 6)
    assert "mount" not in msg  # no mount known, none sent
    assert not back.depth.flags.writeable  # a view of the message, not a copy


@given(
    hnp.arrays(np.uint16, hnp.array_shapes(min_dims=2, max_dims=2, max_side=40)),
    st.integers(0, 2**63 - 1),
    st.integers(0, 2**63 - 1),
    st.text(max_size=20),
)
@FUZZ
def test_depth_round_trip_any_content(depth, seq, stamp, frame_id):
    h, w = depth.shape
    frame = DepthFrame(depth, KINECT_V1.scaled_to(w, h), seq, stamp, frame_id)
    assert_same_depth(frame, wire.decode_depth(wire.encode_depth(frame)))


@given(
    hnp.arrays(
        np.uint8,
        st.tuples(st.integers(1, 30), st.integers(1, 30)),
        elements=st.sampled_from(VALID_IDS),
    )
)
@FUZZ
def test_labels_round_trip(img):
    frame = LabelFrame(img, seq=3, stamp_ns=99, frame_id="x")
    back = wire.decode_labels(wire.encode_labels(frame))
    np.testing.assert_array_equal(back.labels, img)
    assert (back.seq, back.stamp_ns, back.frame_id) == (3, 99, "x")


def test_encoding_is_deterministic():
    rng = np.random.default_rng(2)
    f = small_depth(rng)
    assert wire.encode_depth(f) == wire.encode_depth(f)
    assert wire.encode_depth(wire.decode_depth(wire.encode_depth(f))) == wire.encode_depth(f)


def test_stats_round_trip():
    stats = {
        "stamp_ns": 5,
        "seq": 9,
        "role": "worker",
        "model_id": "forest-abc",
        "fps": 29.5,
        "timings_ms": {"forest": 8.25, "crf": 12.0},
        "counts": {"processed": 100, "dropped": 3, "rejected": 1},
    }
    back = wire.decode_stats(wire.encode_stats(stats))
    assert back == {"v": wire.SCHEMA_VERSION, **stats}


# ----------------------------------------------------------------------------- rejections


def _depth_map(rng) -> dict:
    return msgpack.unpackb(wire.encode_depth(small_depth(rng)))


def test_unknown_label_ids_are_refused_both_ways():
    img = np.zeros((4, 4), np.uint8)
    img[1, 2] = 42
    with pytest.raises(WireError, match="42"):
        wire.encode_labels(LabelFrame(img))
    msg = msgpack.unpackb(wire.encode_labels(LabelFrame(np.zeros((4, 4), np.uint8))))
    msg["data"] = img.tobytes()
    with pytest.raises(WireError, match="label table"):
        wire.decode_labels(msgpack.packb(msg))


def test_every_byte_value_is_judged_by_the_label_table():
    from topseg.core import labels

    valid = {lab.id for lab in labels.LABELS} | {labels.NO_DEPTH}
    for v in range(256):
        img = np.zeros((3, 5), np.uint8)
        img[2, 4] = v
        if v in valid:
            wire.encode_labels(LabelFrame(img))
        else:
            with pytest.raises(WireError, match=str(v)):
                wire.encode_labels(LabelFrame(img))


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("width", 10**9, "width"),
        ("height", 0, "height"),
        ("width", 10, "bytes"),  # size lies: data no longer matches
        ("data", b"\0" * 7, "bytes"),
        ("data", "text", "binary"),
        ("encoding", "8UC1", "encoding"),
        ("v", wire.SCHEMA_VERSION + 1, "newer"),
        ("v", 0, "version"),
        ("v", True, "version"),
        ("seq", -1, "seq"),
        ("seq", 1.5, "seq"),
        ("stamp_ns", 2**64 - 1, "stamp_ns"),
        ("frame_id", "x" * 300, "frame_id"),
        ("fx", 0.0, "focal"),
        ("fy", float("nan"), "finite"),
        ("cx", 1e9, "principal"),
        ("cy", "1", "number"),
    ],
)
def test_bad_field_is_named(field, value, match):
    msg = _depth_map(np.random.default_rng(3))
    msg[field] = value
    with pytest.raises(WireError, match=match):
        wire.decode_depth(msgpack.packb(msg))


def test_missing_and_unknown_fields():
    msg = _depth_map(np.random.default_rng(4))
    del msg["fx"]
    with pytest.raises(WireError, match="missing"):
        wire.decode_depth(msgpack.packb(msg))
    msg = _depth_map(np.random.default_rng(4))
    msg["extra"] = 1
    with pytest.raises(WireError, match="unknown"):
        wire.decode_depth(msgpack.packb(msg))


def test_huge_message_refused_before_parsing():
    with pytest.raises(WireError, match="limit"):
        wire.decode_depth(b"\x00" * (wire.MAX_MESSAGE_BYTES + 1))


def test_error_messages_never_echo_a_payload():
    msg = _depth_map(np.random.default_rng(5))
    msg["encoding"] = "z" * 4000
    with pytest.raises(WireError) as err:
        wire.decode_depth(msgpack.packb(msg))
    assert len(str(err.value)) < 200


def _decoders():
    return [wire.decode_depth, wire.decode_labels, wire.decode_stats]


@given(st.binary(max_size=300))
@FUZZ
def test_random_bytes_raise_only_wire_error(data):
    for decode in _decoders():
        try:
            decode(data)
        except WireError:
            pass


@given(st.data())
@FUZZ
def test_truncated_messages_raise_wire_error(data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    for encoded, decode in (
        (wire.encode_depth(small_depth(rng)), wire.decode_depth),
        (wire.encode_labels(small_labels(rng)), wire.decode_labels),
        (
            wire.encode_stats({"stamp_ns": 1, "timings_ms": {"a": 1.0}, "counts": {"b": 2}}),
            wire.decode_stats,
        ),
    ):
        cut = data.draw(st.integers(0, len(encoded) - 1))
        with pytest.raises(WireError):
            decode(encoded[:cut])


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=10)
    | st.binary(max_size=40),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4)
    ),
    max_leaves=8,
)


@given(st.sampled_from(sorted(wire._DEPTH_FIELDS)), msgpack_values, st.integers(0, 2**16))
@FUZZ
def test_any_value_in_any_depth_field(field, value, seed):
    msg = _depth_map(np.random.default_rng(seed))
    msg[field] = value
    try:
        frame = wire.decode_depth(msgpack.packb(msg))
    except WireError:
        return
    # accepted: then it is a coherent frame
    assert frame.depth.shape == frame.intrinsics.shape


@given(
    st.sampled_from(
        [
            "stamp_ns",
            "seq",
            "role",
            "fps",
            "timings_ms",
            "counts",
            "model_id",
            "zzz",
            "floor_share",
            "mount",
        ]
    ),
    msgpack_values,
)
@FUZZ
def test_any_value_in_any_stats_field(field, value):
    msg = {"v": 2, "stamp_ns": 1, "timings_ms": {"a": 1.0}, "counts": {"b": 2}, field: value}
    try:
        out = wire.decode_stats(msgpack.packb(msg))
    except WireError:
        return
    assert set(out) <= wire._STATS_REQUIRED | wire._STATS_OPTIONAL | wire._STATS_OPTIONAL_V2


@given(st.integers(1, 5000), st.integers(1, 5000), st.integers(0, 64))
@FUZZ
def test_sizes_that_lie(width, height, nbytes):
    msg = msgpack.unpackb(wire.encode_labels(LabelFrame(np.zeros((2, 3), np.uint8))))
    msg.update(width=width, height=height, data=b"\0" * nbytes)
    try:
        frame = wire.decode_labels(msgpack.packb(msg))
    except WireError:
        return
    assert frame.labels.size == nbytes == width * height


def test_non_bytes_input():
    with pytest.raises(WireError, match="bytes"):
        wire.decode_depth("not bytes")  # type: ignore[arg-type]
    with pytest.raises(WireError, match="map"):
        wire.decode_depth(msgpack.packb([1, 2, 3]))


def test_frame_construction_checks():
    with pytest.raises(WireError, match="uint16"):
        DepthFrame(np.zeros((480, 640), np.float32))
    with pytest.raises(WireError, match="does not match"):
        DepthFrame(np.zeros((10, 10), np.uint16))
    with pytest.raises(WireError, match="seq"):
        DepthFrame(np.zeros((480, 640), np.uint16), seq=-1)
    with pytest.raises(WireError, match="side"):
        LabelFrame(np.zeros((1, 5000), np.uint8))


# ----------------------------------------------------------------------------- keys


def test_keys():
    assert wire.depth_key() == "topseg/default/cam0/depth"
    assert wire.labels_key("c1", "top") == "topseg/c1/top/labels"
    assert wire.alive_key("c1", "top", "driver") == "topseg/c1/top/alive/driver"
    for fn in (wire.depth_key, wire.labels_key, wire.truth_key, wire.stats_key, wire.info_key):
        key = fn("cell-2", "cam.1")
        parts = wire.parse_key(key)
        assert (parts.cell, parts.camera, parts.kind) == ("cell-2", "cam.1", key.rsplit("/", 1)[1])
    assert wire.parse_key("topseg/a/b/alive/worker").role == "worker"
    for bad in (
        "a/b",
        "topseg/*/cam0/depth",
        "topseg/a b/c/depth",
        "",
        "topseg/a/b/c",
        "x/a/b/depth",
    ):
        with pytest.raises(WireError):
            wire.parse_key(bad)
    for cell, cam in (("**", "cam0"), ("a/b", "c"), ("", "c"), ("ok", "$*"), ("ok", "x" * 65)):
        with pytest.raises(WireError, match="name"):
            wire.depth_key(cell, cam)


def test_a_message_key_on_the_reserved_pair_names_no_camera():
    """`_any/_any` is the token of a worker serving every camera; a message there (a forged
    depth frame) names no camera: parse_key refuses it, as the services' readers need."""
    for kind in wire.KINDS:
        with pytest.raises(WireError, match="reserved"):
            wire.parse_key(f"topseg/{wire.ANY}/{wire.ANY}/{kind}")
    assert wire.parse_key(wire.any_alive_key("worker", "w1")).cell == wire.ANY
    assert wire.parse_key(f"topseg/{wire.ANY}/cam0/depth").camera == "cam0"


def test_decode_for_key():
    rng = np.random.default_rng(6)
    f = small_labels(rng)
    back = wire.decode_for_key(wire.truth_key(), wire.encode_labels(f))
    np.testing.assert_array_equal(back.labels, f.labels)
    with pytest.raises(WireError):
        wire.decode_for_key(wire.info_key(), b"{}")


def test_intrinsics_survive_exactly():
    k = Intrinsics(33, 20, 31.123456789, 29.5, 16.25, -3.5)
    f = DepthFrame(np.ones((20, 33), np.uint16), k)
    assert wire.decode_depth(wire.encode_depth(f)).intrinsics == k


# ----------------------------------------------------------------------------- the mount (v2)


def a_mount(k=None, height=3312.5, pitch=4.25, roll=-1.5, sensor="kinect_v2", noise=0.37):
    """A tilted mount with a measured noise scale for frames of intrinsics `k` (small ones by
    default)."""
    from topseg.core.camera import TopViewMount

    return TopViewMount(k or KINECT_V1.scaled_to(9, 6), height, pitch, roll, sensor, noise)


def test_depth_with_a_mount_round_trips_and_shows_on_the_wire():
    rng = np.random.default_rng(10)
    f = small_depth(rng)
    m = a_mount(f.intrinsics)
    framed = DepthFrame(f.depth, f.intrinsics, 5, 6, "cam0", m)
    data = wire.encode_depth(framed)
    msg = msgpack.unpackb(data)
    assert msg["v"] == 6 and msg["mount"] == m.to_dict()  # the documented form, decoded apart
    assert msg["mount"]["noise_scale"] == 0.37
    back = wire.decode_depth(data)
    assert_same_depth(framed, back)
    assert back.mount == m
    assert wire.decode_depth(wire.encode_depth(f)).mount is None
    # a radial camera's mount says so; a depth camera's map has no such key (older readers)
    radial = replace(m, radial=True)
    data = wire.encode_depth(DepthFrame(f.depth, f.intrinsics, 5, 6, "cam0", radial))
    assert msgpack.unpackb(data)["mount"]["radial"] is True
    assert wire.decode_depth(data).mount == radial
    assert "radial" not in msg["mount"]
    # a stereo camera whose edges are not fattened says so; the default is not sent
    clean = replace(m, sensor="realsense_d435", edge_thinning=False)
    data = wire.encode_depth(DepthFrame(f.depth, f.intrinsics, 5, 6, "cam0", clean))
    assert msgpack.unpackb(data)["mount"]["edge_thinning"] is False
    assert wire.decode_depth(data).mount == clean
    assert "edge_thinning" not in msg["mount"]


def test_version_2_mounts_without_a_noise_scale_decode_as_modelled():
    rng = np.random.default_rng(13)
    f = small_depth(rng)
    msg = msgpack.unpackb(wire.encode_depth(DepthFrame(f.depth, f.intrinsics, mount=a_mount())))
    msg["v"] = 2
    del msg["mount"]["noise_scale"]
    back = wire.decode_depth(msgpack.packb(msg))
    assert back.mount.noise_scale == 1.0
    assert back.mount == a_mount(noise=1.0)


def test_version_4_mounts_decode_with_their_edges_thinned_as_modelled():
    rng = np.random.default_rng(14)
    f = small_depth(rng)
    mount = a_mount(f.intrinsics, sensor="realsense_d435")
    msg = msgpack.unpackb(wire.encode_depth(DepthFrame(f.depth, f.intrinsics, mount=mount)))
    msg["v"] = 4
    back = wire.decode_depth(msgpack.packb(msg))
    assert back.mount.edge_thinning is True
    assert back.mount == mount


def test_version_1_depth_messages_still_decode():
    msg = _depth_map(np.random.default_rng(11))
    msg["v"] = 1
    frame = wire.decode_depth(msgpack.packb(msg))
    assert frame.mount is None
    msg["mount"] = a_mount().to_dict()  # version 1 had no mount
    with pytest.raises(WireError, match="unknown"):
        wire.decode_depth(msgpack.packb(msg))


def test_an_old_reader_refuses_a_new_message_and_a_new_reader_says_upgrade(monkeypatch):
    rng = np.random.default_rng(12)
    f = small_depth(rng)
    data = wire.encode_depth(DepthFrame(f.depth, f.intrinsics, mount=a_mount(f.intrinsics)))
    stats = wire.encode_stats({"stamp_ns": 1, "timings_ms": {}, "counts": {}, "floor_share": 0.5})
    # what a version-5 topseg is: versions 1 to 5; it names the version and refuses
    monkeypatch.setattr(wire, "READABLE_VERSIONS", (1, 2, 3, 4, 5))
    for decode, payload in ((wire.decode_depth, data), (wire.decode_stats, stats)):
        with pytest.raises(WireError, match=r"schema version 6 is newer .*upgrade topseg"):
            decode(payload)
    monkeypatch.undo()
    msg = msgpack.unpackb(data)
    msg["v"] = 7
    with pytest.raises(WireError) as err:
        wire.decode_depth(msgpack.packb(msg))
    assert str(err.value) == (
        "schema version 7 is newer than this topseg reads (1, 2, 3, 4, 5, 6): "
        "upgrade topseg on this host"
    )


def _mount_msg(**change):
    rng = np.random.default_rng(13)
    f = small_depth(rng)
    msg = msgpack.unpackb(wire.encode_depth(DepthFrame(f.depth, f.intrinsics)))
    mount = a_mount(f.intrinsics).to_dict()
    for path, value in change.items():
        *outer, last = path.split("__")
        target = mount
        for name in outer:
            target = target[name]
        if value is KeyError:
            target.pop(last, None)
        else:
            target[last] = value
    msg["mount"] = mount
    return msgpack.packb(msg)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"height_mm": 0.0}, "height_mm"),
        ({"height_mm": float("inf")}, "finite"),
        ({"height_mm": "3300"}, "number"),
        ({"height_mm": KeyError}, "missing"),
        ({"pitch_deg": 120.0}, "pitch_deg"),
        ({"roll_deg": float("nan")}, "finite"),
        ({"sensor": ""}, "sensor"),
        ({"sensor": 7}, "sensor"),
        ({"sensor": "s" * 300}, "sensor"),
        ({"noise_scale": 0.0}, "noise_scale"),
        ({"noise_scale": 1e6}, "noise_scale"),
        ({"noise_scale": "1"}, "number"),
        ({"colour": "red"}, "unknown"),
        ({"radial": 1}, "radial"),
        ({"radial": "true"}, "radial"),
        ({"edge_thinning": 0}, "edge_thinning"),
        ({"edge_thinning": None}, "edge_thinning"),
        ({"intrinsics": [1, 2]}, "map"),
        ({"intrinsics__width": 10}, "mount is for 10x6"),
        ({"intrinsics__fx": -1.0}, "focal"),
        ({"intrinsics__cy": 1e9}, "principal"),
        ({"intrinsics__cx": KeyError}, "missing"),
    ],
)
def test_bad_mount_field_is_named(change, match):
    with pytest.raises(WireError, match=match):
        wire.decode_depth(_mount_msg(**change))


def test_a_mount_of_another_size_is_refused_when_framed():
    with pytest.raises(WireError, match="mount is for"):
        DepthFrame(np.zeros((6, 9), np.uint16), KINECT_V1.scaled_to(9, 6), mount=a_mount(KINECT_V1))
    with pytest.raises(WireError, match="TopViewMount"):
        DepthFrame(np.zeros((6, 9), np.uint16), KINECT_V1.scaled_to(9, 6), mount={"h": 1})


@given(
    st.sampled_from(sorted(wire._MOUNT_FIELDS | {"zz"})),
    msgpack_values,
    st.sampled_from(sorted(wire._INTRINSICS_FIELDS)),
    msgpack_values,
)
@FUZZ
def test_any_value_in_any_mount_field(field, value, kfield, kvalue):
    msg = msgpack.unpackb(_mount_msg())
    msg["mount"][field] = value
    try:
        frame = wire.decode_depth(msgpack.packb(msg))
    except WireError:
        pass
    else:  # accepted: a coherent frame and mount
        assert frame.mount is not None and frame.mount.intrinsics.shape == frame.depth.shape
    msg = msgpack.unpackb(_mount_msg())
    msg["mount"]["intrinsics"][kfield] = kvalue
    try:
        frame = wire.decode_depth(msgpack.packb(msg))
    except WireError:
        return
    assert frame.mount.intrinsics.shape == frame.depth.shape


def test_stats_carry_floor_share_and_the_mount_in_use():
    mount = {
        "height_mm": 3120.0, "pitch_deg": 2.0, "roll_deg": -0.5, "sensor": "kinect_v1",
        "source": "estimated", "moved": 1,
    }  # fmt: skip
    stats = {"stamp_ns": 5, "timings_ms": {}, "counts": {}, "floor_share": 0.62, "mount": mount}
    assert wire.decode_stats(wire.encode_stats(stats)) == {"v": wire.SCHEMA_VERSION, **stats}
    for bad, match in (
        ({"floor_share": 1.5}, "floor_share"),
        ({"mount": {**mount, "source": "guess"}}, "source"),
        ({"mount": {**mount, "moved": -1}}, "moved"),
        ({"mount": {**mount, "height_mm": 1e9}}, "height_mm"),
        ({"mount": {"height_mm": 3000.0}}, "missing"),
    ):
        with pytest.raises(WireError, match=match):
            wire.encode_stats({**stats, **bad})
    old = {"v": 1, "stamp_ns": 5, "timings_ms": {}, "counts": {}}
    assert wire.decode_stats(msgpack.packb(old)) == old  # version 1 stats still read
    with pytest.raises(WireError, match="unknown"):  # ... and had no floor_share
        wire.decode_stats(msgpack.packb({**old, "floor_share": 0.5}))
