"""Deadline-miss accounting shared by every process that runs against a deadline.

`MissCounter` counts cycle slips as F Prime's rate groups do; `CycleOutcome` is what one monitored
cycle produced (and the DeadlineEvent it publishes). The controller's monitor
(`bench.controller.deadline.DeadlineMonitor`) and the plant's `PlantCommandDeadline` both use them,
so "controller was slow" and "transport was slow" are counted the same way.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bench.bus.schemas import DeadlineEvent, Header


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
