import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def run_bench_cli(*args: str, timeout_s: float = 120, **kwargs) -> subprocess.CompletedProcess:
    """`bench ...` as a user runs it, in a child process."""
    return subprocess.run([sys.executable, "-m", "bench.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s, cwd=kwargs.pop("cwd", REPO), **kwargs)


def bench_processes(run_id: str) -> list[int]:
    """Pids of live processes whose command line names this run id (children left behind)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().split()[2]
        except OSError:
            continue
        if run_id in cmdline and "bench.cli" in cmdline and state != "Z":
            pids.append(int(entry.name))
    return pids


@pytest.fixture
def runs_dir(tmp_path) -> Path:
    return tmp_path / "runs"

