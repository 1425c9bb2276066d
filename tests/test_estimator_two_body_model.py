"""The estimator's two-body relative-motion model (bench/estimator/two_body_model.py) against
independent references: the plant's own integration of the nonlinear equations (scipy DOP853 at
1e-12 in Cartesian LVLH, then bench/plant/curvilinear.py's conversions), central finite
differences for its Jacobian, and the CWH closed form as its linearisation at the target."""
from __future__ import annotations

import numpy as np
import pytest

from bench.estimator.motion_model import cwh_discrete_closed_form
from bench.estimator.two_body_model import TwoBodyRelativeModel
from bench.gnc.cwh import RendezvousParams
from bench.plant.curvilinear import cartesian_to_curvilinear, curvilinear_to_cartesian, thrust_to_lvlh
from bench.plant.dynamics import propagate

PARAMS = RendezvousParams.from_reference()
START_A = np.array(PARAMS.initial_state_m_mps("A"))
THRUST_N = np.array([0.3, -0.2, 0.1])


def model(frame: str) -> TwoBodyRelativeModel:
    return TwoBodyRelativeModel(PARAMS.gravitational_parameter_m3ps2, PARAMS.target_radius_m, PARAMS.mass_kg,
                                PARAMS.time_step_s, frame)


def plant_step(frame: str, state, thrust, n_steps=1):
    """The plant's step in the flight side's coordinates (thrust held in LVLH, as the plant does)."""
    if frame == "cartesian":
        return propagate(state, thrust, n_steps * PARAMS.time_step_s, PARAMS, "nonlinear")
    cartesian = curvilinear_to_cartesian(state, PARAMS.target_radius_m)
    lvlh = thrust_to_lvlh(thrust, cartesian[:3], PARAMS.target_radius_m)
    return cartesian_to_curvilinear(propagate(cartesian, lvlh, n_steps * PARAMS.time_step_s, PARAMS, "nonlinear"),
                                    PARAMS.target_radius_m)


def starts(frame: str):
    far = START_A if frame == "cartesian" else cartesian_to_curvilinear(START_A, PARAMS.target_radius_m)
    near = np.array([-120.0, 800.0, 60.0, 0.05, -0.2, 0.01])
    return [far, near]


@pytest.mark.parametrize("frame", ["cartesian", "curvilinear"])
@pytest.mark.parametrize("n_steps", [1, 2])
def test_propagation_matches_the_plants_integration_of_the_nonlinear_equations(frame, n_steps):
    for start in starts(frame):
        expected = plant_step(frame, start, THRUST_N, n_steps)
        got = model(frame).propagate(start, THRUST_N, n_steps)
        # RK4 at 60 s: ~1.5 mm per step on a 400 km start; the CWH model errs by metres there (below).
        np.testing.assert_allclose(got[:3], expected[:3], rtol=0, atol=5e-3 * n_steps**2)
        np.testing.assert_allclose(got[3:], expected[3:], rtol=0, atol=1e-5 * n_steps**2)


def test_the_linear_model_does_not_pass_the_same_check_on_the_far_start():
    """The check above can fail: CWH in curvilinear coordinates is metres off from A in one step."""
    start = cartesian_to_curvilinear(START_A, PARAMS.target_radius_m)
    a_d, b_d = cwh_discrete_closed_form(PARAMS.mean_motion, PARAMS.mass_kg, PARAMS.time_step_s)
    miss = np.abs(a_d @ start + b_d @ THRUST_N - plant_step("curvilinear", start, THRUST_N))
    assert miss[:3].max() > 1.0


@pytest.mark.parametrize("frame", ["cartesian", "curvilinear"])
def test_jacobian_matches_central_finite_differences(frame):
    m = model(frame)
    for start in starts(frame):
        propagated, jacobian = m.linearise(start, THRUST_N)
        np.testing.assert_allclose(propagated, m.propagate(start, THRUST_N), rtol=0, atol=1e-9)
        steps = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
        finite = np.empty((6, 6))
        for i in range(6):
            e = np.zeros(6)
            e[i] = steps[i]
            finite[:, i] = (m.propagate(start + e, THRUST_N) - m.propagate(start - e, THRUST_N)) / (2 * steps[i])
        np.testing.assert_allclose(jacobian, finite, rtol=1e-6, atol=1e-7 * np.abs(finite).max())


@pytest.mark.parametrize("frame", ["cartesian", "curvilinear"])
def test_linearisation_at_the_target_is_the_cwh_model(frame):
    m = model(frame)
    a_d, b_d = cwh_discrete_closed_form(PARAMS.mean_motion, PARAMS.mass_kg, PARAMS.time_step_s)
    propagated, jacobian = m.linearise(np.zeros(6), np.zeros(3))
    # At rest on the target's orbit: only rounding of n^2 R - mu / R^2 (~1e-15 m/s^2) moves it.
    np.testing.assert_allclose(propagated, np.zeros(6), rtol=0, atol=1e-6)
    # RK4's truncation, ~(n h)^4 / 120 per substep, is the only difference from the exact CWH matrix.
    np.testing.assert_allclose(jacobian, a_d, rtol=0, atol=1e-5 * np.abs(a_d).max())
    # A thrust of 0.3 N held 600 s moves the chaser by ~100 m; the nonlinear terms of that are ~mm.
    np.testing.assert_allclose(m.propagate(np.zeros(6), THRUST_N), b_d @ THRUST_N, rtol=0, atol=1e-2)


def test_bad_input_is_named():
    m = model("curvilinear")
    with pytest.raises(ValueError, match="state_m_mps"):
        m.propagate(np.zeros(5), THRUST_N)
    with pytest.raises(ValueError, match="thrust_n"):
        m.propagate(np.zeros(6), [np.nan, 0, 0])
    with pytest.raises(ValueError, match="n_steps"):
        m.propagate(np.zeros(6), THRUST_N, 0)
    with pytest.raises(ValueError, match="navigation frame"):
        TwoBodyRelativeModel(3.986e14, 7e6, 300.0, 600.0, "polar")
    with pytest.raises(ValueError, match="target_radius_m"):
        TwoBodyRelativeModel(3.986e14, -7e6, 300.0, 600.0, "cartesian")
