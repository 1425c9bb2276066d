"""Starting a bench node as its own operating-system process, and stopping one.

The one way a node process is started, by the launcher (`bench run`) and by the CAN bench
(`bench.runtime.can_bench`): `python -m bench.cli node NAME ...` with the interpreter running now,
so a child imports the same tree (PYTHONPATH is inherited), stdout and stderr into one log file.
Given the launcher's zygote (bench/runtime/zygote.py), the same command is forked from it, already
imported; by fork+exec when the zygote cannot (or BENCH_NODE_START=exec).
"""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from bench.runtime.zygote import ForkedProcess, Zygote


def node_command(name: str, run_id: str, scenario_path: Path, hub: str, run_dir: Path,
                 peers: list[str] | None = None, zenoh_config: str | None = None,
                 extra_args: list[str] | None = None) -> list[str]:
    """The `bench node` command line of node `name`, connecting to the hub endpoint.

    extra_args: e.g. `--cert-dir DIR` or `--deployment FILE --host NAME` (secure and multi-host runs).
    """
    cmd = [sys.executable, "-m", "bench.cli", "node", name, "--run-id", run_id, "--scenario", str(scenario_path),
           "--connect", hub, "--run-dir", str(run_dir)]
    if peers:
        cmd += ["--wait-for", ",".join(peers)]
    if zenoh_config:
        cmd += ["--zenoh-config", zenoh_config]
    return cmd + list(extra_args or [])


def start_node(name: str, run_id: str, scenario_path: Path, hub: str, run_dir: Path, log_path: Path,
               peers: list[str] | None = None, zenoh_config: str | None = None,
               popen_kwargs: dict | None = None, extra_args: list[str] | None = None,
               zygote: "Zygote | None" = None) -> "subprocess.Popen | ForkedProcess":
    """Start node `name` as a child process logging to log_path; stdin closed, so a node
    never waits on the terminal. popen_kwargs: what the launcher adds to own it (process group,
    environment; bench.runtime.ownership). zygote: fork it from there when it can."""
    cmd = node_command(name, run_id, scenario_path, hub, run_dir, peers, zenoh_config, extra_args)
    popen_kwargs = popen_kwargs or {}
    if zygote is not None and zygote.can_start(cmd, popen_kwargs):
        from bench.runtime.zygote import ZygoteFailed
        try:
            return zygote.spawn(cmd, log_path, popen_kwargs.get("process_group", 0), zygote.extra_env(popen_kwargs))
        except ZygoteFailed:
            pass     # said on stderr once; this node and the next by exec
    with open(log_path, "w") as log_file:
        return subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                **popen_kwargs)


def terminate(process, timeout_s: float) -> bool:
    """Stop a process this one started, by its handle: SIGTERM (a node then writes its report),
    and SIGKILL if it has not exited within timeout_s. Whether it had to be killed."""
    if process is None or process.poll() is not None:
        return False
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(timeout=timeout_s)
        return False
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout=timeout_s)
        return True
