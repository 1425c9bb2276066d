"""One controller cycle under its deadline: estimate in, command out, shared by the controller
process and bench.sim so the two cannot drift apart.

The command is saturated at the thrusters' limit u_max per axis, as flight software does before
it commands an actuator; seed 003's `simulate` (bench.studies) leaves it unsaturated on purpose
to study constraint satisfaction, the bench flies what the hardware can do.
"""
from __future__ import annotations

import numpy as np

from bench.controller.deadline import DeadlineMonitor, lqr_fallback_law
from bench.controller.thrust import ThrustLaw
from bench.runtime.deadline import CycleOutcome
from bench.scenario import Scenario


class ControlCycle:
    def __init__(self, scenario: Scenario):
        self.law = ThrustLaw(scenario)
        deadline = scenario.controller.deadline
        lqr_law = lqr_fallback_law(scenario.controller, self.law.params) if deadline.fallback == "lqr" else None
        self.monitor = DeadlineMonitor(deadline, n_inputs=3, lqr_law=lqr_law,
                                       apply_fallback=scenario.run.mode == "real-time")
        self.max_abs_thrust_n = self.law.params.max_abs_thrust_n
        self.saturated_cycles = 0

    def run(self, state_m_mps: np.ndarray, mean_motion_radps: float | None = None,
            start_ns: int | None = None) -> CycleOutcome:
        """start_ns: when the estimate arrived, so time spent queued counts against the budget."""
        self.law.update_model(mean_motion_radps)
        outcome = self.monitor.run_cycle(self.law.to_scaled(state_m_mps), self.law.controller.eval, start_ns)
        saturated = np.clip(outcome.thrust_n, -self.max_abs_thrust_n, self.max_abs_thrust_n)
        if not np.array_equal(saturated, outcome.thrust_n):
            self.saturated_cycles += 1
            outcome.thrust_n = saturated
        return outcome
