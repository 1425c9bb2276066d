"""Deadline monitoring of the control loop, in the manner of F Prime's rate groups.

Every controller cycle has a wall-clock budget (`deadline.budget_s` in the scenario's
[controller] section). `DeadlineMonitor.run_cycle` times the cycle on the monotonic clock, counts
overruns (cycle slips), keeps the worst cycle time and the current streak of consecutive misses,
and on a miss throws the late result away and applies the configured fallback, so the loop keeps
running. proxsuite has no wall-clock limit of its own: the bench owns the budget. A solve whose
result comes too late is abandoned here, and `iteration_cap()` lets an iterative solver stop in
time, from the measured time per iteration of earlier cycles.

`PlantCommandDeadline` is the plant's view of the same deadline in real-time mode: a command for
step k that is not in when step k is integrated is a miss there too. Comparing both tells
"controller was slow" from "transport was slow".

`StressInjector` makes a process slow on purpose (a scenario option), deterministically: a CPU
busy loop or a sleep of `extra_cycle_time_s` on listed cycles or on every Nth cycle.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Annotated, Callable, Literal

import msgspec
import numpy as np

from bench.bus.schemas import DeadlineEvent, Header

Seconds = Annotated[float, msgspec.Meta(ge=0, le=60.0)]
PositiveSeconds = Annotated[float, msgspec.Meta(gt=0, le=60.0)]
FallbackPolicy = Literal["hold", "shifted_plan", "lqr"]
# Processes that apply a StressConfig (call StressInjector(config, name).apply(cycle) in their
# loop). Only the controller does so far; a scenario naming another is refused, not ignored.
StressedProcess = Literal["controller"]

# Key of `info` under which a predictive controller returns its planned inputs, shape (N, n_u),
# in N; the "shifted_plan" fallback replays the rest of the last plan that came in on time.
PLAN_INFO_KEY = "u_plan"


# --- scenario configuration -------------------------------------------------------------------
class StressConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Extra time added to chosen cycles of one process, to make deadline misses on purpose.

    A cycle i (0-based) is stressed if i is in `cycles`, or if `every_nth_cycle` = N > 0 and
    (i + 1) is a multiple of N (the Nth, 2Nth, ... cycle). Over n cycles that is exactly
    len({i in cycles, i < n} | {N-1, 2N-1, ...}) stressed cycles: tests can count them.
    """

    process: StressedProcess = "controller"
    extra_cycle_time_s: Seconds = 0.0
    cycles: Annotated[list[Annotated[int, msgspec.Meta(ge=0, le=100_000)]], msgspec.Meta(max_length=10_000)] = []
    every_nth_cycle: Annotated[int, msgspec.Meta(ge=0, le=100_000)] = 0
    # "busy": burn CPU (load, as a slow solver would); "sleep": a pure delay (as a pre-empted one).
    kind: Literal["busy", "sleep"] = "busy"

    def is_stressed(self, cycle_index: int) -> bool:
        if self.extra_cycle_time_s <= 0:
            return False
        if cycle_index in self.cycles:
            return True
        return self.every_nth_cycle > 0 and (cycle_index + 1) % self.every_nth_cycle == 0

    def stressed_count(self, n_cycles: int) -> int:
        """How many of cycles 0..n_cycles-1 get the extra time."""
        return sum(self.is_stressed(i) for i in range(n_cycles))


class DeadlineConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Scenario [controller.deadline]."""

    # Wall-clock budget from the estimate's arrival to the command being ready. The default is
    # half the step period of real-time mode at its default rate (10 steps per wall second).
    budget_s: PositiveSeconds = 0.05
    fallback: FallbackPolicy = "hold"
    stress: StressConfig = msgspec.field(default_factory=StressConfig)


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


# --- miss bookkeeping shared by the controller's and the plant's view -------------------------
@dataclass
class MissCounter:
    """Cycle slips as F Prime counts them: total, current streak, longest streak, worst time."""

    cycles: int = 0
    misses: int = 0
    consecutive_misses: int = 0
    max_consecutive_misses: int = 0
    worst_cycle_time_s: float = 0.0

    def record(self, cycle_time_s: float, missed: bool) -> None:
        self.cycles += 1
        self.worst_cycle_time_s = max(self.worst_cycle_time_s, cycle_time_s)
        if missed:
            self.misses += 1
            self.consecutive_misses += 1
            self.max_consecutive_misses = max(self.max_consecutive_misses, self.consecutive_misses)
        else:
            self.consecutive_misses = 0

    def summary(self) -> dict:
        return {
            "cycles": self.cycles,
            "misses": self.misses,
            "max_consecutive_misses": self.max_consecutive_misses,
            "worst_cycle_time_s": self.worst_cycle_time_s,
        }


@dataclass
class CycleOutcome:
    """What one monitored cycle produced: the command to send and the deadline bookkeeping."""

    thrust_n: np.ndarray
    info: dict
    cycle_index: int
    cycle_time_s: float
    budget_s: float
    missed: bool
    consecutive_misses: int
    fallback: str | None           # the fallback that produced thrust_n, None if on time
    recovered: bool = False        # first on-time cycle after a streak of misses

    @property
    def has_event(self) -> bool:
        """Publish a DeadlineEvent on every miss and when a streak of misses ends."""
        return self.missed or self.recovered

    def deadline_event(self, header: Header, process: str = "controller") -> DeadlineEvent:
        return DeadlineEvent(
            header=header,
            process=process,
            cycle_time_s=self.cycle_time_s,
            budget_s=self.budget_s,
            missed=self.missed,
            consecutive_misses=self.consecutive_misses,
            fallback=self.fallback,
        )


# --- fallbacks --------------------------------------------------------------------------------
@dataclass
class _LastGood:
    """What the fallbacks replay: the last command sent and the last plan that was on time."""

    command: np.ndarray
    plan: np.ndarray | None = None
    cycles_since_plan: int = 0


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
        self._seconds_per_iteration: float | None = None

    # --- the cycle ---------------------------------------------------------------------------
    def run_cycle(
        self,
        x: np.ndarray,
        compute: Callable[[np.ndarray], tuple[np.ndarray, dict]],
        start_ns: int | None = None,
    ) -> CycleOutcome:
        """One controller cycle. start_ns: when the cycle began (the `controller_received`
        stamp), so time spent queued in the node counts against the budget; default now."""
        start_ns = self.clock_ns() if start_ns is None else start_ns
        cycle_index = self.counter.cycles
        u, info = compute(x)
        self.stress.apply(cycle_index)
        cycle_time_s = (self.clock_ns() - start_ns) / 1e9
        missed = cycle_time_s > self.budget_s
        was_missing = self.counter.consecutive_misses > 0
        self.counter.record(cycle_time_s, missed)
        if missed and self.apply_fallback:
            u, fallback = self._fallback(x)
            self.fallbacks_applied[fallback] = self.fallbacks_applied.get(fallback, 0) + 1
        else:
            fallback = None
            self._accept(info)
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

    def _accept(self, info: dict) -> None:
        """An on-time result: remember its plan and how fast the solver iterated."""
        plan = info.get(PLAN_INFO_KEY)
        if plan is not None:
            self._last.plan = np.atleast_2d(np.asarray(plan, dtype=float))
            self._last.cycles_since_plan = 0
        iterations = int(info.get("iterations") or 0)
        solve_time_s = info.get("solve_time")
        if iterations > 0 and solve_time_s is not None:
            self._seconds_per_iteration = float(solve_time_s) / iterations

    def _fallback(self, x: np.ndarray) -> tuple[np.ndarray, str]:
        """The command the configured fallback gives; "shifted_plan" degrades to "hold" when
        there is no plan or it is used up, and the name returned says which one acted."""
        policy = self.config.fallback
        if policy == "lqr":
            return np.asarray(self.lqr_law(x), dtype=float), "lqr"
        if policy == "shifted_plan" and self._last.plan is not None:
            self._last.cycles_since_plan += 1
            if self._last.cycles_since_plan < len(self._last.plan):
                return self._last.plan[self._last.cycles_since_plan].copy(), "shifted_plan"
        return self._last.command.copy(), "hold"

    # --- helpers for the solver and the report -----------------------------------------------
    def iteration_cap(self, elapsed_s: float = 0.0, safety: float = 0.8) -> int | None:
        """Iterations that fit in what is left of the budget, from the measured time per
        iteration of earlier on-time cycles; None until one has been measured. Pass it to
        proxsuite as settings.max_iter so a solve stops in time instead of being abandoned."""
        if self._seconds_per_iteration is None or self._seconds_per_iteration <= 0:
            return None
        remaining_s = max(0.0, self.budget_s * safety - elapsed_s)
        return max(1, int(remaining_s / self._seconds_per_iteration))

    def summary(self) -> dict:
        """Numbers for metrics.json: cycles, misses, worst cycle time, fallbacks applied."""
        return {
            **self.counter.summary(),
            "budget_s": self.budget_s,
            "fallback": self.config.fallback,
            "fallbacks_applied": dict(self.fallbacks_applied),
            "stress_injected_cycles": len(self.stress.injected_cycles),
        }


def lqr_fallback_law(controller_config, params) -> Callable[[np.ndarray], np.ndarray]:
    """u = K x of the scenario's LQR weights on the scaled model: the "lqr" fallback."""
    # Imported here: bench.controller.config imports this module for DeadlineConfig.
    from bench.controller.factory import weights_from_config
    from bench.controller.lqr import LQR

    q, r = weights_from_config(controller_config)
    lqr = LQR(q, r, params.scaled.A, params.scaled.B)
    return lambda x: lqr.K @ np.asarray(x, dtype=float)


# --- the plant's side -------------------------------------------------------------------------
@dataclass
class PlantCommandDeadline:
    """Real-time mode, plant side: is step k's command in when step k is integrated?

    Call `command_arrived(seq)` for every command received and `check(k, waited_s)` when step k
    is integrated; a miss means the plant applies the last command it has (zero-order hold).
    """

    step_period_s: float
    counter: MissCounter = field(default_factory=MissCounter)
    _arrived: set = field(default_factory=set)

    def command_arrived(self, seq: int) -> None:
        self._arrived.add(seq)

    def check(self, step_k: int, waited_s: float) -> CycleOutcome:
        """waited_s: wall time from sensing step k to integrating it (the plant's cycle time)."""
        missed = step_k not in self._arrived
        was_missing = self.counter.consecutive_misses > 0
        self.counter.record(waited_s, missed)
        self._arrived = {s for s in self._arrived if s > step_k}
        return CycleOutcome(
            thrust_n=np.zeros(0),
            info={},
            cycle_index=step_k,
            cycle_time_s=waited_s,
            budget_s=self.step_period_s,
            missed=missed,
            consecutive_misses=self.counter.consecutive_misses,
            fallback="hold" if missed else None,
            recovered=was_missing and not missed,
        )
