"""The run's node processes on this host: starting each in the run's process group, stopping them
stage by stage (SIGTERM, then SIGKILL), and what their exits say (NodeFailed naming the node)."""
from __future__ import annotations

import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from bench.launcher.endings import NodeFailed
from bench.launcher.parts import BOARD_SIDE_NODES, WATCHERS
from bench.runtime import zygote as node_zygote
from bench.runtime.ownership import CpuProgress, child_environment, kill_group
from bench.runtime.process import start_node
from bench.runtime.reports import REPORT_KEY_ENV, new_report_key

STARTUP_IDLE_S = 5.0      # a starting node whose CPU time did not advance this long is stuck
SHUTDOWN_GRACE_S = 5.0


@dataclass
class Child:
    name: str
    process: subprocess.Popen | node_zygote.ForkedProcess    # forked by the zygote: the same methods
    log_path: Path

    def tail(self, lines: int = 8) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


class ProcessGroup:
    """All nodes of a run in one process group (the first node leads it), killed as one."""

    def __init__(self):
        self.pgid: int | None = None
        self.report_keys: dict[int, bytes] = {}    # pid -> the secret its reports are signed with
        self._next_key: bytes | None = None

    def popen_kwargs(self) -> dict:
        # A group of their own: a terminal's Ctrl-C reaches the launcher only, which stops the
        # nodes in stages (the recorder last) instead of all at once. Each node gets its own
        # report key in its environment (bench/runtime/reports.py), never on its command line.
        self._next_key = new_report_key()
        return {"process_group": self.pgid or 0, "env": child_environment({REPORT_KEY_ENV: self._next_key.hex()})}

    def joined(self, process: subprocess.Popen) -> None:
        if self.pgid is None:
            self.pgid = process.pid
        if self._next_key is not None:
            self.report_keys[process.pid], self._next_key = self._next_key, None

    def kill(self) -> None:
        kill_group(self.pgid)


def _spawn(name: str, run_id: str, scenario_path: Path, hub: str, run_dir: Path, peers: list[str],
           zenoh_config: str | None, group: ProcessGroup | None = None,
           extra_args: list[str] | None = None, zygote: node_zygote.Zygote | None = None) -> Child:
    log_path = run_dir / "logs" / f"{name}.log"
    group = group or ProcessGroup()
    process = start_node(name, run_id, scenario_path, hub, run_dir, log_path, peers, zenoh_config,
                         popen_kwargs=group.popen_kwargs(), extra_args=extra_args, zygote=zygote)
    group.joined(process)
    return Child(name, process, log_path)


def stop_stages(names: list[str]) -> list[list[str]]:
    """The order nodes stop in, each stage's nodes at once: the loop and the flight side, then
    the bus and the board (so the driver never sees the board vanish), then the recorder and the
    live view (so they record and show every other node's last messages)."""
    stages = [[n for n in names if n not in (*BOARD_SIDE_NODES, *WATCHERS)],
              [n for n in names if n in BOARD_SIDE_NODES],
              [n for n in names if n in WATCHERS]]
    return [stage for stage in stages if stage]


def _stop_children(children: list[Child], grace_s: float = SHUTDOWN_GRACE_S) -> None:
    """SIGTERM stage by stage (stop_stages), then SIGKILL whatever is left. A child still working
    after grace_s (its CPU time advancing: a recorder finishing its file on a busy host) is given
    up to three times that; one that idles is killed at grace_s."""
    by_name = {c.name: c for c in children}
    for stage in stop_stages([c.name for c in children]):
        stopping = []
        for child in (by_name[n] for n in stage):
            if child.process.poll() is None:
                try:
                    child.process.send_signal(signal.SIGTERM)
                    stopping.append(child)
                except ProcessLookupError:
                    pass
        for child in stopping:
            _wait_exit_while_working(child.process, grace_s)
    _kill_children(children)


def _wait_exit_while_working(process: subprocess.Popen, grace_s: float) -> None:
    started = time.monotonic()
    progress = CpuProgress(process.pid)
    while True:
        try:
            process.wait(timeout=0.02)    # a forked node's wait returns as soon as the zygote reports its exit
            return
        except subprocess.TimeoutExpired:
            pass
        now = time.monotonic()
        idle_s = progress.idle_s(now)
        if now - started > grace_s and (idle_s > STARTUP_IDLE_S or now - started > 3 * grace_s):
            return


def _kill_children(children: list[Child]) -> None:
    for child in children:
        if child.process.poll() is None:
            try:
                child.process.kill()
                child.process.wait(timeout=5.0)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass


def _check_children(children: list[Child], allowed_done: set[str]) -> None:
    # A node that failed (non-zero code) is named before one that exited 0 early: two seen exited
    # by the same poll were named in start order, so a plant that ended after the bus model died
    # was blamed ("process 'plant' exited with code 0").
    exited = [(child, child.process.poll()) for child in children]
    for child, code in sorted(exited, key=lambda item: item[1] == 0):
        if code is None:
            continue
        if code != 0 or child.name not in allowed_done:
            raise NodeFailed(
                f"process '{child.name}' (pid {child.process.pid}) exited with code {code}; "
                f"last lines of {child.log_path}:\n{child.tail()}"
            )
