"""The launcher's progress watchdog on a fake clock (bench/runtime/progress_watchdog.py): the bound
each scenario gets, when a run counts as stalled, and which stage it names. The runs themselves,
with a node stopped: tests/test_stall_detection.py."""
from __future__ import annotations

import msgspec
import pytest

from bench.bus import keys
from bench.runtime.progress_watchdog import (
    LOCKSTEP_MARGIN_S, REALTIME_MIN_BOUND_S, ProgressWatchdog, StallBound, stage_names, stall_bound,
)
from bench.scenario import ScenarioError, load_scenario, parse_scenario

STAGES = {keys.COMMAND_DIPOLE: "no command from 'controller'", keys.ACTUATOR_MTQ: "no board telemetry (the board)"}
LOCK = StallBound(10.5, "lock-step", startup_s=120.0)


def watchdog(bound=LOCK, lock_step=True, period_s=0.0, now_s=0.0) -> ProgressWatchdog:
    return ProgressWatchdog(bound, lock_step, STAGES, now_s=now_s, period_s=period_s,
                            plant_wait_s=bound.seconds - LOCKSTEP_MARGIN_S if lock_step else None)


def looks(w: ProgressWatchdog, start_s: float, end_s: float, every_s: float = 0.1):
    """The launcher's looks from start_s to end_s; the first stall seen, with its time."""
    t = start_s
    while t <= end_s + 1e-9:
        stall = w.look(t)
        if stall is not None:
            return t, stall
        t = round(t + every_s, 6)
    return None


# --- the bound ----------------------------------------------------------------------------------
def with_run(name: str, **run) -> object:
    scenario = load_scenario(name)
    return parse_scenario(msgspec.to_builtins(msgspec.structs.replace(
        scenario, run=msgspec.structs.replace(scenario.run, **run))), "test")


def test_the_lock_step_bound_is_the_plants_own_wait_and_a_half_second():
    bound = stall_bound(load_scenario("attitude_quick"))
    assert bound.seconds == 10.0 + LOCKSTEP_MARGIN_S == 10.5
    assert "run.command_timeout_s = 10 s" in bound.how and bound.startup_s == 120.0
    assert stall_bound(with_run("rendezvous_lqr", command_timeout_s=2.0)).seconds == 2.5


def test_the_real_time_bound_is_a_number_of_periods_at_the_time_factor_at_least_5_s():
    # attitude_pointing_rt: 0.1 s steps at 1x: 50 periods are 5 s
    assert stall_bound(load_scenario("attitude_pointing_rt")).seconds == pytest.approx(5.0)
    # rendezvous_lqr in real time: 600 s steps at 6000x = 0.1 s periods; 200 of them are 20 s
    slow = with_run("rendezvous_lqr", mode="real-time", liveliness={"stall_periods": 200})
    assert stall_bound(slow).seconds == pytest.approx(20.0) and "stall_periods = 200" in stall_bound(slow).how
    fast = with_run("rendezvous_lqr", mode="real-time", time_factor=600_000.0)     # 1 ms periods
    assert stall_bound(fast).seconds == REALTIME_MIN_BOUND_S
    with pytest.raises(ScenarioError, match="stall_periods"):
        with_run("rendezvous_lqr", liveliness={"stall_periods": 0})


def test_stages_are_named_for_the_bus_the_run_has():
    quick = load_scenario("attitude_quick")
    assert "'mtq', behind the bus model 'canbus'" in stage_names(quick)[keys.ACTUATOR_MTQ]        # wall-clock bus
    simulated = parse_scenario(msgspec.to_builtins(msgspec.structs.replace(
        quick, can=msgspec.structs.replace(quick.can, lock_step_clock="simulated"))), "test")
    assert "'canbus', have not reported the coils" in stage_names(simulated)[keys.ACTUATOR_MTQ]
    assert stage_names(quick)[keys.COMMAND_DIPOLE] == "no command from 'controller'"
    assert keys.ACTUATOR_MTQ not in stage_names(load_scenario("rendezvous_lqr"))
    assert stage_names(load_scenario("rendezvous_lqr"))[keys.COMMAND_THRUST] == "no command from 'controller'"


# --- lock-step ----------------------------------------------------------------------------------
def test_steps_that_keep_coming_never_stall():
    w = watchdog()
    w.step_done(1, 0.5)
    for k in range(2, 200):
        w.step_done(k, k * 5.0)          # 5 s a step: slow, but each well inside the plant's wait
        assert w.look(k * 5.0 + 4.9) is None


def test_a_creeping_run_is_stalled_on_the_wait_that_outlasts_the_plants_own():
    """Issue 44: the board no longer answers; the plant waits 10 s + 1 s for each step's report,
    then goes on. Steps still advance, every 11 s: the wait for the report is the stall."""
    w = watchdog(now_s=100.0)
    w.step_done(459, 100.0)
    w.plant_waits(459, keys.ACTUATOR_MTQ, 1.0, 101.0)           # the plant's report after a second
    t, stall = looks(w, 100.0, 111.1)
    assert t == pytest.approx(110.5)
    assert stall.step == 459 and stall.what == STAGES[keys.ACTUATOR_MTQ] and stall.seconds >= 10.5
    message = stall.describe(w.bound, ["canbus"])
    assert message.startswith("run stalled at step 459: no board telemetry (the board) for 10.5 s (bound 10.5 s")
    assert message.endswith("process 'canbus' is stopped (state T)")


def test_a_slow_step_with_two_waits_each_inside_the_bound_is_not_a_stall():
    w = watchdog()
    w.step_done(10, 0.0)
    w.plant_waits(10, keys.COMMAND_DIPOLE, 1.0, 1.0)             # waits for the command from 0 s ...
    assert looks(w, 0.1, 6.0) is None                             # ... which comes at 6 s,
    w.plant_waits(10, keys.ACTUATOR_MTQ, 1.0, 7.0)               # then for the board's report from 6 s
    assert looks(w, 6.1, 16.4) is None                            # 16 s since the step: no stall,
    t, stall = looks(w, 16.5, 17.0)                               # 10.5 s since the last thing came: one
    assert t == pytest.approx(16.5) and stall.what == STAGES[keys.ACTUATOR_MTQ]


def test_a_plant_that_reports_no_wait_is_named_itself():
    w = watchdog()
    w.step_done(3, 1.0)
    t, stall = looks(w, 1.0, 20.0)
    assert t == pytest.approx(11.5) and stall.step == 3 and "the plant has not finished it and reports no wait" in stall.what


def test_a_wait_report_of_a_step_already_done_is_not_the_stall():
    w = watchdog()
    w.step_done(5, 0.0)
    w.plant_waits(4, keys.COMMAND_DIPOLE, 3.0, 0.05)             # overtaken by step 4's StepDone
    t, stall = looks(w, 0.1, 20.0)
    assert stall.step == 5 and "reports no wait" in stall.what


def test_before_the_first_step_the_start_up_time_is_added():
    w = watchdog()
    assert looks(w, 0.0, 130.0) is None                           # the plant waits up to 120 s for its peers
    assert looks(w, 130.1, 130.6)[1].what == "the loop has not started"
    started = watchdog()
    started.plant_waits(0, keys.COMMAND_DIPOLE, 1.0, 40.0)       # waiting for step 0's command: started
    assert looks(started, 0.0, 49.4) is None and looks(started, 49.5, 49.5) is not None   # 10.5 s after 39 s


def test_the_launchers_own_missed_time_is_not_the_runs():
    w = watchdog()
    w.step_done(7, 0.0)
    assert looks(w, 0.0, 5.0) is None
    assert w.look(25.0) is None            # the launcher was not scheduled for 20 s: nobody's stall
    assert looks(w, 25.1, 29.0) is None
    assert looks(w, 29.1, 40.0) is not None


def test_a_plant_that_gave_up_waiting_is_named_by_what_it_waited_for():
    w = watchdog()
    w.step_done(94, 0.0)
    w.plant_waits(94, keys.COMMAND_DIPOLE, 1.0, 1.1)
    assert w.gave_up(5.0) is None                                 # it failed, but not of waiting: not a stall
    stall = w.gave_up(10.2)                                       # it gave up after its 10 s
    assert stall.step == 94 and stall.what == "no command from 'controller'" and stall.seconds == pytest.approx(10.1)
    assert watchdog().gave_up(50.0) is None                       # no wait reported: nothing to name


# --- real time ----------------------------------------------------------------------------------
RT = StallBound(5.0, "real time", startup_s=120.0)


def test_real_time_a_plant_that_stops_stepping_is_stalled():
    w = watchdog(RT, lock_step=False, period_s=0.1)
    for k in range(1, 50):
        w.step_done(k, k * 0.1)
        assert w.look(k * 0.1) is None
    t, stall = looks(w, 4.9, 20.0)
    assert t == pytest.approx(9.9) and stall.what == "the plant has done no step" and stall.step == 49


def test_real_time_a_controller_that_stops_commanding_is_stalled_while_the_plant_steps_on():
    w = watchdog(RT, lock_step=False, period_s=0.1)
    t = 0.0
    for k in range(1, 150):
        t = k * 0.1
        w.step_done(k, t)
        if t >= 6.0 and abs(t % 1.0) < 1e-6:                       # no command since 5 s: reported every second
            w.plant_waits(k, keys.COMMAND_DIPOLE, t - 5.0, t)
        stall = w.look(t)
        if stall is not None:
            break
    assert t == pytest.approx(10.0) and stall.what == "no command from 'controller'" and stall.seconds == pytest.approx(5.0)


def test_real_time_a_wait_report_no_longer_repeated_is_over():
    w = watchdog(RT, lock_step=False, period_s=0.1)
    w.plant_waits(10, keys.COMMAND_DIPOLE, 4.0, 1.0)              # no command for 4 s, then commands again
    for k in range(11, 150):
        w.step_done(k, k * 0.1)
        assert w.look(k * 0.1) is None
