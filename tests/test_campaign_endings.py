"""A campaign command ends cleanly however it is ended: nothing it started outlives a `kill -9`
of it, and Ctrl-C stops it with one line, exit 130 and the rows done kept (bench/studies/campaign.py).

The command runs in its own session (start_new_session), so every process it started, even one
re-parented to init after the kill, is found by its session id in /proc.
"""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.studies.campaign_results import parts_dir, read_rows

TESTS_DIR = Path(__file__).parent
REPO = TESTS_DIR.parent
EXIT_INTERRUPTED = 130
GONE_WITHIN_S = 5.0

SPEC = '''name = "endings"
base_scenario = "rendezvous_lqr"
seeds = {seeds}
steps = 30
mode = "campaign_cases:{case}"
[controllers.LQR]
controller = {{ type = "lqr" }}
[dynamics.linear]
plant = {{ dynamics = "cwh" }}
[knowledge.truth]
estimator = {{ mode = "truth" }}
[initial_conditions.A]
plant = {{ initial_condition = "A" }}
'''


def _stat_fields(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2:].split()      # state, ppid, pgrp, session, ...


def session_processes(session_id: int) -> dict[int, str]:
    """pid -> command line of every live (not zombie) process of the session."""
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        fields = _stat_fields(int(entry))
        if fields and int(fields[3]) == session_id and fields[0] != "Z":
            try:
                found[int(entry)] = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:120]
            except OSError:
                pass
    return found


def children(pid: int) -> list[int]:
    return [p for p in (int(e) for e in os.listdir("/proc") if e.isdigit())
            if (f := _stat_fields(p)) and int(f[1]) == pid]


def start_campaign(tmp_path: Path, case: str, seeds: int, workers: int = 2):
    spec = tmp_path / "endings.toml"
    spec.write_text(SPEC.format(seeds=seeds, case=case))
    out = tmp_path / "endings.parquet"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(TESTS_DIR), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, "-m", "bench.cli", "campaign", str(spec), "--out", str(out), "--workers", str(workers),
               "--flush-every", "1", "--no-progress", "--no-report"]
    # As from a shell prompt: SIGINT at its default disposition. An ignored SIGINT survives exec and
    # Python then leaves it ignored, and this test's process may have inherited one from whatever
    # ran before it in the same pytest worker (a Ctrl-C then does nothing and the campaign runs on).
    process = subprocess.Popen(command, start_new_session=True, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    return process, out


def wait_for(condition, process, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if process.poll() is not None:
            raise AssertionError(f"the campaign ended (exit {process.returncode}) before {what}: "
                                 f"{process.stderr.read().decode()[-2000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"no {what} after {timeout_s} s")
        time.sleep(0.05)


def wait_until_gone(session_id: int, timeout_s: float) -> dict[int, str]:
    deadline = time.monotonic() + timeout_s
    left = session_processes(session_id)
    while left and time.monotonic() < deadline:
        time.sleep(0.05)
        left = session_processes(session_id)
    return left


def _cleanup(session_id: int) -> None:
    try:
        os.killpg(session_id, signal.SIGKILL)
    except ProcessLookupError:
        pass
    for pid in session_processes(session_id):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_of_a_running_campaign_leaves_no_process_behind(tmp_path):
    # Every case sleeps far longer than the test: both workers are busy when the command dies.
    process, _ = start_campaign(tmp_path, "sleepy_case", seeds=4)
    try:
        # The two pool workers and the resource tracker are the command's children.
        wait_for(lambda: len(children(process.pid)) >= 3, process, 120, "pool workers")
        time.sleep(1.0)              # the workers have run their initializer and taken a case
        before = session_processes(process.pid)
        assert len(before) >= 4, before
        os.kill(process.pid, signal.SIGKILL)           # the command alone, as `kill -9 PID`
        process.wait(timeout=10)
        left = wait_until_gone(process.pid, GONE_WITHIN_S)
        assert not left, f"still alive {GONE_WITHIN_S} s after kill -9 of the campaign: {left}"
    finally:
        _cleanup(process.pid)
        process.stdout.close()
        process.stderr.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_ctrl_c_prints_one_line_exits_130_and_keeps_the_rows_done(tmp_path):
    process, out = start_campaign(tmp_path, "slow_case", seeds=40)
    try:
        wait_for(lambda: len(list(parts_dir(out).glob("part-*.parquet"))) >= 3, process, 180, "three rows written")
        done_before = len(read_rows(out))
        os.killpg(process.pid, signal.SIGINT)          # what Ctrl-C at a terminal sends (the foreground group)
        stdout, stderr = process.communicate(timeout=60)
        lines = stderr.decode().strip().splitlines()
        assert process.returncode == EXIT_INTERRUPTED, stderr.decode()
        assert len(lines) == 1 and "interrupted" in lines[0], lines
        kept = len(read_rows(out))
        assert done_before <= kept < 40
        assert f"{kept} rows kept" in lines[0]
        assert not out.exists(), "the results file is written only by a finished campaign"
        left = wait_until_gone(process.pid, GONE_WITHIN_S)
        assert not left, f"still alive after the interrupted campaign exited: {left}"
    finally:
        _cleanup(process.pid)
