"""The pointing hold and the attitude fault scenarios over the kernel's SocketCAN.

Runs inside user-mode Linux (tests/test_kernel_can_uml.py boots it, with the detumble of
guest_attitude_socketcan.py in the same boot). Each built-in scenario keeps everything but its
bus (tests/uml_guest_attitude/socketcan_scenarios.py): `transport = "socketcan"` on a vcan pair of
its own. Each test checks what the scenario's own run checks over the portable Zenoh transport:
- attitude_fault_all (a study, `make studies`; real time, whole: every fault the bench injects,
  one after the other, in 30 s): the criteria verdict PASS (the detumble goes on, the driver
  detected each fault's kind, the board is healthy at the end), the driver's event kinds for
  each fault injected (as tests/test_attitude_processes.py), and no command applied that the law
  did not give (plant and board side). It runs alone: real-time runs at once on the guest's one
  CPU starve each other.
  The four single-fault scenarios (each injects one of attitude_fault_all's faults; 30 s of real
  time each) run over both transports with their verdicts in
  benchmarks/can_fault_latency_transports.py;
- the pointing hold (lock-step, after the real-time run) cut short with --steps: the run equals
  the in-process loop to 1e-9 (the in-process loop's whole run passes its criteria in
  tests/test_attitude_loop.py), and its criterion (the maximum pointing error) is judged on the
  shortened run too. The planned slew's lock-step loop reaches the bus as the hold's does (its
  planner process never touches the bus), so it runs over SocketCAN in
  benchmarks/can_fault_latency_transports.py --whole-lockstep, whole, and over Zenoh in
  tests/test_planner_process.py; its plan alone took 33 s of the guest's one CPU, twice (the run
  and its in-process reference).
Nothing uncommanded applied is checked always; the rest may fail only where a CAN node measured
the host holding it up (assert_passed_unless_the_host_stalled), as the detumble's tests do: on a
busy host UML's one CPU cannot keep a 10 ms command period, nor the plant's wall-clock wait for
the board's report in lock-step (docs/can-bus.md gives the figures).
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
from socketcan_scenarios import EXPECTED_KINDS, HOLD, fault_names, write_over_socketcan  # noqa: E402

from bench.bus.can import vcan  # noqa: E402
from bench.bus.can.host_lateness import load_host_late_records, longest_host_late_s  # noqa: E402
from bench.bus.can.transport import interface_exists, kernel_has_can  # noqa: E402
from bench.plant.board_dipole import EXACT_REPORT_WAIT_S  # noqa: E402
from bench.plant.mtq_acceptance import board_dipole_without_bus  # noqa: E402
from bench.report.rundata import load_run  # noqa: E402
from bench.sim import simulate_attitude_in_process  # noqa: E402

pytestmark = pytest.mark.skipif(not (kernel_has_can() and interface_exists("vcan1")),
                                reason="runs inside user-mode Linux (tests/test_kernel_can_uml.py)")
# The lock-step run cut short: the hold's first 40 s.
STEPS = {HOLD: 40}
FAULT_SCENARIOS = ("attitude_fault_all",)
# The real-time runs alone, one after the other; then the lock-step run.
REAL_TIME, LOCK_STEP = FAULT_SCENARIOS, (HOLD,)
ORDER = (*REAL_TIME, *LOCK_STEP)
# A hang bound per run, inside the guest's per-test bound (tests/test_kernel_can_uml.py).
RUN_TIMEOUT_S = 900


def vcan_pair(index: int) -> tuple[str, str]:
    """vcan0/vcan1 are the detumble's; each scenario here gets its own two from vcan2 on."""
    return f"vcan{2 + 2 * index}", f"vcan{3 + 2 * index}"


def one_run(runs_dir: Path, name: str, index: int):
    flight, board = vcan_pair(index)
    path = write_over_socketcan(name, flight, board, runs_dir)
    # No report: metrics.json carries the bus's figures and the verdict without it
    # (bench.report.summary.run_metrics), and building it took most of the 90 s between
    # attitude_fault_all's end and the hold's start on the guest's one CPU.
    options = [*(("--steps", str(STEPS[name])) if name in STEPS else ()), "--no-report"]
    return run_bench_cli("run", str(path), *options, "--run-id", name, "--runs-dir", str(runs_dir), "--no-progress",
                         timeout_s=RUN_TIMEOUT_S)


def selected_runs(session) -> set[str]:
    """The scenarios of the tests this session runs (attitude_fault_all is a study: `-m study`)."""
    names = set()
    for item in session.items:
        if item.module.__name__ == __name__:
            names.add(item.callspec.params["scenario"] if hasattr(item, "callspec") else HOLD)
    return names


@pytest.fixture(scope="module")
def runs(request, tmp_path_factory) -> dict[str, Future]:
    """Every selected run started in the background (the real-time ones one at a time, then the
    lock-step ones at once); each test waits for its own."""
    runs_dir = tmp_path_factory.mktemp("socketcan-runs")
    selected = selected_runs(request.session)
    vcan.up(tuple(name for i in range(len(ORDER)) for name in vcan_pair(i)))
    real_time, lock_step = ThreadPoolExecutor(max_workers=1), ThreadPoolExecutor(max_workers=len(LOCK_STEP))
    futures = {name: real_time.submit(one_run, runs_dir, name, ORDER.index(name)) for name in REAL_TIME if name in selected}
    real_time_runs = list(futures.values())

    def after_the_real_time_runs(name):
        for future in real_time_runs:
            future.exception()            # waits; a failed run is its own test's failure
        return one_run(runs_dir, name, ORDER.index(name))

    waiting = {name: lock_step.submit(after_the_real_time_runs, name) for name in LOCK_STEP if name in selected}
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
    return [f"{c['metric']} = {c['value']} (bound {c['bound']})" for c in metrics["verdict"]["criteria"] if not c["passed"]]


def longest_host_stall_s(run) -> float:
    """The longest time the host held a CAN node (driver, board, bus model) up in this run."""
    return longest_host_late_s(load_host_late_records(Path(run.run_dir) / "can"), 0, 2**63)


def assert_passed_unless_the_host_stalled(run, metrics, failures: list[str], stall_bound_s: float) -> None:
    """No failure, or a CAN node measured the host holding it up for stall_bound_s or more: UML's
    one CPU, starved by a busy host, then cannot keep the loop's deadlines, and that is the host,
    not the bus (the same rule as the detumble's tests in guest_attitude_socketcan.py). The guest's
    output says which it was."""
    if not failures:
        return
    stall_s = longest_host_stall_s(run)
    print(f"{run.run_id}: excused by a host stall of {stall_s:.3f} s: {failures}")
    assert stall_s >= stall_bound_s, (f"{failures}; the CAN nodes measured no host stall of {stall_bound_s} s "
                                      f"(longest {stall_s:.3f} s)")


def lockstep_failures(run) -> list[str]:
    """Where the lock-step run differs from the in-process loop. A step the plant got no board report
    for within its wall-clock wait (bench/plant/attitude_node.py: EXACT_REPORT_WAIT_S, then
    REPORT_WAIT_S) has the coils as last reported or off, and the trajectory departs from there."""
    t = run.trajectory
    assert len(t["att_time_s"]) == run.scenario.n_steps
    # Whatever the bus did, the plant applied the board's version of the law's command or nothing.
    applied_ok = [not np.any(a) or np.array_equal(a, board_dipole_without_bus(c, run.scenario.can))
                  for a, c in zip(t["att_dipole_applied_am2"], t["att_dipole_commanded_am2"])]
    assert all(applied_ok) or t["att_refused"][~np.asarray(applied_ok)].all()
    refused = int(np.sum(t["att_refused"]))
    if refused:
        return [f"{refused} of {len(t['att_refused'])} steps without the board's report in time (coils as last reported or off)"]
    reference = simulate_attitude_in_process(run.scenario)
    for name in ("att_q_wxyz", "att_omega_radps", "att_dipole_applied_am2", "att_dipole_commanded_am2"):
        np.testing.assert_allclose(t[name], reference[name], rtol=0, atol=1e-9, err_msg=name)
    return []


# A study (`make studies`): 66 s of UML's one CPU; the kernel's CAN faults are checked in every
# test run by tests/uml_guest_can, and each fault's detection over the portable transport.
@pytest.mark.parametrize("scenario", [pytest.param(name, marks=pytest.mark.study) for name in FAULT_SCENARIOS])
def test_attitude_fault_scenario_over_kernel_socketcan(runs, scenario):
    run, metrics = finished_run(runs, scenario)
    # Safety first, whatever the host did: nothing the law did not command moved the coils.
    check_only_commanded_applied(run, every_step=False)
    driver = json.loads((run.run_dir / "can" / "driver.json").read_text())
    kinds = {e["kind"] for e in driver["events"]}
    failures = [f"{fault}: the driver saw none of {sorted(EXPECTED_KINDS[fault])}"
                for fault in fault_names(scenario) if not kinds & EXPECTED_KINDS[fault]]
    failures += failed_criteria(metrics)
    assert_passed_unless_the_host_stalled(run, metrics, failures, run.scenario.step_s)


def test_pointing_hold_over_kernel_socketcan(runs):
    run, metrics = finished_run(runs, HOLD)
    assert run.scenario.run.mode == "lock-step" and run.scenario.estimator.mode == "smoother"
    failures = lockstep_failures(run) + failed_criteria(metrics)
    assert_passed_unless_the_host_stalled(run, metrics, failures, EXACT_REPORT_WAIT_S)
