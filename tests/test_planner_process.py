"""Issue 12 wiring: the planner process, the "tvlqr_plan" law in the controller, bad plan messages,
the shifted-plan fallback replaying the plan's feed-forward, and a planned slew as processes."""
import json
import threading

import numpy as np
import pytest

from bench.bus import data_auth, keys
from bench.bus.schemas import encode, header
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.config.controller import DeadlineConfig
from bench.controller.deadline import DeadlineMonitor
from bench.controller.plan_tracking import PlanInbox, PlanTrackingLaw
from bench.gnc.attitude_law import AttitudeControlInput
from bench.gnc.attitude_tracking import AttitudePlan, TvlqrAttitudeTracker
from bench.launcher import nodes_for
from bench.bus.plan_message import to_message
from bench.controller.plan_tracking import replan_reason
from bench.report.attitude_metrics import pointing_error_deg
from bench.report.rundata import load_run
from bench.scenario import load_scenario
from bench.scenario import scenario_to_toml_dict
from bench.sim import simulate_attitude_in_process
from conftest import run_bench_cli

RUN_TIMEOUT_S = 900


def small_plan(plan_id=0, start_s=0.0, dt_s=10.0, steps=3):
    states = np.zeros((steps + 1, 7))
    states[:, 0] = 1.0
    dipoles = 0.01 * np.arange(1, 3 * steps + 1, dtype=float).reshape(steps, 3)
    return AttitudePlan(start_s, dt_s, states, dipoles, np.zeros((steps, 3, 6)), plan_id)


def plan_message(plan, seq=4, run_id="r"):
    info = {"stop_reason": "feedforward_small", "iterations": 3, "cost": 1.0, "wall_time_s": 0.1}
    return to_message(plan, header(run_id, seq, plan.start_time_s), [1.0, 0.0, 0.0, 0.0], info)


def test_inbox_counts_and_ignores_inconsistent_or_non_finite_plans():
    inbox = PlanInbox()
    good = plan_message(small_plan())
    short = plan_message(small_plan())
    short.states = short.states[:-1]                   # N states for N dipoles
    nan = plan_message(small_plan())
    nan.dipoles_am2 = [[np.nan, 0.0, 0.0]] + nan.dipoles_am2[1:]
    assert "states" in inbox.add(short) and "non-finite" in inbox.add(nan)
    assert inbox.newest() is None and inbox.rejected == 2
    assert inbox.add(good) is None and inbox.newest().plan_id == 0 and inbox.received == 1
    assert inbox.wait_for(4, timeout_s=0.01) is not None and inbox.wait_for(5, timeout_s=0.01) is None


def test_law_commands_zero_before_the_first_plan_then_tracks_it():
    law = PlanTrackingLaw(0.2, control_period_s=1.0, feedforward_cycles=40)
    x = AttitudeControlInput(0.0, np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([2e-5, 0, 0]))
    dipole, info = law.eval(x)
    assert not np.any(dipole) and info["waiting_for_plan"] and law.cycles_without_plan == 1
    plan = small_plan()
    law.set_plan(plan)
    dipole, info = law.eval(x)
    np.testing.assert_array_equal(dipole, plan.dipoles_am2[0])          # on the plan: the feed-forward
    # u_plan: the planned dipole at t, t + 1 s, ...: 10 cycles per plan step, zero after the plan's end
    np.testing.assert_array_equal(info["u_plan"][[0, 9, 10, 29]], plan.dipoles_am2[[0, 0, 1, 2]])
    assert info["u_plan"].shape == (40, 3) and not np.any(info["u_plan"][30:])


def test_shifted_plan_fallback_replays_the_trackers_feed_forward_on_a_miss():
    plan = small_plan(dt_s=2.0)
    tracker = TvlqrAttitudeTracker(plan, 0.2, control_period_s=1.0, feedforward_cycles=6)
    clock = iter(range(0, 10**12, 10**9))       # every clock read 1 s later: each cycle takes 1 s
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=0.5, fallback="shifted_plan"), clock_ns=lambda: next(clock))
    monitor.budget_s = 1.5                      # first cycle (1 s) on time, the next ones late
    x0 = AttitudeControlInput(0.0, np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([2e-5, 0, 0]))
    first = monitor.run_cycle(x0, tracker.eval)
    assert first.fallback is None
    monitor.budget_s = 0.5
    for cycle in (1, 2, 3):
        x = AttitudeControlInput(float(cycle), x0.q_wxyz, x0.omega_radps, x0.field_body_t)
        outcome = monitor.run_cycle(x, tracker.eval)
        assert outcome.fallback == "shifted_plan"
        # the plan's dipole at t = cycle s (2 s plan steps), as planned at cycle 0
        np.testing.assert_array_equal(outcome.thrust_n, plan.dipoles_am2[cycle // 2])


def test_replan_rule_first_schedule_and_tracking_error():
    settings = load_scenario("attitude_slew_milqr").attitude_control.planner
    q = np.array([1.0, 0, 0, 0])
    plan = small_plan(dt_s=100.0)
    assert settings.first_plan_after_s == 30.0                     # the smoother's bias converges first
    assert replan_reason(29.0, True, q, None, settings) is None
    assert replan_reason(30.0, True, q, None, settings) == "first_plan"
    assert replan_reason(30.0, False, q, None, settings) is None
    assert replan_reason(0.0, True, [np.nan, 0, 0, 1], None, settings) is None
    assert replan_reason(settings.replan_period_s, True, q, plan, settings) == "schedule"
    off = np.array([np.cos(np.deg2rad(6)), np.sin(np.deg2rad(6)), 0, 0])    # 12 deg off the plan
    assert replan_reason(settings.min_replan_interval_s, True, off, plan, settings) == "tracking_error"
    assert replan_reason(settings.min_replan_interval_s - 1, True, off, plan, settings) is None


def test_launcher_starts_the_planner_only_for_the_tracker():
    assert "planner" in nodes_for(load_scenario("attitude_slew_milqr"))
    assert "planner" not in nodes_for(load_scenario("attitude_slew"))


# --- the planned slew as processes -------------------------------------------------------------
def _inject_bad_plans(port: int, run_id: str, stop: threading.Event, sent: list, run_dir) -> None:
    """From outside the loop: a plan whose arrays do not fit, and one with a NaN (JSON null),
    signed with the run's data key (its bus.key): the plan checks are what is tested here (without
    the key they would be dropped before, tests/test_forged_data.py)."""
    key_path = run_dir / data_auth.KEY_FILE
    while not key_path.is_file() or not key_path.read_text().strip():
        if stop.wait(0.05):
            return
    signer = data_auth.Signer(data_auth.read_key_file(key_path), "injector")
    session = open_session(SessionOptions(connect=(loopback_endpoint(port),)))
    try:
        publisher = session.declare_publisher(keys.key(run_id, keys.PLAN_ATTITUDE))
        inconsistent = plan_message(small_plan(plan_id=99), seq=3, run_id=run_id)
        inconsistent.gains = inconsistent.gains[:-1]
        non_finite = plan_message(small_plan(plan_id=98), seq=3, run_id=run_id)
        non_finite.dipoles_am2 = [[float("nan"), 0.0, 0.0]] + non_finite.dipoles_am2[1:]
        while not stop.wait(1.0):
            for payload in (encode(inconsistent), encode(non_finite)):
                publisher.put(payload, attachment=signer(str(publisher.key_expr), payload))
            sent.append(2)
    finally:
        session.close()


@pytest.fixture(scope="module")
def slew_run(tmp_path_factory):
    runs = tmp_path_factory.mktemp("planner_runs")
    port, run_id = free_loopback_port(), "slew_milqr"
    stop, sent = threading.Event(), []
    injector = threading.Thread(target=_inject_bad_plans, args=(port, run_id, stop, sent, runs / run_id), daemon=True)
    injector.start()
    try:
        result = run_bench_cli("run", "attitude_slew_milqr", "--run-id", run_id, "--runs-dir", str(runs),
                               "--no-progress", "--no-report", "--port", str(port), timeout_s=RUN_TIMEOUT_S)
    finally:
        stop.set()
        injector.join(timeout=10)
    assert result.returncode == 0, result.stderr + result.stdout
    return load_run(runs / run_id), sum(sent)


@pytest.mark.timeout(2 * RUN_TIMEOUT_S)
def test_planned_slew_as_processes_ends_within_two_degrees(slew_run):
    """Measured 0.99 deg at 2170 s (the end of the plan's hold; 1.11 deg at 1800 s) in process,
    which the lock-step processes equal (see the slow-planner test below); plans at 30 s (first,
    after the smoother's bias estimate), 930 s (schedule) and 1830 s (schedule, arrived: the hold
    renewed), none for tracking error. docs/attitude_planning.md: the spread over 30 run seeds."""
    run, _ = slew_run
    s, t = run.scenario, run.trajectory
    assert s.estimator.mode == "smoother" and s.attitude_control.law == "tvlqr_plan"
    error = pointing_error_deg(t, s)
    assert error[0] == pytest.approx(90.0, abs=1e-3)
    assert error[-1] < 2.0


@pytest.mark.timeout(2 * RUN_TIMEOUT_S)
def test_planned_slew_as_processes_tracks_every_plan_and_ignores_bad_plans(slew_run):
    run, sent = slew_run
    controller = json.loads((run.run_dir / "deadline_controller.json").read_text())
    planner = json.loads((run.run_dir / "planner.json").read_text())
    assert planner["plans"] and planner["plans"][0]["reason"] == "first_plan"
    # the scheduled replan after the arrival renewed the hold (no manoeuvre) and was flown too
    assert [(p["reason"], p["stop_reason"]) for p in planner["plans"]][-1] == ("schedule", "hold")
    assert controller["plans_applied"] == len(planner["plans"]) and controller["plan_waits_timed_out"] == 0
    # The bad plans were counted (decode failures by the node, inconsistent arrays by the inbox) and
    # the run went on; none of them was flown.
    assert sent > 0 and controller["plans_rejected"] >= 1
    assert "gains" in controller["last_plan_rejection"]
    metrics = json.loads((run.run_dir / "metrics.json").read_text())
    assert all(p["exit_code"] == 0 for p in metrics["processes"].values()) and "planner" in metrics["processes"]
    assert len(run.on(keys.PLAN_ATTITUDE)) >= len(planner["plans"])


# --- determinism: planning time does not reach a lock-step run ---------------------------------
def test_lock_step_planned_slew_as_processes_equals_the_in_process_loop_with_a_slow_planner(tmp_path):
    """100 steps (the first plan at step 30, a scheduled replan at step 70) with every plan held
    back 2 s before the planner publishes it: the controller waits for the plan the replan rule
    says is due, so the processes fly exactly the in-process loop (which plans in line). Plan steps
    of 60 s instead of the scenario's 20 s: a third of the MILQR steps per plan (each plan is made
    twice, by the planner process and in process: 10 s -> 4 s of CPU for both), and when a plan
    arrives does not depend on its size."""
    data = scenario_to_toml_dict(load_scenario("attitude_slew_milqr"))
    data["attitude_control"]["planner"]["replan_period_s"] = 40.0
    data["attitude_control"]["planner"]["plan_step_s"] = 60.0
    data["controller"]["deadline"]["stress"] = {"process": "planner", "extra_cycle_time_s": 2.0, "kind": "sleep",
                                                "every_nth_cycle": 1}
    path = tmp_path / "slow_planner.json"
    path.write_text(json.dumps(data))
    result = run_bench_cli("run", str(path), "--steps", "100", "--run-id", "slow_planner", "--runs-dir",
                           str(tmp_path), "--no-progress", "--no-report", timeout_s=RUN_TIMEOUT_S)
    assert result.returncode == 0, result.stderr + result.stdout
    run = load_run(tmp_path / "slow_planner")
    planner = json.loads((run.run_dir / "planner.json").read_text())
    controller = json.loads((run.run_dir / "deadline_controller.json").read_text())
    assert [(p["seq"], p["reason"]) for p in planner["plans"]] == [(30, "first_plan"), (70, "schedule")]
    assert planner["stress_injected_plans"] == 2
    assert controller["plans_applied"] == 2 and controller["plan_waits_timed_out"] == 0
    reference = simulate_attitude_in_process(run.scenario)
    for name in ("att_q_wxyz", "att_omega_radps", "att_dipole_applied_am2", "att_dipole_commanded_am2"):
        np.testing.assert_allclose(run.trajectory[name], reference[name], rtol=0, atol=1e-9, err_msg=name)
    assert not np.any(run.trajectory["att_refused"])


def test_lock_step_controller_waits_for_its_can_frame_as_long_as_the_plant_waits_for_the_command():
    """The CAN frame carrying a new dipole: 5 command periods in real time; in lock-step as long as
    the plant waits (a 50 ms wall-clock wait ran out on a loaded host and changed a lock-step run)."""
    from bench.controller.attitude_node import command_send_timeout_s

    lock_step = load_scenario("attitude_slew_milqr")
    assert command_send_timeout_s(lock_step) == lock_step.run.command_timeout_s == 300.0
    real_time = load_scenario("attitude_fault_commands")
    assert command_send_timeout_s(real_time) == pytest.approx(5 * real_time.can.driver.command_period_s)
