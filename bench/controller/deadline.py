"""Deadline monitoring of the control loop, in the manner of F Prime's rate groups.

Every controller cycle has a wall-clock budget (`deadline.budget_s` in the scenario's
[controller] section). `DeadlineMonitor.run_cycle` times the cycle on the monotonic clock, counts
overruns (cycle slips, with `bench.runtime.deadline.MissCounter`), and on a miss throws the late
result away and applies the configured fallback, so the loop keeps running. proxsuite has no
wall-clock limit of its own: the bench owns the budget, and a solve whose result comes too late is
abandoned here.

The plant's view of the same deadline (`PlantCommandDeadline`) and the miss bookkeeping both
share are in `bench.runtime.deadline`; the budget, fallback and stress schema in
`bench.config.controller`.

`StressInjector` makes a process slow on purpose (a scenario option), deterministically: a CPU
busy loop or a sleep of `extra_cycle_time_s` on listed cycles or on every Nth cycle.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from bench.bus.spill import SpilledRows
from bench.config.controller import ControllerConfig, DeadlineConfig, StressConfig
from bench.controller.factory import weights_from_config
from bench.gnc.cwh import RendezvousParams
from bench.gnc.lqr import LQR
from bench.runtime.deadline import CycleOutcome, MissCounter

# Key of `info` under which a predictive controller returns its planned inputs, shape (N, n_u),
# in N; the "shifted_plan" fallback replays the rest of the last plan that came in on time.
PLAN_INFO_KEY = "u_plan"


# --- stress -----------------------------------------------------------------------------------
def busy_wait_s(duration_s: float, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
    """Burn CPU for duration_s on the monotonic clock (a loop, not a sleep: it is load)."""
    end_ns = clock_ns() + int(duration_s * 1e9)
    while clock_ns() < end_ns:
        pass


class StressInjector:
    """Applies a StressConfig in the process it names; a no-op in every other process."""

    def __init__(self, config: StressConfig, process: str):
        self.config = config
        self.active = config.process == process and config.extra_cycle_time_s > 0
        self.injected_cycles: list[int] = []

    def apply(self, cycle_index: int) -> bool:
        """Add the extra time if this cycle is stressed; True if it was."""
        if not (self.active and self.config.is_stressed(cycle_index)):
            return False
        if self.config.kind == "busy":
            busy_wait_s(self.config.extra_cycle_time_s)
        else:
            time.sleep(self.config.extra_cycle_time_s)
        self.injected_cycles.append(cycle_index)
        return True


# --- fallbacks --------------------------------------------------------------------------------
@dataclass
class _LastGood:
    """What the fallbacks replay: the last command sent, the last plan that was on time and the
    plant step it was made for (entry k of the plan is the input for k steps later)."""

    command: np.ndarray
    plan: np.ndarray | None = None
    plan_step: int = 0


class DeadlineMonitor:
    """Wraps every controller cycle: times it, counts misses, substitutes the fallback.

    compute(x) -> (u, info) is the controller's `eval`. lqr_law(x) -> u is required for the
    "lqr" fallback (see `lqr_fallback_law`). clock_ns is injectable so tests can drive time.
    """

    def __init__(
        self,
        config: DeadlineConfig,
        n_inputs: int = 3,
        lqr_law: Callable[[np.ndarray], np.ndarray] | None = None,
        stress: StressInjector | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        apply_fallback: bool = True,
    ):
        """apply_fallback=False (lock-step mode): a miss is counted and reported but the late
        result is still used, because the plant waits for it anyway and lock-step runs must not
        depend on how busy the machine was."""
        if config.fallback == "lqr" and lqr_law is None:
            raise ValueError("controller.deadline.fallback = 'lqr' needs an LQR law (lqr_fallback_law)")
        self.config = config
        self.budget_s = config.budget_s
        self.lqr_law = lqr_law
        self.stress = stress or StressInjector(config.stress, "controller")
        self.clock_ns = clock_ns
        self.apply_fallback = apply_fallback
        self.counter = MissCounter()
        self.fallbacks_applied: dict[str, int] = {}
        self._last = _LastGood(command=np.zeros(n_inputs))
        # Per cycle, on disk as they come (bench/bus/spill.py): summary() takes exact percentiles
        # of them, and a controller of any run length keeps a flat memory (issue 44).
        self.cycle_times_s = SpilledRows(())
        # Per cycle, how long after the deadline the OS ran the controller again (a law in a worker
        # process reports it, `WorkerLaw.last_wake_late_s`): the host's share of an overrun, so a
        # report tells a slow solver from a busy machine.
        self.host_wake_late_s = SpilledRows(())

    # --- the cycle ---------------------------------------------------------------------------
    def run_cycle(
        self,
        x: np.ndarray,
        compute: Callable[[np.ndarray], tuple[np.ndarray, dict]],
        start_ns: int | None = None,
        step: int | None = None,
    ) -> CycleOutcome:
        """One controller cycle. start_ns: when the cycle began (the `controller_received`
        stamp), so time spent queued in the node counts against the budget; default now.
        step: the plant step it acts at (the estimate's seq; default: one step per cycle), which
        indexes the shifted plan: a real-time controller passes over superseded estimates."""
        start_ns = self.clock_ns() if start_ns is None else start_ns
        cycle_index = self.counter.cycles
        step = cycle_index if step is None else step
        evaluate = getattr(compute, "evaluate", None)
        if evaluate is not None:
            # A law in a worker process (WorkerLaw): it answers by the deadline or not at all.
            deadline_ns = start_ns + int(self.budget_s * 1e9) if self.apply_fallback else None
            result = evaluate(x, deadline_ns, cycle_index)
        else:
            result = compute(x)
            self.stress.apply(cycle_index)
        cycle_time_s = (self.clock_ns() - start_ns) / 1e9
        self.host_wake_late_s.append(float(getattr(compute, "last_wake_late_s", 0.0)) if evaluate else 0.0)
        if result is None:
            u, info = None, {"ctrl_feas": False, "status": "NO_RESULT_BY_DEADLINE", "solve_time": cycle_time_s,
                             "iterations": 0}
        else:
            u, info = result
        missed = result is None or cycle_time_s > self.budget_s
        was_missing = self.counter.consecutive_misses > 0
        self.counter.record(cycle_time_s, missed)
        self.cycle_times_s.append(cycle_time_s)
        if missed and (self.apply_fallback or result is None):
            u, fallback = self._fallback(x, step)
            self.fallbacks_applied[fallback] = self.fallbacks_applied.get(fallback, 0) + 1
        else:
            fallback = None
            self._accept(info, step)
        self._last.command = np.asarray(u, dtype=float)
        return CycleOutcome(
            thrust_n=self._last.command.copy(),
            info=info,
            cycle_index=cycle_index,
            cycle_time_s=cycle_time_s,
            budget_s=self.budget_s,
            missed=missed,
            consecutive_misses=self.counter.consecutive_misses,
            fallback=fallback,
            recovered=was_missing and not missed,
        )

    def _accept(self, info: dict, step: int) -> None:
        """An on-time result: remember its plan and the step it was made for."""
        plan = info.get(PLAN_INFO_KEY)
        if plan is not None:
            self._last.plan = np.atleast_2d(np.asarray(plan, dtype=float))
            self._last.plan_step = step

    def _fallback(self, x: np.ndarray, step: int) -> tuple[np.ndarray, str]:
        """The command the configured fallback gives. "shifted_plan" replays entry k of the last
        on-time plan k steps after the step it was made for: k counts every step since, missed,
        on time without a plan (an infeasible MPC cycle publishes none) or passed over, since the
        plan's entry k is the input for that time; with no plan, or past its end, LQR acts if a
        law was given, else "hold". The name returned says which one acted."""
        policy = self.config.fallback
        if policy == "shifted_plan" and self._last.plan is not None:
            elapsed_steps = step - self._last.plan_step
            if elapsed_steps < len(self._last.plan):
                return self._last.plan[elapsed_steps].copy(), "shifted_plan"
        if policy in ("lqr", "shifted_plan") and self.lqr_law is not None:
            return np.asarray(self.lqr_law(x), dtype=float), "lqr"
        return self._last.command.copy(), "hold"

    # --- for the report ------------------------------------------------------------------
    def summary(self) -> dict:
        """Numbers for metrics.json: cycles, misses, worst cycle time, fallbacks applied."""
        times = self.cycle_times_s.array() if self.cycle_times_s else np.zeros(1)
        host_late = self.host_wake_late_s.array() if self.host_wake_late_s else np.zeros(1)
        return {
            **self.counter.summary(),
            "cycle_time_p50_s": float(np.percentile(times, 50)),
            "cycle_time_p99_s": float(np.percentile(times, 99)),
            "host_wake_late_p99_s": float(np.percentile(host_late, 99)),
            "host_wake_late_max_s": float(host_late.max()),
            # what the controller itself took, the host's lateness to wake it taken out
            "cycle_time_less_host_p99_s": float(np.percentile(times - host_late, 99)),
            "budget_s": self.budget_s,
            "fallback": self.config.fallback,
            "fallbacks_applied": dict(self.fallbacks_applied),
            "stress_injected_cycles": len(self.stress.injected_cycles),
        }


def lqr_fallback_law(controller_config: ControllerConfig, params: RendezvousParams) -> Callable[[np.ndarray], np.ndarray]:
    """u = K x of the scenario's LQR weights on the scaled model: the "lqr" fallback."""
    q, r = weights_from_config(controller_config)
    lqr = LQR(q, r, params.scaled.A, params.scaled.B)
    return lambda x: lqr.K @ np.asarray(x, dtype=float)
