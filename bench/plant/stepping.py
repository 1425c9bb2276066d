"""What both plant processes (translation: bench/plant/node.py; attitude:
bench/plant/attitude_node.py) step their loops with: the step clock (lock-step or real time,
chosen once by `step_clock`: docs/time-model.md), the per-step stamp log.

Commands pass the output stage (bench/plant/acceptance.py) here: only an acceptable command for
the current step is returned, whoever sent it.
"""
from __future__ import annotations

import queue
import time

import numpy as np

from bench.bus import keys
from bench.bus.schemas import STAGES, StepDone, header
from bench.bus.spill import StepColumn
from bench.plant.acceptance import CommandGate
from bench.runtime.deadline import PlantCommandDeadline
from bench.runtime.node import NodeContext
from bench.runtime.time_model import TimeModel


# A wait of the plant this long is reported to the launcher (a StepDone with `waiting`), once per
# wait in lock-step, every WAIT_REPORT_S while it lasts in real time: its progress watchdog
# (bench/runtime/progress_watchdog.py) then knows which stage a stalled run is stuck on. A healthy
# loop waits milliseconds, so these reports cost nothing until something stalls.
WAIT_REPORT_S = 1.0


class LoopBroken(RuntimeError):
    """Lock-step cannot go on: a command never came."""


class WaitReport:
    """One wait of the plant for step k's message on `topic`; `poll` (at least every 0.2 s while
    waiting) tells the launcher once it has lasted WAIT_REPORT_S (`repeat`: again every WAIT_REPORT_S)."""

    def __init__(self, ctx: NodeContext, k: int, topic: str, since_s: float | None = None, repeat: bool = False):
        self.ctx, self.k, self.topic, self.repeat = ctx, k, topic, repeat
        self.since_s = time.monotonic() if since_s is None else since_s
        self._next_s = self.since_s + WAIT_REPORT_S

    def poll(self) -> None:
        now = time.monotonic()
        if now < self._next_s:
            return
        self._next_s = now + WAIT_REPORT_S if self.repeat else float("inf")
        scenario = self.ctx.scenario
        self.ctx.publish(keys.STATUS_STEP, StepDone(header(self.ctx.run_id, self.k, self.k * scenario.step_s),
                                                    scenario.n_steps, waiting=self.topic,
                                                    waited_s=round(now - self.since_s, 3)))


def command_topic(ctx: NodeContext) -> str:
    return keys.COMMAND_DIPOLE if ctx.scenario.kind == "attitude" else keys.COMMAND_THRUST


class StampLog:
    """Monotonic stamps (ns) of every applied command, one row per step, -1 where absent."""

    def __init__(self, n_steps: int):
        # The recent steps in memory, the rest on disk (bench/bus/spill.py): flat in a run of any length.
        self.stamps = {stage: StepColumn(n_steps, (), np.int64, -1) for stage in STAGES}

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
    waiting = WaitReport(ctx, k, command_topic(ctx))
    while not ctx.stop.is_set():
        waiting.poll()
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


class LockStepClock:
    """Step k starts as soon as step k-1 is integrated, and waits for step k's command (up to the
    run's command timeout): simulated time is the step count, no deadline applies."""

    late_commands = 0       # a command is never late: the step waits for it
    missed_steps = 0

    def __init__(self, command_timeout_s: float):
        self.command_timeout_s = command_timeout_s

    def start_step(self, k: int) -> None:
        """Nothing to wait for: the previous step's command is in."""

    def command_for_step(self, ctx: NodeContext, commands: queue.Queue, k: int, gate: CommandGate, sim_time_s: float,
                         value=lambda command: command.thrust_n):
        """The first acceptable command for step k; None if only refused ones came by the timeout."""
        return wait_command_lockstep(ctx, commands, k, self.command_timeout_s, gate, value)


def step_clock(scenario) -> "LockStepClock | RealTimeClock":
    """The plant's clock for the run's time model (bench/runtime/time_model.py)."""
    if TimeModel.of(scenario).lock_step:
        return LockStepClock(scenario.run.command_timeout_s)
    return RealTimeClock(scenario.step_s / scenario.run.time_factor)


class RealTimeClock:
    """Step ticks on the monotonic clock, and the plant's view of each command's deadline: step k
    starts at t0 + k * period, and its command must be in before step k+1's tick."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.t0 = time.monotonic() + 0.05
        self.deadline = PlantCommandDeadline(period_s)
        self.late_commands = 0     # arrived after their step had been integrated
        self._last_command_s = self.t0       # when a command last came, on time or late
        self._without_command: WaitReport | None = None

    def tick_s(self, k: int) -> float:
        return self.t0 + k * self.period_s

    @property
    def missed_steps(self) -> int:
        return self.deadline.counter.misses

    def start_step(self, k: int) -> None:
        self.sleep_until(self.tick_s(k))

    def command_for_step(self, ctx: NodeContext, commands: queue.Queue, k: int, gate: CommandGate, sim_time_s: float,
                         value=lambda command: command.thrust_n):
        """Step k's acceptable command if it came before step k+1's tick, else None (the plant holds
        the last one); a miss is published as the plant's DeadlineEvent (its header at sim_time_s)."""
        command = self.collect_command(ctx, commands, k, gate, value)
        outcome = self.deadline.check(k, time.monotonic() - self.tick_s(k))
        if outcome.has_event:
            ctx.publish(keys.EVENT_DEADLINE, outcome.deadline_event(header(ctx.run_id, k, sim_time_s), "plant"))
        return command

    def sleep_until(self, t_s: float) -> None:
        delay = t_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    def collect_command(self, ctx: NodeContext, commands: queue.Queue, k: int, gate: CommandGate,
                        value=lambda command: command.thrust_n):
        """The acceptable command for step k if it arrives before step k+1's tick; late ones are counted."""
        deadline = self.tick_s(k + 1)
        refused = False
        if self._without_command is None:
            self._without_command = WaitReport(ctx, k, command_topic(ctx), since_s=self._last_command_s, repeat=True)
        self._without_command.k = k
        self._without_command.poll()
        while True:
            remaining = deadline - time.monotonic()
            try:
                command = commands.get(timeout=remaining) if remaining > 0 else commands.get_nowait()
            except queue.Empty:
                if refused:
                    gate.refuse_step()
                return None
            verdict = gate.check(value(command), seq=command.header.seq, step=k)
            if verdict.accepted or command.header.seq < k:
                self._last_command_s, self._without_command = time.monotonic(), None   # late or not, it is there
            if verdict.accepted:
                self.deadline.command_arrived(k)
                return command
            if command.header.seq < k:
                self.late_commands += 1
            else:
                refused = True
                _log_refusal(ctx, gate, command, k, verdict.reason)
