import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench.runtime.ownership import process_state

REPO = Path(__file__).resolve().parents[1]


def run_bench_cli(*args: str, timeout_s: float = 120, **kwargs) -> subprocess.CompletedProcess:
    """`bench ...` as a user runs it, in a child process."""
    return subprocess.run([sys.executable, "-m", "bench.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s, cwd=kwargs.pop("cwd", REPO), **kwargs)


def assert_rendezvous_lqr_run_equals_in_process(run_dir: Path, steps: int) -> None:
    """The run's trajectory equals `rendezvous_lqr` of `steps` steps simulated in process, to 1e-9
    of each state component's range and of the thrust: lock-step processes reproduce the loop."""
    import msgspec
    import numpy as np

    from bench.scenario import load_scenario
    from bench.sim import simulate_in_process

    with np.load(run_dir / "trajectory.npz") as data:
        trajectory = {k: data[k] for k in data.files}
    scenario = load_scenario("rendezvous_lqr")
    scenario = msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, steps=steps))
    reference, _ = simulate_in_process(scenario)
    scale = np.abs(reference["state_m_mps"]).max(axis=0)
    np.testing.assert_allclose(trajectory["state_m_mps"] / scale, reference["state_m_mps"] / scale, rtol=0, atol=1e-9)
    np.testing.assert_allclose(trajectory["thrust_n"], reference["thrust_n"], rtol=1e-9, atol=1e-15)


def process_cmdline(pid: int) -> list[bytes]:
    """A process's command line, one element per argument ([] once it is gone)."""
    try:
        return open(f"/proc/{pid}/cmdline", "rb").read().split(b"\0")
    except OSError:
        return []


def bench_processes(run_id: str) -> list[int]:
    """Pids of live processes whose command line names this run id (children left behind)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        pid = int(entry.name)
        cmdline = b" ".join(process_cmdline(pid)).decode(errors="replace")
        state = process_state(pid)
        if run_id in cmdline and "bench.cli" in cmdline and state is not None and state.state != "Z":
            pids.append(pid)
    return pids


def parent_pid(pid: int) -> int | None:
    state = process_state(pid)
    return None if state is None else state.parent_pid


def node_pids(pids: list[int]) -> list[int]:
    """The nodes among pids: `bench node NAME`, and not a node's own watchdog (a fork of the node,
    with its command line; pids wrap around during the suite, so a watchdog's can be the lower)."""
    nodes = [p for p in pids if b"node" in process_cmdline(p)]
    return [p for p in nodes if parent_pid(p) not in nodes]


def node_pid(run_id: str, name: str) -> int:
    """The pid of node `name` of a live run."""
    for pid in node_pids(bench_processes(run_id)):
        if name.encode() in process_cmdline(pid):
            return pid
    raise AssertionError(f"no {name} process for {run_id}")


@pytest.fixture
def runs_dir(tmp_path) -> Path:
    return tmp_path / "runs"

