"""One attitude-controller cycle under its deadline: estimate in, dipole out. Shared by the
controller process and the in-process loop (bench.sim) so the two cannot drift apart.

The law picks the dipole (bench.controller.attitude_laws, from the scenario); the deadline monitor
of the translational loop times it, and on a miss in real-time mode holds the last dipole. A law
that needs an attitude gets no say until the estimate is valid: the cycle commands zero (coils off).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.controller.attitude_laws import build_attitude_law
from bench.controller.config import ATTITUDE_FREE_LAWS
from bench.controller.deadline import DeadlineMonitor
from bench.gnc.attitude_law import AttitudeControlInput
from bench.runtime.deadline import CycleOutcome
from bench.scenario import Scenario


@dataclass
class AttitudeCycleOutcome:
    dipole_am2: np.ndarray
    monitored: CycleOutcome | None     # None when no law ran (no valid estimate yet)
    saturated: bool
    weak_field: bool
    error_angle_rad: float | None


class AttitudeCycle:
    def __init__(self, scenario: Scenario):
        self.law_name = scenario.attitude_control.law
        self.law = build_attitude_law(scenario)
        self.needs_attitude = self.law_name not in ATTITUDE_FREE_LAWS
        deadline = scenario.controller.deadline
        if deadline.fallback == "lqr":
            raise ValueError("controller.deadline.fallback: 'lqr' is a translational law; the attitude loop holds")
        self.monitor = DeadlineMonitor(deadline, n_inputs=3, apply_fallback=scenario.run.mode == "real-time")
        self.saturated_cycles = 0
        self.weak_field_cycles = 0
        self.waiting_for_estimate_cycles = 0
        self.bad_estimate_cycles = 0

    def run(self, time_s: float, valid: bool, q_wxyz, omega_radps, field_body_t,
            start_ns: int | None = None) -> AttitudeCycleOutcome:
        if self.needs_attitude and not valid:
            self.waiting_for_estimate_cycles += 1
            return AttitudeCycleOutcome(np.zeros(3), None, False, False, None)
        q, omega, field_t = (np.asarray(v, float) for v in (q_wxyz, omega_radps, field_body_t))
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(omega)) and abs(np.linalg.norm(q) - 1.0) < 1e-6):
            # A schema-valid estimate with a NaN or non-unit attitude: coils off, counted, never fatal.
            self.bad_estimate_cycles += 1
            return AttitudeCycleOutcome(np.zeros(3), None, False, False, None)
        x = AttitudeControlInput(time_s, q, omega, field_t)
        outcome = self.monitor.run_cycle(x, self.law.eval, start_ns)
        dipole = outcome.thrust_n      # the monitor's name for the command vector
        if not np.all(np.isfinite(dipole)):
            # The laws never return one (they check |B| and finiteness); a last guard all the same.
            dipole = np.zeros(3)
        info = outcome.info
        saturated, weak = bool(info.get("saturated", False)), bool(info.get("weak_or_bad_field", False))
        self.saturated_cycles += saturated
        self.weak_field_cycles += weak
        angle = info.get("error_angle_rad")
        return AttitudeCycleOutcome(dipole, outcome, saturated, weak, None if angle is None else float(angle))

    def summary(self) -> dict:
        return self.monitor.summary() | {"law": self.law_name, "saturated_cycles": self.saturated_cycles,
                                         "weak_field_cycles": self.weak_field_cycles,
                                         "waiting_for_estimate_cycles": self.waiting_for_estimate_cycles,
                                         "bad_estimate_cycles": self.bad_estimate_cycles}
