"""Deadline monitor, fallbacks, plant-side deadline and the stress injector.

Cycle times are driven by an injected clock wherever a number is checked, so nothing here
depends on how fast this machine is; the one real-clock test injects delays five times the
budget and counts them.
"""
from __future__ import annotations

import numpy as np
import pytest

from bench.bus.schemas import DeadlineEvent, decode, encode, header
from bench.config.controller import DeadlineConfig, StressConfig
from bench.controller.deadline import DeadlineMonitor, StressInjector, lqr_fallback_law
from bench.runtime.deadline import PlantCommandDeadline
from bench.scenario import ScenarioError, parse_scenario

BUDGET_S = 0.010


class FakeClock:
    """Monotonic nanoseconds that only move when a fake controller says so."""

    def __init__(self):
        self.now_ns = 1_000_000_000

    def __call__(self) -> int:
        return self.now_ns

    def controller(self, cycle_times_s: list[float], plans: bool = False):
        """A controller whose i-th eval takes cycle_times_s[i] and returns u = [i, 0, 0]."""
        calls = iter(range(len(cycle_times_s)))

        def evaluate(x):
            i = next(calls)
            self.now_ns += int(cycle_times_s[i] * 1e9)
            info = {"ctrl_feas": True, "solve_time": cycle_times_s[i], "iterations": 10, "status": "solved"}
            if plans:
                info["u_plan"] = [[i, k, 0.0] for k in range(3)]
            return np.array([float(i), 0.0, 0.0]), info

        return evaluate


def run(monitor: DeadlineMonitor, evaluate, n: int):
    return [monitor.run_cycle(np.zeros(6), evaluate) for _ in range(n)]


def test_misses_worst_cycle_and_streaks_are_counted():
    clock = FakeClock()
    times_s = [0.002, 0.015, 0.020, 0.001, 0.030, 0.004]
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S), clock_ns=clock)
    outcomes = run(monitor, clock.controller(times_s), len(times_s))

    assert [o.missed for o in outcomes] == [False, True, True, False, True, False]
    assert [o.consecutive_misses for o in outcomes] == [0, 1, 2, 0, 1, 0]
    assert [o.cycle_time_s for o in outcomes] == pytest.approx(times_s)
    summary = monitor.summary()
    assert summary["cycles"] == 6 and summary["misses"] == 3
    assert summary["max_consecutive_misses"] == 2
    assert summary["worst_cycle_time_s"] == pytest.approx(0.030)
    assert summary["fallbacks_applied"] == {"hold": 3}
    # Events: every miss, and the first on-time cycle that ends a streak.
    assert [o.cycle_index for o in outcomes if o.has_event] == [1, 2, 3, 4, 5]


def test_hold_fallback_repeats_the_last_command_sent():
    clock = FakeClock()
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S, fallback="hold"), clock_ns=clock)
    outcomes = run(monitor, clock.controller([0.001, 0.001, 0.050, 0.050, 0.001]), 5)
    assert [o.thrust_n[0] for o in outcomes] == [0.0, 1.0, 1.0, 1.0, 4.0]
    assert [o.fallback for o in outcomes] == [None, None, "hold", "hold", None]


def test_hold_before_any_command_is_zero_thrust():
    clock = FakeClock()
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S), clock_ns=clock)
    (outcome,) = run(monitor, clock.controller([0.5]), 1)
    assert outcome.missed and np.array_equal(outcome.thrust_n, np.zeros(3))


def test_shifted_plan_replays_the_last_on_time_plan_then_holds():
    clock = FakeClock()
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S, fallback="shifted_plan"), clock_ns=clock)
    outcomes = run(monitor, clock.controller([0.001, 0.001, 0.05, 0.05, 0.05, 0.001], plans=True), 6)
    # Plan of cycle 1 is [[1,0,0],[1,1,0],[1,2,0]]: misses replay entries 1 and 2, then hold.
    assert [o.thrust_n.tolist() for o in outcomes[2:5]] == [[1, 1, 0], [1, 2, 0], [1, 2, 0]]
    assert [o.fallback for o in outcomes[2:5]] == ["shifted_plan", "shifted_plan", "hold"]
    assert outcomes[5].fallback is None and outcomes[5].thrust_n[0] == 5.0


def test_shifted_plan_is_shifted_by_the_cycles_elapsed_since_the_plan_not_by_the_misses():
    """Issue 27: an on-time cycle without a plan (an infeasible MPC cycle publishes none) between
    the plan and the miss still moves time on: the miss replays the plan's entry for the number of
    cycles since the plan was made."""
    clock = FakeClock()
    times_s = [0.001, 0.001, 0.05, 0.001, 0.05, 0.05]
    plan_cycles = {0}                      # cycle 0 plans; cycle 1 and 3 are on time without one
    calls = iter(range(len(times_s)))

    def evaluate(x):
        i = next(calls)
        clock.now_ns += int(times_s[i] * 1e9)
        info = {"ctrl_feas": i in plan_cycles, "solve_time": times_s[i], "iterations": 10, "status": "s"}
        if i in plan_cycles:
            info["u_plan"] = [[i, k, 0.0] for k in range(5)]
        return np.array([float(i), 0.0, 0.0]), info

    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S, fallback="shifted_plan"), clock_ns=clock)
    outcomes = run(monitor, evaluate, len(times_s))
    assert [o.missed for o in outcomes] == [False, False, True, False, True, True]
    # Plan of cycle 0 is [[0,k,0] for k in 0..4]: cycle c replays entry c (the count of misses
    # would give entries 1, 2, 3), and past the end (cycle 5 of a 5-entry plan) it holds.
    assert [o.thrust_n.tolist() for o in outcomes[2:5]] == [[0, 2, 0], [3, 0, 0], [0, 4, 0]]
    assert [o.fallback for o in outcomes] == [None, None, "shifted_plan", None, "shifted_plan", "hold"]
    assert outcomes[5].thrust_n.tolist() == [0, 4, 0]


def test_shifted_plan_counts_the_steps_a_real_time_controller_passed_over():
    """A real-time controller acts on the newest estimate (bench/controller/newest.py): cycles for
    steps 0, 1, 4, 5 after it passed over the estimates of steps 2 and 3. A miss at step 4 replays
    the entry of the plan of step 1 for step 4 (entry 3), not for the second cycle since (entry 1)."""
    clock = FakeClock()
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S, fallback="shifted_plan"), clock_ns=clock)
    evaluate = clock.controller([0.001, 0.001, 0.05, 0.05], plans=False)

    def planning(x):
        u, info = evaluate(x)
        info["u_plan"] = [[u[0], k, 0.0] for k in range(5)]
        return u, info

    outcomes = [monitor.run_cycle(np.zeros(6), planning, step=step) for step in (0, 1, 4, 5)]
    assert [o.fallback for o in outcomes] == [None, None, "shifted_plan", "shifted_plan"]
    assert [o.thrust_n.tolist() for o in outcomes[2:]] == [[1, 3, 0], [1, 4, 0]]


def test_lqr_fallback_uses_the_scenarios_lqr_gain():
    scenario = parse_scenario({"name": "t", "controller": {"deadline": {"budget_s": BUDGET_S, "fallback": "lqr"}}})
    params = scenario.params()
    law = lqr_fallback_law(scenario.controller, params)
    clock = FakeClock()
    monitor = DeadlineMonitor(scenario.controller.deadline, lqr_law=law, clock_ns=clock)
    x_scaled = np.array(params.scaling) * scenario.initial_state_m_mps()
    (outcome,) = [monitor.run_cycle(x_scaled, clock.controller([0.05]))]
    assert outcome.fallback == "lqr"
    np.testing.assert_allclose(outcome.thrust_n, law(x_scaled))
    assert np.linalg.norm(outcome.thrust_n) > 0


def test_lqr_fallback_without_a_law_is_refused():
    with pytest.raises(ValueError, match="lqr"):
        DeadlineMonitor(DeadlineConfig(fallback="lqr"))


def test_deadline_event_round_trips_through_the_schema():
    clock = FakeClock()
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S), clock_ns=clock)
    (outcome,) = run(monitor, clock.controller([0.02]), 1)
    event = outcome.deadline_event(header("run1", 7, 4200.0), "controller")
    back = decode(encode(event), DeadlineEvent)
    assert back.missed and back.consecutive_misses == 1 and back.fallback == "hold"
    assert back.cycle_time_s == pytest.approx(0.02) and back.budget_s == BUDGET_S


def test_stress_schedule_lists_and_every_nth():
    stress = StressConfig(extra_cycle_time_s=0.05, cycles=[0, 4], every_nth_cycle=3)
    assert [i for i in range(10) if stress.is_stressed(i)] == [0, 2, 4, 5, 8]
    assert stress.stressed_count(10) == 5
    assert StressConfig(cycles=[1]).stressed_count(10) == 0   # no extra time, no stress


def test_stress_only_acts_in_the_process_it_names():
    stress = StressConfig(process="estimator", extra_cycle_time_s=0.05, cycles=[0])
    assert not StressInjector(stress, "controller").apply(0)


def test_injected_delays_far_over_budget_are_each_a_miss_with_fallback():
    """Real clock: 100 ms busy loops against a 20 ms budget, on every 3rd of 9 cycles."""
    stress = StressConfig(extra_cycle_time_s=0.1, every_nth_cycle=3, kind="busy")
    config = DeadlineConfig(budget_s=0.02, fallback="hold", stress=stress)
    monitor = DeadlineMonitor(config, stress=StressInjector(stress, "controller"))
    law = lambda x: (np.ones(3), {"ctrl_feas": True, "solve_time": 0.0, "iterations": 0})
    outcomes = [monitor.run_cycle(np.zeros(6), law) for _ in range(9)]
    assert [o.cycle_index for o in outcomes if o.missed] == [2, 5, 8]
    assert all(o.fallback == "hold" for o in outcomes if o.missed)
    assert monitor.summary()["misses"] == stress.stressed_count(9) == 3
    assert monitor.summary()["stress_injected_cycles"] == 3


def test_plant_side_deadline_counts_steps_without_their_command():
    plant = PlantCommandDeadline(step_period_s=0.1)
    plant.command_arrived(0)
    plant.command_arrived(2)
    outcomes = [plant.check(k, waited_s=0.1) for k in range(4)]
    assert [o.missed for o in outcomes] == [False, True, False, True]
    assert plant.counter.misses == 2 and outcomes[1].fallback == "hold"


def test_stress_in_a_process_that_does_not_apply_it_is_refused():
    with pytest.raises(ScenarioError, match="controller.deadline.stress.process"):
        parse_scenario({"name": "t", "controller": {"deadline": {"stress": {"process": "estimator"}}}})


def test_bad_deadline_section_names_the_field():
    with pytest.raises(ScenarioError, match="controller.deadline.fallback"):
        parse_scenario({"name": "t", "controller": {"deadline": {"fallback": "pray"}}})


def test_lock_step_counts_a_miss_but_keeps_the_late_result():
    # Lock-step's plant waits for every command; substituting a fallback there would make the
    # trajectory depend on how loaded the machine was.
    clock = FakeClock()
    times_s = [0.002, 0.015, 0.001]
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=BUDGET_S), clock_ns=clock, apply_fallback=False)
    outcomes = run(monitor, clock.controller(times_s), len(times_s))
    assert [o.missed for o in outcomes] == [False, True, False]
    assert [o.fallback for o in outcomes] == [None, None, None]
    assert [o.thrust_n[0] for o in outcomes] == [0.0, 1.0, 2.0]
    assert monitor.summary()["misses"] == 1 and monitor.summary()["fallbacks_applied"] == {}


def test_real_time_run_with_a_50ms_solver_against_a_10ms_budget_sends_every_command_on_time(tmp_path):
    """Issue 17, with the processes running: the stress makes every solve in the controller's
    worker 50 ms; the command leaves within budget + 5 ms (loose; the benchmark has percentiles)."""
    import json

    from conftest import run_bench_cli

    scenario = tmp_path / "slow_solver.toml"
    scenario.write_text("""name = "slow_solver"
[run]
mode = "real-time"
steps = 200
[controller]
type = "mpc"
[controller.deadline]
budget_s = 0.010
fallback = "shifted_plan"
[controller.deadline.stress]
process = "controller"
extra_cycle_time_s = 0.050
every_nth_cycle = 1
kind = "sleep"
""")
    result = run_bench_cli("run", str(scenario), "--run-id", "slow", "--runs-dir", str(tmp_path), "--no-progress",
                           "--no-report")
    assert result.returncode == 0, result.stderr + result.stdout
    summary = json.loads((tmp_path / "slow" / "deadline_controller.json").read_text())
    worker = summary["solver_worker"]
    assert summary["cycles"] >= 190 and summary["misses"] == summary["cycles"]
    # The wait for the worker ends at the deadline; on a busy host the OS may run the controller
    # again later (measured up to 5 ms with both cores busy): that share is the host's, reported
    # apart, and the controller's own share must stay within the margin.
    assert summary["cycle_time_less_host_p99_s"] <= 0.010 + 0.005, summary
    assert summary["cycle_time_p99_s"] <= summary["cycle_time_less_host_p99_s"] + summary["host_wake_late_max_s"] + 1e-9
    assert worker["on_time"] == 0 and worker["late_results"] >= worker["timeouts"] - 1 and worker["restarts"] == 0
    assert set(summary["fallbacks_applied"]) <= {"shifted_plan", "lqr"}
