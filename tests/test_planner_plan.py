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
        replace(held, hold_steps=held.steps)
