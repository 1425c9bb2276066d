"""SCHED_FIFO for the real-time loop and the wall-clock CAN nodes (bench/runtime/priority.py), and the measures a fault
check uses to tell the host's hold-ups from the fault (host_lateness.held_s, RunClock's inverse)."""
from __future__ import annotations

import subprocess
import sys

import msgspec
import numpy as np
import pytest

from bench.bus.can.host_lateness import HostLate, held_s
from bench.report.timebase import RunClock
from bench.runtime.priority import CAN_BUS_NODES, node_realtime_priority
from bench.scenario import load_scenario


def brute_force_held_s(records, from_ns, to_ns, step_ns=100_000):
    """The same measure on a 0.1 ms grid: a grid cell counts if any record's hold covers it."""
    grid = np.arange(from_ns, to_ns, step_ns) + step_ns / 2
    covered = np.zeros(grid.size, bool)
    for r in records:
        covered |= (grid >= r.t_ns - r.late_s * 1e9) & (grid < r.t_ns)
    return covered.sum() * step_ns / 1e9


@pytest.mark.parametrize("seed", range(5))
def test_held_s_counts_each_moment_of_overlapping_holds_once(seed):
    rng = np.random.default_rng(seed)
    records = [HostLate(str(rng.choice(["driver", "board", "bus_model"])), int(t_ns), float(late_s))
               for t_ns, late_s in zip(rng.integers(0, 2_000_000_000, 40) // 100_000 * 100_000,
                                       rng.integers(1, 1500, 40) * 1e-4)]
    from_ns, to_ns = 300_000_000, 1_500_000_000
    assert held_s(records, from_ns, to_ns) == pytest.approx(brute_force_held_s(records, from_ns, to_ns), abs=1e-9)
    # one hold noticed by three records counts once, not three times (the sum would say 0.3 s)
    same = [HostLate("bus_model", 1_000_000_000, 0.1), HostLate("bus_model", 1_000_000_000, 0.1), HostLate("board", 990_000_000, 0.09)]
    assert held_s(same, 0, 2_000_000_000) == pytest.approx(0.1)
    assert held_s(same, 950_000_000, 2_000_000_000) == pytest.approx(0.05)   # from the window's start
    assert held_s([], 0, 10) == 0.0


def test_monotonic_ns_is_the_inverse_of_sim_s():
    steps_ns = np.cumsum(np.full(50, 100_000_000)) + np.arange(50) * 3_000_000   # 0.1 s steps, each a little late
    sim_s = np.arange(50) * 0.1
    scenario = load_scenario("attitude_fault_all")                              # real time, factor 1
    clock = RunClock.from_run({"stamp_sensed_ns": steps_ns, "att_time_s": sim_s}, scenario)
    t = np.linspace(-1.0, 6.0, 71)        # inside the loop and outside it on both sides
    np.testing.assert_allclose(clock.sim_s(clock.monotonic_ns(t)), t, atol=1e-9)
    assert clock.monotonic_ns(0.05) == pytest.approx((steps_ns[0] + steps_ns[1]) / 2)


def test_the_loop_in_real_time_and_the_nodes_of_a_bus_on_the_wall_clock_take_the_priority():
    real_time = load_scenario("attitude_fault_all")
    assert real_time.can.realtime_priority == 20 and real_time.run.realtime_priority == 20
    everyone = ("plant", "estimator", "recorder", "planner", *CAN_BUS_NODES)
    assert {n: node_realtime_priority(n, real_time, cpus=2) for n in everyone} == \
        {"plant": 20, "estimator": 20, "recorder": 0, "planner": 0, "mtq": 20, "canbus": 20, "controller": 20}
    # one CPU (the user-mode Linux guest of tests/test_kernel_can_uml.py): the loop needs it all
    assert all(node_realtime_priority(n, real_time, cpus=1) == 0 for n in everyone)
    # lock-step with the bus on simulated time: the host's delays change no step and no frame's time
    lock_step = msgspec.structs.replace(real_time, run=msgspec.structs.replace(real_time.run, mode="lock-step"))
    assert all(node_realtime_priority(n, lock_step, cpus=2) == 0 for n in everyone)
    # each setting on its own; the controller, in both, takes the higher
    def with_priorities(run_priority: int, can_priority: int):
        return msgspec.structs.replace(real_time, run=msgspec.structs.replace(real_time.run, realtime_priority=run_priority),
                                       can=msgspec.structs.replace(real_time.can, realtime_priority=can_priority))
    assert {n: node_realtime_priority(n, with_priorities(0, 20), cpus=2) for n in ("plant", "estimator", "controller", "mtq")} == \
        {"plant": 0, "estimator": 0, "controller": 20, "mtq": 20}
    assert {n: node_realtime_priority(n, with_priorities(30, 0), cpus=2) for n in ("plant", "estimator", "controller", "mtq")} == \
        {"plant": 30, "estimator": 30, "controller": 30, "mtq": 0}
    assert all(node_realtime_priority(n, with_priorities(0, 0), cpus=2) == 0 for n in everyone)
    # no CAN bus: the loop in real time only
    rendezvous = load_scenario("rendezvous_lqr")
    assert all(node_realtime_priority(n, rendezvous, cpus=2) == 0 for n in everyone)
    rendezvous_rt = msgspec.structs.replace(rendezvous, run=msgspec.structs.replace(rendezvous.run, mode="real-time"))
    assert {n: node_realtime_priority(n, rendezvous_rt, cpus=2) for n in ("plant", "estimator", "controller", "recorder")} == \
        {"plant": 20, "estimator": 20, "controller": 20, "recorder": 0}


INHERITANCE = """
import os, threading, sys
from bench.runtime.priority import set_realtime_priority
assert set_realtime_priority(7, inherited=sys.argv[1] == "1")
seen = []
t = threading.Thread(target=lambda: seen.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)))
t.start(); t.join()
child = os.fork()
if child == 0:
    os._exit(0 if os.sched_getscheduler(0) == os.SCHED_FIFO else 1)
_, status = os.waitpid(child, 0)
print(seen[0][0] == os.SCHED_FIFO, seen[0][1], os.waitstatus_to_exitcode(status) == 0)
"""


@pytest.mark.skipif(not hasattr(__import__("os"), "sched_setscheduler"), reason="no sched_setscheduler")
def test_a_whole_process_priority_reaches_threads_started_after_it_and_a_thread_one_does_not():
    def run(inherited: str) -> str:
        result = subprocess.run([sys.executable, "-c", INHERITANCE, inherited], capture_output=True, text=True, timeout=60)
        if "AssertionError" in result.stderr:
            pytest.skip("SCHED_FIFO refused here (no CAP_SYS_NICE)")
        assert result.returncode == 0, result.stderr
        return result.stdout.split()
    # a node's whole process: Zenoh's threads, started after it, and the driver's thread run at it
    assert run("1") == ["True", "7", "True"]
    # one thread's (the controller's cycle): its workers and other threads start at normal priority
    assert run("0") == ["False", "0", "False"]


RAISING = """
import threading
from bench.runtime.priority import raise_realtime_priority, set_realtime_priority, thread_realtime_priority
seen = [thread_realtime_priority()]
assert set_realtime_priority(20, inherited=True)           # a loop node's whole process
seen += [raise_realtime_priority(10), thread_realtime_priority()]   # the controller's cycle: not lowered
seen += [raise_realtime_priority(30), thread_realtime_priority()]   # raised where asked higher
t = threading.Thread(target=lambda: seen.append(thread_realtime_priority()))
t.start(); t.join()                                        # started after the raise: reset on fork, as a worker
print(*seen)
"""


@pytest.mark.skipif(not hasattr(__import__("os"), "sched_setscheduler"), reason="no sched_setscheduler")
def test_the_controller_cycle_never_runs_below_its_process_priority():
    result = subprocess.run([sys.executable, "-c", RAISING], capture_output=True, text=True, timeout=60)
    if "AssertionError" in result.stderr:
        pytest.skip("SCHED_FIFO refused here (no CAP_SYS_NICE)")
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["0", "True", "20", "True", "30", "0"]
