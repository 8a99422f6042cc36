"""The safety state on the wire: what is encoded decodes to the same decision, and anything
else is one WireError naming what is wrong."""

import math

import msgpack
import pytest

from topseg.core.formats import wire
from topseg.core.formats.safety_wire import (
    MAX_REASONS,
    SafetyState,
    cut_reason,
    decode_safety,
    encode_safety,
    safety_alive_key,
    safety_key,
)
from topseg.core.formats.wire import WireError


def full_state(**changes) -> SafetyState:
    fields = dict(
        seq=7,
        stamp_ns=1_700_000_000_000_000_000,
        state="warning",
        speed_scale=0.4,
        min_distance_m=0.83,
        part="hand",
        link="panda_link7",
        reaction_ms=41.5,
        reasons=("hand 0.83 m from panda_link7 < S_p 1.10 m",),
        zones={"robot": "warning", "door": "clear"},
        nearest_m=((0.1, 0.2, 1.0), (0.3, 0.2, 0.9)),
        frame=("cam0", 1234),
    )
    fields.update(changes)
    return SafetyState(**fields)


def test_round_trip_keeps_every_field():
    state = full_state()
    assert decode_safety(encode_safety(state)) == state


def test_a_state_with_no_person_and_no_frame_round_trips():
    state = SafetyState(
        seq=0, stamp_ns=1, state="stop", speed_scale=0.0, reasons=("cam0: no labelled frame yet",)
    )
    back = decode_safety(encode_safety(state))
    assert back == state
    assert back.min_distance_m is None and back.reaction_ms is None and back.nearest_m is None


def test_keys():
    assert safety_key("cell1") == "topseg/cell1/safety"
    token = safety_alive_key("cell1", "abc123")
    assert token == "topseg/cell1/safety/alive/safety/abc123"
    parts = wire.parse_key(token)  # a token of the shape every service holds
    assert (parts.cell, parts.camera, parts.role, parts.instance) == (
        "cell1",
        "safety",
        "safety",
        "abc123",
    )
    with pytest.raises(WireError):
        safety_key("bad/name")


@pytest.mark.parametrize(
    "changes, words",
    [
        (dict(state="go"), "state"),
        (dict(speed_scale=1.5), "speed_scale"),
        (dict(speed_scale=math.nan), "speed_scale"),
        (dict(state="stop", speed_scale=0.5), "stop"),
        (dict(min_distance_m=-0.1), "min_distance_m"),
        (dict(min_distance_m=math.inf), "min_distance_m"),
        (dict(reaction_ms=math.nan), "reaction_ms"),
        (dict(reasons=("x",) * (MAX_REASONS + 1)), "reasons"),
        (dict(reasons=("x" * 1000,)), "reason"),
        (dict(zones={"a": "maybe"}), "zone"),
        (dict(nearest_m=((0, 0), (1, 1, 1))), "nearest_m"),
        (dict(seq=-1), "seq"),
    ],
)
def test_a_bad_state_is_refused_before_it_is_sent(changes, words):
    with pytest.raises(WireError, match=words):
        full_state(**changes)


def _raw(**changes) -> bytes:
    msg = msgpack.unpackb(encode_safety(full_state()), raw=False)
    for key, value in changes.items():
        if value is ...:
            msg.pop(key)
        else:
            msg[key] = value
    return msgpack.packb(msg, use_bin_type=True)


@pytest.mark.parametrize(
    "data, words",
    [
        (b"", "msgpack"),
        (b"\xc1garbage", "msgpack"),
        (msgpack.packb([1, 2]), "map"),
        (b"\x00" * (1 << 20), "limit"),
        (_raw(v=2), "upgrade"),
        (_raw(v="1"), "version"),
        (_raw(state=...), "missing"),
        (_raw(extra=1), "unknown"),
        (_raw(speed_scale="1"), "speed_scale"),
        (_raw(reasons="stop"), "reasons"),
        (_raw(reasons=[1]), "reason"),
        (_raw(zones=[1]), "zones"),
        (_raw(nearest_m=[1, 2]), "nearest_m"),
        (_raw(frame={"camera": "cam0"}), "frame"),
        (_raw(seq=True), "seq"),
    ],
)
def test_damaged_messages_are_one_wire_error(data, words):
    with pytest.raises(WireError, match=words):
        decode_safety(data)


def test_a_long_reason_is_cut_to_fit():
    reason = cut_reason("x" * 500)
    assert full_state(reasons=(reason,)).reasons == (reason,)
    assert reason.endswith("...")
