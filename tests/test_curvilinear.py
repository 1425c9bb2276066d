"""Curvilinear relative coordinates (bench/plant/curvilinear.py) and the plant boundary."""
import numpy as np
import pytest

from bench.plant.curvilinear import (cartesian_to_curvilinear, curvilinear_to_cartesian,
                                     position_to_curvilinear_m, thrust_to_lvlh)
from bench.gnc.cwh import RendezvousParams
from bench.plant.dynamics import propagate

R = 7.0e6


def test_round_trip_both_ways():
    rng = np.random.default_rng(11)
    for _ in range(50):
        cart = np.concatenate([rng.uniform(-1, 1, 3) * [3e4, 8e5, 3e4], rng.uniform(-1, 1, 3) * 30.0])
        curv = cartesian_to_curvilinear(cart, R)
        np.testing.assert_allclose(curvilinear_to_cartesian(curv, R), cart, rtol=0, atol=1e-6)
        np.testing.assert_allclose(cartesian_to_curvilinear(curvilinear_to_cartesian(curv, R), R), curv,
                                   rtol=0, atol=1e-6)
        np.testing.assert_allclose(position_to_curvilinear_m(cart[:3], R), curv[:3], atol=1e-9)


def test_known_values():
    # On the target's orbit, 400 km behind: Cartesian x = R (cos(theta) - 1) ~ -11.4 km.
    curv = np.array([0.0, -400e3, 0.0, 0.0, 0.0, 0.0])
    cart = curvilinear_to_cartesian(curv, R)
    theta = -400e3 / R
    np.testing.assert_allclose(cart[:3], [R * (np.cos(theta) - 1), R * np.sin(theta), 0.0], atol=1e-6)
    assert cart[0] == pytest.approx(-(400e3) ** 2 / (2 * R), rel=1e-3)


def test_velocity_is_the_time_derivative():
    """Velocity conversion against finite differences of the position conversion along a path."""
    rng = np.random.default_rng(5)
    cart = np.concatenate([rng.uniform(-1, 1, 3) * [2e4, 5e5, 2e4], rng.uniform(-1, 1, 3) * 20.0])
    h = 1e-3
    p_plus = position_to_curvilinear_m(cart[:3] + h * cart[3:], R)
    p_minus = position_to_curvilinear_m(cart[:3] - h * cart[3:], R)
    np.testing.assert_allclose(cartesian_to_curvilinear(cart, R)[3:], (p_plus - p_minus) / (2 * h), rtol=1e-6,
                               atol=1e-9)


def test_thrust_frame_is_orthonormal_and_radial_at_target_axis():
    u = np.array([0.3, -0.7, 0.2])
    position = np.array([-11e3, -400e3, 5e3])
    lvlh = thrust_to_lvlh(u, position, R)
    assert np.linalg.norm(lvlh) == pytest.approx(np.linalg.norm(u), rel=1e-12)
    radial = (position + [R, 0, 0]) / np.linalg.norm(position + [R, 0, 0])
    assert lvlh @ radial == pytest.approx(u[0], abs=1e-12)
    np.testing.assert_allclose(thrust_to_lvlh(u, np.zeros(3), R), u, atol=1e-15)


def test_bad_input_named():
    with pytest.raises(ValueError, match="state_m_mps"):
        cartesian_to_curvilinear(np.zeros(5), R)
    with pytest.raises(ValueError, match="target_radius_m"):
        curvilinear_to_cartesian(np.zeros(6), -1.0)


def test_cwh_in_curvilinear_matches_nonlinear_better_over_half_orbit_at_400km():
    """Free motion from 400 km along track for half an orbit: CWH propagated in curvilinear
    coordinates lands far closer to the nonlinear two-body motion than CWH in Cartesian LVLH."""
    params = RendezvousParams.from_reference()
    n = params.mean_motion
    half_orbit_steps = int(round(np.pi / n / params.time_step_s))
    a_d, _ = params.discrete_si()
    a_half = np.linalg.matrix_power(a_d, half_orbit_steps)
    for curv0 in ([0.0, -400e3, 0.0, 0.0, 0.0, 0.0],                        # on the target orbit
                  [-2e3, -400e3, 1e3, 0.0, 1.5 * n * 2e3, 0.0],               # 2 km below, drifting
                  [1e3, 400e3, -2e3, 0.5, -1.5 * n * 1e3, 0.3]):
        curv0 = np.array(curv0)
        cart0 = curvilinear_to_cartesian(curv0, R)
        truth = cart0
        for _ in range(half_orbit_steps):
            truth = propagate(truth, np.zeros(3), params.time_step_s, params, "nonlinear")
        from_cartesian = a_half @ cart0
        from_curvilinear = curvilinear_to_cartesian(a_half @ curv0, R)
        error_cartesian_m = np.linalg.norm(from_cartesian[:3] - truth[:3])
        error_curvilinear_m = np.linalg.norm(from_curvilinear[:3] - truth[:3])
        assert error_curvilinear_m < 0.05 * error_cartesian_m, (error_curvilinear_m, error_cartesian_m)
        assert error_cartesian_m > 10e3      # Cartesian CWH is off by tens of km here


def test_lqr_flies_the_400km_approach_on_the_nonlinear_plant_in_curvilinear_coordinates():
    """The plant boundary converts sensing and thrust: LQR from A meets the seed's terminal bounds
    on the nonlinear plant in curvilinear coordinates, and misses by thousands of km in Cartesian."""
    from bench.scenario import load_scenario, parse_scenario, scenario_to_toml_dict
    from bench.sim import simulate_in_process

    base = scenario_to_toml_dict(load_scenario("rendezvous_lqr"))
    finals = {}
    for frame in ("cartesian", "curvilinear"):
        data = dict(base, plant=dict(base["plant"], dynamics="nonlinear", navigation_frame=frame))
        _, metrics = simulate_in_process(parse_scenario(data))
        finals[frame] = metrics["final_position_error_m"], metrics["final_velocity_error_mps"]
    assert finals["curvilinear"][0] < 100.0 and finals["curvilinear"][1] < 1.0
    assert finals["cartesian"][0] > 1e5


def test_curvilinear_frame_needs_the_nonlinear_plant():
    from bench.scenario import ScenarioError, parse_scenario

    with pytest.raises(ScenarioError, match="navigation_frame"):
        parse_scenario({"name": "x", "plant": {"dynamics": "cwh", "navigation_frame": "curvilinear"}})
