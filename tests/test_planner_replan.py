"""Issue 12: a replan keeps the current plan's arrival however little of it is left (a late
tracking-error replan that started a fresh Gramian horizon ended seed 4 of attitude_slew_milqr 106 deg
off the target). The seed sweep itself is benchmarks/bench_milqr_seed_sweep.py."""
import msgspec
import numpy as np
import pytest

from bench.gnc.attitude_tracking import AttitudePlan
from bench.planner.planner import AttitudePlanner
from bench.report.attitude_metrics import pointing_error_deg
from bench.scenario import load_scenario
from bench.sim import simulate_attitude_in_process


def plan_with_hold(start_s: float, dt_s: float, steps: int, hold_steps: int) -> AttitudePlan:
    states = np.tile([1.0, 0, 0, 0, 0, 0, 0], (steps + 1, 1))
    return AttitudePlan(start_s, dt_s, states, np.zeros((steps, 3)), np.zeros((steps, 3, 6)), 1, hold_steps)


def test_a_replan_keeps_the_arrival_to_its_last_step_and_once_arrived_renews_the_hold():
    planner = AttitudePlanner(load_scenario("attitude_slew_milqr"))
    dt_s = planner.config.dt_s
    assert planner.horizon_steps(30.0) is None                      # the first plan: the Gramian horizon
    planner.plan = plan_with_hold(930.0, dt_s, steps=62, hold_steps=30)
    assert planner.plan.arrival_time_s == 1570.0
    assert planner.horizon_steps(930.0) == 32
    assert planner.horizon_steps(1473.0) == 5                       # seed 4's replan: 97 s left -> 1573 s
    assert planner.horizon_steps(1569.0) == 1                       # never a fresh horizon before the arrival
    # arrived: the schedule renews the hold (no manoeuvre), the tracking-error bound plans afresh
    assert planner.horizon_steps(1570.0) == 0 and planner.horizon_steps(1700.0, "schedule") == 0
    assert planner.horizon_steps(1700.0, "tracking_error") is None


@pytest.mark.timeout(600)
def test_late_tracking_error_replan_of_seed_4_keeps_the_arrival_and_ends_near_the_target():
    """Seed 4 of attitude_slew_milqr in process (~20-60 s): the tracker, saturated, leaves the plan
    by 10 deg 97 s before the arrival. Before: a fresh plan arriving at 3693 s, 106 deg off at 1800 s."""
    s = load_scenario("attitude_slew_milqr")
    s = msgspec.structs.replace(s, run=msgspec.structs.replace(s.run, seed=4))
    t = simulate_attitude_in_process(s)
    reasons = list(t["planner_plan_reason"])
    assert "tracking_error" in reasons, reasons                      # the case this test is about happened
    late = reasons.index("tracking_error")
    assert t["planner_plan_time_s"][late] > t["planner_arrival_time_s"][late - 1] - 300.0
    # the replan arrives when its predecessor did (to the plan step), not a Gramian horizon later
    assert abs(t["planner_arrival_time_s"][late] - t["planner_arrival_time_s"][late - 1]) <= s.attitude_control.planner.plan_step_s / 2
    # Measured 1.20 deg at the end of the plan's hold (2170 s): 3.2 deg at the arrival, 2.2 deg at
    # 1800 s; the hold after a late, saturated arrival needs its few hundred seconds
    # (docs/attitude_planning.md, seed sweep).
    error = pointing_error_deg(t, s)
    assert error[-1] < 2.0
