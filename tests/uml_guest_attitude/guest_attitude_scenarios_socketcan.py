"""The planned slew, the pointing hold and the attitude fault scenarios over the kernel's SocketCAN.

Runs inside user-mode Linux (tests/test_kernel_can_uml.py boots it, with the detumble of
guest_attitude_socketcan.py in the same boot). Each built-in scenario keeps everything but its
bus (tests/uml_guest_attitude/socketcan_scenarios.py): `transport = "socketcan"` on a vcan pair of
its own. Each test checks what the scenario's own run checks over the portable Zenoh transport:
- attitude_fault_all (real time, whole: every fault the bench injects, one after the other, in
  30 s): the criteria verdict PASS (the detumble goes on, the driver detected each fault's kind,
  the board is healthy at the end), the driver's event kinds for each fault injected (as
  tests/test_attitude_processes.py), and no command applied that the law did not give (plant and
  board side). It runs alone: seven real-time runs at once on the guest's one CPU starved each
  other (measured: telemetry timeouts of 10 s, a process's liveliness lapsed for 60 s, partial
  runs). The four single-fault scenarios (30 s of real time each, one after the other: 4-5 min
  more of this boot) run over both transports with their verdicts in
  benchmarks/can_fault_latency_transports.py;
- the planned slew and the hold (lock-step, where timing does not matter: both at once, after
  the real-time run) cut short with --steps: the run equals the in-process loop to 1e-9 (as
  tests/test_planner_process.py over Zenoh; the in-process loop's whole runs pass their criteria
  in tests/test_attitude_loop.py and test_planner_process.py); the hold's criterion (the maximum
  pointing error) is judged on its shortened run too. The slew's criterion is its final error
  after 2170 s, which a shortened run cannot meet: its whole run over SocketCAN is
  benchmarks/can_fault_latency_transports.py --whole-lockstep.
"""
from __future__ import annotations

import json
import sys
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))
from conftest import run_bench_cli  # noqa: E402
from guest_attitude_socketcan import check_only_commanded_applied  # noqa: E402
from socketcan_scenarios import EXPECTED_KINDS, HOLD, SLEW, fault_names, write_over_socketcan  # noqa: E402

from bench.bus.can import vcan  # noqa: E402
from bench.bus.can.transport import interface_exists, kernel_has_can  # noqa: E402
from bench.report.rundata import load_run  # noqa: E402
from bench.sim import simulate_attitude_in_process  # noqa: E402

pytestmark = pytest.mark.skipif(not (kernel_has_can() and interface_exists("vcan1")),
                                reason="runs inside user-mode Linux (tests/test_kernel_can_uml.py)")
# Lock-step runs cut short: the slew's first plan comes at 30 s (first_plan_after_s) and is
# tracked for 30 steps; the hold's 160 steps cross its star-tracker outage (120-150 s).
STEPS = {SLEW: 60, HOLD: 160}
FAULT_SCENARIOS = ("attitude_fault_all",)
# The real-time runs alone, one after the other; then the lock-step runs at once.
REAL_TIME, LOCK_STEP = FAULT_SCENARIOS, (SLEW, HOLD)
ORDER = (*REAL_TIME, *LOCK_STEP)
# A hang bound per run, inside the guest's per-test bound (tests/test_kernel_can_uml.py).
RUN_TIMEOUT_S = 900


def vcan_pair(index: int) -> tuple[str, str]:
    """vcan0/vcan1 are the detumble's; each scenario here gets its own two from vcan2 on."""
    return f"vcan{2 + 2 * index}", f"vcan{3 + 2 * index}"


def one_run(runs_dir: Path, name: str, index: int):
    flight, board = vcan_pair(index)
    path = write_over_socketcan(name, flight, board, runs_dir)
    steps = ["--steps", str(STEPS[name])] if name in STEPS else []
    result = run_bench_cli("run", str(path), *steps, "--run-id", name, "--runs-dir", str(runs_dir), "--no-progress",
                           "--no-report", timeout_s=RUN_TIMEOUT_S)
    return result


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Future]:
    """Every run started in the background (the real-time ones one at a time, then the lock-step
    ones at once); each test waits for its own."""
    runs_dir = tmp_path_factory.mktemp("socketcan-runs")
    vcan.up(tuple(name for i in range(len(ORDER)) for name in vcan_pair(i)))
    real_time, lock_step = ThreadPoolExecutor(max_workers=1), ThreadPoolExecutor(max_workers=len(LOCK_STEP))
    futures = {name: real_time.submit(one_run, runs_dir, name, ORDER.index(name)) for name in REAL_TIME}
    real_time_runs = list(futures.values())

    def after_the_real_time_runs(name):
        for future in real_time_runs:
            future.exception()            # waits; a failed run is its own test's failure
        return one_run(runs_dir, name, ORDER.index(name))

    waiting = {name: lock_step.submit(after_the_real_time_runs, name) for name in LOCK_STEP}
    futures.update(waiting)
    futures["runs_dir"] = runs_dir
    yield futures
    real_time.shutdown(wait=True)
    lock_step.shutdown(wait=True)


def finished_run(runs, name: str):
    result = runs[name].result(timeout=RUN_TIMEOUT_S + 60)
    assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-2000:]
    run_dir = runs["runs_dir"] / name
    run = load_run(run_dir)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert all(p["exit_code"] == 0 for p in metrics["processes"].values()), metrics["processes"]
    assert run.scenario.can.transport == "socketcan"
    assert run.scenario.can.flight_channel == vcan_pair(ORDER.index(name))[0]
    return run, metrics


def failed_criteria(metrics: dict) -> list:
    return [c for c in metrics["verdict"]["criteria"] if not c["passed"]]


def assert_equals_the_in_process_loop(run) -> None:
    reference = simulate_attitude_in_process(run.scenario)
    assert len(run.trajectory["att_time_s"]) == run.scenario.n_steps
    for name in ("att_q_wxyz", "att_omega_radps", "att_dipole_applied_am2", "att_dipole_commanded_am2"):
        np.testing.assert_allclose(run.trajectory[name], reference[name], rtol=0, atol=1e-9, err_msg=name)


@pytest.mark.parametrize("scenario", FAULT_SCENARIOS)
def test_attitude_fault_scenario_over_kernel_socketcan(runs, scenario):
    run, metrics = finished_run(runs, scenario)
    assert metrics["verdict"]["passed"], failed_criteria(metrics)
    driver = json.loads((run.run_dir / "can" / "driver.json").read_text())
    kinds = {e["kind"] for e in driver["events"]}
    for fault in fault_names(scenario):
        assert kinds & EXPECTED_KINDS[fault], f"{fault}: the driver saw {sorted(kinds)}"
    check_only_commanded_applied(run)


def test_planned_slew_over_kernel_socketcan(runs):
    run, _ = finished_run(runs, SLEW)
    assert run.scenario.run.mode == "lock-step" and run.scenario.attitude_control.law == "tvlqr_plan"
    planner = json.loads((run.run_dir / "planner.json").read_text())
    controller = json.loads((run.run_dir / "deadline_controller.json").read_text())
    assert [p["reason"] for p in planner["plans"]] == ["first_plan"]
    assert controller["plans_applied"] == 1 and controller["plan_waits_timed_out"] == 0
    assert_equals_the_in_process_loop(run)


def test_pointing_hold_over_kernel_socketcan(runs):
    run, metrics = finished_run(runs, HOLD)
    assert run.scenario.run.mode == "lock-step" and run.scenario.estimator.mode == "smoother"
    assert metrics["verdict"]["passed"], failed_criteria(metrics)
    assert_equals_the_in_process_loop(run)
