"""One controller cycle under its deadline: estimate in, command out, shared by the controller
process and bench.sim so the two cannot drift apart.

The command is saturated at the thrusters' limit u_max per axis, as flight software does before
it commands an actuator; seed 003's `simulate` (bench.studies) leaves it unsaturated on purpose
to study constraint satisfaction, the bench flies what the hardware can do.
"""
from __future__ import annotations

import numpy as np

from bench.config.controller import StressConfig
from bench.controller.deadline import DeadlineMonitor, StressInjector, lqr_fallback_law
from bench.controller.thrust import ThrustLaw
from bench.runtime.deadline import CycleOutcome
from bench.runtime.priority import raise_realtime_priority, thread_realtime_priority
from bench.runtime.time_model import TimeModel
from bench.runtime.solver_worker import WorkerLaw
from bench.scenario import Scenario

# The command's status in a cycle without a valid estimate (the law did not run; zero thrust).
WAITING_FOR_ESTIMATE = "waiting_for_estimate"


class ControlCycle:
    """Real-time mode runs the law in a solver worker process (the command leaves by the deadline
    whatever the solver does, and a mean-motion update builds the new law there while the old one
    serves); lock-step mode runs it in-process, where the plant waits for every command anyway."""

    def __init__(self, scenario: Scenario):
        # Real time: the law runs in a solver worker process under the deadline (bench/runtime/time_model.py).
        real_time = TimeModel.of(scenario).deadlines_apply
        self.law = ThrustLaw(scenario, in_process=not real_time)
        deadline = scenario.controller.deadline
        lqr_law = (lqr_fallback_law(scenario.controller, self.law.params)
                   if deadline.fallback in ("lqr", "shifted_plan") else None)
        stress = StressInjector(deadline.stress, "controller")
        self.worker = None
        self.realtime_priority_granted = False
        self.cycle_realtime_priority = 0
        if real_time:
            # The stress acts on the solve, in the worker, as a slow solver would.
            self.worker = WorkerLaw(self.law.factory, nx=6, nu=3, plan_rows=max(scenario.controller.horizon, 1),
                                    hard_limit_s=deadline.hard_limit_s, stress=stress)
            self.worker.wait_ready()
            stress = StressInjector(StressConfig(), "controller")
            # The thread that builds the cycle runs it (the node's main loop); at its process's
            # priority if that is higher (the loop's, [run] realtime_priority), never below it.
            self.realtime_priority_granted = (deadline.realtime_priority > 0
                                              and raise_realtime_priority(deadline.realtime_priority))
            self.cycle_realtime_priority = thread_realtime_priority()
        self.monitor = DeadlineMonitor(deadline, n_inputs=3, lqr_law=lqr_law, stress=stress,
                                       apply_fallback=real_time)
        self.max_abs_thrust_n = self.law.params.max_abs_thrust_n
        self.saturated_cycles = 0
        self.waiting_for_estimate_cycles = 0

    def run(self, state_m_mps: np.ndarray | None, mean_motion_radps: float | None = None,
            start_ns: int | None = None, step: int | None = None) -> CycleOutcome:
        """start_ns: when the estimate arrived, so time spent queued counts against the budget;
        step: the plant step it acts at (the estimate's seq; DeadlineMonitor.run_cycle).
        state_m_mps None: no valid estimate yet (before the estimator's first fix); the law does
        not run and the thrust is zero, as the attitude loop switches its coils off."""
        if state_m_mps is None:
            self.waiting_for_estimate_cycles += 1
            return CycleOutcome(np.zeros(3), {"status": WAITING_FOR_ESTIMATE, "ctrl_feas": True},
                                cycle_index=-1, cycle_time_s=0.0, budget_s=self.monitor.budget_s,
                                missed=False, consecutive_misses=0, fallback=None)
        if self.law.update_model(mean_motion_radps) and self.worker is not None:
            self.worker.replace(self.law.factory)
        compute = self.worker if self.worker is not None else self.law.controller.eval
        outcome = self.monitor.run_cycle(self.law.to_scaled(state_m_mps), compute, start_ns, step)
        saturated = np.clip(outcome.thrust_n, -self.max_abs_thrust_n, self.max_abs_thrust_n)
        if not np.array_equal(saturated, outcome.thrust_n):
            self.saturated_cycles += 1
            outcome.thrust_n = saturated
        return outcome

    def summary(self) -> dict:
        out = self.monitor.summary() | {"saturated_cycles": self.saturated_cycles,
                                        "waiting_for_estimate_cycles": self.waiting_for_estimate_cycles,
                                        "model_updates": self.law.model_updates}
        if self.worker is not None:
            out["solver_worker"] = self.worker.stats.summary()
            out["stress_injected_cycles"] = self.worker.stats.stress_injected     # applied in the worker
            out["realtime_priority_granted"] = self.realtime_priority_granted
            out["cycle_realtime_priority"] = self.cycle_realtime_priority     # SCHED_FIFO the cycle ran at
        return out

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
