"""Speed and separation monitoring and power and force limiting after ISO/TS 15066:2016.

Protective separation distance (clause 5.5.4, formula 1 with constant speeds):

    S_p = S_h + S_r + S_s + C + Z_d + Z_r
    S_h = v_h (T_r + T_s)     the person approaching while the robot reacts and stops
    S_r = v_r T_r             the robot moving on at v_r while it reacts
    S_s                       the robot's stopping distance (its datasheet)

T_r is the reaction time: topseg's own, measured per frame (`reaction_s`: depth stamp to
decision), plus the robot controller's (`SeparationParams.controller_reaction_s`). C is the
intrusion distance, Z_d and Z_r the person's and the robot's position uncertainty.
`allowed_robot_speed` solves S_p(v_r) = d for v_r.

Transient contact (Annex A.3, formula A.6): a robot of effective mass m_R meeting a body
region of effective mass m_H and spring constant k may do so at most at

    v = F_max / sqrt(mu k),   mu = (1/m_H + 1/m_R)^-1

with F_max the region's transient force limit (2x its quasi-static limit, table A.2).

The functions take scalars or numpy arrays and return floats for scalars. A NaN or
negative input gives the strict answer (S_p inf, speeds 0), never a permissive one.
"""

from __future__ import annotations

import numpy as np

from topseg.core.safety.cell import BodyRegion, RobotSpec, SeparationParams


def _out(value: np.ndarray) -> float | np.ndarray:
    """A 0-d result as a float, an array as it is."""
    return float(value) if np.ndim(value) == 0 else value


def total_reaction_s(sep: SeparationParams, reaction_s: float | np.ndarray) -> np.ndarray:
    """T_r: topseg's measured reaction time plus the controller's; NaN where `reaction_s`
    is NaN or negative (the callers turn NaN into the strict answer)."""
    r = np.asarray(reaction_s, np.float64)
    return np.where(r >= 0, r + sep.controller_reaction_s, np.nan)


def protective_distance(
    sep: SeparationParams,
    robot: RobotSpec,
    reaction_s: float | np.ndarray,
    robot_speed_mps: float | np.ndarray,
) -> float | np.ndarray:
    """S_p (m), ISO/TS 15066 5.5.4, for a robot moving at `robot_speed_mps` and a reaction
    time `reaction_s` (topseg's; the controller's is added). inf for NaN or negative input."""
    t_r = total_reaction_s(sep, reaction_s)
    v_r = np.asarray(robot_speed_mps, np.float64)
    s_h = sep.human_speed_mps * (t_r + robot.stopping_time_s)
    s_r = v_r * t_r
    fixed = robot.stopping_distance_m + sep.intrusion_m
    s_p = s_h + s_r + fixed + sep.sensor_uncertainty_m + sep.robot_uncertainty_m
    bad = ~np.isfinite(s_p) | (v_r < 0)
    return _out(np.where(bad, np.inf, s_p))


def allowed_robot_speed(
    sep: SeparationParams,
    robot: RobotSpec,
    reaction_s: float | np.ndarray,
    distance_m: float | np.ndarray,
) -> float | np.ndarray:
    """v_r (m/s) with S_p(v_r) = `distance_m`: (d - S_p(0)) / T_r, clamped to
    0..`robot.max_speed_mps`. 0 when even a standing robot does not fit (d < S_p(0)) and for
    a NaN distance or reaction time; the full speed for an infinite distance."""
    d = np.asarray(distance_m, np.float64)
    t_r = total_reaction_s(sep, reaction_s)
    s_p0 = protective_distance(sep, robot, reaction_s, 0.0)
    slack = d - s_p0
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(t_r > 0, slack / t_r, np.where(slack >= 0, np.inf, 0.0))
    v = np.where(np.isnan(v) | np.isnan(d) | np.isnan(t_r), 0.0, v)
    return _out(np.clip(v, 0.0, robot.max_speed_mps))


def permissible_contact_speed(
    region: BodyRegion, robot_mass_kg: float | np.ndarray
) -> float | np.ndarray:
    """The highest relative speed (m/s) of a transient contact with `region` by a robot of
    effective mass `robot_mass_kg` (m_R), ISO/TS 15066 A.3: F / sqrt(mu k) with F the
    region's transient force limit, k its spring constant (N/m) and mu the reduced mass of
    m_H and m_R. 0 for a region that allows no contact and for a mass that is not a positive
    number."""
    m_r = np.asarray(robot_mass_kg, np.float64)
    if not region.contact_allowed:
        return _out(np.zeros_like(m_r))
    k = region.spring_constant_n_per_mm * 1000.0
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = 1.0 / (1.0 / region.effective_mass_kg + 1.0 / m_r)
        v = region.transient_force_n / np.sqrt(mu * k)
    ok = np.isfinite(m_r) & (m_r > 0) & np.isfinite(v)
    return _out(np.where(ok, v, 0.0))
