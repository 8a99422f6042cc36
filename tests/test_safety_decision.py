"""The cell's decision: faults and zones stop, separation scales the speed (numbers worked
by hand), body-region limits where contact is allowed, bad numbers fail towards stop, and
properties: a person closer, more faults or more unseen never make it less strict."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from topseg.core import labels
from topseg.core.safety.cell import CellConfig, RobotSpec, SeparationParams, Zone
from topseg.core.safety.decision import CLEAR, STATES, STOP, WARNING, decide

SQUARE = ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0))
ROBOT = RobotSpec(
    "arm",
    "panda",
    stopping_time_s=0.5,
    stopping_distance_m=0.3,
    max_speed_mps=1.5,
    effective_mass_kg=15.0,
)
SEP = SeparationParams(
    human_speed_mps=1.6,
    controller_reaction_s=0.1,
    detection_capability_mm=40.0,
    sensor_uncertainty_m=0.1,
    robot_uncertainty_m=0.05,
    warning_margin_m=0.5,
)
CELL = CellConfig(
    "c1",
    robot=ROBOT,
    zones=(Zone("press", "protective", SQUARE), Zone("aisle", "warning", SQUARE)),
    separation=SEP,
    max_unseen_fraction=0.05,
)
CONTACT_CELL = replace(CELL, contact_allowed=True)
SEEN = {"press": 0.0}
REACTION = 0.05  # T_r = 0.05 + 0.1 = 0.15 s; S_p(0) = 1.698 m, S_p(1.5 m/s) = 1.923 m
HUMAN = st.sampled_from(labels.HUMAN_IDS)


@dataclass(frozen=True)
class Near:
    """A stand-in for the separation's nearest pair: what `decide` reads of it."""

    distance_m: float
    part: int = labels.HAND
    link: str = "link5"


def test_nobody_is_clear():
    d = decide(CELL, None, [], SEEN, REACTION, ())
    assert (d.state, d.speed_scale, d.min_distance_m, d.part, d.link, d.reasons) == (
        CLEAR, 1.0, math.inf, "", "", (),
    )  # fmt: skip


def test_faults_stop_with_them_as_reasons():
    d = decide(CELL, None, [], SEEN, REACTION, ("labels stale 240 ms", "cam0 blinded"))
    assert (d.state, d.speed_scale) == (STOP, 0.0)
    assert d.reasons == ("labels stale 240 ms", "cam0 blinded")
    assert decide(CELL, None, [], SEEN, REACTION, "joints stale").reasons == ("joints stale",)


def test_zones():
    d = decide(CELL, None, ["press"], SEEN, REACTION, ())
    assert (d.state, d.speed_scale, d.reasons) == (STOP, 0.0, ("person in protective zone press",))
    d = decide(CELL, None, ["aisle"], SEEN, REACTION, ())
    assert (d.state, d.speed_scale, d.reasons) == (WARNING, 1.0, ("person in warning zone aisle",))
    assert decide(CELL, None, ["unknown"], SEEN, REACTION, ()).state == STOP


@pytest.mark.parametrize(
    ("unseen", "reason"),
    [
        ({"press": 0.12}, "protective zone press 12% unseen > 5%"),
        ({}, "protective zone press: no view of it"),
        ({"press": math.nan}, "protective zone press: unseen share nan"),
        ({"press": math.inf}, "protective zone press: unseen share inf"),
    ],
)
def test_an_unseen_protective_zone_stops(unseen, reason):
    d = decide(CELL, None, [], unseen, REACTION, ())
    assert (d.state, d.speed_scale, d.reasons) == (STOP, 0.0, (reason,))


def test_unseen_within_the_limit_is_clear():
    assert decide(CELL, None, [], {"press": 0.05}, REACTION, ()).state == CLEAR


def test_separation_worked_examples():
    # d = 1.773 m: v_r = (1.773 - 1.698) / 0.15 = 0.5 m/s, a third of 1.5 m/s
    d = decide(CELL, Near(1.773), [], SEEN, REACTION, ())
    assert (d.state, d.part, d.link, d.min_distance_m) == (WARNING, "hand", "link5", 1.773)
    assert d.speed_scale == pytest.approx(1 / 3)
    assert d.reasons == ("hand 1.77 m from link5 < S_p 1.92 m: speed 33%",)
    # d = 1.0 m < S_p(0) = 1.698 m: even a standing robot is too close
    d = decide(CELL, Near(1.0), [], SEEN, REACTION, ())
    assert (d.state, d.speed_scale, d.reasons) == (
        STOP, 0.0, ("hand 1.00 m from link5 < S_p 1.70 m",),
    )  # fmt: skip
    # S_p(1.5) = 1.923 m < d = 2.2 m < 1.923 + 0.5: full speed, but warned
    d = decide(CELL, Near(2.2), [], SEEN, REACTION, ())
    assert (d.state, d.speed_scale) == (WARNING, 1.0)
    assert d.reasons == ("hand 2.20 m from link5 within S_p 1.92 m + 0.50 m margin",)
    assert decide(CELL, Near(3.0), [], SEEN, REACTION, ()).state == CLEAR


def test_a_slower_frame_needs_more_distance():
    fast = decide(CELL, Near(1.85), [], SEEN, 0.02, ())
    slow = decide(CELL, Near(1.85), [], SEEN, 0.08, ())
    assert slow.speed_scale < fast.speed_scale


def test_no_robot_no_separation():
    cell = replace(CELL, robot=None)
    d = decide(cell, Near(0.1), [], SEEN, REACTION, ())
    assert (d.state, d.speed_scale, d.min_distance_m) == (CLEAR, 1.0, 0.1)


def test_body_region_limit_caps_the_speed_where_contact_is_allowed():
    # body: F = 2 x 110 N, k = 25 000 N/m, m_H = 40 kg, m_R = 15 kg: mu = 10.909 kg,
    # v = 220 / sqrt(10.909 * 25 000) = 0.4213 m/s, 28 % of 1.5 m/s. At d = 1.9 m the
    # separation alone allows (1.9 - 1.698) / 0.15 = 1.347 m/s, 90 %.
    torso = Near(1.9, labels.BODY)
    assert decide(CELL, torso, [], SEEN, REACTION, ()).speed_scale == pytest.approx(0.8978, 1e-3)
    d = decide(CONTACT_CELL, torso, [], SEEN, REACTION, ())
    assert d.state == WARNING
    assert d.speed_scale == pytest.approx(0.4213 / 1.5, 1e-3)
    assert d.reasons[-1] == "body 1.90 m from link5: contact limit 0.42 m/s, speed 28%"
    # beyond S_p at full speed the robot stops before any contact: no cap
    assert decide(CONTACT_CELL, Near(2.0, labels.BODY), [], SEEN, REACTION, ()).speed_scale == 1.0


def test_head_within_protective_distance_stops_where_contact_is_allowed():
    head = Near(1.9, labels.HEAD)
    d = decide(CONTACT_CELL, head, [], SEEN, REACTION, ())
    assert (d.state, d.speed_scale) == (STOP, 0.0)
    assert d.reasons[-1] == "head 1.90 m from link5: no contact allowed"
    assert decide(CONTACT_CELL, Near(1.95, labels.HEAD), [], SEEN, REACTION, ()).state == WARNING


def test_unknown_part_near_a_contact_cell_stops():
    d = decide(CONTACT_CELL, Near(1.9, 77), [], SEEN, REACTION, ())
    assert d.state == STOP and d.part == "part 77"


@pytest.mark.parametrize("distance", [math.nan, math.inf, -0.5])
def test_a_distance_that_is_not_a_distance_stops(distance):
    d = decide(CELL, Near(distance), [], SEEN, REACTION, ())
    assert (d.state, d.speed_scale) == (STOP, 0.0)


@pytest.mark.parametrize("reaction", [math.nan, math.inf, -0.01, None, "fast"])
def test_a_reaction_time_that_is_not_a_time_stops(reaction):
    assert decide(CELL, None, [], SEEN, reaction, ()).state == STOP
    assert decide(CELL, Near(5.0), [], SEEN, reaction, ()).state == STOP


def severity(state: str) -> int:
    return STATES.index(state)


@settings(max_examples=300, deadline=None)
@given(
    st.floats(0.0, 6.0),
    st.floats(0.0, 6.0),
    HUMAN,
    st.booleans(),
    st.floats(0.0, 0.2),
)
def test_a_person_closer_is_never_less_strict(d1, d2, part, contact, reaction):
    near, far = sorted((d1, d2))
    cell = CONTACT_CELL if contact else CELL
    closer = decide(cell, Near(near, part), [], SEEN, reaction, ())
    farther = decide(cell, Near(far, part), [], SEEN, reaction, ())
    assert closer.speed_scale <= farther.speed_scale
    assert severity(closer.state) >= severity(farther.state)


FAULT = st.text(min_size=1, max_size=12)
UNSEEN = st.one_of(st.floats(0.0, 1.0), st.just(math.nan), st.just(math.inf))


@settings(max_examples=300, deadline=None)
@given(
    st.lists(FAULT, max_size=3),
    st.lists(FAULT, max_size=3),
    st.one_of(st.none(), st.floats(0.0, 6.0)),
    st.lists(st.sampled_from(["press", "aisle"]), max_size=2),
    UNSEEN,
)
def test_more_faults_are_never_less_strict(faults, more, distance, occupied, unseen):
    nearest = None if distance is None else Near(distance)
    fewer = decide(CELL, nearest, occupied, {"press": unseen}, REACTION, tuple(faults))
    most = decide(CELL, nearest, occupied, {"press": unseen}, REACTION, (*faults, *more))
    assert severity(most.state) >= severity(fewer.state)
    assert most.speed_scale <= fewer.speed_scale
    if faults or more:
        assert most.state == STOP and most.speed_scale == 0.0
    if not 0 <= unseen <= CELL.max_unseen_fraction:
        assert fewer.state == STOP  # never clear with an unseen protective zone


@settings(max_examples=200, deadline=None)
@given(UNSEEN, UNSEEN, st.one_of(st.none(), st.floats(0.0, 6.0)))
def test_more_unseen_is_never_less_strict(u1, u2, distance):
    nearest = None if distance is None else Near(distance)
    if not (math.isnan(u1) or math.isnan(u2)):
        u1, u2 = sorted((u1, u2))
    less = decide(CELL, nearest, [], {"press": u1}, REACTION, ())
    more = decide(CELL, nearest, [], {"press": u2}, REACTION, ())
    if not math.isnan(u1):
        assert severity(more.state) >= severity(less.state)
