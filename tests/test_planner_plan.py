"""Plan message round trip and the pure planning step (short horizon, coarse steps to stay quick)."""
import numpy as np
import pytest

from bench.bus.schemas import MalformedMessage, decode, encode, header
from bench.gnc import quaternion as qt
from bench.bus.plan_message import AttitudePlanMessage, from_message, to_message
from bench.planner.plan import PlannerConfig, plan_from_estimate
from bench.plant.attitude import CircularOrbit, TiltedDipole


@pytest.fixture(scope="module")
def planned():
    config = PlannerConfig(inertia_kgm2=np.diag([0.03, 0.04, 0.02]), dt_s=120.0)
    target = qt.exp(np.deg2rad(30.0) * np.array([1.0, 0.0, 0.0]))
    plan, info = plan_from_estimate(300.0, qt.IDENTITY_WXYZ, np.zeros(3), target, CircularOrbit(), TiltedDipole(),
                                    config, plan_id=4)
    return plan, info, target


def test_plan_from_estimate_reaches_the_target_over_the_gramian_horizon(planned):
    plan, info, target = planned
    assert info["horizon_reached"] and info["gramian_condition_number"] <= 3.0
    assert plan.steps * plan.dt_s == pytest.approx(info["horizon_s"])
    assert plan.start_time_s == 300.0 and plan.plan_id == 4
    assert info["converged"], info["stop_reason"]
    assert qt.angle_between_rad(plan.states[-1, :4], target) < np.deg2rad(1.0)
    assert np.all(np.abs(plan.dipoles_am2) <= 0.2)


def test_message_round_trip_and_rejects_inconsistent_lengths(planned):
    plan, info, target = planned
    msg = to_message(plan, header("run", 3, 300.0), target, info)
    back = from_message(decode(encode(msg), AttitudePlanMessage))
    np.testing.assert_array_equal(back.states, plan.states)
    np.testing.assert_array_equal(back.gains, plan.gains)
    assert back.dt_s == plan.dt_s and back.plan_id == plan.plan_id
    short = to_message(plan, header("run", 3, 300.0), target, info)
    short.states = short.states[:-1]
    with pytest.raises(ValueError, match="states"):
        from_message(decode(encode(short), AttitudePlanMessage))
    with pytest.raises(MalformedMessage):
        decode(encode(msg).replace(b'"dt_s":120.0', b'"dt_s":-1.0'), AttitudePlanMessage)


def test_plan_ends_with_a_designed_hold_of_the_target_after_the_arrival(planned):
    """hold_after_arrival_s: the target at rest with zero dipole after the MILQR arrival, TVLQR gains
    along it (they follow the field: not the last manoeuvre gain repeated), carried by the message."""
    from dataclasses import replace

    plan, info, target = planned
    config = PlannerConfig(inertia_kgm2=np.diag([0.03, 0.04, 0.02]), dt_s=120.0, hold_after_arrival_s=1200.0)
    held, _ = plan_from_estimate(300.0, qt.IDENTITY_WXYZ, np.zeros(3), target, CircularOrbit(), TiltedDipole(),
                                 config, plan_id=4)
    assert held.hold_steps == 10 and held.steps == plan.steps + 10
    assert held.arrival_time_s == pytest.approx(plan.end_time_s) and held.end_time_s == pytest.approx(plan.end_time_s + 1200)
    np.testing.assert_array_equal(held.states[:plan.steps + 1], plan.states)       # the same manoeuvre
    np.testing.assert_array_equal(held.dipoles_am2[plan.steps:], 0.0)
    assert all(qt.angle_between_rad(q, target) < 1e-12 for q in held.states[plan.steps + 1:, :4])
    np.testing.assert_array_equal(held.states[plan.steps + 1:, 4:], 0.0)
    hold_gains = held.gains[plan.steps:]
    assert np.all(np.isfinite(hold_gains)) and np.abs(hold_gains[0] - hold_gains[4]).max() > 1e-3 * np.abs(hold_gains).max()
    back = from_message(decode(encode(to_message(held, header("run", 3, 300.0), target, info)), AttitudePlanMessage))
    assert back.hold_steps == 10 and back.arrival_time_s == held.arrival_time_s
    with pytest.raises(ValueError, match="hold_steps"):
        replace(held, hold_steps=held.steps + 1)


def test_a_hold_plan_is_the_manoeuvre_plans_hold_from_its_arrival_and_pulls_an_error_in():
    """horizon_steps=0 (a scheduled replan once arrived): no manoeuvre, the target at rest from now.
    Its gains equal those of a manoeuvre plan's hold over the same steps (same field, same end),
    and on the planning model they take a 3 deg error at rest down."""
    from bench.gnc.attitude_planning import MagnetorquerAttitudeModel, field_along_orbit_t
    from bench.gnc.attitude_tracking import TvlqrAttitudeTracker
    from bench.gnc.attitude_law import AttitudeControlInput

    target = qt.exp(np.deg2rad(30.0) * np.array([1.0, 0.0, 0.0]))
    config = PlannerConfig(inertia_kgm2=np.diag([0.03, 0.04, 0.02]), dt_s=120.0, hold_after_arrival_s=1200.0)
    held, _ = plan_from_estimate(300.0, qt.IDENTITY_WXYZ, np.zeros(3), target, CircularOrbit(), TiltedDipole(), config)
    manoeuvre_steps = held.steps - held.hold_steps
    hold, hold_info = plan_from_estimate(held.arrival_time_s, qt.IDENTITY_WXYZ, np.zeros(3), target, CircularOrbit(),
                                         TiltedDipole(), config, plan_id=5, horizon_steps=0)
    assert hold_info["stop_reason"] == "hold" and hold.plan_id == 5
    assert hold.hold_steps == hold.steps == 10 and hold.arrival_time_s == hold.start_time_s == held.arrival_time_s
    np.testing.assert_array_equal(hold.dipoles_am2, 0.0)
    assert all(qt.angle_between_rad(q, target) < 1e-12 for q in hold.states[:, :4])
    # the first hold step of the manoeuvre plan starts from MILQR's end state, not the target itself
    np.testing.assert_allclose(hold.gains[1:], held.gains[manoeuvre_steps + 1:], rtol=1e-9, atol=1e-12)
    back = from_message(decode(encode(to_message(hold, header("run", 9, hold.start_time_s), target, hold_info)),
                               AttitudePlanMessage))
    assert back.hold_steps == back.steps == 10 and back.arrival_time_s == hold.start_time_s
    # 3 deg off at rest, the tracker at every plan step on the planning model (its own discretisation)
    field = field_along_orbit_t(CircularOrbit(), TiltedDipole(), hold.start_time_s, hold.dt_s, hold.steps)
    model = MagnetorquerAttitudeModel(config.inertia_kgm2, field, hold.dt_s)
    tracker = TvlqrAttitudeTracker(hold, config.dipole_limit_am2)
    x = np.concatenate([qt.multiply(target, qt.exp(np.deg2rad(3.0) * np.array([0.6, -0.48, 0.64]))), np.zeros(3)])
    start_deg = np.rad2deg(qt.angle_between_rad(x[:4], target))
    for k in range(hold.steps):
        dipole, _ = tracker.eval(AttitudeControlInput(hold.start_time_s + k * hold.dt_s, x[:4], x[4:], np.ones(3)))
        x = model.step(x, dipole, k)
    assert start_deg == pytest.approx(3.0, abs=0.01)
    assert np.rad2deg(qt.angle_between_rad(x[:4], target)) < 0.5 * start_deg
