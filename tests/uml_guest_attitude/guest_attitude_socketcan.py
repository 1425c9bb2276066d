"""The attitude loop closed through the magnetorquer board over the kernel's SocketCAN.

Runs inside user-mode Linux (tests/test_can_attitude_uml.py boots it): `bench run` of
attitude_detumble_socketcan in real time, as separate processes: the controller's driver on
vcan0, the bus model and fault injector (`bench node canbus`) bridging vcan0 and vcan1, the board
(`bench node mtq`) on vcan1, plant, estimator and recorder over Zenoh. The same checks as the
portable-transport runs of tests/test_attitude_processes.py: the board applied only what the law
commanded (or zero), the body slowed; with commands dropped, the board went coils-off, the driver
said so, and the loop recovered after the fault.
"""
from __future__ import annotations

import json
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from conftest import run_bench_cli  # noqa: E402

from bench.bus.can.transport import interface_exists, kernel_has_can  # noqa: E402
from bench.plant.mtq_acceptance import board_dipole_without_bus  # noqa: E402
from bench.report.attitude import fault_windows_sim_s  # noqa: E402
from bench.report.attitude_metrics import applied_is_commanded_or_zero, loop_recovery_s  # noqa: E402
from bench.report.rundata import load_run  # noqa: E402

pytestmark = pytest.mark.skipif(not (kernel_has_can() and interface_exists("vcan1")),
                                reason="runs inside user-mode Linux (tests/test_can_attitude_uml.py)")
SCENARIO = "attitude_detumble_socketcan"
SCENARIO_FILE = Path(__file__).resolve().parents[2] / "bench" / "scenarios" / f"{SCENARIO}.toml"
# Six processes start on UML's one CPU (each took 10-20 s when measured, more under host load),
# then 12 s of real time and the shutdown: a hang bound, inside the guest's per-test timeout
# (tests/test_can_attitude_uml.py), so a hung run fails with the launcher's output.
RUN_TIMEOUT_S = 500
DROP_START_S = 5.0
DROP_COUNT = 25            # 0.5 s of 20 ms commands: five board command timeouts long


def bench_run(tmp_path: Path, scenario: str, run_id: str):
    runs = tmp_path / "runs"
    result = run_bench_cli("run", scenario, "--run-id", run_id, "--runs-dir", str(runs), "--no-progress",
                           "--no-report", timeout_s=RUN_TIMEOUT_S)
    assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-2000:]
    run = load_run(runs / run_id)
    metrics = json.loads((runs / run_id / "metrics.json").read_text())
    assert all(p["exit_code"] == 0 for p in metrics["processes"].values()), metrics["processes"]
    assert run.scenario.can.transport == "socketcan"
    return run


def check_only_commanded_applied(run) -> None:
    """Plant side and board side: every applied dipole is zero or the board's version of a dipole
    the law published (the recording's command/dipole)."""
    published = [m.body["dipole_am2"] for m in run.on("command/dipole")]
    assert len(published) >= len(run.trajectory["att_time_s"]) - 5
    assert applied_is_commanded_or_zero(run.trajectory, run.scenario.can, published).all()
    board = json.loads((run.run_dir / "can" / "board.json").read_text())
    expected = {tuple(board_dipole_without_bus(c, run.scenario.can)) for c in published}
    assert board["applied"], "the board applied nothing"
    assert all(tuple(a["dipole_am2"]) in expected or not any(a["dipole_am2"]) for a in board["applied"])


def body_rate(run) -> np.ndarray:
    return np.linalg.norm(run.trajectory["att_omega_radps"], axis=1)


def test_attitude_detumble_over_kernel_socketcan(tmp_path):
    run = bench_run(tmp_path, SCENARIO, "socketcan-clean")
    t = run.trajectory
    # Every step's command went out on the kernel's vcan0 and the board's report came back.
    assert np.all(t["stamp_can_sent_ns"] > 0) and np.all(t["stamp_board_received_ns"] > 0)
    check_only_commanded_applied(run)
    rate = body_rate(run)
    assert rate[-1] < rate[0]


def test_attitude_detumble_with_dropped_commands_over_kernel_socketcan(tmp_path):
    scenario = tomllib.loads(SCENARIO_FILE.read_text())
    scenario["name"] = f"{SCENARIO}_drop"
    scenario["can"]["faults"] = [{"name": "drop", "frames": ["MTQ_CMD"], "start_s": DROP_START_S, "count": DROP_COUNT}]
    path = tmp_path / "scenario.json"      # load_scenario reads JSON like TOML
    path.write_text(json.dumps(scenario))
    run = bench_run(tmp_path, str(path), "socketcan-drop")
    t = run.trajectory
    check_only_commanded_applied(run)
    assert body_rate(run)[-1] < body_rate(run)[0]
    injections = [json.loads(x) for x in (run.run_dir / "can" / "injections.jsonl").read_text().splitlines() if x]
    assert sum(r["action"] == "dropped" for r in injections) == DROP_COUNT
    driver = json.loads((run.run_dir / "can" / "driver.json").read_text())
    assert "board_command_timeout" in {e["kind"] for e in driver["events"]}, driver["events"]
    (name, start, end), = fault_windows_sim_s(run.run_dir, run.scenario, t)
    assert name == "drop" and 0.0 < start < end < t["att_time_s"][-1]
    # The fault mattered: the plant saw the coils off while commands were being dropped ...
    during = (t["att_time_s"] >= start) & (t["att_time_s"] <= end + 0.2)
    assert any(not np.any(a) for a in t["att_dipole_applied_am2"][during])
    # ... and the loop was whole again within 2 s of its end.
    recovery = loop_recovery_s(t, run.scenario.can, end)
    assert recovery is not None and recovery < 2.0
