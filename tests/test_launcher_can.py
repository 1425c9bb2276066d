"""`bench run` with the magnetorquer on the CAN bus: driver in the controller process, bus model
and board in their own, faults from the scenario, and what the driver saw in the run directory."""
import json
from collections import Counter

import can
import cantools
import numpy as np
import pytest

from bench.bus.can.protocol import DBC_PATH
from conftest import run_bench_cli


@pytest.fixture(scope="module")
def can_run(tmp_path_factory):
    runs = tmp_path_factory.mktemp("runs")
    result = run_bench_cli("run", "rendezvous_mtq_bus", "--run-id", "mtq", "--runs-dir", str(runs), "--no-progress",
                           timeout_s=180)
    assert result.returncode == 0, result.stderr + result.stdout
    return runs / "mtq"


def test_all_five_processes_ran(can_run):
    metrics = json.loads((can_run / "metrics.json").read_text())
    assert {"plant", "estimator", "controller", "canbus", "mtq"} <= set(metrics["processes"])
    assert all(p["exit_code"] == 0 for p in metrics["processes"].values())


def test_driver_in_the_controller_process_detected_each_scripted_fault(can_run):
    driver = json.loads((can_run / "can" / "driver.json").read_text())
    kinds = Counter(e["kind"] for e in driver["events"])
    # corrupt (2 command frames): the board rejects them and says so on its emergency frame.
    assert kinds["command_rejected"] >= 2
    # drop (3 telemetry frames): gaps in the telemetry counter.
    assert kinds["telemetry_out_of_sequence"] + kinds["telemetry_lost"] >= 1
    # board death for 1 s: lost within 3 heartbeat periods (0.3 s), then back.
    lost = [e for e in driver["events"] if e["kind"] == "heartbeat_timeout"]
    assert lost and all(e["latency_s"] <= 0.3 for e in lost)
    assert kinds["heartbeat_resumed"] >= 1
    assert driver["health"]["ok"] is True


def test_no_corrupted_command_was_applied(can_run):
    from bench.bus.can import protocol as p
    from bench.scenario import load_scenario

    can_cfg = load_scenario("rendezvous_mtq_bus").can
    command_frame = p.PROFILES[can_cfg.security.profile]
    board = json.loads((can_run / "can" / "board.json").read_text())
    # The two corrupted frames: refused by the E2E CRC, or on secoc (the default) by the MAC first.
    assert board["rejected"].get("WRONG_CRC", 0) + board["rejected"].get("WRONG_MAC", 0) >= 2
    assert len(board["applied"]) == board["accepted"]
    # Every command heard was applied, rejected, or ignored before the driver's NMT start.
    ignored = sum(n for what, n in board["ignored"].items() if what.startswith(f"{command_frame} while"))
    command_rejections = sum(n for what, n in board["rejected"].items() if not what.startswith("NMT"))
    assert board["accepted"] + command_rejections + ignored == board["received"][command_frame]
    # Flipped data bits would change a dipole: every applied one is a value the profile scripts.
    scripted = {tuple(step.dipole_am2) for step in can_cfg.dipole_profile}
    assert {tuple(a["dipole_am2"]) for a in board["applied"]} <= scripted


def test_plant_recorded_the_applied_dipole(can_run):
    with np.load(can_run / "trajectory.npz") as data:
        dipoles = data["mtq_dipole_am2"]
    assert len(dipoles) > 10
    assert np.abs(dipoles).max() == pytest.approx(0.1, abs=2e-3)   # the scripted profile's 0.1 A m^2


def test_capture_decodes_with_the_dbc_and_the_report_shows_the_bus(can_run):
    db = cantools.database.load_file(DBC_PATH)
    frames = list(can.LogReader(str(can_run / "can.log")))
    assert len(frames) > 100
    known = {m.frame_id for m in db.messages}
    decoded = [db.decode_message(f.arbitration_id, f.data) for f in frames if f.arbitration_id in known and not f.is_error_frame]
    assert len(decoded) > 100
    report = (can_run / "report.md").read_text()
    assert "## CAN bus" in report and "heartbeat_timeout" in report
