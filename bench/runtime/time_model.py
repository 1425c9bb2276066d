"""What the run's time model (docs/time-model.md) asks of a node that does not keep time itself:
the one place such a node learns `[run] mode`. The plant keeps the run's time with its step clock
(bench/plant/stepping.py); the CAN bus its own (bench/bus/can/sim_window.py).

Lock-step: simulated time moves only when the plant steps, so every message is for a step the
plant waits on. A node takes every message, in order; a message the step promises (the previous
command, a scheduled sensor sample, a plan that is due) is on its way, so it is waited for; and no
deadline applies (a slow host makes the run slower, never different).
Real time: the monotonic clock moves on whatever the nodes do. The newest message is the one that
matters (those queued behind it are stale before they are used), a promised message that is not
in within a sliver of the step is late and the node goes on without it, and deadlines apply.
"""
from __future__ import annotations

from dataclasses import dataclass

# Lock-step: how long a node waits for a message its step promises before it goes on without it
# (a message that never comes: its sender is hung or gone; the launcher's watchdog names which).
LOCK_STEP_PROMISED_WAIT_S = 2.0


@dataclass(frozen=True)
class TimeModel:
    lock_step: bool

    @classmethod
    def of(cls, scenario) -> "TimeModel":
        return cls(lock_step=scenario.run.mode == "lock-step")

    @property
    def takes_every_message(self) -> bool:
        """Every message in order (lock-step), or only the newest of those queued (real time)."""
        return self.lock_step

    @property
    def deadlines_apply(self) -> bool:
        return not self.lock_step

    def promised_wait_s(self, real_time_s: float) -> float:
        """How long to wait for a message the step promises: in real time `real_time_s`, the node's
        sliver of the step; in lock-step LOCK_STEP_PROMISED_WAIT_S (it is on its way)."""
        return LOCK_STEP_PROMISED_WAIT_S if self.lock_step else real_time_s
