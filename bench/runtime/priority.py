"""SCHED_FIFO for the parts of a real-time run that stand for hardware, physics or flight software.

On a loaded host the default scheduler can hold a process up for a hundred milliseconds or more.
For the controller's cycle thread that is a missed deadline (on the 2-core bench machine at load
average 17, 200 cycles, 50 ms solve, 10 ms budget: command out at p99 budget + 5.5 ms and max
+ 8.3 ms under the default scheduler, budget + 0.2 ms under SCHED_FIFO: the wake-up after
sem_timedwait waits for a CPU otherwise); for the CAN nodes it is a fault the bus never had: a
board whose command timeout fires because the bus model delivered late, commands refused as
stale, a dropped-frame fault hidden behind a timeout the host caused. The kernel's RT throttling
(sched_rt_runtime_us) still leaves 5 % of each CPU to other tasks.
"""
from __future__ import annotations

import contextlib
import os


def set_realtime_priority(priority: int, inherited: bool = False) -> bool:
    """SCHED_FIFO at `priority` for the calling thread (0: the default scheduler); False if the
    system refuses (no CAP_SYS_NICE), and the thread keeps its policy. inherited=False: threads
    and processes it starts afterwards run at normal priority (SCHED_RESET_ON_FORK, which the
    kernel applies to threads as to processes); True: they inherit it (a whole process: Zenoh's
    threads, started when the session opens after this)."""
    try:
        if priority > 0:
            reset = 0 if inherited else os.SCHED_RESET_ON_FORK
            os.sched_setscheduler(0, os.SCHED_FIFO | reset, os.sched_param(priority))
        else:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return True
    except (PermissionError, OSError, AttributeError):
        return False


def thread_realtime_priority() -> int:
    """The calling thread's SCHED_FIFO priority; 0 under any other policy."""
    policy = os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
    return os.sched_getparam(0).sched_priority if policy == os.SCHED_FIFO else 0


def raise_realtime_priority(priority: int) -> bool:
    """The calling thread at SCHED_FIFO `priority` unless it already runs higher (a thread of a
    process at [run] realtime_priority); whether it now runs at `priority` or above."""
    if thread_realtime_priority() >= priority:
        return True
    return set_realtime_priority(priority)


@contextlib.contextmanager
def realtime_priority(priority: int):
    """The calling thread at SCHED_FIFO `priority` inside the block; yields whether it took."""
    granted = set_realtime_priority(priority)
    try:
        yield granted
    finally:
        if granted:
            set_realtime_priority(0)


# The processes that carry the actuator bus: the board ("mtq"), the bus model ("canbus") and the
# controller, one of whose threads is the flight-side driver.
CAN_BUS_NODES = ("mtq", "canbus", "controller")
# The processes of the loop from sensing to the command: in real time each wakes for every step.
LOOP_NODES = ("plant", "estimator", "controller")


def node_realtime_priority(name: str, scenario, cpus: int | None = None) -> int:
    """The SCHED_FIFO priority node `name` takes for its whole process before its session opens,
    or 0. In real time the loop's nodes take `[run] realtime_priority`: a loop node the host holds
    up delays every step's command (sense -> board p99 at SCHED_FIFO 20 against the default
    scheduler: docs/performance.md). The nodes of a CAN bus on the wall clock (real time, a
    kernel bus, a part from outside) take `[can] realtime_priority`; on simulated time (lock-step,
    bench/bus/can/sim_window.py) the host's delays change no frame's time. The controller, in both,
    takes the higher. The recorder and the planner never take one: what they do can wait, and
    the planner's long solves would hold the loop up. Nor does any node on a host with one CPU
    (`cpus`: this process's, by default): there the priority would only move the host's delays
    from one of the loop's processes to another."""
    from bench.bus.can.sim_window import bus_on_simulated_time

    if (len(os.sched_getaffinity(0)) if cpus is None else cpus) < 2:
        return 0
    priority = 0
    if name in LOOP_NODES and scenario.run.mode == "real-time":
        priority = scenario.run.realtime_priority
    config = getattr(scenario, "can", None)
    if config is not None and name in CAN_BUS_NODES and not bus_on_simulated_time(scenario):
        priority = max(priority, config.realtime_priority)
    return priority
