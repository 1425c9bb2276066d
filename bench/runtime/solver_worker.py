"""A control law run in a worker process, so a command can leave by its deadline whatever the law does.

proxsuite holds Python's GIL for a whole solve (a 165 ms solve let a 1 ms ticker thread run
twice), so no thread of the flight process can act while it runs: the law runs in its own process.
The flight side writes the state into shared memory and posts a semaphore; the worker evaluates
`law.eval(x) -> (u, info)` and writes u, the plan (info["u_plan"], N x nu) and the scalar info
fields back; the flight side waits on a second semaphore with a timeout equal to what is left of
its budget (sem_timedwait releases the GIL). Then:

- result in time: returned;
- budget reached: `evaluate` returns None (the caller publishes its fallback and counts the miss);
  the request stays outstanding and no new one is sent until it is answered;
- the late result, when it arrives, is read and discarded (counted as `late_results`);
- a request outstanding longer than `hard_limit_s`: the worker is killed and a new one started,
  which rebuilds the law from its factory (so the solver's warm start is rebuilt from scratch);
  counted as `restarts`.

`replace(factory)` swaps the law without a gap: a new worker builds the new law while the old one
keeps serving, and takes over once it is ready (used when the mean-motion estimate moves: the
terminal set's LPs, seconds on this machine, never run in a control cycle).

Fast path: a law that offers `explicit_path()` (CondensedMPC: its explicit law and KKT
certificate, bench.gnc.mpc.ExplicitPath) has it sent once to the flight process when the worker has
built the law. A cycle with no request outstanding and no stress tries it first in the flight
process: where its certificate holds, it is the answer (bit-identical to the worker's, the same
object computes both), a fixed few matrix-vector products with no round trip (counted as
`explicit_cycles`); elsewhere the state goes to the worker as above. The path belongs to its
worker: after `replace()` or a restart, the new worker's path serves, never the old law's.

Any object with `eval(x) -> (u, info)` can be served: the MPC family, LQR, attitude laws, the
MILQR tracker. The factory must be picklable (a module-level function or functools.partial).

Shared memory and semaphores rather than a Pipe: see benchmarks/bench_mpc.py for the round trip
of both on this machine.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import time
from dataclasses import dataclass, field
from multiprocessing import shared_memory
from typing import Callable

import numpy as np

from bench.runtime.priority import set_realtime_priority

PLAN_INFO_KEY = "u_plan"
STATUS_BYTES = 64
_STOP = -1


# Integer and float slots of the shared block (plain ndarray views: a structured record's field
# access cost ~4 us each, 60-70 us per cycle on both sides).
REQ_SEQ, RESP_SEQ, READY, ERROR, PLAN_ROWS, CTRL_FEAS, ITERATIONS, CYCLE = range(8)
N_INTS = 8
OBJECTIVE, SOLVE_TIME = range(2)


class _SharedBlock:
    """Views on one shared-memory block: ints[8], floats[2], x[nx], u[nu], plan[rows, nu], status."""

    def __init__(self, buf, nx: int, nu: int, plan_rows: int):
        sizes = [("ints", np.int64, (N_INTS,)), ("floats", np.float64, (2,)), ("x", np.float64, (nx,)),
                 ("u", np.float64, (nu,)), ("plan", np.float64, (plan_rows, nu)), ("status", np.uint8, (STATUS_BYTES,))]
        offset = 0
        for name, dtype, shape in sizes:
            view = np.ndarray(shape, dtype=dtype, buffer=buf, offset=offset)
            setattr(self, name, view)
            offset += view.nbytes

    @staticmethod
    def nbytes(nx: int, nu: int, plan_rows: int) -> int:
        return 8 * (N_INTS + 2 + nx + nu + plan_rows * nu) + STATUS_BYTES

    def set_status(self, text: str) -> None:
        raw = text.encode(errors="replace")[:STATUS_BYTES]
        self.status[:] = 0
        self.status[:len(raw)] = np.frombuffer(raw, dtype=np.uint8)

    def get_status(self) -> str:
        return self.status.tobytes().rstrip(b"\0").decode(errors="replace")

    def release(self) -> None:
        for name in ("ints", "floats", "x", "u", "plan", "status"):
            setattr(self, name, None)


def _offered_path(law, unpack):
    """The law's explicit path for the flight process, or None (laws on a packed record: no)."""
    offer = getattr(law, "explicit_path", None)
    if unpack is not None or not callable(offer):
        return None
    return offer()


def _worker_main(factory, shm_name, shape, request, response, stress=None, priority=0, unpack=None,
                 parent_pid=None, path_conn=None) -> None:
    shm = shared_memory.SharedMemory(name=shm_name)
    blk = _SharedBlock(shm.buf, *shape)
    try:
        law = factory()
        if path_conn is not None:
            # Before READY: the flight side takes the worker as ready only with its path in hand.
            # The worker's law skips the cycles the flight process answers on this path; the MPC
            # reads and writes no solver state (warm start, last active set) on its explicit path,
            # so its later solves are the ones it would have made seeing every cycle.
            try:
                try:
                    path_conn.send(_offered_path(law, unpack))
                except OSError:
                    raise
                except Exception:         # no or an unpicklable path: the worker serves every cycle
                    path_conn.send(None)
            except OSError:               # the flight side closed its end: it is stopping us
                pass
            finally:
                path_conn.close()
        set_realtime_priority(priority)   # 0 too: not its parent's, whatever that runs at
        blk.ints[READY] = 1
        plan_cap = blk.plan.shape[0]
        parent = os.getppid() if parent_pid is None else parent_pid   # passed in: no race with its death
        while True:
            if not request.acquire(timeout=1.0):
                if os.getppid() != parent:       # the flight process died (SIGKILL): do not linger
                    return
                continue
            seq = int(blk.ints[REQ_SEQ])
            if seq == _STOP:
                return
            x = blk.x.copy()
            try:
                u, info = law.eval(x if unpack is None else unpack(x))
                if stress is not None:               # on the controller's cycle index
                    stress.apply(int(blk.ints[CYCLE]))
                blk.u[:] = np.asarray(u, dtype=float).reshape(-1)
                plan = info.get(PLAN_INFO_KEY)
                rows = 0
                if plan is not None:
                    plan = np.atleast_2d(np.asarray(plan, dtype=float))[:plan_cap]
                    rows = plan.shape[0]
                    blk.plan[:rows] = plan
                blk.ints[PLAN_ROWS] = rows
                blk.ints[CTRL_FEAS] = int(bool(info.get("ctrl_feas", True)))
                blk.ints[ITERATIONS] = int(info.get("iterations", 0))
                blk.floats[OBJECTIVE] = float(info.get("objective", np.nan))
                blk.floats[SOLVE_TIME] = float(info.get("solve_time", 0.0))
                blk.set_status(str(info.get("status", "")))
                blk.ints[ERROR] = 0
            except Exception as exc:          # a law that raises is reported, not fatal
                blk.ints[ERROR] = 1
                blk.ints[CTRL_FEAS] = 0
                blk.ints[PLAN_ROWS] = 0
                blk.set_status(f"{type(exc).__name__}: {exc}")
            blk.ints[RESP_SEQ] = seq
            response.release()
    finally:
        blk.release()
        shm.close()


@dataclass
class WorkerStats:
    requests: int = 0
    on_time: int = 0
    timeouts: int = 0
    late_results: int = 0          # answers that came after their deadline, discarded
    busy_cycles: int = 0           # cycles where the worker was still on an old request
    starting_cycles: int = 0       # cycles where the (re)started worker was not ready yet
    restarts: int = 0              # workers killed at the hard limit
    replacements: int = 0          # laws swapped by replace()
    errors: int = 0                # the law raised inside the worker
    stress_injected: int = 0       # requests the stress made slow on purpose (StressInjector)
    explicit_cycles: int = 0       # cycles answered in the flight process on the law's explicit path

    def summary(self) -> dict:
        return dict(self.__dict__)


@dataclass
class _Worker:
    process: mp.Process
    shm: shared_memory.SharedMemory
    blk: _SharedBlock
    request: object
    response: object
    path_conn: object = None       # receives the law's explicit path (or None) once, at start-up
    path: object = None            # that path, e.g. bench.gnc.mpc.ExplicitPath

    def ready(self) -> bool:
        """The law is built and its explicit path (if any) received."""
        if self.path_conn is not None:
            if not self.path_conn.poll():
                return False
            try:
                self.path = self.path_conn.recv()
            except (EOFError, OSError):     # the worker died while starting: READY stays 0
                self.path = None
            self.path_conn.close()
            self.path_conn = None
        return bool(self.blk.ints[READY])

    def stop(self, kill: bool = False) -> None:
        if self.path_conn is not None:          # first: a worker blocked sending its path gets EPIPE
            self.path_conn.close()
            self.path_conn = None
        if self.process.is_alive():
            if kill:
                self.process.kill()
            else:
                self.blk.ints[REQ_SEQ] = _STOP
                self.request.release()
                self.process.join(1.0)
                if self.process.is_alive():
                    self.process.kill()
        self.process.join(1.0)
        self.blk.release()
        self.shm.close()
        self.shm.unlink()


@dataclass
class WorkerLaw:
    """`eval` with a deadline, the law running in a worker process (see the module docstring).

    factory() -> law; nx, nu: state and input sizes; plan_rows: the longest plan kept.
    hard_limit_s: an outstanding request older than this gets its worker killed and restarted.
    stress: a StressInjector applied in the worker after each eval (a slow solver on purpose).
    unpack: turns the state vector into the law's input in the worker (a picklable function), for
    laws whose input is a record, e.g. an attitude law's AttitudeControlInput packed as
    [t, q_wxyz, omega, B] (11 floats); None: the law takes the vector.
    worker_priority: SCHED_FIFO priority of the worker once its law is built (0: default
    scheduler); set it below the flight thread's, so the flight side still acts at its deadline.
    explicit_fast_path: answer on the law's explicit path in this process where it holds (see the
    module docstring); False sends every cycle to the worker (the benchmark's baseline).
    """

    factory: Callable
    nx: int
    nu: int
    plan_rows: int = 64
    hard_limit_s: float = 1.0
    stress: object | None = None
    worker_priority: int = 0
    unpack: Callable | None = None
    clock_ns: Callable[[], int] = time.monotonic_ns
    explicit_fast_path: bool = True
    stats: WorkerStats = field(default_factory=WorkerStats)

    def __post_init__(self):
        self._ctx = mp.get_context("spawn")       # the flight process has Zenoh threads: no fork
        self._shape = (self.nx, self.nu, self.plan_rows)
        self._seq = 0
        self._cycles = 0                 # cycles served, explicit or by the worker (default cycle index)
        self.last_wake_late_s = 0.0
        self._outstanding: tuple[int, int] | None = None     # (seq, sent_ns)
        self._worker = self._start(self.factory)
        self._next: _Worker | None = None
        self._next_factory = None

    # --- process management -------------------------------------------------------------------
    def _start(self, factory) -> _Worker:
        shm = shared_memory.SharedMemory(create=True, size=_SharedBlock.nbytes(*self._shape))
        blk = _SharedBlock(shm.buf, *self._shape)
        blk.ints[:] = 0
        request, response = self._ctx.Semaphore(0), self._ctx.Semaphore(0)
        path_recv, path_send = self._ctx.Pipe(duplex=False)
        proc = self._ctx.Process(target=_worker_main, daemon=True, name="solver-worker",
                                 args=(factory, shm.name, self._shape, request, response, self.stress,
                                       self.worker_priority, self.unpack, os.getpid(), path_send))
        proc.start()
        path_send.close()          # the worker holds its own copy: a dead worker reads as EOF here
        return _Worker(proc, shm, blk, request, response, path_recv)

    def wait_ready(self, timeout_s: float = 60.0) -> bool:
        """Block until the current worker has built its law (start-up, before the loop runs)."""
        end = time.monotonic() + timeout_s
        while not self._worker.ready():
            if not self._worker.process.is_alive() or time.monotonic() > end:
                return False
            time.sleep(0.002)
        return True

    def replace(self, factory) -> None:
        """Build `factory`'s law in a new worker; it takes over when ready (see `_swap_if_ready`)."""
        if self._next is not None:
            self._next.stop(kill=True)
        self._next, self._next_factory = self._start(factory), factory

    def _swap_if_ready(self) -> None:
        if self._next is not None and self._next.ready() and self._outstanding is None:
            old, self._worker = self._worker, self._next
            self.factory, self._next, self._next_factory = self._next_factory, None, None
            old.stop()
            self.stats.replacements += 1

    def _restart(self) -> None:
        self._worker.stop(kill=True)
        self._worker = self._start(self.factory)
        self._outstanding = None
        self.stats.restarts += 1

    def close(self) -> None:
        for w in (self._worker, self._next):
            if w is not None:
                w.stop()
        self._next = None

    # --- one cycle ----------------------------------------------------------------------------
    def _collect_late(self) -> None:
        """Drain a late answer of the outstanding request, or restart a worker past the hard limit."""
        if self._outstanding is None:
            return
        if self._worker.response.acquire(block=False):
            self.stats.late_results += 1
            self._outstanding = None
            return
        seq, sent_ns = self._outstanding
        if (self.clock_ns() - sent_ns) / 1e9 > self.hard_limit_s or not self._worker.process.is_alive():
            self._restart()

    def evaluate(self, x: np.ndarray, deadline_ns: int | None,
                 cycle_index: int | None = None) -> tuple[np.ndarray, dict] | None:
        """(u, info) if the law answers by deadline_ns (None: wait as long as it takes), else None.
        cycle_index: the controller's cycle (the stress schedule follows it; default the request count).
        After a timeout, `last_wake_late_s` says how long after deadline_ns this thread ran again:
        the host's share of the overrun (the wait ends at the deadline; a busy machine runs us later)."""
        self.last_wake_late_s = 0.0
        self._collect_late()
        self._swap_if_ready()
        if self._outstanding is not None:
            self.stats.busy_cycles += 1
            return None
        w = self._worker
        if not w.ready():
            if not w.process.is_alive():
                self._restart()
            self.stats.starting_cycles += 1
            return None
        cycle = self._cycles if cycle_index is None else int(cycle_index)
        self._cycles += 1
        stressed = self.stress is not None and self.stress.active and self.stress.config.is_stressed(cycle)
        # A stressed cycle stands for a slow solve: it goes to the worker, explicit region or not.
        if self.explicit_fast_path and w.path is not None and not stressed:
            out = w.path.eval(x)
            if out is not None:
                self.stats.explicit_cycles += 1
                return out
        self._seq += 1
        blk = w.blk
        blk.x[:] = x
        blk.ints[CYCLE] = cycle
        if stressed:
            self.stats.stress_injected += 1
        blk.ints[REQ_SEQ] = self._seq
        self._outstanding = (self._seq, self.clock_ns())
        self.stats.requests += 1
        w.request.release()
        timeout = None if deadline_ns is None else max(0.0, (deadline_ns - self.clock_ns()) / 1e9)
        if not w.response.acquire(timeout=timeout):
            self.stats.timeouts += 1
            self.last_wake_late_s = max(0.0, (self.clock_ns() - deadline_ns) / 1e9)
            return None
        self._outstanding = None
        if int(blk.ints[RESP_SEQ]) != self._seq:          # cannot happen: one request at a time
            raise RuntimeError("solver worker answered another request")
        self.stats.on_time += 1
        ints, floats = blk.ints.tolist(), blk.floats.tolist()
        info = {
            "ctrl_feas": bool(ints[CTRL_FEAS]),
            "objective": floats[OBJECTIVE],
            "solve_time": floats[SOLVE_TIME],
            "iterations": ints[ITERATIONS],
            "status": blk.get_status(),
        }
        if ints[PLAN_ROWS]:
            info[PLAN_INFO_KEY] = blk.plan[:ints[PLAN_ROWS]].copy()
        if ints[ERROR]:
            self.stats.errors += 1
        return blk.u.copy(), info

    def eval(self, x) -> tuple[np.ndarray, dict]:
        """The law's own interface, without a deadline (waits for the answer)."""
        out = self.evaluate(np.asarray(x, dtype=float), None)
        if out is None:
            raise RuntimeError("solver worker is busy or starting")
        return out
