"""The coils between the board's coil drivers and the torque: the plant's hook for coil faults.

The board sets each coil driver to a dipole (what it reports as applied); `CoilModel` says what
the coils make of it, per coil: `gain * applied` from `from_s` on ([attitude.coils]). A gain of 1
is a healthy coil, 0 an open one, -1 one wired backwards after the current sensor, 0.5 a weak one.
AttitudePlant.apply turns the result into torque (m x B), so the in-process loop and the plant
process get the same fault at the same step; the board, its telemetry and the driver see nothing.

Kept minimal on purpose: the named hardware faults of the bus (coil_open, coil_reversed,
coil_gain, coil_stuck, board_power_loss in [[can.faults]]) are to be built on the board and on
this hook; a stuck coil (a constant dipole whatever is set) would add an offset here.
"""
from __future__ import annotations

import numpy as np

from bench.config.plant import CoilsConfig


class CoilModel:
    def __init__(self, config: CoilsConfig | None = None):
        config = config or CoilsConfig()
        self.gain = np.asarray(config.gain, float)
        self.from_s = float(config.from_s)
        self.healthy = bool(np.all(self.gain == 1.0))

    def dipole_am2(self, time_s: float, applied_am2: np.ndarray) -> np.ndarray:
        """The dipole the coils produce over a step starting at `time_s` for the drivers' setting."""
        if self.healthy or time_s < self.from_s:
            return applied_am2
        return self.gain * applied_am2
