"""The built-in attitude scenarios moved onto the kernel's SocketCAN, for user-mode Linux.

Used by the guest tests (guest_attitude_scenarios_socketcan.py) and by
benchmarks/can_fault_latency_transports.py. A scenario keeps everything it has (law, faults,
criteria, seed, mode) but its `[can]` transport: `socketcan` on a vcan pair of its own, so that
several runs can share one guest at once. Real-time runs take the start-up bounds of
attitude_detumble_socketcan (UML's one CPU starts six processes slowly).
"""
from __future__ import annotations

import json
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = REPO / "bench" / "scenarios"
SLEW = "attitude_slew_milqr"
HOLD = "attitude_pointing_hold"
FAULTS = ("attitude_fault_all", "attitude_fault_babble", "attitude_fault_board_death", "attitude_fault_commands",
          "attitude_fault_stuck")
# What the driver must report for each fault (tests/test_attitude_processes.py checks the same
# over the portable transport); the scenario's criteria name the kind its fault shows as.
EXPECTED_KINDS = {
    "board_power_loss": {"heartbeat_timeout"},
    "drop": {"board_command_timeout"},
    "corrupt": {"command_rejected"},
    "telemetry_freeze": {"actuator_mismatch", "telemetry_repeated"},
    "coil_stuck": {"actuator_mismatch"},
    "flood": {"board_command_timeout", "telemetry_timeout", "heartbeat_timeout", "command_rejected"},
}


def builtin(name: str) -> dict:
    return tomllib.loads((SCENARIOS / f"{name}.toml").read_text())


# A starved guest held a lock-step run's plant (running, CPU time advancing) off Zenoh for over
# 60 s (measured at host load 13-18 with two runs at once: the launcher ended the run as hung).
UML_HANG_TIMEOUT_S = 300.0
# SecOC's freshness window is one command period plus freshness_margin_s (30 ms by default): a
# frame from the driver crosses two vcans and the bus model's process before the board checks it,
# and on a starved guest that took longer. Measured at host load 3-5 with the default margin: the
# board refused 3,628 of ~4,000 commands of a 40-step hold as STALE (each step then waited out the
# plant's wait for the board's report: 4 s a step) and every NMT start of the slew beside it (the
# board never became operational). These runs test the kernel's CAN path, not the replay window
# (tests/test_can_freshness.py does), so the guest's margin is one second.
UML_FRESHNESS_MARGIN_S = 1.0


def uml_liveliness() -> dict:
    """attitude_detumble_socketcan's start-up and lease bounds (measured on UML there), and a
    hang bound for a guest that several runs share."""
    liveliness = dict(builtin("attitude_detumble_socketcan")["run"]["liveliness"])
    liveliness["hang_timeout_s"] = max(liveliness.get("hang_timeout_s", 0.0), UML_HANG_TIMEOUT_S)
    return liveliness


def over_socketcan(name: str, flight_channel: str, board_channel: str) -> dict:
    """The built-in scenario `name` with its bus on the kernel's SocketCAN (flight_channel for
    the driver, board_channel for the board, the bus model between)."""
    data = builtin(name)
    if "can" not in data:
        raise ValueError(f"scenario {name!r} has no [can] section: nothing to move onto SocketCAN")
    data["name"] = f"{name}_socketcan"
    data["can"].update(transport="socketcan", flight_channel=flight_channel, board_channel=board_channel)
    data["run"]["liveliness"] = uml_liveliness()
    data["can"].setdefault("security", {})["freshness_margin_s"] = UML_FRESHNESS_MARGIN_S
    return data


def write_over_socketcan(name: str, flight_channel: str, board_channel: str, directory: Path) -> Path:
    path = Path(directory) / f"{name}_socketcan.json"     # load_scenario reads JSON like TOML
    path.write_text(json.dumps(over_socketcan(name, flight_channel, board_channel)))
    return path


def fault_names(name: str) -> list[str]:
    return [f["name"] for f in builtin(name)["can"].get("faults", [])]


def detection_latencies_s(driver_report: dict) -> dict[str, list[float]]:
    """The driver's detection latency of each event, per kind (can/driver.json)."""
    by_kind: dict[str, list[float]] = {}
    for event in driver_report["events"]:
        by_kind.setdefault(event["kind"], []).append(float(event["latency_s"]))
    return by_kind
