"""TVLQR attitude tracker: interface, saturation, hold after the plan, and closed loop on the truth
model (rigid body at 10 Hz, torque m x B from the simulated field) tracking a MILQR slew plan."""
import numpy as np
import pytest

from bench.gnc import quaternion as qt
from bench.gnc.attitude_planning import MagnetorquerAttitudeModel, field_along_orbit_t, gramian_horizon
from bench.gnc.attitude_tracking import AttitudePlan, TvlqrAttitudeTracker, tvlqr_gains_along
from bench.gnc.milqr import GeodesicAttitudeCost, milqr
from bench.gnc.tvlqr import bryson_weights
from bench.plant.attitude import AttitudeSensorSpec, AttitudeSimulation, CircularOrbit, TiltedDipole, magnetorquer_torque_nm

from bench.gnc.attitude_law import AttitudeControlInput

INERTIA = np.diag([0.03, 0.04, 0.02])
LIMIT_AM2 = 0.2
GOAL = qt.exp(np.deg2rad(90.0) * np.array([0.0, 0.0, 1.0]))
ORBIT = CircularOrbit()          # the truth model's default orbit: plan on the plant's own field model


def tracking_weights():
    # Bryson: 1 deg of attitude (Rodrigues tan(0.5 deg)), 0.5 mrad/s of rate, the board's dipole limit
    return bryson_weights([np.tan(np.deg2rad(0.5))] * 3 + [5e-4] * 3, [LIMIT_AM2] * 3)


@pytest.fixture(scope="module")
def slew_plan():
    dt = 20.0
    horizon = gramian_horizon(field_along_orbit_t(ORBIT, TiltedDipole(), 0.0, dt, 300), dt)
    model = MagnetorquerAttitudeModel(INERTIA, field_along_orbit_t(ORBIT, TiltedDipole(), 0.0, dt, horizon.steps), dt)
    cost = GeodesicAttitudeCost(GOAL, np.zeros(3), 0.1, 10.0 * np.eye(3), np.eye(3), 1000.0, 1e7 * np.eye(3))
    x0 = np.array([1.0, 0, 0, 0, 0, 0, 0])
    result = milqr(model, cost, x0, np.zeros((horizon.steps, 3)), -LIMIT_AM2, LIMIT_AM2)
    assert result.info["converged"]
    Q, R = tracking_weights()
    gains = tvlqr_gains_along(model, result.states, result.dipoles_am2, Q, R, 10 * Q)
    return AttitudePlan(0.0, dt, result.states, result.dipoles_am2, gains, plan_id=7)


def control_input(t, q, w, b=np.array([2e-5, 0.0, 1e-5])):
    return AttitudeControlInput(t, q, w, b)


def test_on_plan_state_gets_the_feedforward(slew_plan):
    law = TvlqrAttitudeTracker(slew_plan, LIMIT_AM2)
    k = 10
    x = slew_plan.states[k]
    dipole, info = law.eval(control_input(k * slew_plan.dt_s, x[:4], x[4:]))
    np.testing.assert_allclose(dipole, np.clip(slew_plan.dipoles_am2[k], -LIMIT_AM2, LIMIT_AM2), atol=1e-12)
    assert info["plan_step"] == k and info["phase"] == "in_plan" and info["plan_id"] == 7
    assert info["attitude_error_rad"] < 1e-7


def test_error_gives_gain_times_rodrigues_error_and_saturates_per_axis(slew_plan):
    law = TvlqrAttitudeTracker(slew_plan, LIMIT_AM2)
    k = 5
    x = slew_plan.states[k]
    phi = np.array([1e-3, -2e-3, 0.5e-3])
    q = qt.multiply(x[:4], qt.cayley(phi))
    dipole, _ = law.eval(control_input(k * slew_plan.dt_s, q, x[4:]))
    expected = slew_plan.dipoles_am2[k] - slew_plan.gains[k] @ np.concatenate([phi, np.zeros(3)])
    np.testing.assert_allclose(dipole, np.clip(expected, -LIMIT_AM2, LIMIT_AM2), atol=1e-12)
    big, info = law.eval(control_input(k * slew_plan.dt_s, qt.multiply(x[:4], qt.exp([0.0, 0.0, 1.0])), x[4:] + 0.05))
    assert np.all(np.abs(big) <= LIMIT_AM2) and info["saturated"]


def test_after_the_plan_it_holds_the_final_state_with_the_last_gain(slew_plan):
    law = TvlqrAttitudeTracker(slew_plan, LIMIT_AM2)
    x_end = slew_plan.states[-1]
    phi = np.array([0.0, 1e-3, 0.0])
    dipole, info = law.eval(control_input(slew_plan.end_time_s + 500.0, qt.multiply(x_end[:4], qt.cayley(phi)), x_end[4:]))
    assert info["phase"] == "after_plan"
    np.testing.assert_allclose(dipole, np.clip(-slew_plan.gains[-1] @ np.concatenate([phi, np.zeros(3)]), -LIMIT_AM2, LIMIT_AM2))


def test_non_finite_input_is_named(slew_plan):
    law = TvlqrAttitudeTracker(slew_plan, LIMIT_AM2)
    dipole, info = law.eval(control_input(0.0, qt.IDENTITY_WXYZ, np.array([np.nan, 0, 0])))
    assert info["bad_input"] == "omega_radps" and np.all(dipole == 0.0)
    dipole, info = law.eval(control_input(0.0, qt.IDENTITY_WXYZ, np.zeros(3), np.array([np.inf, 0, 0])))
    assert info["bad_input"] == "field_body_t" and np.all(dipole == 0.0)
    with pytest.raises(ValueError, match="plan shapes"):
        AttitudePlan(0.0, 1.0, np.zeros((3, 7)), np.zeros((3, 3)), np.zeros((3, 3, 6)))


def test_closed_loop_on_truth_model_ends_within_half_a_degree(slew_plan):
    """Truth model stepped (and the law evaluated) at 2 Hz to keep the test short (the 10 Hz cost is
    in benchmarks/bench_milqr.py); initial attitude 3 deg off the plan; truth-state feedback."""
    q0 = qt.multiply(slew_plan.states[0, :4], qt.exp(np.deg2rad(3.0) * qt.normalize(np.array([1.0, -1.0, 0.5]))))
    sensors = AttitudeSensorSpec(gyro_rate_hz=2.0)
    sim = AttitudeSimulation(INERTIA, q0, np.zeros(3), sensors=sensors, orbit=ORBIT, seed=3)
    law = TvlqrAttitudeTracker(slew_plan, LIMIT_AM2)
    end_s = slew_plan.end_time_s + 120.0
    while sim.time_s < end_s:
        field_body = sim.field_body_t()
        dipole, _ = law.eval(control_input(sim.time_s, sim.q_wxyz, sim.omega_body_radps, field_body))
        sim.step(magnetorquer_torque_nm(dipole, field_body))
    closed_deg = np.rad2deg(qt.angle_between_rad(sim.q_wxyz, GOAL))
    assert closed_deg < 0.5
    # open loop (feed-forward only) from the same start for contrast: feedback is what gets it there
    sim_ol = AttitudeSimulation(INERTIA, q0, np.zeros(3), sensors=sensors, orbit=ORBIT, seed=3)
    while sim_ol.time_s < slew_plan.end_time_s:
        k = min(int(sim_ol.time_s / slew_plan.dt_s), slew_plan.steps - 1)
        sim_ol.step(magnetorquer_torque_nm(slew_plan.dipoles_am2[k], sim_ol.field_body_t()))
    open_deg = np.rad2deg(qt.angle_between_rad(sim_ol.q_wxyz, GOAL))
    print(f"truth feedback: final pointing error {closed_deg:.3f} deg; feed-forward only {open_deg:.2f} deg")
    assert open_deg > closed_deg


def test_closed_loop_with_the_smoother_in_the_loop_ends_within_two_degrees(slew_plan):
    """Plant with noisy gyro (biased), magnetometer and star tracker at 2 Hz / 1 s / 10 s; the gtsam
    attitude smoother estimates attitude and gyro bias; the law sees the estimate propagated with
    bias-corrected gyro between keyframes and the estimated rate (gyro minus bias)."""
    from bench.estimator.attitude import AttitudeSmoother
    from bench.config.estimator import AttitudeSmootherConfig

    sensors = AttitudeSensorSpec(gyro_rate_hz=2.0)
    sim = AttitudeSimulation(INERTIA, slew_plan.states[0, :4], np.zeros(3), sensors=sensors, orbit=ORBIT, seed=5)
    smoother = AttitudeSmoother(AttitudeSmootherConfig())
    estimate = smoother.update(0, 0.0, star_tracker_wxyz=sim.q_wxyz)   # a first star-tracker fix at t = 0
    q_est, bias, omega_est = estimate.q_wxyz, estimate.gyro_bias_radps, np.zeros(3)
    law = TvlqrAttitudeTracker(slew_plan, LIMIT_AM2)
    keyframe, dipole = 0, np.zeros(3)
    end_s = slew_plan.end_time_s + 120.0
    while sim.time_s < end_s:
        field_body_est = qt.rotation_matrix(q_est).T @ TiltedDipole().field_t(ORBIT.position_m(sim.time_s), sim.time_s)
        dipole, _ = law.eval(control_input(sim.time_s, q_est, omega_est, field_body_est))
        sample = sim.step(magnetorquer_torque_nm(dipole, sim.field_body_t()))
        smoother.add_gyro(sample.gyro_radps, sim.dt_s)
        omega_est = sample.gyro_radps - bias
        q_est = qt.multiply(q_est, qt.exp(omega_est * sim.dt_s))
        if sample.magnetometer_t is not None or sample.star_tracker_wxyz is not None:
            keyframe += 1
            r = smoother.update(keyframe, sample.time_s, sample.magnetometer_t, sample.field_inertial_t,
                                sample.star_tracker_wxyz)
            q_est, bias = r.q_wxyz, r.gyro_bias_radps
            omega_est = sample.gyro_radps - bias
    final_error_deg = np.rad2deg(qt.angle_between_rad(sim.q_wxyz, GOAL))
    print(f"smoother in the loop: final pointing error {final_error_deg:.3f} deg")
    assert smoother.failed_updates == 0
    assert final_error_deg < 2.0
