"""Running a campaign's cases (bench/studies/campaign.py): one case in a worker, under its
wall-clock timeout, as one row that holds its metrics or its error (run_case: a case's failure
never raises); and the engines that run many, a local process pool whose workers end with the
campaign command however that ends, or Ray.
"""
from __future__ import annotations

import importlib
import json
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable

from bench.scenario import parse_scenario

# The case functions live with what they run (the in-process loop, the launcher), above this
# layer; they are found by name, as `bench.cli` finds subcommands.
RUNNERS = {"in-process": "bench.sim:campaign_case", "processes": "bench.launcher:campaign_case"}
# Case.cell's columns, one per axis (bench.studies.campaign.AXES), in its order.
CELL_COLUMNS = ("controller", "dynamics", "knowledge", "initial_conditions", "fault")


@dataclass(frozen=True)
class Case:
    case_id: str
    index: int                      # position in the spec's expansion: the results file's order
    cell: dict                      # axis column -> value name
    seed: int
    scenario: dict                  # the full scenario, plain data
    mode: str
    timeout_s: float


# ------------------------------------------------------------------------------------------------
# Running one case (in a worker)
# ------------------------------------------------------------------------------------------------
class CaseTimeout(BaseException):
    """Raised in the worker's main thread when a case overruns its wall-clock budget. A
    BaseException so that code under test catching Exception does not swallow it."""


def _runner(mode: str) -> Callable:
    """The case function (imported before the case's clock starts: imports take seconds)."""
    module, _, function = RUNNERS.get(mode, mode).partition(":")
    return getattr(importlib.import_module(module), function)


class _Alarm:
    """SIGALRM after timeout_s in the main thread (where pool and Ray workers run their tasks)."""

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.armed = threading.current_thread() is threading.main_thread() and hasattr(signal, "setitimer")

    def _fire(self, _signum, _frame):
        raise CaseTimeout()

    def __enter__(self):
        if self.armed:
            self.previous = signal.signal(signal.SIGALRM, self._fire)
            signal.setitimer(signal.ITIMER_REAL, self.timeout_s)
        return self

    def __exit__(self, *exc):
        if self.armed:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self.previous)
        return False


def run_case(case: Case) -> dict:
    """One row: the case's columns, its metrics or its error. Never raises for a case's failure."""
    row = {"case_id": case.case_id, "case_index": case.index, **case.cell, "seed": case.seed,
           "scenario_json": json.dumps(case.scenario, sort_keys=True), "status": "ok", "error": ""}
    start = time.perf_counter()
    try:
        runner = _runner(case.mode)
        scenario = parse_scenario(case.scenario, case.case_id)
        with _Alarm(case.timeout_s):
            row.update(runner(scenario))
    except CaseTimeout:
        row.update(status="timeout", error=f"timed out after {case.timeout_s:g} s")
    except Exception as exc:            # a case's failure is a row, whatever it was
        row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    row["wall_time_s"] = time.perf_counter() - start
    return row


# ------------------------------------------------------------------------------------------------
# Engines
# ------------------------------------------------------------------------------------------------
def _failed_row(case: Case, status: str, message: str) -> dict:
    return {"case_id": case.case_id, "case_index": case.index, **case.cell, "seed": case.seed,
            "scenario_json": json.dumps(case.scenario, sort_keys=True), "status": status, "error": message,
            "wall_time_s": float("nan")}


# A pool worker whose driver is gone (the kernel's parent-death signal missed: not Linux, or a
# worker stuck in C) notices within this and ends itself.
_PARENT_POLL_S = 0.5
# A worker asked to stop (SIGTERM) when the campaign is interrupted is killed after this.
_WORKER_STOP_S = 5.0
PR_SET_PDEATHSIG = 1          # linux/prctl.h


def _die_with_driver(driver_pid: int) -> None:
    """Pool worker initializer: the worker ends with the campaign command, however that ends.

    - Its own process group: Ctrl-C at a terminal signals the foreground group, which is then the
      command alone; the command stops the pool (one line, exit 130), no traceback per worker.
    - On Linux, SIGTERM from the kernel when the driver dies (prctl PR_SET_PDEATHSIG), also after
      SIGKILL; SIGTERM, not SIGKILL, so a `processes` case's launcher stops its nodes.
    - Everywhere, a thread that polls the parent pid, for where the signal is not available.
    The multiprocessing resource tracker ends by itself once no worker holds its pipe.
    """
    os.setpgid(0, 0)
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):
        pass                                    # not Linux: the thread below still notices
    if os.getppid() != driver_pid:              # the driver died before prctl took effect
        os._exit(1)
    threading.Thread(target=_watch_driver, args=(driver_pid,), name="watch-driver", daemon=True).start()


def _watch_driver(driver_pid: int) -> None:
    while os.getppid() == driver_pid:
        time.sleep(_PARENT_POLL_S)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(_WORKER_STOP_S)
    os._exit(1)


def _stop_pool(pool) -> None:
    """Interrupted: cancel what has not started, stop the workers running a case (SIGTERM, then
    SIGKILL), without waiting for their cases. ProcessPoolExecutor has no public way to stop a
    running task; its worker processes are in `_processes`."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)     # a second Ctrl-C: no traceback
    try:
        processes = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        deadline = time.monotonic() + _WORKER_STOP_S
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.kill()
                process.join(1.0)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def run_local(cases: list[Case], workers: int, on_row: Callable[[dict], None]) -> None:
    """A local process pool (spawned workers: no state inherited from the driver), whose workers
    end with the driver (`_die_with_driver`) and are stopped when it is interrupted."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    if workers == 1:
        for case in cases:
            on_row(run_case(case))
        return
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_die_with_driver, initargs=(os.getpid(),))
    try:
        futures = {pool.submit(run_case, case): case for case in cases}
        for future in as_completed(futures):
            try:
                row = future.result()
            except Exception as exc:            # the worker process itself died (not the case)
                row = _failed_row(futures[future], "error", f"worker died: {type(exc).__name__}: {exc}")
            on_row(row)
    except BaseException:                       # Ctrl-C (KeyboardInterrupt), SIGTERM handlers, bugs
        _stop_pool(pool)
        raise
    pool.shutdown(wait=True)


# On this 24 GiB machine Ray would reserve 30 % of memory for its object store; a campaign passes
# a scenario dict in and a row of numbers out per task, so 256 MiB is plenty.
RAY_OBJECT_STORE_BYTES = 256 * 1024**2
RAY_WAIT_S = 0.5


def run_ray(cases: list[Case], workers: int, on_row: Callable[[dict], None], address: str | None) -> None:
    """Ray tasks, one per case. Connects to `address`, or to this process's running Ray, or
    starts a local one with `workers` CPUs (and shuts down only what it started)."""
    import ray

    started_here = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            # address="local": a new cluster of our own, never one somebody else started on this host.
            ray.init(address="local", num_cpus=workers, object_store_memory=RAY_OBJECT_STORE_BYTES,
                     include_dashboard=False, log_to_driver=False)
        started_here = True
    pending: dict = {}
    try:
        # max_retries=0: a case that kills its worker is a failed row, not a silent re-run.
        remote_case = ray.remote(num_cpus=1, max_retries=0)(run_case)
        pending = {remote_case.remote(case): case for case in cases}
        while pending:
            # With a timeout: a ray.wait that blocks for a whole case never lets Python act on Ctrl-C.
            done, _ = ray.wait(list(pending), num_returns=1, timeout=RAY_WAIT_S)
            for ref in done:
                case = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except Exception as exc:         # worker crash, node loss
                    row = _failed_row(case, "error", f"ray task failed: {type(exc).__name__}: {exc}")
                on_row(row)
    except BaseException:                # interrupted: stop the cases still running or queued
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except Exception:            # noqa: BLE001 - already finished or its worker gone
                pass
        raise
    finally:
        if started_here:
            ray.shutdown()
