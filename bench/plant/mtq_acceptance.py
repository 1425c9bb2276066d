"""The plant's output stage for the magnetorquer: which applied-dipole report it turns into torque.

A report is used only if it is finite, inside the board's envelope (per-axis limit plus half a DAC
step) and current (reported within the board's command timeout plus one driver command period);
anything else is replaced by zero (coils off) and counted with its reason. Issue 10 writes the
plant-wide command-acceptance check; this one function is where it plugs in.
"""
from __future__ import annotations

import time
from collections import Counter
from functools import lru_cache

import numpy as np

from bench.bus.can.config import BoardConfig, CanConfig, DriverConfig


class DipoleAcceptance:
    def __init__(self, can: CanConfig | None):
        board = can.board if can is not None else BoardConfig()
        driver = can.driver if can is not None else DriverConfig()
        self.envelope_am2 = board.max_dipole_am2 + 0.5 * board.dipole_resolution_am2
        self.max_age_s = board.command_timeout_s + driver.command_period_s
        self.rejected: Counter = Counter()

    def accept(self, dipole_am2, reported_ns: int | None, now_ns: int | None = None) -> tuple[np.ndarray, str | None]:
        """(dipole to apply, reason it was refused or None). reported_ns None: no age to check
        (lock-step pairs the report with its command instead)."""
        dipole = np.asarray(dipole_am2, dtype=float)
        reason = None
        if dipole.shape != (3,) or not np.all(np.isfinite(dipole)):
            reason = "not_finite"
        elif np.any(np.abs(dipole) > self.envelope_am2):
            reason = "out_of_envelope"
        elif reported_ns is not None:
            now_ns = time.monotonic_ns() if now_ns is None else now_ns
            if (now_ns - reported_ns) / 1e9 > self.max_age_s:
                reason = "stale"
        if reason is not None:
            self.rejected[reason] += 1
            return np.zeros(3), reason
        return dipole, None


@lru_cache(maxsize=8)
def _protocol(node_id: int):
    from bench.bus.can import protocol as p

    return p.Protocol(node_id)     # ~0.4 ms to build: once per node id


def board_dipole_without_bus(commanded_am2, can: CanConfig | None) -> np.ndarray:
    """The dipole the board would apply for a command, without a bus: the command frame's DBC
    scaling (1e-4 A m^2), then the board's quantisation and saturation. The in-process loop and a
    scenario without [can] use this; over CAN the board itself reports it."""
    from bench.bus.can import protocol as p
    from bench.bus.can.board import coil_driver_dipole

    board = can.board if can is not None else BoardConfig()
    protocol = _protocol(can.node_id if can is not None else 0x10)
    frame = protocol.decode(protocol.command(np.asarray(commanded_am2, float), 0))
    requested = np.array([frame.signals[f"Dipole{a}"] for a in p.AXES])
    return coil_driver_dipole(requested, board)[0]
