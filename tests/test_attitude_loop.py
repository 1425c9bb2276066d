"""The attitude loop's parts in one process: scenario validation (a bad value names its field), the
plant's acceptance of the board's reports, the law registry, the nadir target, and a short loop."""
import copy
import tomllib
from importlib import resources

import numpy as np
import pytest

from bench.report.attitude_metrics import (
    applied_is_commanded_or_zero, attitude_metrics, continuous_rotation_angle_deg, pointing_error_deg,
)
from bench.sim import simulate_attitude_in_process
from bench.controller.attitude_laws import build_attitude_law, nadir_target
from bench.config.controller import ATTITUDE_LAWS
from bench.gnc import quaternion as qt
from bench.plant.attitude import CircularOrbit
from bench.plant.mtq_acceptance import DipoleAcceptance, board_dipole_without_bus
from bench.scenario import ScenarioError, parse_scenario


def builtin(name: str) -> dict:
    return tomllib.loads(resources.files("bench.scenarios").joinpath(f"{name}.toml").read_text())


def with_change(data: dict, path: str, value) -> dict:
    data = copy.deepcopy(data)
    *parents, leaf = path.split(".")
    node = data
    for part in parents:
        node = node.setdefault(part, {})
    node[leaf] = value
    return data


@pytest.mark.parametrize("path, value, field", [
    ("attitude.initial_q_wxyz", [1.0, 0.2, 0.0, 0.0], "attitude.initial_q_wxyz"),
    ("attitude.initial_q_wxyz", [float("nan"), 0.0, 0.0, 1.0], "attitude.initial_q_wxyz"),
    ("attitude.inertia_kgm2", [2e-3, 0.0, 2e-3], "attitude.inertia_kgm2"),
    ("attitude.inertia_kgm2", [1e-3, 2e-3, 0, 2e-3, 1e-3, 0, 0, 0, 1e-3], "attitude.inertia_kgm2"),
    ("attitude_control.dipole_limit_am2", 0.0, "attitude_control.dipole_limit_am2"),
    ("attitude_control.dipole_limit_am2", -0.1, "attitude_control.dipole_limit_am2"),
    ("attitude_control.dipole_limit_am2", 0.5, "attitude_control.dipole_limit_am2"),    # above the board's
    ("attitude_control.law", "lqr", "attitude_control.law"),
    ("attitude_control.target.q_wxyz", [0.0, 0.0, 0.0, 0.0], "attitude_control.target.q_wxyz"),
    ("attitude.orbit", {"model": "sgp4", "tle": ["1 00005U 58002B   00179.78495062  .00000023  00000-0  28098-4 0  4753",
                                                 "2 00005  34.2682 348.7242 1859667 331.7664  19.3264 10.8241915741366X"]},
     "attitude.orbit.tle"),
    ("run.mode", "real-time", "run.time_factor"),          # the default factor 6000 is for 600 s steps
    ("can.board.max_dipole_am2", 0.0, "can.board.max_dipole_am2"),
])
def test_bad_attitude_scenario_is_an_error_naming_the_field(path, value, field):
    with pytest.raises(ScenarioError) as error:
        parse_scenario(with_change(builtin("attitude_slew"), path, value), "test")
    assert f"test: {field}" in str(error.value)


def test_every_builtin_attitude_scenario_loads():
    names = [n[:-5] for n in (p.name for p in resources.files("bench.scenarios").iterdir()) if n.startswith("attitude_")]
    assert len(names) >= 8
    for name in names:
        assert parse_scenario(builtin(name), name).kind == "attitude"


def test_acceptance_refuses_non_finite_out_of_envelope_and_stale_reports():
    acceptance = DipoleAcceptance(None)      # default board: 0.2 A m^2, 1e-3 steps, 0.1 s timeout
    now_ns = 10**12
    assert acceptance.accept([0.1, -0.2, 0.0], now_ns - 50_000_000, now_ns)[1] is None
    for dipole, reported_ns, reason in [([np.nan, 0, 0], now_ns, "not_finite"), ([0.3, 0, 0], now_ns, "out_of_envelope"),
                                        ([0.1, 0, 0], now_ns - 200_000_000, "stale")]:
        applied, why = acceptance.accept(dipole, reported_ns, now_ns)
        assert why == reason and not np.any(applied)
    assert sum(acceptance.rejected.values()) == 3


def test_board_model_without_bus_quantises_and_saturates_as_the_board():
    np.testing.assert_array_equal(board_dipole_without_bus([0.12345, -0.31, 0.0004], None), [0.123, -0.2, 0.0])


def test_law_registry_builds_every_law_and_none_commands_non_finite_dipoles():
    data = builtin("attitude_slew")
    for law in ATTITUDE_LAWS:
        scenario = parse_scenario(with_change(data, "attitude_control.law", law), law)
        built = build_attitude_law(scenario)
        from bench.gnc.attitude_law import AttitudeControlInput

        for field_t in ([0.0, 0.0, 0.0], [np.nan, 1e-5, 0.0], [2e-5, -1e-5, 3e-5]):
            for t in (0.0, 0.1):
                dipole, _ = built.eval(AttitudeControlInput(t, np.array([0.5, 0.5, 0.5, 0.5]), np.array([0.01, 0.0, -0.02]),
                                                            np.array(field_t)))
                assert np.all(np.isfinite(dipole)) and np.all(np.abs(dipole) <= 0.2)


def test_nadir_target_points_z_down_and_turns_at_the_orbit_rate():
    orbit = CircularOrbit(radius_m=6.9e6, inclination_rad=np.deg2rad(60.0), raan_rad=0.4)
    target = nadir_target(orbit)
    for t in (0.0, 1234.5):
        state = target(t)
        z_inertial = qt.rotation_matrix(state.q_wxyz) @ np.array([0.0, 0.0, 1.0])
        np.testing.assert_allclose(z_inertial, -orbit.position_m(t) / np.linalg.norm(orbit.position_m(t)), atol=1e-12)
        # The LVLH frame turns about its -y axis at the mean motion (in its own axes).
        np.testing.assert_allclose(state.omega_radps, [0.0, -orbit.mean_motion_radps, 0.0], atol=1e-9)


def test_short_in_process_detumble_applies_only_what_was_commanded_and_slows_the_body():
    scenario = parse_scenario(with_change(builtin("attitude_detumble"), "run.steps", 300), "short")
    trajectory = simulate_attitude_in_process(scenario)
    assert applied_is_commanded_or_zero(trajectory, scenario.can).all()
    metrics = attitude_metrics(trajectory, scenario)
    assert metrics["final_rate_dps"] < metrics["initial_rate_dps"]
    # B-dot only removes energy: kinetic energy never rises by more than the disturbances could add.
    omega = trajectory["att_omega_radps"]
    inertia = scenario.attitude.inertia_matrix()
    energy = 0.5 * np.einsum("ni,ij,nj->n", omega, inertia, omega)
    disturbance_power = np.linalg.norm(trajectory["att_torque_disturbance_nm"], axis=1) * np.linalg.norm(omega, axis=1)
    assert energy[-1] < 0.9 * energy[0]
    assert np.all(np.diff(energy) <= 1.01 * disturbance_power[:-1] * scenario.step_s)


def test_cycle_commands_zero_for_a_nan_or_non_unit_estimate_and_counts_it():
    from bench.controller.attitude_cycle import AttitudeCycle

    cycle = AttitudeCycle(parse_scenario(builtin("attitude_slew"), "slew"))
    for q in ([np.nan, 0.0, 0.0, 1.0], [1.0, 0.1, 0.0, 0.0]):
        outcome = cycle.run(0.0, True, q, [0.0, 0.0, 0.0], [2e-5, 0.0, 1e-5])
        assert not np.any(outcome.dipole_am2)
    assert cycle.bad_estimate_cycles == 2
    assert np.any(cycle.run(0.0, True, [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2e-5, 0.0, 1e-5]).dipole_am2)


# ---- convergence over orbits, in process (the lock-step test shows the processes reproduce it) ----
ORBIT_S = 5670.0     # 500 km circular


def test_detumble_scenario_gets_below_0_1_dps_within_one_orbit_and_stays():
    """The `attitude_detumble` story at its 1 Hz loop rate: B-dot from 8 deg/s, rate damping below
    2 deg/s. 1.5 orbits (~10-50 s on a loaded host). Beside the metric: in the rate-damping phase
    the law's own torque (the command plus the calibrated residual dipole it offsets) never feeds
    energy in at a sample, omega . (m x B) <= 0, on the plant's logged truth."""
    scenario = parse_scenario(with_change(builtin("attitude_detumble"), "run.steps", 8500), "detumble")
    trajectory = simulate_attitude_in_process(scenario)
    metrics = attitude_metrics(trajectory, scenario)
    print({k: metrics[k] for k in ("time_to_detumble_s", "first_below_detumble_threshold_s", "final_rate_dps")})
    assert metrics["initial_rate_dps"] == pytest.approx(8.0, abs=0.1)
    assert metrics["time_to_detumble_s"] is not None and metrics["time_to_detumble_s"] < ORBIT_S
    assert metrics["final_rate_dps"] < 0.07
    assert applied_is_commanded_or_zero(trajectory, scenario.can).all()
    omega = trajectory["att_omega_radps"]
    handover = int(np.argmax(np.rad2deg(np.linalg.norm(omega, axis=1)) < scenario.attitude_control.handover_rate_dps))
    assert 0 < handover < len(omega) // 4
    law_dipole = trajectory["att_dipole_commanded_am2"] + np.asarray(scenario.attitude_control.residual_dipole_compensation_am2)
    power = np.einsum("ni,ni->n", omega, np.cross(law_dipole, trajectory["att_field_body_t"]))
    assert np.all(power[handover + 1:] <= 1e-20)


def test_heavily_damped_pd_holds_an_inertial_target_over_an_orbit_with_magnetorquers_only():
    """`attitude_pointing_pd` (truth estimate, 1 Hz, IGRF, gravity gradient, residual dipole with a
    10 % calibration, the board's rounding): from 3 deg, the error stays below 4 deg for a whole
    orbit (measured 0.88-3.80 deg). This shows the magnetorquer-only hold is bounded over an orbit,
    not that it converges (with the full 3-axis torque a PD converges to 0.0 deg: docs/attitude.md)."""
    scenario = parse_scenario(builtin("attitude_pointing_pd"), "pointing_pd")
    assert scenario.n_steps == 5670
    trajectory = simulate_attitude_in_process(scenario)
    error = pointing_error_deg(trajectory, scenario)
    print(f"pointing error: min {error.min():.2f}, max {error.max():.2f}, final {error[-1]:.2f} deg")
    assert error[0] == pytest.approx(3.0, abs=1e-3)
    assert error.max() < 4.0
    assert error[len(error) // 2:].min() < 1.5     # it comes back towards the target, not only stays
    assert applied_is_commanded_or_zero(trajectory, scenario.can).all()


def test_pointing_with_the_smoother_in_the_loop_closes_in_on_the_target():
    """`attitude_pointing` (10 Hz, gtsam smoother with a star-tracker outage, PD with the residual
    dipole offset) from 3 deg: never above 3.1 deg, 2.21 deg after 300 s (measured), falling."""
    scenario = parse_scenario(builtin("attitude_pointing"), "pointing")
    assert scenario.estimator.mode == "smoother"
    trajectory = simulate_attitude_in_process(scenario)
    error = pointing_error_deg(trajectory, scenario)
    print(f"pointing error: max {error.max():.3f}, final {error[-1]:.3f} deg")
    assert error.max() < 3.1
    assert error[-1] < 2.4
    assert error[-1] < error[len(error) // 2] < error[0]
    assert trajectory["att_estimate_valid"].all()


@pytest.mark.study
def test_sliding_mode_from_200_degrees_converges_the_short_way_over_three_orbits():
    """`attitude_slew` (1 Hz, truth estimate, IGRF, gravity gradient, residual dipole calibrated to
    1 %, the board's rounding with the law's error feedback): seed 002's sliding mode with
    lambda = 1e-3 rad/s, k = 5e-3 /s from 200 deg. The rotation angle never goes below where it
    started (the short way, 160 deg, not the long 200); the error is below 10 deg from one orbit on
    and below 5 deg over the last orbit (measured: 8.3 deg at one orbit, 1.4-2.6 deg over the last,
    1.37 deg at the end). The old gains (0.03, 0.01), k = 0.01, no error feedback, or a 10 %
    calibration fail this (docs/attitude.md). ~17000 steps: 20-60 s on a loaded host."""
    scenario = parse_scenario(builtin("attitude_slew"), "slew")
    assert scenario.n_steps == 17010
    trajectory = simulate_attitude_in_process(scenario)
    error = pointing_error_deg(trajectory, scenario)
    angle = continuous_rotation_angle_deg(trajectory, scenario)
    t = trajectory["att_time_s"]
    after_one, last = t >= ORBIT_S, t >= t[-1] - ORBIT_S
    print(f"slew: min angle {angle.min():.2f} deg; error at one orbit {error[int(ORBIT_S)]:.2f}, max after it "
          f"{error[after_one].max():.2f}, last orbit {error[last].min():.2f}-{error[last].max():.2f}, final {error[-1]:.2f} deg")
    assert angle[0] == pytest.approx(200.0, abs=1e-6)
    assert angle.min() > 199.9            # the long way would take it down through 180 deg
    assert error[after_one].max() < 10.0
    assert error[last].max() < 5.0
    assert applied_is_commanded_or_zero(trajectory, scenario.can).all()


@pytest.mark.study
def test_pointing_hold_with_the_smoother_stays_within_5_degrees_over_two_orbits():
    """`attitude_pointing_hold` (1 Hz, gtsam smoother through a star-tracker outage, the slew's
    sliding-mode gains, 1 %-calibrated residual dipole): from 3 deg the error stays below 5 deg for
    two orbits and below 4 deg over the second (measured: at most 3.01 deg, 1.02-2.66 deg over the
    second orbit, 2.31 deg at the end). Bounded by the disturbances, not converging to zero (with
    gravity gradient alone the slew settles at 1.1 deg). ~11000 steps with the smoother: 30-90 s."""
    scenario = parse_scenario(builtin("attitude_pointing_hold"), "hold")
    assert scenario.estimator.mode == "smoother" and scenario.n_steps == 11340
    trajectory = simulate_attitude_in_process(scenario)
    error = pointing_error_deg(trajectory, scenario)
    t = trajectory["att_time_s"]
    second = t >= ORBIT_S
    print(f"hold: max {error.max():.2f}, second orbit {error[second].min():.2f}-{error[second].max():.2f}, "
          f"final {error[-1]:.2f} deg")
    assert error[0] == pytest.approx(3.0, abs=1e-3)
    assert error.max() < 5.0
    assert error[second].max() < 4.0
    assert trajectory["att_estimate_valid"].all()
    assert applied_is_commanded_or_zero(trajectory, scenario.can).all()
