"""What both plant processes (translation: bench/plant/node.py; attitude:
bench/plant/attitude_node.py) step their loops with: the lock-step wait for step k's command, the
real-time clock and its command deadline, the per-step stamp log.

Commands pass the output stage (bench/plant/acceptance.py) here: only an acceptable command for
the current step is returned, whoever sent it.
"""
from __future__ import annotations

import queue
import time

import numpy as np

from bench.bus.schemas import STAGES
from bench.plant.acceptance import CommandGate
from bench.runtime.deadline import PlantCommandDeadline
from bench.runtime.node import NodeContext


class LoopBroken(RuntimeError):
    """Lock-step cannot go on: a command never came."""


class StampLog:
    """Monotonic stamps (ns) of every applied command, one row per step, -1 where absent."""

    def __init__(self, n_steps: int):
        self.stamps = {stage: np.full(n_steps, -1, dtype=np.int64) for stage in STAGES}

    def record(self, k: int, stamps_ns: dict[str, int]) -> None:
        for stage, value in stamps_ns.items():
            if stage in self.stamps:
                self.stamps[stage][k] = value


def wait_command_lockstep(ctx: NodeContext, commands: queue.Queue, k: int, timeout_s: float,
                           gate: CommandGate, value=lambda command: command.thrust_n):
    """The first acceptable command for step k; None if only refused ones came by the timeout.
    value: the commanded quantity the gate checks (thrust here; the attitude plant's dipole)."""
    deadline = time.monotonic() + timeout_s
    refused = 0
    while not ctx.stop.is_set():
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            if refused:
                ctx.log.error("step %d: only refused commands within %.3g s; applying the %s policy", k, timeout_s,
                              gate.on_reject)
                gate.refuse_step()
                return None
            raise LoopBroken(f"no thrust command for step {k} within {timeout_s} s")
        if ctx.lost_peer(ctx.scenario.run.liveliness.hang_timeout_s):
            raise LoopBroken(f"peer '{ctx.lost_peer(0.0)}' lost while waiting for the command of step {k}")
        try:
            command = commands.get(timeout=min(remaining, 0.2))
        except queue.Empty:
            continue
        verdict = gate.check(value(command), seq=command.header.seq, step=k)
        if verdict.accepted:
            return command
        refused += 1
        _log_refusal(ctx, gate, command, k, verdict.reason)
    raise LoopBroken("stopped")


def _log_refusal(ctx: NodeContext, gate: CommandGate, command, k: int, reason: str) -> None:
    n = gate.rejected[reason]
    if n <= 5 or n % 100 == 0:    # a flood must not flood the log too
        ctx.log.warning("refused command #%d (%s) at step %d: seq %d, thrust %s N", n, reason, k,
                        command.header.seq, command.thrust_n)


class RealTimeClock:
    """Step ticks on the monotonic clock, and the plant's view of each command's deadline."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.t0 = time.monotonic() + 0.05
        self.deadline = PlantCommandDeadline(period_s)
        self.late_commands = 0     # arrived after their step had been integrated

    def tick_s(self, k: int) -> float:
        return self.t0 + k * self.period_s

    def sleep_until(self, t_s: float) -> None:
        delay = t_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    def collect_command(self, ctx: NodeContext, commands: queue.Queue, k: int, gate: CommandGate,
                        value=lambda command: command.thrust_n):
        """The acceptable command for step k if it arrives before step k+1's tick; late ones are counted."""
        deadline = self.tick_s(k + 1)
        refused = False
        while True:
            remaining = deadline - time.monotonic()
            try:
                command = commands.get(timeout=remaining) if remaining > 0 else commands.get_nowait()
            except queue.Empty:
                if refused:
                    gate.refuse_step()
                return None
            verdict = gate.check(value(command), seq=command.header.seq, step=k)
            if verdict.accepted:
                self.deadline.command_arrived(k)
                return command
            if command.header.seq < k:
                self.late_commands += 1
            else:
                refused = True
                _log_refusal(ctx, gate, command, k, verdict.reason)
