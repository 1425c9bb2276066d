"""The CWH discretisation against the closed-form Clohessy-Wiltshire solution."""
import numpy as np
import pytest
from scipy.integrate import quad_vec

from bench.gnc.cwh import RendezvousParams, cwh_continuous, discretise_zoh, scale_system
from bench.plant.dynamics import propagate


def cw_transition(n: float, t: float) -> np.ndarray:
    """Closed-form state transition of the CW equations (x radial, y along track, z normal)."""
    c, s = np.cos(n * t), np.sin(n * t)
    return np.array([
        [4 - 3 * c, 0, 0, s / n, 2 * (1 - c) / n, 0],
        [6 * (s - n * t), 1, 0, -2 * (1 - c) / n, (4 * s - 3 * n * t) / n, 0],
        [0, 0, c, 0, 0, s / n],
        [3 * n * s, 0, 0, c, 2 * s, 0],
        [-6 * n * (1 - c), 0, 0, -2 * s, 4 * c - 3, 0],
        [0, 0, -n * s, 0, 0, c],
    ])


@pytest.fixture(scope="module")
def params():
    return RendezvousParams.from_reference()


def test_state_transition_matches_closed_form(params):
    n, dt = params.mean_motion, params.time_step_s
    a_d, _ = discretise_zoh(*cwh_continuous(n, params.mass_kg), dt)
    np.testing.assert_allclose(a_d, cw_transition(n, dt), rtol=1e-10, atol=1e-12)


def test_input_matrix_is_the_held_thrust_integral(params):
    n, dt, m = params.mean_motion, params.time_step_s, params.mass_kg
    _, b_c = cwh_continuous(n, m)
    _, b_d = discretise_zoh(*cwh_continuous(n, m), dt)
    expected, _ = quad_vec(lambda tau: cw_transition(n, dt - tau) @ b_c, 0.0, dt, epsabs=1e-14, epsrel=1e-12)
    np.testing.assert_allclose(b_d, expected, rtol=1e-9, atol=1e-14)


def test_many_steps_match_closed_form_trajectory(params):
    x0 = params.initial_state_m_mps("A")
    x = x0.copy()
    for _ in range(288):
        x = propagate(x, np.zeros(3), params.time_step_s, params, "cwh")
    expected = cw_transition(params.mean_motion, 288 * params.time_step_s) @ x0
    np.testing.assert_allclose(x, expected, rtol=1e-8, atol=1e-6)


def test_scaling_describes_the_same_dynamics(params):
    a_d, b_d = params.discrete_si()
    a, b = scale_system(a_d, b_d, np.asarray(params.scaling))
    x_si = params.initial_state_m_mps("B")
    u = np.array([0.3, -0.2, 0.1])
    v = np.diag(params.scaling)
    np.testing.assert_allclose(a @ (v @ x_si) + b @ u, v @ (a_d @ x_si + b_d @ u), rtol=1e-12)


def test_nonlinear_model_agrees_with_cwh_near_the_target(params):
    # 10 m from the target the linearisation error is far below a millimetre over one step.
    x = np.array([10.0, -8.0, 5.0, 0.01, -0.02, 0.005])
    u = np.array([0.1, 0.0, -0.1])
    linear = propagate(x, u, params.time_step_s, params, "cwh")
    nonlinear = propagate(x, u, params.time_step_s, params, "nonlinear")
    np.testing.assert_allclose(nonlinear, linear, atol=1e-4)


def test_nonpositive_time_step_is_rejected(params):
    with pytest.raises(ValueError, match="time_step_s must be positive"):
        discretise_zoh(*params.continuous(), 0.0)
