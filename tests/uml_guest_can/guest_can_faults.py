"""The SocketCAN subset of the fault suite, on a real kernel vcan inside user-mode Linux.

Driver on vcan0, board on vcan1, the bus model bridging them: the same processes, checks and
bounds as tests/test_can_faults.py (imported from there), only the transport differs. The subset
is what the kernel's sockets carry differently: every frame across them (clean), a board timeout
across them (dropped commands), and a flood through their queues (babbling node). The faults that
alter frames in the bus model run on simulated time and in real time on the host. The host's
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


def test_socketcan_babbling_node(tmp_path):
    r = run(tmp_path, {"name": "flood", "start_s": suite.FAULT_START_S, "duration_s": 0.5})
    assert suite.latency_s(r, "heartbeat_timeout", suite.window_start_ns(r)) <= 3 * suite.HEARTBEAT_PERIOD_S
    assert r.report["peak_load_pct"] > 99
    suite.check_all(r)
