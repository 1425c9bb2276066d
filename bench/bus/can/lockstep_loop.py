"""The lock-step bus of the attitude loop in one process: what the controller and canbus processes
do with each step's CAN window, without the hops (the in-process loop with faults, bench/sim.py).

The controller's `LockStepLink` hands the flight-side driver (`WindowedDriver`) each step's dipole
and sends the frames of the step [k dt, (k+1) dt) as a CanWindow; the canbus process runs them
through `LockStepBus` (bus model, fault injector, board and its hardware) and answers with the
frames the driver heard and the coils' output over the step (MtqApplied), which the plant
integrates; the driver handles what it heard before the next step's window. Here the same objects
are called in the same order with the same values, so a lock-step run with faults and this loop
give the same trajectory to the last bit, as long as both use the same SecOC key (the MAC's bits
change the frames' stuff bits, hence their timing): the run's key where the scenario carries one
(the run directory's scenario.json), else one derived from the run's seed.
"""
from __future__ import annotations

import hashlib

import numpy as np

from bench.bus.can.driver import FaultEvent
from bench.bus.can.lockstep_bus import LockStepBus, StepCoils
from bench.bus.can.run_key import can_needs_key, can_with_key
from bench.bus.can.sim_window import mission_s, sim_ns
from bench.bus.can.windowed_driver import BOOT_WINDOWS, WindowedDriver


def seeded_key_hex(seed: int) -> str:
    """A SecOC key from the run's seed: the bus lives in this process, so it guards nothing, and a
    seeded key keeps the frames' timing, hence the run, the same wherever it runs."""
    return hashlib.sha256(f"bus co-simulation seed {seed}".encode()).hexdigest()[:32]


class LockStepLoopBus:
    """`step(k, dipole_am2) -> StepCoils`: step k's command through the driver, the bus and the
    board on simulated time; `events`: what the driver detected, as (mission s, FaultEvent)."""

    def __init__(self, can_config, step_s: float, seed: int):
        if can_needs_key(can_config):
            can_config = can_with_key(can_config, seeded_key_hex(seed))
        self.config = can_config
        self.step_s = step_s
        self.windowed = WindowedDriver(can_config)
        self.bus = LockStepBus(can_config, seed=seed)
        self.events: list[tuple[float, FaultEvent]] = []
        for _, start_ns, end_ns in BOOT_WINDOWS:       # boot-up heartbeat, then the driver's NMT start
            self._window(start_ns, end_ns, None)

    def _window(self, start_ns: int, end_ns: int, dipole) -> StepCoils:
        frames, _, _ = self.windowed.window(start_ns, end_ns, dipole)
        heard, coils = self.bus.advance(start_ns, end_ns, frames)
        self.events += [(mission_s(e.detected_ns), e) for e in self.windowed.heard(heard)]
        return coils

    def board_ok(self) -> bool:
        """The flight-side driver's word on the board after the last window (BoardHealth.ok)."""
        return self.windowed.driver.health().ok

    def step(self, k: int, dipole_am2) -> StepCoils:
        return self._window(sim_ns(k * self.step_s), sim_ns((k + 1) * self.step_s),
                            np.asarray(dipole_am2, float))
