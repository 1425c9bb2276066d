"""The SocketCAN subset of the fault suite, on a real kernel vcan inside user-mode Linux.

Driver on vcan0, board on vcan1, the bus model bridging them: the same processes, checks and
bounds as tests/test_can_faults.py (imported from there), only the transport differs. The host's
test_kernel_can_uml.py boots UML and runs this file there.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import test_can_faults as suite  # noqa: E402

from bench.bus.can.transport import kernel_has_can  # noqa: E402

pytestmark = pytest.mark.skipif(not kernel_has_can(), reason="runs inside user-mode Linux (tests/uml.py)")


def run(tmp_path, *faults):
    return suite.run_fault(tmp_path, *faults, transport=suite.SOCKETCAN)


def test_socketcan_clean_bus(tmp_path):
    r = run(tmp_path)
    assert suite.before_silence(r) == []
    assert r.board["accepted"] == r.driver_sent
    suite.check_all(r)


def test_socketcan_dropped_commands(tmp_path):
    r = run(tmp_path, {"name": "drop", "start_s": suite.FAULT_START_S, "count": 10})
    assert suite.latency_s(r, "board_command_timeout", r.first_injection_ns("dropped")) <= 3 * suite.COMMAND_TIMEOUT_S
    suite.check_all(r)


def test_socketcan_corrupted_commands(tmp_path):
    r = run(tmp_path, {"name": "corrupt", "start_s": suite.FAULT_START_S, "count": 5, "every": 10,
                       "params": {"bits": 3}})
    assert r.board["rejected"] == {"WRONG_CRC": suite.affected(r)}, suite.diagnosis(r)
    assert suite.latency_s(r, "command_rejected", r.first_injection_ns("replaced"), "WRONG_CRC") <= 5 * suite.COMMAND_PERIOD_S
    suite.check_all(r)


def test_socketcan_spoofed_commands(tmp_path):
    r = run(tmp_path, {"name": "spoof", "start_s": suite.FAULT_START_S, "count": 3, "every": 10})
    assert r.board["rejected"] == {"WRONG_CRC": suite.injected_frames_on_the_wire(r)}, suite.diagnosis(r)
    assert suite.latency_s(r, "spoofed_command", suite.first_injection_on_the_wire_ns(r)) <= 5 * suite.COMMAND_PERIOD_S
    suite.check_all(r)


def test_socketcan_board_death(tmp_path):
    r = run(tmp_path, {"name": "board_death", "start_s": suite.FAULT_START_S, "duration_s": 0.6})
    assert suite.latency_s(r, "heartbeat_timeout", suite.window_start_ns(r)) <= 3 * suite.HEARTBEAT_PERIOD_S
    suite.check_all(r)


def test_socketcan_babbling_node(tmp_path):
    r = run(tmp_path, {"name": "flood", "start_s": suite.FAULT_START_S, "duration_s": 0.5})
    assert suite.latency_s(r, "heartbeat_timeout", suite.window_start_ns(r)) <= 3 * suite.HEARTBEAT_PERIOD_S
    assert r.report["peak_load_pct"] > 99
    suite.check_all(r)
