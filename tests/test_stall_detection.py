"""A run whose steps stop advancing ends within its bound, with exit 1 naming the stage that
stopped (issue 44; bench/runtime/progress_watchdog.py, unit tests in test_progress_watchdog.py).

Each run here has a node stopped without dying (SIGSTOP) and liveliness told to look away
(`stopped_grace_s` 60 s, `hang_timeout_s` 600 s), as when a node's presence keeps answering while
its work has stopped: what ends the run is the progress watchdog. Before it, a stopped bus model
left a lock-step run creeping at one step per `command_timeout_s` + 1 s for ever, and a real-time
run went on with no command at all."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

from conftest import REPO, node_pid

LENIENT = "liveliness = { stopped_grace_s = 60.0, hang_timeout_s = 600.0 }"
# Past the bound: the launcher looks every 0.1 s; the plant reports a real-time gap every second.
NAMING_SLACK_S = 1.5


def attitude_quick_toml(tmp_path, name: str, command_timeout_s: float = 2.0):
    """attitude_quick (lock-step, the CAN bus on the wall clock: bus model 'canbus', board 'mtq'),
    with a short command timeout and liveliness looking away."""
    text = (REPO / "bench" / "scenarios" / "attitude_quick.toml").read_text()
    run = '[run]\nmode = "lock-step"\nseed = 3\n'
    assert run in text
    text = text.replace(run, f"{run}command_timeout_s = {command_timeout_s}\n{LENIENT}\n")
    text = text.replace('name = "attitude_quick"', f'name = "{name}"')
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def run_and_stop(runs_dir, run_id: str, scenario, node: str, *extra, after_s: float = 0.3):
    """Start the run, stop `node` (SIGSTOP) once the loop steps; (return code, stderr, seconds from
    the stop to the launcher's exit)."""
    cmd = [sys.executable, "-m", "bench.cli", "run", str(scenario), "--run-id", run_id, "--runs-dir", str(runs_dir),
           "--no-progress", "--no-report", *extra]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pid = None
    try:
        log = runs_dir / run_id / "logs" / "plant.log"
        deadline = time.monotonic() + 120
        while not (log.exists() and "peers ready" in log.read_text()):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1]
            time.sleep(0.05)
        time.sleep(after_s)
        pid = node_pid(run_id, node)
        os.kill(pid, signal.SIGSTOP)
        stopped_at = time.monotonic()
        _, stderr = proc.communicate(timeout=120)    # the old launcher: never, or only after the whole run
        return proc.returncode, stderr, time.monotonic() - stopped_at
    finally:
        if pid is not None:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def stall_line(stderr: str) -> str:
    return next((line for line in stderr.splitlines() if "run stalled at step" in line), stderr[-2000:])


def stalled_for_s(line: str) -> float:
    return float(re.search(r" for ([0-9.]+) s \(bound", line).group(1))


def end_reason(runs_dir, run_id: str) -> str:
    return json.loads((runs_dir / run_id / "metrics.json").read_text())["end_reason"]


def test_a_bus_model_that_stops_forwarding_ends_a_lock_step_run_naming_the_board_stage(tmp_path, runs_dir):
    """The bus model stops (alive, stopped): the board gets no commands, the plant no report of
    them. Before, the plant waited command_timeout_s + 1 s per step and went on: 600 steps in 30 min."""
    scenario = attitude_quick_toml(tmp_path, "stall_bus")
    code, stderr, _ = run_and_stop(runs_dir, "stall-bus", scenario, "canbus")
    line = stall_line(stderr)
    assert code == 1, stderr[-2000:]
    assert re.search(r"run stalled at step \d+: no board telemetry \(the board 'mtq', behind the bus model 'canbus'", line), line
    assert "process 'canbus' is stopped" in line and "run.command_timeout_s = 2 s" in line
    assert 2.5 <= stalled_for_s(line) <= 2.5 + NAMING_SLACK_S, line
    assert end_reason(runs_dir, "stall-bus").startswith("run stalled at step")


def test_a_stopped_controller_ends_a_lock_step_run_naming_the_command_stage(tmp_path, runs_dir):
    """The plant waits command_timeout_s for the command, gives up; the launcher names the stage
    the plant was waiting for, not only a process (the old launcher: "process 'controller' is
    stopped", or, for a controller stuck but not stopped, the plant's exit)."""
    scenario = attitude_quick_toml(tmp_path, "stall_controller")
    code, stderr, _ = run_and_stop(runs_dir, "stall-controller", scenario, "controller")
    line = stall_line(stderr)
    assert code == 1, stderr[-2000:]
    assert re.search(r"run stalled at step \d+: no command from 'controller' for", line), line
    assert "process 'controller' is stopped" in line
    assert 2.0 * 0.95 <= stalled_for_s(line) <= 2.5 + NAMING_SLACK_S, line


def test_a_stopped_controller_ends_a_real_time_run_within_its_periods(tmp_path, runs_dir):
    """Real time: the plant steps on without commands. 50 periods of 0.1 s (rendezvous at 6000x):
    5 s without a command. The old launcher let the run go on (every step missed) to its end."""
    scenario = tmp_path / "stall_rt.toml"
    scenario.write_text(f'name = "stall_rt"\n[run]\nmode = "real-time"\nsteps = 900\n{LENIENT}\n')
    code, stderr, _ = run_and_stop(runs_dir, "stall-rt", scenario, "controller", after_s=1.0)
    line = stall_line(stderr)
    assert code == 1, stderr[-2000:]
    assert re.search(r"run stalled at step \d+: no command from 'controller' for", line), line
    assert "real time: run.liveliness.stall_periods = 50 periods of 0.1 s" in line
    assert 5.0 <= stalled_for_s(line) <= 5.0 + NAMING_SLACK_S, line
