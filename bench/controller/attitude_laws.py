"""Which attitude law the controller runs: the builders the registry names.

`bench.config.controller.ATTITUDE_LAWS` maps a scenario's law name to "module:builder" (one line
per law); a builder takes the scenario and returns an object with
`eval(AttitudeControlInput) -> (dipole_am2, info)` (bench.gnc.attitude_law). The laws themselves
are pure algorithms in bench.gnc; this module only reads the scenario.
"""
from __future__ import annotations

import importlib

import numpy as np
from scipy.spatial.transform import Rotation

from bench.gnc import quaternion as qt
from bench.gnc.attitude_law import (
    AttitudeLaw, AttitudeTarget, BDotDetumble, DetumbleSequence, PdTracking, QuantisationErrorFeedback, RateDamping,
    ResidualDipoleCompensation, SlidingModeTracking,
    TargetState, inertial_hold,
)
from bench.config.controller import ATTITUDE_LAWS
from bench.config.plant import inertia_matrix
from bench.scenario import Scenario

def dipole_limit_am2(scenario: Scenario) -> float:
    control = scenario.attitude_control
    if control.dipole_limit_am2 is not None:
        return control.dipole_limit_am2
    return scenario.can.board.max_dipole_am2 if scenario.can is not None else 0.2


def believed_inertia(scenario: Scenario) -> np.ndarray:
    control = scenario.attitude_control
    if control.inertia_kgm2 is not None:
        return inertia_matrix(control.inertia_kgm2, "attitude_control.inertia_kgm2")
    return scenario.attitude.inertia_matrix()


def nadir_target(orbit, step_s: float = 1.0) -> AttitudeTarget:
    """Body z to nadir, body y to the negative orbit normal, x completing (along the velocity on a
    circular orbit). The rate comes from a central difference of the frame over +-step_s (the
    frame turns at the orbit rate, ~1e-3 rad/s: the difference's error is ~1e-10 rad/s)."""

    def frame(time_s: float) -> np.ndarray:
        r = orbit.position_m(time_s)
        v = (orbit.position_m(time_s + 0.5) - orbit.position_m(time_s - 0.5))
        z = -r / np.linalg.norm(r)
        y = -np.cross(r, v)
        y /= np.linalg.norm(y)
        return Rotation.from_matrix(np.column_stack([np.cross(y, z), y, z])).as_quat(scalar_first=True)

    def target(time_s: float) -> TargetState:
        q = frame(time_s)
        q_before, q_after = frame(time_s - step_s), frame(time_s + step_s)
        omega = qt.log(qt.multiply(qt.conjugate(q_before), q_after)) / (2 * step_s)
        return TargetState(q, omega, np.zeros(3))

    return target


def attitude_target(scenario: Scenario) -> AttitudeTarget:
    target = scenario.attitude_control.target
    if target.kind == "nadir":
        from bench.plant.attitude_plant import build_orbit   # the flight side's orbit model

        return nadir_target(build_orbit(scenario.attitude))
    return inertial_hold(target.q_wxyz)


def bdot(s: Scenario) -> AttitudeLaw:
    return BDotDetumble(s.attitude_control.bdot_gain_am2_s_per_t, dipole_limit_am2(s))


def rate_damping(s: Scenario) -> AttitudeLaw:
    return RateDamping(s.attitude_control.rate_damping_gain_nms, dipole_limit_am2(s))


def bdot_then_rate_damping(s: Scenario) -> AttitudeLaw:
    return DetumbleSequence(bdot(s), rate_damping(s), np.deg2rad(s.attitude_control.handover_rate_dps))


def sliding_mode(s: Scenario) -> AttitudeLaw:
    c = s.attitude_control
    return SlidingModeTracking(attitude_target(s), believed_inertia(s), dipole_limit_am2(s),
                               c.sliding_gain_radps, c.convergence_gain_radps)


def pd(s: Scenario) -> AttitudeLaw:
    c = s.attitude_control
    return PdTracking(attitude_target(s), dipole_limit_am2(s), c.kp_nm, c.kd_nms)


def build_attitude_law(scenario: Scenario) -> AttitudeLaw:
    module, _, builder = ATTITUDE_LAWS[scenario.attitude_control.law].partition(":")
    law = getattr(importlib.import_module(module), builder)(scenario)
    residual = np.asarray(scenario.attitude_control.residual_dipole_compensation_am2, float)
    if not np.all(np.isfinite(residual)):
        raise ValueError("attitude_control.residual_dipole_compensation_am2: must be finite")
    if np.any(residual):
        law = ResidualDipoleCompensation(law, residual, dipole_limit_am2(scenario))
    if scenario.attitude_control.quantisation_error_feedback:
        resolution = scenario.can.board.dipole_resolution_am2 if scenario.can is not None else 1e-3
        law = QuantisationErrorFeedback(law, resolution, dipole_limit_am2(scenario))
    return law
