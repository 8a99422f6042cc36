"""ISO/TS 15066 formulas against numbers worked by hand: S_p (5.5.4), the speed that keeps a
distance, and the permissible transient contact speed (Annex A.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.safety.cell import DEFAULT_REGIONS, BodyRegion, RobotSpec, SeparationParams
from topseg.core.safety.iso15066 import (
    allowed_robot_speed,
    permissible_contact_speed,
    protective_distance,
)

SEP = SeparationParams(
    human_speed_mps=1.6,
    controller_reaction_s=0.1,
    detection_capability_mm=40.0,  # C = 8 (40 - 14) mm = 0.208 m
    sensor_uncertainty_m=0.1,
    robot_uncertainty_m=0.05,
)
ROBOT = RobotSpec(
    "arm",
    "panda",
    stopping_time_s=0.5,
    stopping_distance_m=0.3,
    max_speed_mps=1.5,
    effective_mass_kg=15.0,
)


def test_protective_distance_worked_example():
    # T_r = 0.05 (topseg) + 0.1 (controller) = 0.15 s
    # S_h = 1.6 * (0.15 + 0.5) = 1.04; S_r = 1.0 * 0.15 = 0.15; S_s = 0.3
    # S_p = 1.04 + 0.15 + 0.3 + 0.208 + 0.1 + 0.05 = 1.848 m
    assert protective_distance(SEP, ROBOT, 0.05, 1.0) == pytest.approx(1.848)
    # a standing robot: S_r = 0, S_p = 1.698 m
    assert protective_distance(SEP, ROBOT, 0.05, 0.0) == pytest.approx(1.698)


def test_protective_distance_grows_with_speed_and_reaction_time():
    speeds = np.array([0.0, 0.5, 1.0, 1.5])
    s_p = protective_distance(SEP, ROBOT, 0.05, speeds)
    assert isinstance(s_p, np.ndarray) and np.all(np.diff(s_p) > 0)
    np.testing.assert_allclose(np.diff(s_p), 0.5 * 0.15)  # dS_p/dv_r = T_r
    assert protective_distance(SEP, ROBOT, 0.10, 1.0) > protective_distance(SEP, ROBOT, 0.05, 1.0)


@pytest.mark.parametrize(("reaction", "speed"), [(math.nan, 1.0), (-0.1, 1.0), (0.05, math.nan)])
def test_protective_distance_of_bad_input_is_infinite(reaction, speed):
    assert protective_distance(SEP, ROBOT, reaction, speed) == math.inf


def test_allowed_speed_inverts_the_protective_distance():
    # d = 1.848 m is S_p at 1.0 m/s (the worked example), so 1.0 m/s is allowed
    assert allowed_robot_speed(SEP, ROBOT, 0.05, 1.848) == pytest.approx(1.0)
    # (1.773 - 1.698) / 0.15 = 0.5 m/s
    assert allowed_robot_speed(SEP, ROBOT, 0.05, 1.773) == pytest.approx(0.5)
    for v in (0.2, 0.7, 1.3):
        d = protective_distance(SEP, ROBOT, 0.03, v)
        assert allowed_robot_speed(SEP, ROBOT, 0.03, d) == pytest.approx(v)


def test_allowed_speed_is_clamped():
    assert allowed_robot_speed(SEP, ROBOT, 0.05, 1.0) == 0.0  # below S_p(0) = 1.698
    assert allowed_robot_speed(SEP, ROBOT, 0.05, 10.0) == 1.5  # capped at max speed
    assert allowed_robot_speed(SEP, ROBOT, 0.05, math.inf) == 1.5
    assert allowed_robot_speed(SEP, ROBOT, 0.05, math.nan) == 0.0
    assert allowed_robot_speed(SEP, ROBOT, math.nan, 10.0) == 0.0
    assert allowed_robot_speed(SEP, ROBOT, -1.0, 10.0) == 0.0
    d = np.array([0.5, 1.773, 5.0])
    np.testing.assert_allclose(allowed_robot_speed(SEP, ROBOT, 0.05, d), [0.0, 0.5, 1.5])


def test_allowed_speed_without_any_reaction_time():
    sep = SeparationParams(controller_reaction_s=0.0)
    s_p0 = protective_distance(sep, ROBOT, 0.0, 0.0)
    assert allowed_robot_speed(sep, ROBOT, 0.0, s_p0 + 0.01) == ROBOT.max_speed_mps
    assert allowed_robot_speed(sep, ROBOT, 0.0, s_p0 - 0.01) == 0.0


def test_permissible_contact_speed_hand_worked_example():
    # hand: F = 2 * 140 N (transient), k = 75 N/mm = 75 000 N/m, m_H = 0.6 kg, m_R = 15 kg
    # mu = 1 / (1/0.6 + 1/15) = 0.576 923 kg; v = 280 / sqrt(0.576 923 * 75 000) = 1.3461 m/s
    hand = DEFAULT_REGIONS[labels.HAND]
    assert permissible_contact_speed(hand, 15.0) == pytest.approx(1.3461, abs=1e-4)


def test_permissible_contact_speed_falls_with_robot_mass():
    hand = DEFAULT_REGIONS[labels.HAND]
    masses = np.array([1.0, 5.0, 15.0, 50.0])
    v = permissible_contact_speed(hand, masses)
    assert np.all(np.diff(v) < 0)


def test_no_contact_region_and_bad_mass_give_zero():
    assert permissible_contact_speed(DEFAULT_REGIONS[labels.HEAD], 15.0) == 0.0
    hand = DEFAULT_REGIONS[labels.HAND]
    for mass in (0.0, -3.0, math.nan):
        assert permissible_contact_speed(hand, mass) == 0.0


def test_transient_factor_scales_the_force():
    single = BodyRegion(140.0, 0.6, 75.0, transient_factor=1.0)
    double = BodyRegion(140.0, 0.6, 75.0, transient_factor=2.0)
    assert permissible_contact_speed(double, 15.0) == pytest.approx(
        2 * permissible_contact_speed(single, 15.0)
    )
