"""Roles a user takes over in the attitude loop over the magnetorquer CAN bus (issue 25,
docs/contract.md): the test starts the outside part itself, as another team's flight computer or a
real board would be, and `bench run` starts everything else.

- flight software external (`--external controller`): the controller process (the law and the
  magnetorquer driver on the CAN bus) is `bench node controller`, started by the test; in
  lock-step the run equals the built-in loop (the in-process reference) to 1e-9.
- board external (`--external board`, real time only): no simulated board and no bus model from the
  launcher; the test starts `bench node mtq` on the board's channel as the hardware. The plant reads
  the board's telemetry frames; the loop closes (the body slows, the driver sees the board healthy),
  and its difference from the in-process loop is measured, not hidden (tests below print it).
"""
import json
import subprocess
import sys
import time

import msgspec
import numpy as np
import pytest

from bench.bus.can import protocol as p
from bench.bus.session import free_loopback_port, loopback_endpoint
from bench.launcher import external_parts, nodes_for, with_driver_on_the_board_bus
from bench.plant.board_telemetry import BoardTelemetry
from bench.report.rundata import load_run
from bench.scenario import ScenarioError, load_scenario
from bench.sim import simulate_attitude_in_process
from conftest import REPO

RUN_TIMEOUT_S = 600
pytestmark = pytest.mark.timeout(2 * RUN_TIMEOUT_S)


def _with_run(scenario, **run):
    return msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, **run))


# --- which parts may be external, and what the launcher starts then ----------------------------
def test_the_attitude_controller_may_be_external_with_its_can_driver():
    scenario = _with_run(load_scenario("attitude_detumble"), external=["controller"])
    assert external_parts(scenario) == {"controller": "external"}
    assert {"canbus", "mtq", "plant", "estimator", "controller"} <= set(nodes_for(scenario))


def test_an_external_board_replaces_the_simulated_board_and_the_bus_model_in_real_time_only():
    realtime = _with_run(load_scenario("attitude_detumble_rt"), external=["board"])
    assert external_parts(realtime) == {}          # no Zenoh node to wait for
    names = nodes_for(realtime)
    assert "mtq" not in names and "canbus" not in names and "controller" in names
    # No bus model between them: the driver opens the board's bus.
    assert with_driver_on_the_board_bus(realtime).can.driver_bus == realtime.can.bus_spec("board")
    with pytest.raises(ScenarioError, match="real time only"):
        external_parts(_with_run(realtime, mode="lock-step"))
    with pytest.raises(ScenarioError, match="attitude loop with \\[can\\]"):
        external_parts(_with_run(load_scenario("rendezvous_lqr"), external=["board"]))


# --- the plant's listener against frames the board model builds ----------------------------------
def test_board_telemetry_reports_the_dipole_frame_with_the_coil_frame_counter():
    protocol = p.Protocol()
    reports = []
    listener = BoardTelemetry(bus=None, protocol=protocol, run_id="t", on_report=reports.append)
    coil = protocol.encode(p.TLM_COIL, {"CoilCurrentX": 0.05, "LastCommandCounter": 9}, counter=0)
    dipole = protocol.encode(p.TLM_DIPOLE, {"AppliedDipoleX": 0.1234, "AppliedDipoleZ": -0.05, "SafeState": 0}, counter=0)
    assert listener.handle(coil, 1) is None
    report = listener.handle(dipole, 2)
    np.testing.assert_allclose(report.dipole_am2, [0.1234, 0.0, -0.05], atol=0.5e-4)   # the DBC's 1e-4 scaling
    assert report.alive_counter == 9 and report.header.stamps_ns["applied"] == 2 and not report.safe_state
    # A corrupted frame and a repeated counter are refused (E2E), never reported.
    bad = bytearray(dipole.data)
    bad[0] ^= 0xFF
    assert listener.handle(_with_data(dipole, bad), 3) is None
    assert listener.handle(dipole, 4) is None
    assert listener.reports == 1 and sum(listener.refused.values()) == 2


def _with_data(msg, data):
    import can

    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=bytes(data), is_fd=msg.is_fd)


# --- the runs --------------------------------------------------------------------------------------
def _bench(*args: str) -> list[str]:
    return [sys.executable, "-m", "bench.cli", *args]


def run_with_outside_node(runs, scenario: str, run_id: str, node: str, *run_args: str):
    """`bench run ... --port P` in the background; once its scenario.json is written, `bench node
    NODE` from that file, connected to the hub; both waited for."""
    port = free_loopback_port()
    run_dir = runs / run_id
    launcher = subprocess.Popen(_bench("run", scenario, "--run-id", run_id, "--runs-dir", str(runs), "--port", str(port),
                                       "--no-progress", "--no-report", *run_args),
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    outside = None
    try:
        deadline = time.monotonic() + 120
        while not (run_dir / "scenario.json").is_file():
            assert launcher.poll() is None, launcher.communicate()
            assert time.monotonic() < deadline, "no scenario.json"
            time.sleep(0.05)
        log = open(runs / f"{run_id}-outside-{node}.log", "w")
        outside = subprocess.Popen(_bench("node", node, "--run-id", run_id, "--scenario", str(run_dir / "scenario.json"),
                                          "--connect", loopback_endpoint(port), "--run-dir", str(run_dir)),
                                   cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        out, err = launcher.communicate(timeout=RUN_TIMEOUT_S)
        assert launcher.returncode == 0, err + out
        if node == "mtq":
            outside.terminate()    # hardware stays on after a run: the test switches its board off
        # A node named in [run] external stops when the launcher's token goes (bench/runtime/node_cli.py).
        assert outside.wait(timeout=60) == 0, (runs / f"{run_id}-outside-{node}.log").read_text()[-3000:]
        return load_run(run_dir), err
    finally:
        for process in (launcher, outside):      # only what this test started, by its handle
            if process is not None and process.poll() is None:
                process.kill()
                process.wait(timeout=10)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return tmp_path_factory.mktemp("external_roles")


def test_external_flight_software_equals_the_built_in_loop_in_lock_step(runs):
    run, err = run_with_outside_node(runs, "attitude_detumble", "fsw", "controller", "--steps", "40",
                                     "--external", "controller")
    assert "waiting for the external controller" in err
    reference = simulate_attitude_in_process(run.scenario)
    for name in ("att_q_wxyz", "att_omega_radps", "att_dipole_applied_am2", "att_dipole_commanded_am2"):
        np.testing.assert_allclose(run.trajectory[name], reference[name], rtol=0, atol=1e-9, err_msg=name)
    assert run.trajectory["att_q_wxyz"].shape == (40, 4)
    # Every command went over CAN (alive counter) and the board applied it (the launcher's mtq).
    assert np.all(run.trajectory["att_alive_counter"] >= 0) and not run.trajectory["att_refused"].any()
    metrics = json.loads((run.run_dir / "metrics.json").read_text())
    assert metrics["processes"]["controller"] == {"host": "external", "pid": None, "exit_code": None}
    assert metrics["processes"]["mtq"]["exit_code"] == 0
    # The outside driver wrote what it saw of the bus where a built-in one does.
    assert json.loads((run.run_dir / "can" / "driver.json").read_text())


BOARD_STEPS = 100      # 10 s of attitude_detumble_rt (10 Hz, real time)


def test_an_external_board_closes_the_loop_in_real_time(runs):
    run, err = run_with_outside_node(runs, "attitude_detumble_rt", "board", "mtq", "--steps", str(BOARD_STEPS),
                                     "--external", "board")
    assert "the magnetorquer board is external" in err
    t = run.trajectory
    rate = np.linalg.norm(t["att_omega_radps"], axis=1)
    assert rate[-1] < 0.9 * rate[0], (rate[0], rate[-1])
    driver = json.loads((run.run_dir / "can" / "driver.json").read_text())
    assert driver["health"]["ok"] and driver["health"]["nmt_state"] == p.NMT_OPERATIONAL, driver["health"]
    heard = json.loads((run.run_dir / "can" / "plant_board_telemetry.json").read_text())
    assert heard["reports"] > BOARD_STEPS / 2 and not heard["refused"]
    metrics = json.loads((run.run_dir / "metrics.json").read_text())
    assert metrics["processes"]["mtq"]["host"] == "external" and "canbus" not in metrics["processes"]
    # Measured, not hidden: the applied dipole is the coils' current from the telemetry frames,
    # against the in-process loop (the coil drivers' target, no bus).
    reference = simulate_attitude_in_process(run.scenario)
    rate_ref = np.linalg.norm(reference["att_omega_radps"], axis=1)
    print(f"external board, {BOARD_STEPS} steps real time: final rate {np.degrees(rate[-1]):.4f} deg/s, "
          f"in process {np.degrees(rate_ref[-1]):.4f} deg/s; max |omega - omega_ref| "
          f"{np.degrees(np.abs(t['att_omega_radps'] - reference['att_omega_radps']).max()):.4f} deg/s; "
          f"max |applied - applied_ref| {np.abs(t['att_dipole_applied_am2'] - reference['att_dipole_applied_am2']).max():.4f} A m^2")
