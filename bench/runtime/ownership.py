"""The launcher owns its children, whatever happens to it; and how it tells hung from slow.

Two mechanisms, because each covers what the other cannot:
- every node started by the launcher asks the kernel for SIGTERM when its parent dies
  (`prctl(PR_SET_PDEATHSIG)`), so a launcher killed by SIGKILL (a supervisor, a container stop, an
  out-of-memory kill) takes its nodes with it; SIGTERM lets the recorder finish its MCAP file. A
  watchdog process of each node kills it ORPHAN_EXIT_S later if it has not stopped by then;
- all nodes of a run share one process group, which the launcher kills at the end of every
  run, so nothing a node started (a solver worker) outlives the run either.

`process_state` reads /proc/PID/stat: the scheduler state and the CPU time used. A process that is
stopped (state T: SIGSTOP, a debugger) is hung; a runnable one whose token lapsed on a busy
machine is only slow, and its token comes back when it is scheduled.
"""
from __future__ import annotations

import ctypes
import os
import signal
import time
from dataclasses import dataclass

LAUNCHER_PID_ENV = "BENCH_LAUNCHER_PID"
# Set in a node forked by the launcher's zygote (bench/runtime/zygote.py): its parent is the
# zygote, which itself dies with the launcher. Absent: the launcher is the node's parent.
PARENT_PID_ENV = "BENCH_NODE_PARENT_PID"
PR_SET_PDEATHSIG = 1
# An orphaned node has this long to stop cleanly after its SIGTERM before it exits hard: the
# recorder's last chunk and MCAP summary take ~50 ms; a node blocked in a Zenoh call may never.
ORPHAN_EXIT_S = 1.2
ORPHAN_EXIT_CODE = 129
_PARENT_POLL_S = 0.1


def child_environment(extra: dict[str, str] | None = None) -> dict[str, str]:
    """Environment of a node the launcher starts: it names the launcher the node must die with."""
    return {**os.environ, LAUNCHER_PID_ENV: str(os.getpid()), **(extra or {})}


def die_with_launcher() -> None:
    """In a node started by the launcher: SIGTERM when the launcher dies, SIGKILL soon after.

    The SIGKILL comes from a small watchdog process forked here, not from a thread: a node whose
    main thread is stuck in a C call holding the GIL (a Zenoh close) runs no Python thread, and on
    a loaded machine such a node outlived the 2 s bound. The watchdog dies with its node
    (PDEATHSIG SIGKILL). No-op in a node started by hand (no BENCH_LAUNCHER_PID).

    A node forked by the zygote has the zygote as parent (BENCH_NODE_PARENT_PID): the SIGTERM
    comes when the zygote dies, which the kernel kills when the launcher dies.
    """
    text = os.environ.get(LAUNCHER_PID_ENV)
    parent_text = os.environ.pop(PARENT_PID_ENV, "")    # not for what the node itself starts
    if not text or not text.isdigit():
        return
    launcher_pid = int(text)
    parent_pid = int(parent_text) if parent_text.isdigit() else launcher_pid
    _set_parent_death_signal(signal.SIGTERM)
    if os.getppid() != parent_pid:
        os._exit(ORPHAN_EXIT_CODE)   # the launcher (or zygote) died before prctl took effect
    node_pid = os.getpid()
    if os.fork() == 0:               # the watchdog; called before the node opens its session
        _watchdog(node_pid, launcher_pid, parent_pid)


def _set_parent_death_signal(sig: int) -> None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
    except (OSError, AttributeError):
        pass     # not Linux: the watchdog still notices the launcher is gone


def _watchdog(node_pid: int, launcher_pid: int, parent_pid: int) -> None:
    """Child of the node: once the launcher (or the node's parent, the zygote) is gone, SIGTERM
    the node, SIGKILL it ORPHAN_EXIT_S later."""
    try:
        os.setsid()                  # out of the run's process group: Ctrl-C and killpg are for the node
        _set_parent_death_signal(signal.SIGKILL)
        if os.getppid() != node_pid:
            os._exit(0)
        while _alive(launcher_pid) and _alive(parent_pid) and os.getppid() == node_pid:
            time.sleep(_PARENT_POLL_S)
        if os.getppid() == node_pid:
            os.kill(node_pid, signal.SIGTERM)     # where PDEATHSIG is not available
            time.sleep(ORPHAN_EXIT_S)
            os.kill(node_pid, signal.SIGKILL)
    except Exception:    # noqa: BLE001 - the watchdog must never linger or print into the node's log
        pass
    os._exit(0)


def _alive(pid: int) -> bool:
    state = process_state(pid)
    return state is not None and state.state != "Z"


def kill_group(pgid: int | None, sig: int = signal.SIGKILL) -> None:
    """Signal a whole process group; quiet if it is already gone."""
    if pgid is None:
        return
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


@dataclass(frozen=True)
class ProcessState:
    state: str             # R running, S sleeping, D disk wait, T stopped, t traced, Z zombie, ...
    cpu_ticks: int         # utime + stime, in clock ticks
    parent_pid: int

    @property
    def stopped(self) -> bool:
        return self.state in ("T", "t")


def process_state(pid: int) -> ProcessState | None:
    """State, CPU time and parent of a process from /proc/PID/stat; None if it is gone (or not Linux)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            text = f.read()
    except OSError:
        return None
    # The command name (field 2) is in parentheses and may itself hold spaces or ')'.
    fields = text[text.rindex(")") + 2:].split()
    return ProcessState(state=fields[0], cpu_ticks=int(fields[11]) + int(fields[12]), parent_pid=int(fields[1]))


class CpuProgress:
    """When a process's CPU time last advanced: a process still working (slow on a busy machine)
    against one that idles or is stuck."""

    def __init__(self, pid: int):
        self.pid = pid
        self._ticks: int | None = None
        self._advanced_s = time.monotonic()

    def idle_s(self, now_s: float) -> float:
        """Seconds since its CPU time last advanced, as of now_s (reads /proc once)."""
        state = process_state(self.pid)
        if state is not None and state.cpu_ticks != self._ticks:
            self._ticks, self._advanced_s = state.cpu_ticks, now_s
        return now_s - self._advanced_s
